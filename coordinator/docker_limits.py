"""A node profile as a container's cgroup limits, and the container's CFS counters read back from
the host side (docs/architecture.md sec. 5, docs/compute.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from coordinator.launcher import NodeLimits

CFS_PERIOD_US = 10_000
# The kernel refuses a CFS quota below 1 ms: at a 10 ms period the smallest node is 0.1 cpus.
CFS_MIN_QUOTA_US = 1_000


def cfs_quota_us(cpus: float, period_us: int = CFS_PERIOD_US) -> int:
    """The CFS quota (us per ``period_us``) that gives ``cpus`` host cores."""
    if cpus <= 0:
        raise ValueError(f"cpus must be > 0, got {cpus}")
    quota = int(round(cpus * period_us))
    if quota < CFS_MIN_QUOTA_US:
        raise ValueError(
            f"cpus={cpus} gives a CFS quota of {quota} us per {period_us} us period, below the "
            f"kernel's minimum of {CFS_MIN_QUOTA_US} us: use cpus >= "
            f"{CFS_MIN_QUOTA_US / period_us:g}"
        )
    return quota


def cpu_limit_cores(limits: NodeLimits) -> float | None:
    """The CPU the container may use, in host cores (None: unlimited).

    A ``wall``-timed node is its quota: cpus x period, so a job's wall time is the emulation.
    A ``cpu``- or ``model``-timed node takes its durations from the job's own CPU time (or a
    draw), so a fractional quota would only stretch the wall clock -- and cost CPU time: a job
    throttled in mid-run resumes on a core that slept (caches and branch predictors cold, the
    core clocked down), measured on this platform's 2-core VM as 1.18-1.42x the CPU time of the
    same loop on a busy core (``make calibrate``, idle-wake penalty), which is exactly the error
    ``cpu`` timing is there to avoid. Such a node gets whole cores instead: ceil(cpus), which
    still bounds how many threads it runs in parallel."""
    if limits.cpus is None:
        return None
    if limits.timing == "wall":
        return limits.cpus
    return float(math.ceil(limits.cpus))


def cgroup_limits(limits: NodeLimits) -> dict[str, Any]:
    """docker SDK ``containers.run`` keyword arguments for a node profile."""
    kw: dict[str, Any] = {}
    cores = cpu_limit_cores(limits)
    if cores is not None:
        kw["cpu_period"] = CFS_PERIOD_US
        kw["cpu_quota"] = cfs_quota_us(cores)
    if limits.mem_mb is not None:
        if limits.mem_mb < 6:
            raise ValueError(f"mem_mb={limits.mem_mb}: docker needs at least 6 MiB")
        kw["mem_limit"] = f"{limits.mem_mb}m"
        # Same value: no swap on top of the limit, so an over-budget node is OOM-killed (and
        # reported as such) instead of silently slowing down.
        kw["memswap_limit"] = f"{limits.mem_mb}m"
    return kw



@dataclass(frozen=True)
class CpuThrottling:
    """CFS counters of a container: usage and throttling since it started."""

    usage_ns: int  # CPU time consumed by every task of the container
    periods: int  # CFS periods in which the container was runnable
    throttled_periods: int  # periods in which it hit its quota
    throttled_ns: int  # total time its run queues spent throttled


def container_cpu_throttling(container: Any) -> CpuThrottling:
    """Read a container's CFS counters through the daemon (``docker stats``, one shot).

    Works from the host or from the compose coordinator alike and under cgroup v1 and v2: the
    daemon reads cpu.stat (v1: ``throttled_time`` ns, v2: ``throttled_usec``) and reports ns.
    """
    stats = container.stats(stream=False, one_shot=True)
    cpu = stats.get("cpu_stats") or {}
    thr = cpu.get("throttling_data") or {}
    return CpuThrottling(
        usage_ns=int((cpu.get("cpu_usage") or {}).get("total_usage", 0)),
        periods=int(thr.get("periods", 0)),
        throttled_periods=int(thr.get("throttled_periods", 0)),
        throttled_ns=int(thr.get("throttled_time", 0)),
    )
