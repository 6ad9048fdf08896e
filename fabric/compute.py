"""Compute emulation: a node runs its jobs for real, one at a time per emulated core.

The timing mode (``cpu``, ``wall`` or ``model``) gives each job's simulated duration; each job's
queueing delay, duration, CPU and wall time are recorded. The contract: docs/architecture.md
sec. 5; the detail: docs/compute.md.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import cache
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from fabric import host_speed, metrics
from fabric.host_speed import HostScore
from scenario.schema import JobModel, NodeProfile, Nodes

T = TypeVar("T")

# What ``model`` timing draws from when a profile gives no ``model_us`` for a kind: each job kind's
# work fitted from cpu-timed runs of the real workloads (``cosim5g calibrate --fit-job-models``;
# docs/compute.md, "Model timing"), scaled to the node's cpus.
JOB_MODELS_FILE = "data/job_models.json"
JOB_MODELS_PATH = Path(__file__).parent / JOB_MODELS_FILE
# The node each job kind runs on, for the defaults at the default profiles.
JOB_NODES = {"compress": "camera", "pose": "edge", "policy": "edge", "control": "robot"}


class JobModelsError(ValueError):
    """The fitted job models file cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class FittedJobModel:
    """A job kind's work in ``model`` timing: ``work_us``, its CPU time on one reference core (us);
    ``sd``, its standard deviation relative to ``work_us``; ``threads``, how many threads it keeps
    busy in parallel (1: one thread)."""

    work_us: float
    sd: float = 0.0
    threads: float = 1.0

    def at(self, cpus: float) -> JobModel:
        """The distribution of its duration on a node of ``cpus`` reference cores, as ``cpu``
        timing gives it (``ComputeNode.cpu_duration_us``): the work spread over its threads, at
        most the node's ``ceil(cpus)`` cores, each core ``cpus / cores`` reference cores fast."""
        cores = max(1, math.ceil(cpus))
        mean = self.work_us / (min(self.threads, cores) * cpus / cores)
        # A spread, however small, keeps its draw: one normal draw per job (``draw_model_us``).
        sd_us = max(1, round(self.sd * mean)) if self.sd > 0 else 0
        return JobModel(mean_us=max(1, round(mean)), sd_us=sd_us)


def parse_job_models(data: Any, where: str) -> dict[str, FittedJobModel]:
    """The fitted job models in ``data`` (the JSON of ``JOB_MODELS_FILE``, read from ``where``),
    checked: per kind under ``kinds``, ``work_us`` > 0, 0 <= ``sd`` < 1, ``threads`` >= 1."""

    def refused(what: str) -> JobModelsError:
        return JobModelsError(f"{where}: {what}; write the file again with `cosim5g calibrate --fit-job-models`")

    kinds = data.get("kinds") if isinstance(data, dict) else None
    if not isinstance(kinds, dict) or not kinds:
        raise refused("expected an object whose 'kinds' maps each job kind to {work_us, sd, threads}")
    out = {}
    for kind, entry in kinds.items():
        if not isinstance(entry, dict):
            raise refused(f"kinds.{kind} is {entry!r}, not an object")
        values = {}
        for name, default, ok, allowed in (("work_us", None, lambda v: v > 0, "a number > 0"),
                                           ("sd", 0.0, lambda v: 0 <= v < 1, "a number in [0, 1)"),
                                           ("threads", 1.0, lambda v: v >= 1, "a number >= 1")):
            value = entry.get(name, default)
            if value is None:
                raise refused(f"kinds.{kind}.{name} is missing ({allowed})")
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
                    or not ok(value):
                raise refused(f"kinds.{kind}.{name} is {value!r}, expected {allowed}")
            values[name] = float(value)
        out[str(kind)] = FittedJobModel(**values)
    return out


def load_job_models(path: Path = JOB_MODELS_PATH) -> dict[str, FittedJobModel]:
    """The fitted job models in the file ``path`` (default: the package's)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise JobModelsError(f"{path}: cannot read the fitted job models ({exc.strerror}); write it with "
                             "`cosim5g calibrate --fit-job-models`") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise JobModelsError(f"{path}: not JSON ({exc}); write it again with "
                             "`cosim5g calibrate --fit-job-models`") from None
    return parse_job_models(data, str(path))


@cache
def fitted_job_models() -> dict[str, FittedJobModel]:
    """The package's fitted job models (read once a process)."""
    return load_job_models()


@cache
def default_job_models() -> dict[str, JobModel]:
    """The fitted models at the default node profiles (camera 0.25, Edge 1.0, robot 0.25 cpus),
    for a model of a loop without nodes (the policy's training environment)."""
    nodes = Nodes()
    fitted = fitted_job_models()
    return {kind: fitted[kind].at(getattr(nodes, node).cpus) for kind, node in JOB_NODES.items() if kind in fitted}


def __getattr__(name: str) -> Any:
    # DEFAULT_JOB_MODELS is read on first use, not at import: the fit that writes the file runs
    # jobs through this module, and a run with no model-timed node never needs it.
    if name == "DEFAULT_JOB_MODELS":
        return default_job_models()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def draw_model_us(dist: JobModel, rng: np.random.Generator) -> int:
    """A job's duration in ``model`` timing, simulated microseconds (at least 1): a draw from
    ``rng`` of the normal distribution ``dist`` (``mean_us``, ``sd_us``), clipped at a tenth of
    the mean."""
    draw = rng.normal(dist.mean_us, dist.sd_us) if dist.sd_us else dist.mean_us
    return max(1, int(round(max(draw, dist.mean_us * 0.1))))


# ``wall`` timing: the shortest job, in CFS periods of the node's cgroup, whose wall time says
# something about the node's speed. A job of ideal duration d under a quota of cpus x P per
# period P finishes up to (1 - cpus) x P early (it may run out its quota at full speed and never be
# throttled), so its error is up to (1 - cpus) x P / d: 15% at 0.25 cpus and 5 periods.
WALL_MIN_PERIODS = 5
# ``wall`` timing: how far the cgroup's quota may be from the profile's cpus (rounding of quota_us).
QUOTA_TOLERANCE = 0.02
# A node whose measured speed during the run is this far from the score its durations were scaled
# by is flagged: its compute latencies cannot be trusted (host contention, frequency changes).
DRIFT_LIMIT = 0.10
# How often (simulated time) a node probes its speed during a run, besides at start and finish.
PROBE_PERIOD_US = 10_000_000


class WallTimingRefused(ValueError):
    """``wall`` timing cannot emulate this node: no matching CPU quota, or jobs too short."""


@dataclass(frozen=True)
class CpuQuota:
    """The CFS bandwidth limit of this process's cgroup."""

    quota_us: int
    period_us: int

    @property
    def cpus(self) -> float:
        """The cores the quota amounts to: quota / period."""
        return self.quota_us / self.period_us


CGROUP_ROOT = Path("/sys/fs/cgroup")
SELF_CGROUP = Path("/proc/self/cgroup")


def _own_cgroups(self_cgroup: Path) -> dict[str, str]:
    """Controller (``""`` for cgroup v2) -> this process's cgroup path, from /proc/self/cgroup."""
    out: dict[str, str] = {}
    try:
        text = self_cgroup.read_text()
    except OSError:
        return out
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3:
            for ctrl in parts[1].split(",") if parts[1] else [""]:
                out[ctrl] = parts[2].strip().lstrip("/")
    return out


def read_cpu_quota(root: Path = CGROUP_ROOT, self_cgroup: Path = SELF_CGROUP) -> CpuQuota | None:
    """This process's CPU quota (cgroup v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``), None if none;
    ``root`` is where the cgroup hierarchies are mounted, ``self_cgroup`` the process's cgroup file.

    Inside a container the cgroup is mounted at the root of the hierarchy; on a host it is the
    path /proc/self/cgroup names, so both places are tried, the process's own first."""
    own = _own_cgroups(self_cgroup)
    for base in (root / own.get("", ""), root):
        try:
            quota, period = (base / "cpu.max").read_text().split()
        except (OSError, ValueError):
            continue
        return None if quota == "max" else CpuQuota(int(quota), int(period))
    for mount in (root / "cpu", root / "cpu,cpuacct"):
        for base in (mount / own.get("cpu", ""), mount):
            try:
                quota_us = int((base / "cpu.cfs_quota_us").read_text())
                period_us = int((base / "cpu.cfs_period_us").read_text())
            except (OSError, ValueError):
                continue
            return None if quota_us < 0 else CpuQuota(quota_us, period_us)
    return None


@cache
def cpu_stat_path(root: Path = CGROUP_ROOT, self_cgroup: Path = SELF_CGROUP) -> Path | None:
    """Where this process's cgroup ``cpu.stat`` with throttling counters is (None: nowhere);
    found once, read at every job."""
    own = _own_cgroups(self_cgroup)
    candidates = [root / own.get("", ""), root]
    for mount in (root / "cpu", root / "cpu,cpuacct"):
        candidates += [mount / own.get("cpu", ""), mount]
    for base in candidates:
        try:
            text = (base / "cpu.stat").read_text()
        except OSError:
            continue
        if "throttled_usec" in text or "throttled_time" in text:
            return base / "cpu.stat"
    return None


_stat_fd: dict[Path, int] = {}


def read_cpu_stat() -> dict[str, int] | None:
    """This process's cgroup ``cpu.stat`` (v2: ``throttled_usec``, ``nr_throttled``; v1:
    ``throttled_time`` ns, ``nr_throttled``), None where not visible. The file stays open: a
    re-read from offset 0 costs a few microseconds, an open tens, and nodes read it twice a job."""
    path = cpu_stat_path()
    if path is None:
        return None
    try:
        fd = _stat_fd.get(path)
        if fd is None:
            fd = _stat_fd[path] = os.open(path, os.O_RDONLY)
        text = os.pread(fd, 4096, 0).decode()
    except OSError:
        return None
    stat = {}
    for line in text.splitlines():
        name, _, value = line.partition(" ")
        if value.strip().lstrip("-").isdigit():
            stat[name] = int(value)
    return stat


def read_throttled_ns() -> int | None:
    """Cumulative CPU-quota throttling of this process's cgroup, nanoseconds (None if not
    visible)."""
    stat = read_cpu_stat()
    if stat is None:
        return None
    if "throttled_usec" in stat:
        return stat["throttled_usec"] * 1000
    return stat.get("throttled_time")


def _thread_clock_id(tid: int) -> int:
    """The clock id of another thread's CPU clock (Linux MAKE_THREAD_CPUCLOCK(tid, SCHED)); the
    kernel lets a process read the CPU clocks of its own threads."""
    return ((~tid) << 3) | 4 | 2


def _read_comm(path: str) -> str | None:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return None


@dataclass(frozen=True)
class CpuSample:
    """CPU time a job used, ns: on the thread that ran it and on each library worker thread."""

    own_ns: int
    helpers_ns: tuple[int, ...] = ()

    @property
    def total_ns(self) -> int:
        """CPU time on every thread the job used, nanoseconds."""
        return self.own_ns + sum(self.helpers_ns)

    @property
    def longest_ns(self) -> int:
        """The busiest thread's CPU time, nanoseconds: the job cannot be shorter, however many
        cores."""
        return max((self.own_ns, *self.helpers_ns))


class CpuClock(Protocol):
    """Measures the CPU time of a job run by the calling thread."""

    def start(self) -> Any:
        """Begin measuring a job on the calling thread; returns the token ``stop`` takes."""

    def stop(self, token: Any) -> CpuSample:
        """The CPU time the job used since ``start`` gave ``token``."""


class ThreadCpuClock:
    """The calling thread's CPU clock plus the CPU clocks of the library worker threads.

    Worker threads are the process's unnamed native threads: OpenCV's, ONNX Runtime's and BLAS
    pools start threads that keep the process's name. Runtimes name theirs (zenoh's ``rx-0``,
    ``net-0``, ``app-0``...), and threads started from Python are known to ``threading``: neither
    kind ever counts. A federate runs its pools at the node's cores (one thread where cpus <= 1),
    so on a one-core node the worker threads stay idle and a job's CPU time is its thread's."""

    def __init__(self) -> None:
        self._comm = _read_comm("/proc/self/comm")
        self._runtime: set[int] = set()  # named threads, never a job's
        self._workers: set[int] = set()  # unnamed native threads seen twice
        self._unnamed_once: set[int] = set()  # a new thread may not have named itself yet

    def workers(self) -> list[int]:
        """Thread ids of this process's library worker threads (the caller excluded)."""
        me = threading.get_native_id()
        try:
            tids = [int(t) for t in os.listdir("/proc/self/task")]
        except OSError:
            return []
        python = {t.native_id for t in threading.enumerate()}
        out = []
        for tid in tids:
            if tid == me or tid in self._runtime or tid in python:
                continue
            if tid not in self._workers:
                comm = _read_comm(f"/proc/self/task/{tid}/comm")
                if comm is None:
                    continue  # gone
                if comm != self._comm:
                    self._runtime.add(tid)
                    continue
                if tid in self._unnamed_once:
                    self._workers.add(tid)
                else:
                    self._unnamed_once.add(tid)
            out.append(tid)
        return out

    @staticmethod
    def _thread_ns(tid: int) -> int | None:
        try:
            return time.clock_gettime_ns(_thread_clock_id(tid))
        except OSError:
            return None  # the thread has exited

    def start(self) -> tuple[dict[int, int], int]:
        """The worker threads' CPU clocks and the calling thread's, nanoseconds: the token
        ``stop`` takes."""
        before = {tid: ns for tid in self.workers() if (ns := self._thread_ns(tid)) is not None}
        return before, time.thread_time_ns()

    def stop(self, token: tuple[dict[int, int], int]) -> CpuSample:
        """The CPU time used since ``start`` gave ``token``: the calling thread's, and each
        worker thread's that grew (all of it for a thread started meanwhile)."""
        own = time.thread_time_ns() - token[1]
        before = token[0]
        helpers = []
        for tid in self.workers():
            ns = self._thread_ns(tid)
            if ns is not None and ns > before.get(tid, 0):  # a thread started by the job: all of it
                helpers.append(ns - before.get(tid, 0))
        return CpuSample(own, tuple(helpers))


@dataclass(slots=True)
class JobRecord:
    """One job's timing, simulated microseconds except where named otherwise (``cpu_us`` and
    ``wall_us`` are host time: the job's CPU time on every thread it used, and its wall time;
    ``cpu_us`` is None in ``model`` timing, which draws the duration and reads no CPU clock)."""

    node: str
    kind: str
    arrival_us: int
    start_us: int
    end_us: int
    queue_us: int
    duration_us: int
    cpu_us: int | None
    wall_us: int
    throttled_us: int | None
    timing: str


JOB_RECORD_FIELDS = tuple(f.name for f in fields(JobRecord))


class ComputeNode:
    """The emulated processor of one node.

    ``node``: its name in the records and metrics; ``profile``: its ``cpus`` (reference cores),
    timing mode and ``model_us`` distributions; ``rng``: the stream ``model`` timing draws from.
    ``host`` (this host's score), ``clock`` (the job CPU clock) and ``probe`` (a short speed
    measurement, a score) are injectable; by default the score comes from
    ``host_speed.host_score()`` (``COSIM5G_HOST_SCORE``, the cache or a measurement), only for
    ``cpu`` and ``wall`` timing, and only once a job needs it: a node that never runs one (the
    Edge of a run whose loops are all abstract) measures nothing."""

    def __init__(self, node: str, profile: NodeProfile, rng: np.random.Generator, *,
                 host: HostScore | None = None, clock: CpuClock | None = None,
                 probe: Callable[[], float] | None = None) -> None:
        self.node = node
        self.profile = profile
        self.cores = max(1, math.ceil(profile.cpus))
        self.core_speed = profile.cpus / self.cores  # reference cores per emulated core
        self._free_at = [0] * self.cores
        self._series: dict[str, tuple[Any, ...]] = {}
        # Per job kind, what ``publish_metrics`` moves into the series: durations, queueing
        # delays, CPU and throttled time (s; throttled only where the cgroup is read).
        self._unpublished: dict[str, tuple[list[float], list[float], list[float], list[float]]] = {}
        # Where the node enters itself at its first job since it last published (``watch``): a
        # federate holding hundreds of nodes publishes only those that ran.
        self._ran: list[ComputeNode] | None = None
        self._announced = False
        self._job_models: dict[str, JobModel] = {}
        self._rng = rng
        self.records: list[JobRecord] = []
        self.measured = profile.timing != "model"
        # Throttling only matters to a job whose duration is measured: a drawn one never reads it.
        self._cgroup_visible = self.measured and read_throttled_ns() is not None
        self.quota: CpuQuota | None = None
        self.probes: list[tuple[int, float]] = []  # the first is taken at the first job
        self._probe_fn = probe or host_speed.probe
        self._next_probe_us = 0
        self._host = host
        self._scale: float | None = None if self.measured else 1.0
        if self.measured:
            self._clock: CpuClock = clock or ThreadCpuClock()
            self.reference = host_speed.reference()

    @property
    def host(self) -> HostScore:
        """This host's score (measured at the first use unless given or cached)."""
        if self._host is None:
            self._host = host_speed.host_score()
        return self._host

    @property
    def scale(self) -> float:
        """Reference cores per host core: what a measured duration is multiplied by (1 in
        ``model`` timing)."""
        if self._scale is None:
            self._scale = self.host.score / self.reference.score
        return self._scale

    @property
    def free_us(self) -> int:
        """When the node's first core is free, simulated microseconds: a job arriving then or
        later starts as it arrives."""
        return min(self._free_at)

    @property
    def threads(self) -> int:
        """Threads a job's library pools may use: the node's emulated cores."""
        return self.cores

    def run(self, kind: str, arrival_us: int, fn: Callable[..., T], *args: Any) -> tuple[T, int]:
        """Run ``fn(*args)`` now (for real) as a job of ``kind`` (``compress``, ``pose``...)
        arriving at ``arrival_us``, simulated microseconds; returns its result and the simulated
        time, microseconds, at which it is done. ``WallTimingRefused`` where ``wall`` timing
        cannot emulate it."""
        if self.profile.timing == "wall" and self.quota is None:
            # Checked at the first job rather than at start: a window's error reaches the run's
            # reason, a failed start only the federate's log.
            self.quota = self._wall_quota()
        core = 0 if self.cores == 1 else min(range(self.cores), key=self._free_at.__getitem__)
        start = max(arrival_us, self._free_at[core])
        throttled = None
        cpu_ns: int | None
        if self.measured:
            throttled0 = read_throttled_ns() if self._cgroup_visible else None
            token = self._clock.start()
            wall0 = time.perf_counter_ns()
            result = fn(*args)
            wall_ns = max(1, time.perf_counter_ns() - wall0)
            cpu = self._clock.stop(token)
            if throttled0 is not None:
                after = read_throttled_ns()
                throttled = None if after is None else (after - throttled0) // 1000
            cpu_ns = cpu.total_ns
            duration = self._measured_duration_us(kind, cpu, wall_ns)
        else:
            # The duration is drawn. The wall time is kept for information; the thread's CPU
            # time is not read: a syscall (microseconds) on each of thousands of jobs a simulated
            # second, for a number the job's duration does not use.
            wall0 = time.perf_counter_ns()
            result = fn(*args)
            cpu_ns = None
            wall_ns = max(1, time.perf_counter_ns() - wall0)
            duration = draw_model_us(self._job_model(kind), self._rng)
        end = start + duration
        self._free_at[core] = end
        pending = self._unpublished.get(kind)
        if pending is None:
            pending = self._unpublished[kind] = ([], [], [], [])
        if not self._announced and self._ran is not None:
            self._announced = True
            self._ran.append(self)
        pending[0].append(duration / 1e6)
        pending[1].append((start - arrival_us) / 1e6)
        if cpu_ns is not None:
            pending[2].append(cpu_ns / 1e9)
        if throttled is not None:  # zero too: a node inside its cgroup shows a flat line, not none
            pending[3].append(max(0, throttled) / 1e6)
        self.records.append(JobRecord(
            node=self.node, kind=kind, arrival_us=arrival_us, start_us=start, end_us=end,
            queue_us=start - arrival_us, duration_us=duration, cpu_us=None if cpu_ns is None else cpu_ns // 1000,
            wall_us=wall_ns // 1000, throttled_us=throttled, timing=self.profile.timing,
        ))
        if self.measured and arrival_us >= self._next_probe_us:
            self._probe(arrival_us)
        return result, end

    def watch(self, ran: list[ComputeNode]) -> None:
        """Append this node to ``ran`` at its first job after each ``publish_metrics``."""
        self._ran = ran

    def publish_metrics(self) -> None:
        """Move the jobs run since the last call into the metric series, a kind at a time (the
        federate calls it every 100 simulated ms at most: a lock per series, not per job and
        series)."""
        self._announced = False
        for kind, (durations, queues, cpu, throttled) in self._unpublished.items():
            if not durations:
                continue
            series = self._series.get(kind)
            if series is None:
                labels = (self.node, kind)
                series = self._series[kind] = (metrics.JOB_DURATION.labels(*labels),
                                               metrics.JOB_QUEUE.labels(*labels),
                                               metrics.JOB_CPU.labels(*labels),
                                               metrics.JOB_THROTTLED.labels(*labels))
            metrics.observe_all(series[0], durations)
            metrics.observe_all(series[1], queues)
            series[2].inc(sum(cpu))
            if throttled:
                series[3].inc(sum(throttled))
            for values in (durations, queues, cpu, throttled):
                values.clear()

    def cpu_duration_us(self, cpu: CpuSample) -> float:
        """A job's duration on this node in host time, microseconds, from its CPU time ``cpu``:
        over the node's speed, spread over the threads it used but no more than the node's cores."""
        return max(cpu.longest_ns, cpu.total_ns / self.cores) / 1000 / self.core_speed

    def _job_model(self, kind: str) -> JobModel:
        """The distribution ``model`` timing draws a ``kind`` job's duration from: the profile's
        ``model_us`` (absolute), else the fitted model at the node's cpus."""
        dist = self._job_models.get(kind)
        if dist is None:
            dist = self.profile.model_us.get(kind)
            if dist is None:  # the fitted models are read only when the profile gives none
                fitted = fitted_job_models()
                if kind not in fitted:
                    raise KeyError(
                        f"{self.node}: timing 'model' needs nodes.<node>.model_us.{kind} "
                        f"(has: {sorted(self.profile.model_us)}; fitted kinds: {sorted(fitted)})"
                    )
                dist = fitted[kind].at(self.profile.cpus)
            self._job_models[kind] = dist
        return dist

    def _measured_duration_us(self, kind: str, cpu: CpuSample, wall_ns: int) -> int:
        """A job's duration in ``cpu`` or ``wall`` timing."""
        mode = self.profile.timing
        ideal_us = self.cpu_duration_us(cpu)
        if mode == "wall":
            assert self.quota is not None
            shortest_us = WALL_MIN_PERIODS * self.quota.period_us
            if ideal_us < shortest_us:
                raise WallTimingRefused(
                    f"{self.node}: timing 'wall' refused for {kind!r} jobs: this one takes "
                    f"{ideal_us / 1000:.2f} ms at cpus={self.profile.cpus} (CPU {cpu.total_ns / 1e6:.2f} ms, "
                    f"wall {wall_ns / 1e6:.2f} ms), shorter than {WALL_MIN_PERIODS} CFS periods of "
                    f"{self.quota.period_us / 1000:g} ms ({shortest_us / 1000:g} ms): a job that short "
                    "finishes inside a period's quota without being throttled, so its wall time does "
                    "not show the node's speed; use timing 'cpu' (the default) or 'model'")
            return max(1, int(round(wall_ns / 1000 * self.scale)))
        return max(1, int(round(ideal_us * self.scale)))

    def _wall_quota(self) -> CpuQuota:
        quota = read_cpu_quota()
        cpus = self.profile.cpus
        if quota is None:
            raise WallTimingRefused(
                f"{self.node}: timing 'wall' needs the node inside a CPU-limited cgroup (the docker "
                f"runtime makes one from the profile's cpus); none is visible here, so wall time "
                f"would not show cpus={cpus}: use timing 'cpu' (the default) or 'model'")
        if abs(quota.cpus - cpus) > QUOTA_TOLERANCE * cpus:
            raise WallTimingRefused(
                f"{self.node}: timing 'wall' needs the cgroup's CPU quota to match cpus={cpus}, "
                f"but it gives {quota.cpus:.3f} cpus ({quota.quota_us} us per {quota.period_us} us "
                "period): use timing 'cpu' (the default) or run the node in the docker runtime")
        return quota

    def _probe(self, t_us: int) -> None:
        self.probes.append((t_us, float(self._probe_fn())))
        self._next_probe_us = t_us + PROBE_PERIOD_US

    def speed_summary(self, t_us: int | None = None) -> dict[str, Any]:
        """The node's speed for the run's KPIs: the score its durations were scaled by, the
        reference, the scale, the speed probed during the run (a last probe at ``t_us``,
        simulated microseconds, if none was taken then) and whether it drifted more than
        ``DRIFT_LIMIT`` (then its compute latencies are suspect)."""
        if not self.measured:
            return {"timing": "model", "host_independent": True}
        if not self.probes:  # no job ran: no duration was scaled, the host was never scored
            return {"timing": self.profile.timing, "cpus": self.profile.cpus, "jobs": 0}
        if t_us is not None and self.probes[-1][0] < t_us:
            self._probe(t_us)
        scores = [s for _, s in self.probes]
        ratios = [s / self.host.score for s in scores]
        worst = max(ratios, key=lambda r: abs(r - 1.0))
        flagged = abs(worst - 1.0) > DRIFT_LIMIT
        out: dict[str, Any] = {
            "timing": self.profile.timing,
            "cpus": self.profile.cpus,
            "host_score": round(self.host.score, 2),
            "host_score_source": self.host.source,
            "host_score_measured_at": self.host.measured_at,
            "cpu_model": self.host.env.get("cpu_model") or host_speed.cpu_model(),
            "reference_score": round(self.reference.score, 2),
            "reference_cpu_model": self.reference.env.get("cpu_model", ""),
            "scale": round(self.scale, 4),
            "run_score_median": round(statistics.median(scores), 2),
            "run_score_min": round(min(scores), 2),
            "run_score_max": round(max(scores), 2),
            "drift": round(worst - 1.0, 4),
            "drift_limit": DRIFT_LIMIT,
            "flagged": flagged,
            "probes": [[t, round(s, 2)] for t, s in self.probes],
        }
        if flagged:
            out["warning"] = (
                f"{self.node}: speed during the run {worst - 1.0:+.0%} from the score its durations "
                f"were scaled by ({self.host.score:.1f}): the host was contended or changed speed; "
                "this run's compute latencies of this node cannot be trusted")
        return out

    def add_record_columns(self, columns: dict[str, list[Any]]) -> None:
        """Append the records' fields to ``columns`` (a list per field, made if missing): a node
        writes thousands of records a simulated second, so they reach the table a column at a
        time, with no dict per record."""
        records = self.records
        for name in JOB_RECORD_FIELDS:
            columns.setdefault(name, []).extend([getattr(r, name) for r in records])
