"""``model`` timing's job models: fitted work in reference-core time, scaled to a node's cpus as
``cpu`` timing scales a job's CPU time; a profile's ``model_us`` still wins; the packaged fit
covers every job kind the federates run, and a bad file is refused by name."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coordinator.calibrate import FIT_KINDS, CalibrateError, fit
from domain.frame_model import camera_settings
from fabric import compute
from fabric.compute import (
    ComputeNode,
    CpuSample,
    FittedJobModel,
    JobModelsError,
    fitted_job_models,
    load_job_models,
)
from fabric.seeding import rng
from scenario.schema import JobModel, NodeProfile, parse_scenario

FEDERATE_KINDS = {"compress", "pose", "policy", "control"}


def durations(kind: str, cpus: float, n: int = 50, **profile: Any) -> list[int]:
    """The drawn durations of ``n`` ``kind`` jobs on a model-timed node of ``cpus``, one seed."""
    node = ComputeNode("n", NodeProfile(cpus=cpus, timing="model", **profile), rng(1, "n"))
    for _ in range(n):
        node.run(kind, 0, int)
    return [rec.duration_us for rec in node.records]


@pytest.mark.parametrize("kind", sorted(FEDERATE_KINDS))
def test_a_kinds_duration_is_its_work_over_cpus_on_one_core(kind: str) -> None:
    model = fitted_job_models()[kind]
    # One seed, one normal draw per job: each draw at 0.25 cpus is four times the draw at 1.0
    # (a node of one core: whatever threads the kind could use).
    quarter, whole = durations(kind, 0.25), durations(kind, 1.0)
    for q, w in zip(quarter, whole, strict=True):
        assert q == pytest.approx(4 * w, rel=0.05, abs=4)  # mean and sd each rounded to 1 us
    assert ComputeNode("n", NodeProfile(cpus=0.5, timing="model"), rng(1, "n"))._job_model(kind) == \
        model.at(0.5) == JobModel(mean_us=round(model.work_us / 0.5), sd_us=round(model.sd * model.work_us / 0.5))


@pytest.mark.parametrize("threads", [1.0, 1.6, 2.0, 3.0])
@pytest.mark.parametrize("cpus", [0.25, 0.5, 1.0, 1.5, 2.0, 4.0])
def test_the_model_scales_as_cpu_timing_does(threads: float, cpus: float) -> None:
    work_ns = 12_000_000  # spread evenly over ``threads`` threads
    parts = int(threads) if threads == int(threads) else 2
    longest = work_ns / threads
    sample = CpuSample(int(longest), tuple(int((work_ns - longest) / (parts - 1)) for _ in range(parts - 1)))
    node = ComputeNode("n", NodeProfile(cpus=cpus, timing="model"), rng(1, "n"))
    measured_us = node.cpu_duration_us(sample)
    assert FittedJobModel(work_us=work_ns / 1000, threads=threads).at(cpus).mean_us == \
        pytest.approx(measured_us, rel=1e-3)


def test_a_profiles_model_us_still_wins() -> None:
    fixed = {"compress": JobModel(mean_us=7_000, sd_us=0)}
    for cpus in (0.25, 1.0, 4.0):
        assert set(durations("compress", cpus, n=5, model_us=fixed)) == {7_000}  # absolute: no cpus
    assert durations("pose", 0.25, n=1, model_us=fixed) != [7_000]  # other kinds: the fitted model


def test_model_timing_draws_one_normal_per_job() -> None:
    stream = rng(7, "n")
    node = ComputeNode("n", NodeProfile(cpus=0.25, timing="model"), stream)
    for kind in sorted(FEDERATE_KINDS):
        node.run(kind, 0, int)
    twin = rng(7, "n")
    twin.normal(size=len(FEDERATE_KINDS))
    assert stream.normal() == twin.normal()  # the stream is where one draw per job leaves it


def test_an_unknown_kind_names_what_is_there() -> None:
    with pytest.raises(KeyError, match=r"model_us.job .*fitted kinds: \['compress', 'control', 'policy', 'pose'\]"):
        ComputeNode("n", NodeProfile(cpus=1.0, timing="model"), rng(1, "n")).run("job", 0, int)


def test_the_packaged_fit_covers_every_federate_kind_at_the_default_camera() -> None:
    models = load_job_models()
    assert FEDERATE_KINDS <= set(models) and set(FIT_KINDS) == FEDERATE_KINDS
    data = json.loads(compute.JOB_MODELS_PATH.read_text())
    assert data["camera"] == camera_settings(parse_scenario({"loops": 1}).camera)
    assert data["host"]["score"] > 0 and data["fitted_at"][:2] == "20" and data["reference"]["score"] > 0
    for kind in FEDERATE_KINDS:
        rows = data["kinds"][kind]["fitted_from"]
        assert len({r["cpus"] for r in rows}) >= 2 and all(r["jobs"] > 0 for r in rows)
    defaults = compute.DEFAULT_JOB_MODELS
    assert defaults["compress"] == models["compress"].at(0.25) and defaults["pose"] == models["pose"].at(1.0)
    assert defaults["control"] == models["control"].at(0.25) and defaults["policy"] == models["policy"].at(1.0)


@pytest.mark.parametrize(("text", "message"), [
    ("{", "not JSON"),
    ("[]", "expected an object whose 'kinds'"),
    ('{"kinds": {}}', "expected an object whose 'kinds'"),
    ('{"kinds": {"pose": 4000}}', "kinds.pose is 4000, not an object"),
    ('{"kinds": {"pose": {"sd": 0.1}}}', r"kinds.pose.work_us is missing \(a number > 0\)"),
    ('{"kinds": {"pose": {"work_us": -5}}}', r"kinds.pose.work_us is -5, expected a number > 0"),
    ('{"kinds": {"pose": {"work_us": 4000, "sd": "wide"}}}', r"kinds.pose.sd is 'wide', expected a number in \[0, 1\)"),
    ('{"kinds": {"pose": {"work_us": 4000, "threads": 0.5}}}', r"kinds.pose.threads is 0.5, expected a number >= 1"),
])
def test_a_bad_file_is_refused_by_name(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "job_models.json"
    path.write_text(text)
    with pytest.raises(JobModelsError, match=message) as err:
        load_job_models(path)
    assert str(path) in str(err.value) and "cosim5g calibrate --fit-job-models" in str(err.value)


def test_a_missing_file_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(JobModelsError, match="cannot read the fitted job models"):
        load_job_models(tmp_path / "none.json")


def test_the_fit_takes_reference_work_and_parallel_threads_from_the_jobs() -> None:
    gen = np.random.default_rng(0)
    mix_ms = 10.0  # the reference core's time for the scoring mix

    def result(cpus: float, speed: float, cpu_us: float, threads: float, idle_us: float = 0) -> dict[str, Any]:
        """A process on a core ``speed`` reference cores fast, its jobs ``cpu_us`` of CPU there
        spread over ``threads``, plus ``idle_us`` of CPU on idle pool workers where cpus > 1."""
        cores = max(1, -(-cpus // 1))
        jobs = []
        for c in gen.normal(cpu_us, cpu_us * 0.1, 400):
            busy = max(c / threads, c / cores)  # what cpu timing gives, at the reference score
            extra = idle_us if cores > 1 else 0
            jobs.append({"cpu_us": float(c + extra), "duration_us": busy / (cpus / cores)})
        mix = [{"cpu_us": mix_ms * 1000 / speed}] * 5
        return {"env": {"host_score": 1.0}, "workloads": {**{k: jobs for k in FIT_KINDS}, "score": mix}}

    # Jobs of 2 ms of CPU on a core twice the reference's speed: 4 ms of reference work; on a
    # core at half the speed (the host was busy), 8 ms of CPU for the same work.
    fitted = fit([(0.25, result(0.25, 2.0, 2_000, 1.8)), (2.0, result(2.0, 0.5, 8_000, 1.8))], mix_ms)
    pose = fitted["kinds"]["pose"]
    assert pose["work_us"] == pytest.approx(4_000, rel=0.05) and pose["sd"] == pytest.approx(0.1, rel=0.3)
    assert pose["threads"] == pytest.approx(1.8, abs=0.05) and fitted["speeds"] == [2.0, 0.5]
    for row in pose["fitted_from"]:
        assert row["model_mean_us"] == pytest.approx(row["cpu_timing_median_us"], rel=0.05)
    serial = fit([(0.25, result(0.25, 1.0, 2_000, 1.0)), (2.0, result(2.0, 1.0, 2_000, 1.0))], mix_ms)
    assert serial["kinds"]["compress"]["threads"] == 1.0
    idle = fit([(1.0, result(1.0, 1.0, 2_000, 1.0)), (2.0, result(2.0, 1.0, 2_000, 1.0, idle_us=300))], mix_ms)
    assert idle["kinds"]["compress"]["threads"] == 1.0  # more CPU, no faster
    one_core = fit([(0.25, result(0.25, 1.0, 2_000, 1.8))], mix_ms)  # no node of more cores
    assert one_core["kinds"]["pose"]["threads"] == 1.0
    no_mix = result(1.0, 1.0, 2_000, 1.0)
    del no_mix["workloads"]["score"]
    with pytest.raises(CalibrateError, match="cpus=1.0 ran no scoring mix"):
        fit([(1.0, no_mix)], mix_ms)
