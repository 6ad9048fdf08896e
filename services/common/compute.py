"""Compute emulation (DESIGN 5): a node runs its jobs for real, one at a time per emulated core,
and each job's emulated duration comes from the node's timing mode.

- ``wall``: the job's wall-clock duration (meaningful inside a CPU-limited cgroup);
- ``cpu``: CPU time consumed / per-core speed, divided by the parallelism the job really used
  (capped by the node's cores) -- insensitive to what else the host runs;
- ``model``: a seeded draw from the configured distribution -- deterministic.

A job arriving at simulated time t starts at max(t, earliest free core) and its outputs are due
at start + duration. Per job we keep queueing delay, emulated duration, CPU time, wall time and,
where the cgroup exposes it, the CPU time the kernel throttled the node for.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from services.common import metrics
from services.common.scenario import JobModel, NodeProfile

T = TypeVar("T")

# cgroup v2 then v1 files that count the time the node was throttled by its CPU quota.
_THROTTLE_FILES = (
    (Path("/sys/fs/cgroup/cpu.stat"), "throttled_usec", 1_000),
    (Path("/sys/fs/cgroup/cpu/cpu.stat"), "throttled_time", 1),
    (Path("/sys/fs/cgroup/cpu,cpuacct/cpu.stat"), "throttled_time", 1),
)


def read_throttled_ns() -> int | None:
    """Cumulative CPU-quota throttling of this process's cgroup, ns (None if not visible)."""
    for path, field, scale in _THROTTLE_FILES:
        try:
            for line in path.read_text().splitlines():
                name, _, value = line.partition(" ")
                if name == field:
                    return int(value) * scale
        except OSError:
            continue
    return None


# Emulated durations of the platform's jobs when a profile gives none: cpu-mode medians of the
# smoke scenario (424x240 frames; camera 0.25, Edge 1.0, robot 0.25 cpus), rounded up. compress:
# JPEG + decimated delta-zlib depth; pose: decode + the learned estimator (docs/perception.md).
DEFAULT_JOB_MODELS = {
    "compress": JobModel(mean_us=5_000, sd_us=800),
    "pose": JobModel(mean_us=4_000, sd_us=500),
    "policy": JobModel(mean_us=50, sd_us=10),
    "control": JobModel(mean_us=1_600, sd_us=300),
}


@dataclass(slots=True)
class JobRecord:
    """One job's timing, simulated microseconds except where named otherwise."""

    node: str
    kind: str
    arrival_us: int
    start_us: int
    end_us: int
    queue_us: int
    duration_us: int
    cpu_us: int
    wall_us: int
    throttled_us: int | None
    timing: str


class ComputeNode:
    """The emulated processor of one node."""

    def __init__(self, node: str, profile: NodeProfile, rng: np.random.Generator) -> None:
        self.node = node
        self.profile = profile
        self.cores = max(1, math.ceil(profile.cpus))
        self.core_speed = profile.cpus / self.cores  # fraction of a host core per emulated core
        self._free_at = [0] * self.cores
        self._rng = rng
        self._cgroup_visible = read_throttled_ns() is not None
        self.records: list[JobRecord] = []

    def run(self, kind: str, arrival_us: int, fn: Callable[..., T], *args: Any) -> tuple[T, int]:
        """Run ``fn(*args)`` now (for real) as a job arriving at ``arrival_us``; returns its result
        and the simulated time at which it is done."""
        core = min(range(self.cores), key=lambda c: self._free_at[c])
        start = max(arrival_us, self._free_at[core])
        throttled0 = read_throttled_ns() if self._cgroup_visible else None
        cpu0, wall0 = time.process_time_ns(), time.perf_counter_ns()
        result = fn(*args)
        cpu_ns = time.process_time_ns() - cpu0
        wall_ns = max(1, time.perf_counter_ns() - wall0)
        throttled = None
        if throttled0 is not None:
            after = read_throttled_ns()
            throttled = None if after is None else (after - throttled0) // 1000
        duration = self._duration_us(kind, cpu_ns, wall_ns)
        end = start + duration
        self._free_at[core] = end
        labels = (self.node, kind)
        metrics.JOB_DURATION.labels(*labels).observe(duration / 1e6)
        metrics.JOB_QUEUE.labels(*labels).observe((start - arrival_us) / 1e6)
        metrics.JOB_CPU.labels(*labels).inc(cpu_ns / 1e9)
        if throttled is not None:  # zero too: a node inside its cgroup shows a flat line, not none
            metrics.JOB_THROTTLED.labels(*labels).inc(max(0, throttled) / 1e6)
        self.records.append(JobRecord(
            node=self.node, kind=kind, arrival_us=arrival_us, start_us=start, end_us=end,
            queue_us=start - arrival_us, duration_us=duration, cpu_us=cpu_ns // 1000,
            wall_us=wall_ns // 1000, throttled_us=throttled, timing=self.profile.timing,
        ))
        return result, end

    def _duration_us(self, kind: str, cpu_ns: int, wall_ns: int) -> int:
        mode = self.profile.timing
        if mode == "model":
            dist = self.profile.model_us.get(kind) or DEFAULT_JOB_MODELS.get(kind)
            if dist is None:
                raise KeyError(
                    f"{self.node}: timing 'model' needs nodes.<node>.model_us.{kind} "
                    f"(has: {sorted(self.profile.model_us)})"
                )
            draw = self._rng.normal(dist.mean_us, dist.sd_us) if dist.sd_us else dist.mean_us
            return max(1, int(round(max(draw, dist.mean_us * 0.1))))
        if mode == "wall":
            return max(1, wall_ns // 1000)
        parallelism = min(max(cpu_ns / wall_ns, 1.0), self.cores)
        return max(1, int(round(cpu_ns / 1000 / self.core_speed / parallelism)))

    def record_dicts(self) -> list[dict[str, Any]]:
        return [asdict(r) for r in self.records]
