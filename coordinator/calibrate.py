"""``cosim5g calibrate``: how faithful compute emulation is, measured on the real workloads.

Every workload of ``domain.workloads`` runs as jobs of nodes of 1, 0.5 and 0.25 cpus and of an
unlimited node, in each runtime; what is measured and reported (results/bench/calibrate.{md,json},
``--rebuild`` from the JSON): docs/compute.md, "Calibration: make calibrate". ``--fit-job-models``
fits what ``model`` timing draws from instead (docs/compute.md, "Model timing").
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from coordinator.launcher import NodeLimits
from fabric.compute import JOB_MODELS_PATH
from fabric.settings import one_thread_pools
from scenario.schema import Scenario

PROFILES = (1.0, 0.5, 0.25)
RUNTIMES = ("process", "docker", "docker-wall", "cgroup")
ROOT = Path(__file__).parents[1]
BOOTSTRAP = 2000
TARGET = 0.05  # cpu-mode / ideal should be within 5% of 1 (median)
JOB_COLUMNS = ("runtime", "round", "cpus", "workload", "cpu_us", "thread_us", "helper_us", "process_us",
               "wall_us", "duration_us", "throttled_us", "throttled_periods", "nivcsw")
WORKER_TIMEOUT_S = 3600


class CalibrateError(RuntimeError):
    """The calibration cannot run as asked; the message says why and what to do."""


def _last_json_line(text: str, where: str) -> dict[str, Any]:
    for line in reversed(text.strip().splitlines()):
        if line.startswith("{"):
            return dict(json.loads(line))
    raise CalibrateError(f"{where}: the workloads printed no result; its output ended with:\n{text[-2000:]}")


# The workloads process calls ``domain.workloads.main`` from the installed package alone: the
# runtime image has the packages but no scripts. Its arguments follow in sys.argv[1:].
WORKER = "import sys; from domain.workloads import main; sys.exit(main(sys.argv[1:]))"


def _worker_argv(cpus: float | None, jobs: int, only: list[str] | None, worker: str = WORKER) -> list[str]:
    argv = ["-c", worker, "--jobs", str(jobs)]
    if cpus is not None:
        argv += ["--cpus", repr(cpus)]
    if only:
        argv += ["--only", *only]
    return argv


class ProcessRunner:
    """The workloads in a plain process, with the process runtime's environment; no CPU limit."""

    name = "process"
    worker = WORKER

    def __init__(self, only: list[str] | None = None) -> None:
        self.only = only

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        env.setdefault("MUJOCO_GL", "egl")
        one_thread_pools(env)  # as coordinator.runtime_process starts federates
        return env

    def run(self, cpus: float | None, jobs: int) -> dict[str, Any]:
        return self._spawn(cpus, jobs, None)

    def _spawn(self, cpus: float | None, jobs: int, preexec: Callable[[], None] | None) -> dict[str, Any]:
        proc = subprocess.run([sys.executable, *_worker_argv(cpus, jobs, self.only, self.worker)], cwd=ROOT,
                              env=self.env(), capture_output=True, text=True, timeout=WORKER_TIMEOUT_S,
                              preexec_fn=preexec)
        if proc.returncode != 0:
            raise CalibrateError(f"{self.name} workloads (cpus={cpus}) failed with exit code "
                                 f"{proc.returncode}:\n{proc.stderr[-3000:]}")
        return _last_json_line(proc.stdout, f"{self.name} workloads (cpus={cpus})")


class CgroupRunner(ProcessRunner):
    """The workloads in a plain process inside a new cgroup with the docker runtime's limits."""

    name = "cgroup"

    def __init__(self, only: list[str] | None = None) -> None:
        super().__init__(only)
        root = Path("/sys/fs/cgroup")
        self.v2 = (root / "cgroup.controllers").exists()
        self.parent = root if self.v2 else root / "cpu"
        if not os.access(self.parent, os.W_OK) or (self.v2 and "cpu" not in _read(root / "cgroup.subtree_control")):
            raise CalibrateError(
                f"the cgroup runtime needs a writable cgroup hierarchy with the cpu controller "
                f"({self.parent}): run as root, or use --runtime process or docker")
        self.count = 0

    def run(self, cpus: float | None, jobs: int) -> dict[str, Any]:
        if cpus is None:
            return self._spawn(None, jobs, None)
        from coordinator.docker_limits import CFS_PERIOD_US, cfs_quota_us

        self.count += 1
        group = self.parent / f"cosim5g-calibrate-{os.getpid()}-{self.count}"
        group.mkdir()
        try:
            quota = cfs_quota_us(cpus)
            if self.v2:
                (group / "cpu.max").write_text(f"{quota} {CFS_PERIOD_US}\n")
            else:
                (group / "cpu.cfs_period_us").write_text(f"{CFS_PERIOD_US}\n")
                (group / "cpu.cfs_quota_us").write_text(f"{quota}\n")
            procs = group / "cgroup.procs"

            def join() -> None:  # in the child, before it runs any workload
                procs.write_text(f"{os.getpid()}\n")

            return self._spawn(cpus, jobs, join)
        finally:
            group.rmdir()


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


class DockerRunner:
    """The workloads in a container of the runtime image, with the docker runtime's cgroup limits
    and environment (no BLAS thread setting: the docker runtime sets none). ``timing`` is the
    node's: ``cpu`` (whole cores, what `cpu`-mode figures are for) or ``wall`` (quota cpus x
    period, what `wall` figures are for)."""

    def __init__(self, only: list[str] | None = None, source: bool = False, timing: str = "cpu") -> None:
        from docker.errors import ImageNotFound

        from coordinator.runtime_docker import RUNTIME_IMAGE, DockerRuntimeError, docker_client

        self.only = only
        self.source = source
        self.timing = timing
        self.name = "docker" if timing == "cpu" else f"docker-{timing}"
        self.image = RUNTIME_IMAGE
        try:
            self.client = docker_client()
        except DockerRuntimeError as exc:
            raise CalibrateError(str(exc)) from None
        try:
            self.client.images.get(self.image)
        except ImageNotFound:
            raise CalibrateError(f"image {self.image} not found: build it with `make images`, or "
                                 "use --runtime process (or cgroup)") from None

    def run(self, cpus: float | None, jobs: int) -> dict[str, Any]:
        from coordinator.docker_limits import cgroup_limits

        env = {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl", "HOME": "/tmp"}
        mounts = {}
        if self.source:  # this working tree's code instead of the copy installed in the image
            env.update(PYTHONPATH="/src", PYTHONDONTWRITEBYTECODE="1")
            mounts = {str(ROOT): {"bind": "/src", "mode": "ro"}}
        raw = self.client.containers.run(
            self.image, ["python", *_worker_argv(cpus, jobs, self.only)],
            environment=env, volumes=mounts,
            remove=True, read_only=True, tmpfs={"/tmp": "size=64m"}, cap_drop=["ALL"],
            security_opt=["no-new-privileges"], network_mode="none",
            **cgroup_limits(NodeLimits(cpus=cpus, mem_mb=1024, timing=self.timing)),
        )
        return _last_json_line(raw.decode(), f"{self.name} workloads (cpus={cpus})")


RUNNERS: dict[str, type[ProcessRunner]] = {"process": ProcessRunner, "cgroup": CgroupRunner}


# ---- statistics -------------------------------------------------------------------------------

def ratio_of_medians(num: np.ndarray, den: np.ndarray, gen: np.random.Generator,
                     n_boot: int = BOOTSTRAP) -> dict[str, Any]:
    """median(num) / median(den) with a percentile-bootstrap 95% CI (both samples resampled)."""
    point = float(np.median(num) / np.median(den))
    bn = np.median(num[gen.integers(0, len(num), (n_boot, len(num)))], axis=1)
    bd = np.median(den[gen.integers(0, len(den), (n_boot, len(den)))], axis=1)
    lo, hi = np.percentile(bn / bd, [2.5, 97.5])
    return {"median": round(point, 4), "ci95": [round(float(lo), 4), round(float(hi), 4)]}


def _col(jobs: list[dict[str, Any]], name: str) -> np.ndarray:
    return np.array([j[name] for j in jobs if j[name] is not None], dtype=float)


def analyse(jobs: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """One row per runtime, workload and cpus (the unlimited baseline included, as cpus None)."""
    gen = np.random.default_rng(seed)
    rows = []
    cells: dict[tuple[str, str, float | None], list[dict[str, Any]]] = {}
    for j in jobs:
        cells.setdefault((j["runtime"], j["workload"], j["cpus"]), []).append(j)
    for runtime in [r for r in RUNTIMES if any(k[0] == r for k in cells)]:
        workloads = sorted({k[1] for k in cells if k[0] == runtime}, key=_workload_order)
        for w in workloads:
            base = cells.get((runtime, w, None), [])
            if not base:
                continue
            base_cpu, base_proc = _col(base, "cpu_us"), _col(base, "process_us")
            rows.append({"runtime": runtime, "workload": w, "cpus": None, "n": len(base),
                         "cpu_ms": round(float(np.median(base_cpu)) / 1000, 3)})
            for cpus in PROFILES:
                lim = cells.get((runtime, w, cpus), [])
                if not lim:
                    continue
                cpu, wall = _col(lim, "cpu_us"), _col(lim, "wall_us")
                row: dict[str, Any] = {
                    "runtime": runtime, "workload": w, "cpus": cpus, "n": len(lim),
                    "ideal_ms": round(float(np.median(base_cpu)) / cpus / 1000, 3),
                    "cpu_mode_ms": round(float(np.median(_col(lim, "duration_us"))) / 1000, 3),
                    "cpu_mode_over_ideal": ratio_of_medians(_col(lim, "duration_us"), base_cpu / cpus, gen),
                    "wall_over_ideal": ratio_of_medians(wall, base_cpu / cpus, gen),
                    "process_clock_over_ideal": ratio_of_medians(_col(lim, "process_us"), base_proc, gen),
                    "helper_cpu_share": round(float(_col(lim, "helper_us").sum() / max(cpu.sum(), 1)), 4),
                    "nivcsw_per_job": float(np.median(_col(lim, "nivcsw"))),
                }
                periods = _col(lim, "throttled_periods")
                if len(periods) == len(lim):
                    row["throttled_periods_per_job"] = float(np.median(periods))
                    hit, missed = cpu[periods > 0], cpu[periods == 0]
                    if len(hit) >= 5 and len(missed) >= 5:
                        # Jobs of one cell differ in whether the quota ran out during them (the
                        # phase of the period they start in): the CPU time a throttle costs.
                        row["throttled_over_unthrottled_cpu"] = round(float(np.median(hit) / np.median(missed)), 4)
                rows.append(row)
    return rows


def _workload_order(name: str) -> tuple[int, str]:
    order = ("spin", "compress", "pose", "control", "score")
    return (order.index(name) if name in order else len(order), name)


def diagnose(rows: list[dict[str, Any]], jobs: list[dict[str, Any]],
             meta: dict[str, Any] | None = None) -> list[str]:
    """Measured causes of the errors that remain (sentences for the report)."""
    out = []
    penalty = (meta or {}).get("idle_wake_penalty") or {}
    if penalty:
        out.append("Idle-wake penalty (CPU time of a 2 ms L1-resident loop right after 10 ms of idle "
                   "over right after busy, median of 30 pairs; a node throttled by its quota meets it "
                   "at every period): " + ", ".join(f"{k} {v:.3f}" for k, v in sorted(penalty.items()))
                   + ".")
    by = {(r["runtime"], r["workload"], r["cpus"]): r for r in rows}
    for runtime in sorted({r["runtime"] for r in rows}, key=RUNTIMES.index):
        rounds = sorted({j["round"] for j in jobs if j["runtime"] == runtime})
        speeds = []
        for rnd in rounds:
            score_cpu = [j["cpu_us"] for j in jobs if j["runtime"] == runtime and j["round"] == rnd
                         and j["workload"] == "score" and j["cpus"] is None]
            if score_cpu:
                speeds.append(statistics.median(score_cpu))
        if len(speeds) > 1:
            out.append(f"{runtime}: host speed drift between rounds (scoring mix, unlimited node): "
                       f"slowest round / fastest = {max(speeds) / min(speeds):.3f}.")
        for cpus in PROFILES:
            spin = by.get((runtime, "spin", cpus))
            for w in ("spin", "compress", "pose", "control", "score"):
                r = by.get((runtime, w, cpus))
                if r is None:
                    continue
                ratio = r["cpu_mode_over_ideal"]["median"]
                if abs(ratio - 1) <= TARGET:
                    continue
                parts = [f"{runtime} {w} at {cpus} cpus: cpu-mode / ideal {ratio:.3f}"]
                if spin is not None and w != "spin":
                    # spin's working set fits L1: its excess is the core's clock (frequency, host
                    # speed), the rest of this job's excess is what spin does not have (caches).
                    clock = spin["cpu_mode_over_ideal"]["median"]
                    parts.append(f"spin (clock-speed control, same cells) {clock:.3f}, so clock speed "
                                 f"{clock - 1:+.1%} and caches/memory {ratio - clock:+.1%}")
                elif w == "spin":
                    parts.append("spin's working set fits L1: a change of the core's clock (frequency, "
                                 "host contention between the rounds)")
                if "throttled_periods_per_job" in r:
                    parts.append(f"{r['throttled_periods_per_job']:g} throttled CFS periods per job")
                if "throttled_over_unthrottled_cpu" in r:
                    parts.append(f"jobs throttled at least once used {r['throttled_over_unthrottled_cpu'] - 1:+.1%} "
                                 "CPU time vs jobs never throttled (cache refills after throttling)")
                parts.append(f"{r['nivcsw_per_job']:g} involuntary context switches per job")
                if r["helper_cpu_share"] > 0.01:
                    parts.append(f"{r['helper_cpu_share']:.1%} of its CPU on library worker threads")
                out.append("; ".join(parts) + ".")
    return out


# ---- report -----------------------------------------------------------------------------------

def _ci(cell: dict[str, Any]) -> str:
    lo, hi = cell["ci95"]
    return f"{cell['median']:.3f} [{lo:.3f}, {hi:.3f}]"


def render(meta: dict[str, Any], rows: list[dict[str, Any]], notes: list[str]) -> str:
    lines = [
        "# Compute emulation calibration",
        "",
        f"{meta['date']}, {meta['cpu_model']} ({meta['cores']} cores), load average (1 min) "
        f"{meta['load_start']:.2f} at the start and {meta['load_end']:.2f} at the end; {meta['rounds']} "
        f"interleaved rounds x {meta['jobs']} jobs per workload and profile. Medians with bootstrap "
        "95% CIs of the ratio of medians. Ideal = the unlimited node's CPU time for the job / cpus.",
        f"Reference core: score {meta['reference_score']:.1f} ({meta['reference_cpu_model']}, "
        f"{meta['reference_date']}); scores measured here: "
        + ", ".join(f"{k} {v:.1f}" for k, v in meta["host_scores"].items()) + ".",
        "",
    ]
    for runtime in [r for r in RUNTIMES if any(x["runtime"] == r for x in rows)]:
        lines += [f"## {runtime}", ""]
        if runtime == "process":
            lines += ["No cgroup: nothing limits the node's CPU, so wall / ideal is about cpus "
                      "(wall timing is refused there); cpu-mode / ideal is the check.", ""]
        elif runtime == "docker":
            lines += ["The limits of a `cpu`-timed node: whole cores, ceil(cpus); no job is throttled in "
                      "mid-run. cpu-mode / ideal is the check; wall / ideal is about cpus.", ""]
        elif runtime in ("docker-wall", "cgroup"):
            lines += ["The limits of a `wall`-timed node: quota cpus x 10 ms period. wall / ideal is the "
                      "check; cpu-mode / ideal shows what throttling in mid-job costs in CPU time.", ""]
        lines += ["| workload | cpus | n | unlimited CPU ms | ideal ms | cpu-mode / ideal | wall / ideal | "
                  "process clock / ideal (before) | throttled periods / job |",
                  "|---|---|---|---|---|---|---|---|---|"]
        base = {r["workload"]: r for r in rows if r["runtime"] == runtime and r["cpus"] is None}
        for r in rows:
            if r["runtime"] != runtime or r["cpus"] is None:
                continue
            lines.append(
                f"| {r['workload']} | {r['cpus']:.2f} | {r['n']} | {base[r['workload']]['cpu_ms']:.2f} | "
                f"{r['ideal_ms']:.2f} | {_ci(r['cpu_mode_over_ideal'])} | {_ci(r['wall_over_ideal'])} | "
                f"{_ci(r['process_clock_over_ideal'])} | {r.get('throttled_periods_per_job', '-')} |")
        lines.append("")
    lines += ["## Where an error remains", ""]
    lines += [f"- {n}" for n in notes] or ["- every cpu-mode / ideal median is within 5%."]
    return "\n".join(lines) + "\n"


def _reference_meta() -> dict[str, Any]:
    from fabric import host_speed

    ref = host_speed.reference()
    return {"reference_score": ref.score, "reference_cpu_model": ref.env.get("cpu_model", ""),
            "reference_date": ref.measured_at}


def calibrate(runtimes: list[str], rounds: int, jobs: int, only: list[str] | None,
              log: Callable[[str], None] = print, source: bool = False,
              ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Run the rounds; (meta, per-job rows)."""
    from fabric import host_speed

    def make_runner(name: str) -> Any:
        if name.startswith("docker"):
            return DockerRunner(only, source, "wall" if name == "docker-wall" else "cpu")
        return RUNNERS[name](only)

    runners = [make_runner(r) for r in runtimes]
    load_start = os.getloadavg()[0]
    rows: list[dict[str, Any]] = []
    scores: dict[str, list[float]] = {}
    penalties: dict[str, list[float]] = {}
    profiles: list[float | None] = [None, *PROFILES]
    for rnd in range(rounds):
        for k in range(len(runners)):
            runner = runners[(rnd + k) % len(runners)]
            for i in range(len(profiles)):
                cpus = profiles[(rnd + i) % len(profiles)]
                log(f"round {rnd + 1}/{rounds}: {runner.name}, cpus={cpus or 'unlimited'}")
                result = runner.run(cpus, jobs)
                scores.setdefault(runner.name, []).append(float(result["env"]["host_score"]))
                penalty = result["env"].get("idle_wake_penalty")
                if penalty is not None:
                    penalties.setdefault(f"{runner.name} {cpus or 'unlimited'}", []).append(float(penalty))
                for name, per_job in result["workloads"].items():
                    for j in per_job:
                        rows.append({"runtime": runner.name, "round": rnd, "cpus": cpus,
                                     "workload": name, **{c: j.get(c) for c in JOB_COLUMNS[4:]}})
    meta = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "cpu_model": host_speed.cpu_model(), "cores": os.cpu_count(),
        "load_start": load_start, "load_end": os.getloadavg()[0],
        "rounds": rounds, "jobs": jobs, "runtimes": runtimes, "docker_source": source,
        "host_scores": {k: statistics.median(v) for k, v in scores.items()},
        "idle_wake_penalty": {k: statistics.median(v) for k, v in penalties.items()},
        **_reference_meta(),
    }
    return meta, rows


def write(out: Path, meta: dict[str, Any], jobs: list[dict[str, Any]]) -> str:
    rows = analyse(jobs)
    notes = diagnose(rows, jobs, meta)
    text = render(meta, rows, notes)
    out.mkdir(parents=True, exist_ok=True)
    data = {"meta": meta, "rows": rows, "notes": notes,
            "jobs": {"columns": list(JOB_COLUMNS), "rows": [[j[c] for c in JOB_COLUMNS] for j in jobs]}}
    for name, body in (("calibrate.json", json.dumps(data, indent=1) + "\n"), ("calibrate.md", text)):
        tmp = out / f".{name}.tmp"
        tmp.write_text(body)
        tmp.replace(out / name)
    return text


# ---- job models: what ``model`` timing draws -----------------------------------------------------

# The fit's profiles: the default nodes' cpus (camera and robot 0.25, Edge 1.0) and a node of two
# cores, where a job's library pools get two threads: whether a kind uses more than one shows there.
FIT_PROFILES = (0.25, 1.0, 2.0)
FIT_KINDS = ("compress", "pose", "policy", "control")
# The scenario whose camera (frame size and codec), estimator and policy the jobs are fitted at.
FIT_SCENARIO = Path("configs") / "scenarios" / "co_design.yaml"
# A kind uses more than one thread only where, on a node of two cores, its CPU time is at least
# this many times its duration (both in the same processes, free of the noise between them). The
# platform's kinds measured 1.00-1.12: OpenCV's idle pool workers add up to 12% of CPU time to a
# compress job without making it any faster (its duration there equals its work on one core).
PARALLEL_MIN_SPEEDUP = 1.25
FIT_WORKER = "import sys; from coordinator.calibrate import fit_worker; sys.exit(fit_worker(sys.argv[1:]))"


class FitRunner(ProcessRunner):
    """The fit's workloads in a plain process: ``domain.workloads`` for compress, pose and control,
    and the Edge's policy job (``fit_worker``)."""

    worker = FIT_WORKER


def fit_scenario(path: Path = FIT_SCENARIO) -> Scenario:
    """The scenario the job models are fitted at; its camera and estimator must be the defaults,
    which ``domain.workloads`` renders and estimates with."""
    from domain.frame_model import camera_settings
    from scenario.schema import ScenarioError, load_scenario, parse_scenario

    try:
        sc = load_scenario(ROOT / path)
    except (OSError, ScenarioError) as exc:
        raise CalibrateError(f"the job models are fitted at {path}, which does not load: {exc}") from None
    default = parse_scenario({"loops": 1})
    if camera_settings(sc.camera) != camera_settings(default.camera) or sc.edge.estimator != default.edge.estimator:
        raise CalibrateError(f"{path} sets another camera or estimator than the defaults the workloads "
                             "run with (domain/workloads.py): fit the job models at the defaults")
    return sc


def _policy_job() -> Callable[[], Any]:
    """The Edge's policy job as its federate runs it (``CoDesign.decide`` for the fit scenario's
    policy), every policy period, on a tracker that follows the parts on a belt."""
    from domain.edge_side import CoDesign, update_tracks
    from domain.tracker import Tracker
    from domain.world import World

    sc = fit_scenario()
    world = World(sc)
    world.spawn(0)
    tracker = Tracker((sc.work_cell.belt_speed_m_s, 0.0, 0.0))
    for t_us in range(1_000_000, 1_500_001, 100_000):
        world.advance_to(t_us)
        update_tracks(tracker, t_us, [np.asarray(o["p"]) for o in world.objects(0)])
    codesign = CoDesign.for_scenario(sc)
    state = {"t_us": 1_500_000}

    def policy() -> Any:
        state["t_us"] += sc.edge.policy_period_ms * 1000
        return codesign.decide(0, state["t_us"], tracker, state["t_us"] - 33_000)

    return policy


def _measure_policy(cpus: float, jobs: int) -> list[dict[str, Any]]:
    """``jobs`` policy jobs on a ``cpu``-timed node of ``cpus`` at the reference core's score (as
    ``domain.workloads.measure`` runs the others), each right after a pose estimate, untimed, as
    on the Edge: after one, a decision takes 3 to 4 times its CPU time on warm caches."""
    from domain.workloads import build_jobs
    from fabric import host_speed
    from fabric.compute import ComputeNode
    from fabric.seeding import rng
    from scenario.schema import NodeProfile

    ref = host_speed.reference()
    node = ComputeNode("fit", NodeProfile(cpus=cpus, timing="cpu"), rng(0, "fit"),
                       host=host_speed.HostScore(score=ref.score, source="injected"), probe=lambda: ref.score)
    job, pose = _policy_job(), build_jobs()["pose"]
    for _ in range(2):
        pose()
        job()
    for _ in range(jobs):
        pose()
        node.run("policy", 0, job)
    return [{"cpu_us": r.cpu_us, "duration_us": r.duration_us, "wall_us": r.wall_us} for r in node.records]


def fit_worker(argv: list[str]) -> int:
    """The fit's workloads process (``FIT_WORKER``): every kind of ``FIT_KINDS`` run ``--jobs``
    times on a ``cpu``-timed node of ``--cpus``; prints one JSON object as ``domain.workloads``."""
    from domain.workloads import measure

    ap = argparse.ArgumentParser(prog="cosim5g calibrate --fit-job-models (workloads)")
    ap.add_argument("--cpus", type=float, required=True)
    ap.add_argument("--jobs", type=int, required=True)
    args = ap.parse_args(argv)
    result = measure(args.cpus, args.jobs, [*(k for k in FIT_KINDS if k != "policy"), "score"])
    result["workloads"]["policy"] = _measure_policy(args.cpus, args.jobs)
    print(json.dumps(result))
    return 0


def fit(results: list[tuple[float, dict[str, Any]]], reference_mix_ms: float) -> dict[str, Any]:
    """The job models from the workloads' results, one ``(cpus, result)`` per worker process.

    A job's work is its CPU time in reference-core microseconds: its CPU time x its process's
    speed, the reference core's time for the scoring mix (``reference_mix_ms``, the sum of its
    components) over the median CPU time of the process's ``score`` jobs, which ran interleaved
    with the others: other load on the host slows the mix as it slows the jobs, and cancels.
    Per kind: ``work_us``, the median work on nodes of one core (one thread: a job's duration
    there is its CPU time over cpus); ``sd``, its interquartile range / 1.349 over the median; ``threads``, 1
    unless its CPU time on a node of two or more cores is at least ``PARALLEL_MIN_SPEEDUP`` times
    its duration there, then ``work_us`` over that duration at one reference core a core, so that
    model and ``cpu`` timing agree there too. Per profile it keeps the jobs' count, their median
    ``cpu``-timing duration in reference time, the model's mean there and, on more cores, the
    speedup (CPU time over duration)."""
    from fabric.compute import FittedJobModel

    speeds = []
    for cpus, result in results:
        mix = [j["cpu_us"] for j in result["workloads"].get("score", [])]
        if not mix:
            raise CalibrateError(f"the workloads at cpus={cpus} ran no scoring mix: the fit needs it")
        speeds.append(reference_mix_ms * 1000 / statistics.median(mix))
    kinds: dict[str, Any] = {}
    for kind in FIT_KINDS:
        by_cpus: dict[float, list[tuple[float, dict[str, Any]]]] = {}
        for (cpus, result), speed in zip(results, speeds, strict=True):
            by_cpus.setdefault(cpus, []).extend((speed, j) for j in result["workloads"].get(kind, []))
        work = np.array([speed * j["cpu_us"] for cpus, jobs in by_cpus.items() if cpus <= 1
                         for speed, j in jobs], dtype=float)
        if len(work) < 2:
            raise CalibrateError(f"the fit measured {len(work)} {kind} jobs on nodes of at most 1 cpu: "
                                 "at least 2 are needed")
        median = float(np.median(work))
        q1, q3 = np.percentile(work, [25, 75])
        speedups, gains = {}, [1.0]
        for cpus, jobs in by_cpus.items():
            cores = math.ceil(cpus)
            if cores > 1 and jobs:
                busy = [j["duration_us"] * cpus / cores for _, j in jobs]
                speedups[cpus] = float(np.median([j["cpu_us"] for _, j in jobs]) / np.median(busy))
                if speedups[cpus] >= PARALLEL_MIN_SPEEDUP:
                    gains.append(median / float(np.median([speed * b for (speed, _), b in zip(jobs, busy, strict=True)])))
        threads = round(max(gains), 2)
        model = FittedJobModel(work_us=round(median, 1), sd=round(float(q3 - q1) / 1.349 / median, 3),
                               threads=threads)
        fitted_from = []
        for cpus in sorted(by_cpus):
            jobs = by_cpus[cpus]
            measured = float(np.median([speed * j["duration_us"] for speed, j in jobs]))
            row = {"cpus": cpus, "jobs": len(jobs), "cpu_timing_median_us": round(measured, 1),
                   "model_mean_us": model.at(cpus).mean_us}
            if cpus in speedups:
                row["speedup"] = round(speedups[cpus], 3)
            fitted_from.append(row)
        kinds[kind] = {"work_us": model.work_us, "sd": model.sd, "threads": model.threads,
                       "fitted_from": fitted_from}
    return {"kinds": kinds, "speeds": [round(v, 4) for v in speeds],
            "host_scores": [round(float(r["env"]["host_score"]), 2) for _, r in results]}


def fit_job_models(out: Path, rounds: int, jobs: int, profiles: tuple[float, ...] = FIT_PROFILES,
                   log: Callable[[str], None] = print) -> dict[str, Any]:
    """Measure every kind of ``FIT_KINDS`` at each of ``profiles`` (cpus) in ``cpu`` timing,
    ``rounds`` interleaved rounds of ``jobs`` jobs per kind and profile, fit the job models and
    write them to ``out`` (the package's ``fabric/data/job_models.json`` by default)."""
    from domain.frame_model import camera_settings
    from fabric import host_speed
    from fabric.compute import parse_job_models

    sc = fit_scenario()
    runner = FitRunner()
    load_start = os.getloadavg()[0]
    results: list[tuple[float, dict[str, Any]]] = []
    for rnd in range(rounds):
        for i in range(len(profiles)):
            cpus = profiles[(rnd + i) % len(profiles)]
            log(f"job models, round {rnd + 1}/{rounds}: cpus={cpus}")
            results.append((cpus, runner.run(cpus, jobs)))
    ref = host_speed.reference()
    fitted = fit(results, sum(ref.components_ms.values()))
    data = {
        "about": "What model timing draws a job's duration from, per job kind: work_us, its CPU time on "
                 "one reference core (median), sd relative to it, threads it runs in parallel; fitted by "
                 "cosim5g calibrate --fit-job-models from cpu-timed runs of the real workloads "
                 "(docs/compute.md, Model timing). host: the fit's processes' scores at their start and "
                 "speeds (reference core = 1) from the scoring mix run among the jobs.",
        "fitted_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "scenario": str(FIT_SCENARIO), "camera": camera_settings(sc.camera),
        "estimator": sc.edge.estimator, "policy": sc.policy.name,
        "profiles_cpus": list(profiles), "rounds": rounds, "jobs_per_round": jobs,
        "host": {"cpu_model": host_speed.cpu_model(), "cores": os.cpu_count(),
                 "score": round(statistics.median(fitted["host_scores"]), 2), "scores": fitted["host_scores"],
                 "speed": round(statistics.median(fitted["speeds"]), 4), "speeds": fitted["speeds"],
                 "load_start": round(load_start, 2), "load_end": round(os.getloadavg()[0], 2)},
        "reference": {"score": round(ref.score, 2), "cpu_model": ref.env.get("cpu_model", ""),
                      "measured_at": ref.measured_at},
        "kinds": fitted["kinds"],
    }
    parse_job_models(data, str(out))  # what the nodes will load
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp"
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(out)
    return data


def render_job_models(data: dict[str, Any]) -> str:
    """The fitted job models as a table: per kind and profile, the ``cpu``-timing median duration
    against the model's mean."""
    host = data["host"]
    lines = [f"# Job models ({data['fitted_at']}, {host['cpu_model']}, speed {host['speed']:.3f} reference "
             f"cores, from {min(host['speeds']):.3f} to {max(host['speeds']):.3f})", "",
             "| kind | work at 1 ref. core us | sd | threads | cpus | jobs | cpu timing median us | model mean us |",
             "|---|---|---|---|---|---|---|---|"]
    for kind, m in data["kinds"].items():
        for row in m["fitted_from"]:
            lines.append(f"| {kind} | {m['work_us']:g} | {m['sd']:g} | {m['threads']:g} | {row['cpus']:g} | "
                         f"{row['jobs']} | {row['cpu_timing_median_us']:g} | {row['model_mean_us']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="cosim5g calibrate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runtime", choices=[*RUNTIMES, "both"], default="both",
                    help="where the workloads run (both: process, docker and docker-wall)")
    ap.add_argument("--rounds", type=int, default=6, help="interleaved rounds over runtimes and profiles")
    ap.add_argument("--jobs", type=int, default=6, help="jobs per workload, profile and round")
    ap.add_argument("--only", nargs="*", help="workload names (default: all)")
    ap.add_argument("--out", type=Path, default=Path("results") / "bench",
                    help="folder for calibrate.md and calibrate.json (default results/bench)")
    ap.add_argument("--rebuild", action="store_true", help="render the report again from OUT/calibrate.json")
    ap.add_argument("--source", action="store_true",
                    help="docker: run this working tree's code (mounted read-only) in the runtime image, "
                    "instead of the copy installed in it at `make images`")
    ap.add_argument("--fit-job-models", nargs="?", const=JOB_MODELS_PATH, type=Path, metavar="JSON",
                    help="instead: fit what model timing draws from, each job kind at cpus "
                    f"{', '.join(map(str, FIT_PROFILES))} in the process runtime (--rounds x --jobs jobs "
                    "per kind and cpus), and write it to JSON (default: the package's fabric/data/job_models.json)")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.jobs < 1:
        ap.error("--rounds and --jobs must be at least 1")
    try:
        if args.fit_job_models is not None:
            data = fit_job_models(args.fit_job_models, args.rounds, args.jobs,
                                  log=lambda m: print(m, file=sys.stderr))
            print(render_job_models(data), end="")
            print(f"written to {args.fit_job_models}", file=sys.stderr)
            return 0
        if args.rebuild:
            data = json.loads((args.out / "calibrate.json").read_text())
            cols = data["jobs"]["columns"]
            jobs = [dict(zip(cols, r, strict=True)) for r in data["jobs"]["rows"]]
            meta = data["meta"]
        else:
            runtimes = ["process", "docker", "docker-wall"] if args.runtime == "both" else [args.runtime]
            if args.rounds * args.jobs < 30:
                print(f"note: {args.rounds * args.jobs} jobs per cell (fewer than 30): a functional check, "
                      "not a calibration", file=sys.stderr)
            meta, jobs = calibrate(runtimes, args.rounds, args.jobs, args.only,
                                   log=lambda m: print(m, file=sys.stderr), source=args.source)
    except (CalibrateError, OSError) as exc:
        print(f"calibrate: {exc}", file=sys.stderr)
        return 2
    print(write(args.out, meta, jobs), end="")
    print(f"written to {args.out / 'calibrate.md'} and calibrate.json", file=sys.stderr)
    return 0
