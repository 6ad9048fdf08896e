"""Pure parts of the docker runtime (no daemon needed): limits, exit reasons, run owners."""

from __future__ import annotations

import os
import socket

import pytest

from coordinator.docker_limits import cfs_quota_us, cgroup_limits
from coordinator.docker_runs import _owner_alive, owner_id
from coordinator.launcher import NodeLimits
from coordinator.runtime_docker import _exit_reason


def test_cgroup_limits_of_a_wall_timed_node_are_its_quota() -> None:
    assert cgroup_limits(NodeLimits(cpus=0.25, mem_mb=512, timing="wall")) == {
        "cpu_period": 10_000, "cpu_quota": 2_500, "mem_limit": "512m", "memswap_limit": "512m"}
    assert cgroup_limits(NodeLimits()) == {}
    assert cfs_quota_us(1.5) == 15_000


@pytest.mark.parametrize(("cpus", "cores"), [(0.25, 1), (1.0, 1), (1.5, 2)])
@pytest.mark.parametrize("timing", ["cpu", "model"])
def test_cpu_and_model_timed_nodes_get_whole_cores_never_throttled_mid_job(
        cpus: float, cores: int, timing: str) -> None:
    """Their durations come from CPU time (or a draw): a fractional quota would only add the
    cost of resuming on a cold core to the CPU time it measures."""
    kw = cgroup_limits(NodeLimits(cpus=cpus, timing=timing))
    assert kw == {"cpu_period": 10_000, "cpu_quota": cores * 10_000}


@pytest.mark.parametrize("cpus", [0.0, -1.0, 0.05])
def test_unusable_cpus_are_refused_with_the_reason(cpus: float) -> None:
    with pytest.raises(ValueError, match="cpus"):
        cgroup_limits(NodeLimits(cpus=cpus, timing="wall"))


def test_exit_reasons() -> None:
    assert _exit_reason({"ExitCode": 0}, None) == "exited with code 0"
    assert _exit_reason({"ExitCode": 137}, None) == "exited with code 137 (killed by SIGKILL)"
    oom = _exit_reason({"ExitCode": 137, "OOMKilled": True}, NodeLimits(mem_mb=64))
    assert oom == "exited with code 137 (OOM-killed: memory limit of 64 MiB exceeded)"


def test_owner_liveness() -> None:
    me = owner_id()
    assert me.startswith(f"{socket.gethostname()}/{os.getpid()}/")
    assert _owner_alive(me, [])
    host, pid, ticks = me.split("/")
    assert not _owner_alive(f"{host}/{pid}/{int(ticks) + 1}", [])  # pid reused by another process
    assert not _owner_alive(f"{host}/999999999/1", [])
    assert _owner_alive("0123456789ab/1/5", ["0123456789abcdef"])  # coordinator container runs
    assert not _owner_alive("0123456789ab/1/5", [])
    assert not _owner_alive("garbage", [])
