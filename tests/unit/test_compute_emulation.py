"""Compute emulation you can trust: a job's CPU time is its own thread's (plus its library worker
threads'), durations are in reference-core time whatever the host, ``wall`` timing refuses what
it cannot emulate, and a node whose speed drifts during a run is flagged."""

from __future__ import annotations

import json
import os
import re
import statistics
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from coordinator.run import free_port
from fabric import compute, host_speed
from fabric.compute import (
    ComputeNode,
    CpuQuota,
    CpuSample,
    ThreadCpuClock,
    WallTimingRefused,
    read_cpu_quota,
)
from fabric.host_speed import HostScore
from fabric.seeding import rng
from fabric.zenoh_bus import ZenohBus
from scenario.schema import NodeProfile

REF = host_speed.reference()


def at_score(score: float) -> HostScore:
    return HostScore(score=score, source="injected")


def node(cpus: float = 0.5, timing: str = "cpu", score: float = REF.score, **kw: Any) -> ComputeNode:
    """A node on a host of the given score whose speed probes read that same score."""
    kw.setdefault("probe", lambda: score)
    return ComputeNode("n", NodeProfile(cpus=cpus, timing=timing), rng(1, "n"), host=at_score(score), **kw)  # type: ignore[arg-type]


def spin(n: int) -> int:
    """Interpreted arithmetic: a small working set, so cache sharing with other threads barely
    changes its CPU time."""
    acc = 0
    for i in range(n):
        acc = (acc * 31 + i) % 1_000_003
    return acc


class FakeClock:
    """A job CPU clock that reports given samples (a host of any speed, on demand)."""

    def __init__(self, samples: list[CpuSample]) -> None:
        self.samples = iter(samples)

    def start(self) -> None:
        return None

    def stop(self, token: None) -> CpuSample:
        return next(self.samples)


# ---- a job's CPU time is its own ------------------------------------------------------------

@contextmanager
def switchable(work: Callable[[], object]) -> Iterator[Callable[[bool], None]]:
    """A thread of this process doing ``work`` over and over while switched on."""
    on, stop = threading.Event(), threading.Event()

    def loop() -> None:
        while not stop.is_set():
            if on.is_set():
                work()
            else:
                time.sleep(0.0005)

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    try:
        yield lambda active: on.set() if active else on.clear()
    finally:
        stop.set()
        t.join()


@contextmanager
def burning_python_thread() -> Iterator[Callable[[bool], None]]:
    """Another thread of this process compressing data (zlib releases the GIL: the thread burns
    a core in parallel with the job, as zenoh's receive threads do)."""
    data = np.random.default_rng(0).integers(0, 64, 1 << 18, dtype=np.uint8).tobytes()
    with switchable(lambda: zlib.compress(data, 6)) as set_load:
        yield set_load


@contextmanager
def zenoh_traffic() -> Iterator[Callable[[bool], None]]:
    """A router and a client session of this process, the client receiving a flood of 64 kB
    messages: zenoh's own threads decode and deliver them while the job runs."""
    port = free_port()
    router = ZenohBus(f"tcp/127.0.0.1:{port}", mode="router")
    client = ZenohBus(f"tcp/127.0.0.1:{port}", mode="client")
    received = [0]
    client.subscribe("cosim/test/flood", lambda key, payload: received.__setitem__(0, received[0] + 1))
    payload = bytes(65_536)
    try:
        with switchable(lambda: router.publish("cosim/test/flood", payload)) as set_load:
            yield set_load
    finally:
        client.close()
        router.close()
    assert received[0] > 0


@pytest.mark.parametrize("load", [burning_python_thread, zenoh_traffic])
def test_a_job_is_charged_its_own_cpu_time_whatever_else_the_process_runs(load: Any) -> None:
    n = node(cpus=0.25)
    spin(100_000)
    ratios = []
    process_cpu = {False: 0, True: 0}  # the process CPU clock over the jobs, quiet and loaded
    with load() as set_load:
        # Quiet and loaded jobs come in pairs, in alternating order, so the host's own speed
        # changes (a shared host's speed drifts within seconds) hit both alike; the median of the
        # pairs' ratios is compared.
        for i in range(40):
            duration, process = {}, {}
            for active in (False, True) if i % 2 else (True, False):
                set_load(active)
                time.sleep(0.005)  # the load is running before the job starts
                p0 = time.process_time_ns()
                n.run("job", 0, spin, 100_000)
                process[active] = time.process_time_ns() - p0
                duration[active] = n.records[-1].duration_us
            set_load(False)
            ratios.append(duration[True] / duration[False])
            for active in (False, True):
                process_cpu[active] += process[active]
    # Charged the process's CPU time, a loaded job would count much of the load thread's time
    # too (x1.5-1.6 with the burning thread on an idle 2-core host). Its own time still grows a
    # little: the two cores of a small VM may be threads of one physical core, and a busy
    # sibling slows the job itself (up to 8% seen).
    assert statistics.median(ratios) == pytest.approx(1.0, abs=0.15)
    # The other threads really ran alongside: the process CPU clock (what jobs used to be
    # charged) grew. By how much depends on how often the host lets the load thread run beside
    # the job (10-25% on an idle 2-core host, a few % when other processes take the second
    # core), so over all jobs and with a low bar: enough that charging it would be seen.
    assert process_cpu[True] > 1.02 * process_cpu[False]


def test_a_node_with_cores_counts_its_worker_threads_and_one_core_pools_stay_on_the_thread() -> None:
    img = np.random.default_rng(1).random((1200, 1200), dtype=np.float32)
    kernel = np.ones((9, 9), np.float32) / 81
    clock = ThreadCpuClock()
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(2)
        cv2.filter2D(img, -1, kernel)  # the pool starts
        two = []
        for _ in range(5):
            tok = clock.start()
            cv2.filter2D(img, -1, kernel)
            two.append(clock.stop(tok))
        cv2.setNumThreads(1)
        one = []
        for _ in range(5):
            tok = clock.start()
            cv2.filter2D(img, -1, kernel)
            one.append(clock.stop(tok))
    finally:
        cv2.setNumThreads(threads)
    # Two threads: OpenCV's worker did part of the work and is charged to the job.
    assert sum(sum(s.helpers_ns) for s in two) > 0.2 * sum(s.total_ns for s in two)
    # One thread: the job ran on the calling thread alone.
    assert sum(sum(s.helpers_ns) for s in one) < 0.02 * sum(s.total_ns for s in one)


def test_parallel_work_is_spread_over_the_nodes_cores_and_no_more() -> None:
    two_threads = CpuSample(own_ns=10_000_000, helpers_ns=(10_000_000,))  # 20 ms on 2 threads
    four_threads = CpuSample(own_ns=5_000_000, helpers_ns=(5_000_000,) * 3)  # 20 ms on 4 threads
    for sample, expect_us in ((two_threads, 10_000), (four_threads, 10_000)):
        n = node(cpus=2.0, clock=FakeClock([sample]))
        n.run("job", 0, int)
        assert n.records[0].duration_us == expect_us  # 2 cores: 20 ms of work takes 10 ms
    single = node(cpus=1.0, clock=FakeClock([two_threads]))
    single.run("job", 0, int)
    assert single.records[0].duration_us == 20_000  # one core: the threads take turns


# ---- host-independent speed --------------------------------------------------------------------

def test_a_host_twice_as_fast_gives_the_same_emulated_duration() -> None:
    work_ms = [12.0, 7.5, 30.25]  # the same jobs' CPU time on the reference core
    ref_host = node(cpus=0.25, score=REF.score,
                    clock=FakeClock([CpuSample(int(ms * 1e6)) for ms in work_ms]))
    fast_host = node(cpus=0.25, score=2 * REF.score,
                     clock=FakeClock([CpuSample(int(ms * 1e6 / 2)) for ms in work_ms]))
    for host in (ref_host, fast_host):
        for _ in work_ms:
            host.run("compress", 0, int)
    assert [r.duration_us for r in fast_host.records] == [r.duration_us for r in ref_host.records]
    assert [r.duration_us for r in ref_host.records] == [round(ms * 1000 / 0.25) for ms in work_ms]
    assert fast_host.scale == pytest.approx(2.0)


def test_an_injected_score_scales_real_jobs(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(host_speed.SCORE_ENV, str(2 * REF.score))
    host_speed.host_score.cache_clear()
    try:
        n = ComputeNode("n", NodeProfile(cpus=0.5), rng(1, "n"), probe=lambda: 2 * REF.score)
        assert n.host.source == "injected" and n.scale == pytest.approx(2.0)
    finally:
        host_speed.host_score.cache_clear()
    n.run("job", 0, spin, 50_000)
    rec = n.records[0]
    assert rec.duration_us == pytest.approx(rec.cpu_us * 2 / 0.5, abs=5)  # cpu_us is floored
    summary = n.speed_summary(1_000_000)
    assert summary["scale"] == pytest.approx(2.0) and summary["host_score_source"] == "injected"


def test_a_score_measured_while_other_work_ran_is_not_cached(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(host_speed.SCORE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    busy = iter([100.0, 160.0])  # the host's busy CPU seconds before and after: far more than ours
    monkeypatch.setattr(host_speed, "_host_cpu_s", lambda: next(busy))
    monkeypatch.setattr(host_speed, "measure_components",
                        lambda reps=1: {"python": 8.0, "numpy": 4.0, "opencv": 2.0, "zlib": 2.0})
    host_speed.host_score.cache_clear()
    try:
        got = host_speed.host_score()
    finally:
        host_speed.host_score.cache_clear()
    assert got.source.startswith("measured (not cached:") and "other cores busy" in got.source
    assert not (tmp_path / "cosim5g" / "host_score.json").exists()
    assert host_speed._others_busy_cores(10.0, 10.5, 0.5, 1.0) == 0.0
    assert host_speed._others_busy_cores(10.0, 12.5, 0.5, 2.0) == 1.0


def test_a_bad_injected_score_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(host_speed.SCORE_ENV, "fast")
    with pytest.raises(ValueError, match="COSIM5G_HOST_SCORE.*'fast'.*valid number"):
        host_speed.injected_score()


def test_the_host_score_is_cached_with_the_cpu_model_and_date(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(host_speed.SCORE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(host_speed, "_host_cpu_s", lambda: 100.0)  # an otherwise idle host
    calls = []

    def fake_components(reps: int = 1) -> dict[str, float]:
        calls.append(reps)
        return {"python": 8.0, "numpy": 4.0, "opencv": 2.0, "zlib": 2.0}

    monkeypatch.setattr(host_speed, "measure_components", fake_components)
    host_speed.host_score.cache_clear()
    try:
        first = host_speed.host_score()
        host_speed.host_score.cache_clear()
        second = host_speed.host_score()
        cached = json.loads((tmp_path / "cosim5g" / "host_score.json").read_text())
        # Another interpreter or CPU: the cache does not apply.
        cached["env"]["cpu_model"] = "another CPU"
        (tmp_path / "cosim5g" / "host_score.json").write_text(json.dumps(cached))
        host_speed.host_score.cache_clear()
        third = host_speed.host_score()
    finally:
        host_speed.host_score.cache_clear()
    assert (first.source, second.source, third.source) == ("measured", "cache", "measured")
    assert len(calls) == 2
    assert first.score == second.score == pytest.approx(host_speed.score_of(fake_components()))
    assert cached["env"]["python"].startswith("CPython") and cached["measured_at"][:2] == "20"
    assert cached["env"]["cpu_model"] == "another CPU"  # (as written above)
    assert first.env["cpu_model"] == host_speed.cpu_model()


@pytest.mark.parametrize("edit", [{"score": -50.0}, {"score": 0.0}, {"score": "NaN"}, {"score": "Infinity"},
                                  {"score": REF.score / 1000}, {"measured_at": "2099-01-01T00:00:00+00:00"}])
def test_a_cached_score_no_measurement_gives_is_measured_again(tmp_path: Path, edit: dict[str, Any]) -> None:
    # Every job's duration is scaled by it: a run on it completed with every latency 1 us.
    env = host_speed.environment()
    good = {"score": REF.score, "components_ms": REF.components_ms, "env": env,
            "measured_at": host_speed._now()}
    path = tmp_path / "host_score.json"
    path.write_text(json.dumps(good))
    assert host_speed._read_cache(path, env) is not None
    path.write_text(json.dumps({**good, **edit}).replace('"NaN"', "NaN").replace('"Infinity"', "Infinity"))
    assert host_speed._read_cache(path, env) is None


def test_the_cache_folder_setting_holds_the_host_score_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COSIM5G_CACHE_DIR", str(tmp_path / "cache"))
    assert host_speed.cache_path() == tmp_path / "cache" / "host_score.json"
    monkeypatch.delenv("COSIM5G_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert host_speed.cache_path() == tmp_path / "xdg" / "cosim5g" / "host_score.json"


def test_the_reference_core_is_recorded_with_its_cpu_and_date() -> None:
    assert REF.score > 0 and REF.env["cpu_model"] and REF.measured_at
    assert set(REF.components_ms) == set(host_speed.COMPONENTS)
    assert REF.env["score_version"] == str(host_speed.SCORE_VERSION)


def test_the_scoring_workload_is_deterministic() -> None:
    assert host_speed._python() == host_speed._python()
    assert host_speed._numpy() == host_speed._numpy()
    assert host_speed._opencv() == host_speed._opencv()
    assert host_speed._zlib() == host_speed._zlib()


# ---- wall timing ------------------------------------------------------------------------------

def test_wall_timing_refuses_jobs_shorter_than_a_few_cfs_periods(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(compute, "read_cpu_quota", lambda: CpuQuota(2_500, 10_000))
    short = CpuSample(2_000_000)  # 2 ms of CPU: 8 ms at 0.25 cpus, under one 10 ms period
    n = node(cpus=0.25, timing="wall", clock=FakeClock([short]))
    with pytest.raises(WallTimingRefused) as err:
        n.run("control", 0, int)
    msg = str(err.value)
    for part in ("n:", "'control'", "8.00 ms", "cpus=0.25", "CFS periods of 10 ms", "timing 'cpu'"):
        assert part in msg
    long = CpuSample(15_000_000)  # 60 ms at 0.25 cpus: 6 periods
    ok = node(cpus=0.25, timing="wall", score=2 * REF.score, clock=FakeClock([long]))
    ok.run("compress", 0, time.sleep, 0.002)
    rec = ok.records[0]
    assert rec.duration_us == pytest.approx(rec.wall_us * 2, abs=2)  # wall time, in reference time


def test_wall_timing_needs_a_cpu_quota_matching_the_profile(monkeypatch: pytest.MonkeyPatch) -> None:
    ran: list[int] = []
    monkeypatch.setattr(compute, "read_cpu_quota", lambda: None)
    with pytest.raises(WallTimingRefused, match="n: timing 'wall' needs the node inside a CPU-limited cgroup"):
        node(cpus=0.25, timing="wall").run("pose", 0, ran.append, 1)
    monkeypatch.setattr(compute, "read_cpu_quota", lambda: CpuQuota(10_000, 10_000))
    with pytest.raises(WallTimingRefused, match=r"match cpus=0.25, but it gives 1.000 cpus"):
        node(cpus=0.25, timing="wall").run("pose", 0, ran.append, 1)
    assert not ran  # refused before the job runs


@pytest.mark.parametrize("layout", ["v2", "v1-container", "v1-host", "none"])
def test_the_cpu_quota_is_read_from_cgroup_v1_and_v2(tmp_path: Path, layout: str) -> None:
    root = tmp_path / "cgroup"
    own = tmp_path / "self_cgroup"
    if layout == "v2":
        own.write_text("0::/run/node\n")
        (root / "run" / "node").mkdir(parents=True)
        (root / "run" / "node" / "cpu.max").write_text("2500 10000\n")
    elif layout == "v1-container":  # the container's cgroup is mounted at the root
        own.write_text("4:cpu,cpuacct:/docker/abc\n")
        (root / "cpu,cpuacct").mkdir(parents=True)
        (root / "cpu,cpuacct" / "cpu.cfs_quota_us").write_text("2500\n")
        (root / "cpu,cpuacct" / "cpu.cfs_period_us").write_text("10000\n")
    elif layout == "v1-host":
        own.write_text("1:cpu:/cal/node\n")
        (root / "cpu" / "cal" / "node").mkdir(parents=True)
        (root / "cpu" / "cal" / "node" / "cpu.cfs_quota_us").write_text("2500\n")
        (root / "cpu" / "cal" / "node" / "cpu.cfs_period_us").write_text("10000\n")
        (root / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
        (root / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    else:
        own.write_text("0::/\n")
        root.mkdir()
        (root / "cpu.max").write_text("max 100000\n")
    quota = read_cpu_quota(root, own)
    assert quota == (None if layout == "none" else CpuQuota(2500, 10000))


# ---- speed during the run ---------------------------------------------------------------------

def test_a_node_whose_speed_drifts_is_flagged() -> None:
    speeds = iter([REF.score, 0.97 * REF.score, 0.8 * REF.score])
    n = node(cpus=0.25, probe=lambda: next(speeds))
    n.run("job", 0, int)
    n.run("job", compute.PROBE_PERIOD_US, int)  # the second probe, one period later
    summary = n.speed_summary(25_000_000)  # and the last at the end
    assert [t for t, _ in summary["probes"]] == [0, compute.PROBE_PERIOD_US, 25_000_000]
    assert summary["flagged"] and summary["drift"] == pytest.approx(-0.2)
    assert "cannot be trusted" in summary["warning"]
    for key in ("host_score", "reference_score", "scale", "cpu_model", "run_score_median"):
        assert key in summary
    steady = node(cpus=0.25, probe=iter([REF.score, 1.05 * REF.score]).__next__)
    steady.run("job", 0, int)
    assert not steady.speed_summary(1_000)["flagged"]


def test_a_node_that_runs_no_job_never_scores_the_host() -> None:
    def no_probe() -> float:
        raise AssertionError("a node with no job must not measure the host")

    n = ComputeNode("n", NodeProfile(cpus=0.5), rng(1, "n"), probe=no_probe)
    assert n.speed_summary(5_000_000) == {"timing": "cpu", "cpus": 0.5, "jobs": 0}
    assert n._host is None and not n.probes


def test_model_timing_stays_host_independent() -> None:
    def no_probe() -> float:
        raise AssertionError("a model-timed node must not measure the host")

    n = ComputeNode("n", NodeProfile(cpus=0.25, timing="model"), rng(1, "n"), probe=no_probe)
    n.run("compress", 0, spin, 10_000)
    assert n.scale == 1.0 and n.speed_summary(1_000) == {"timing": "model", "host_independent": True}
    assert n.records[0].duration_us == ComputeNode(
        "n", NodeProfile(cpus=0.25, timing="model"), rng(1, "n")).run("compress", 0, int)[1]


def test_helper_threads_are_unnamed_native_threads_only() -> None:
    """zenoh's threads are named (never a job's); Python threads are known to ``threading``."""
    clock = ThreadCpuClock()
    router = ZenohBus(f"tcp/127.0.0.1:{free_port()}", mode="router")
    try:
        clock.workers()
        workers = set(clock.workers())
        names = {tid: Path(f"/proc/self/task/{tid}/comm").read_text().strip() for tid in workers}
        own = Path("/proc/self/comm").read_text().strip()
        assert all(name == own for name in names.values())
        assert os.getpid() not in workers and threading.get_native_id() not in workers
        zenoh_threads = [t for t in os.listdir("/proc/self/task")
                         if Path(f"/proc/self/task/{t}/comm").read_text().strip() != own]
        assert zenoh_threads and not workers & {int(t) for t in zenoh_threads}
    finally:
        router.close()


# ---- the calibration report -------------------------------------------------------------------

def test_calibration_reports_ratios_with_intervals_and_measured_causes() -> None:
    from coordinator.calibrate import analyse, diagnose, render

    gen = np.random.default_rng(3)
    jobs = []
    # Unlimited: 10 ms per compress job and 50 ms per spin job. At 0.25 cpus compress uses 20%
    # more CPU when throttled (70% of its jobs are), spin (the clock control) is unchanged.
    for rnd in range(3):
        for _ in range(12):
            for w, base in (("compress", 10_000.0), ("spin", 50_000.0)):
                for cpus in (None, 0.25):
                    throttled = int(cpus is not None and gen.random() < 0.7)
                    cpu = base * (1 + 0.2 * throttled * (w == "compress")) * gen.normal(1, 0.01)
                    wall = cpu / (cpus or 1)
                    jobs.append({"runtime": "docker", "round": rnd, "cpus": cpus, "workload": w,
                                 "cpu_us": cpu, "thread_us": cpu, "helper_us": 0, "process_us": cpu * 1.3,
                                 "wall_us": wall, "duration_us": cpu / (cpus or 1), "throttled_us": 0,
                                 "throttled_periods": throttled * 3, "nivcsw": 1})
    rows = analyse(jobs)
    cell = next(r for r in rows if r["workload"] == "compress" and r["cpus"] == 0.25)
    assert cell["n"] == 36
    lo, hi = cell["cpu_mode_over_ideal"]["ci95"]
    assert lo <= cell["cpu_mode_over_ideal"]["median"] <= hi and 1.1 < cell["cpu_mode_over_ideal"]["median"] < 1.25
    assert cell["throttled_over_unthrottled_cpu"] == pytest.approx(1.2, abs=0.02)
    spin_cell = next(r for r in rows if r["workload"] == "spin" and r["cpus"] == 0.25)
    assert spin_cell["cpu_mode_over_ideal"]["median"] == pytest.approx(1.0, abs=0.01)
    notes = diagnose(rows, jobs)
    compress_note = next(n for n in notes if "compress at 0.25" in n)
    # spin says the clock did not change; the excess is the job's own, and comes with throttling.
    assert re.search(r"so clock speed [-+]0\.\d% and caches/memory \+(19|20|21)\.\d%", compress_note)
    assert re.search(r"jobs throttled at least once used \+(19|20|21)\.\d% CPU time", compress_note)
    meta = {"date": "d", "cpu_model": "c", "cores": 2, "load_start": 0.1, "load_end": 0.2, "rounds": 3,
            "jobs": 12, "reference_score": 300.0, "reference_cpu_model": "c", "reference_date": "d",
            "host_scores": {"docker": 300.0}}
    text = render(meta, rows, notes)
    assert "| compress | 0.25 | 36 |" in text and "## Where an error remains" in text


def test_a_node_enters_the_watch_list_once_per_publication_and_only_when_it_ran() -> None:
    from prometheus_client import REGISTRY

    ran: list[ComputeNode] = []
    busy, idle = (ComputeNode(name, NodeProfile(cpus=0.25, timing="model"), rng(1, name))
                  for name in ("watch-busy", "watch-idle"))
    for n in (busy, idle):
        n.watch(ran)
    busy.run("compress", 0, int)
    busy.run("compress", 1_000, int)
    assert ran == [busy]
    for n in ran:
        n.publish_metrics()
    ran.clear()
    count = REGISTRY.get_sample_value("cosim_compute_job_duration_seconds_count",
                                      {"node": "watch-busy", "kind": "compress"})
    assert count == 2
    assert REGISTRY.get_sample_value("cosim_compute_job_duration_seconds_count",
                                     {"node": "watch-idle", "kind": "compress"}) is None
    busy.run("compress", 2_000, int)
    assert ran == [busy], "listed again at its first job after publishing"
