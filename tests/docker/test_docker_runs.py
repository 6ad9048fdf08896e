"""Whole runs in the docker runtime: the 2-loop smoke scenario in containers with their node
profiles' cgroup limits, and a killed container failing its run quickly and leaving nothing."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytest

from coordinator.conductor import Progress
from coordinator.docker_runs import LABEL_RUN
from coordinator.run import execute_run
from coordinator.runtime_docker import DockerLauncher
from scenario.schema import load_scenario

pytestmark = pytest.mark.docker
SMOKE = Path(__file__).parents[2] / "configs" / "scenarios" / "smoke.yaml"
MIB = 1024 * 1024


def leftovers(client: Any, run_id: str) -> list[str]:
    selector = {"label": f"{LABEL_RUN}={run_id}"}
    return ([c.name for c in client.containers.list(all=True, filters=selector)]
            + [n.name for n in client.networks.list(filters=selector)]
            + [v.name for v in client.volumes.list(filters=selector)])


def test_smoke_runs_in_containers_with_the_camera_profile_limits(docker_client: Any, tmp_path: Path) -> None:
    sc = load_scenario(SMOKE, ["runtime=docker", "duration_s=6"])
    launcher = DockerLauncher(docker_client)
    inspected: dict[str, Any] = {}

    def on_progress(p: Progress) -> None:
        if not inspected:
            inspected.update(docker_client.api.inspect_container(launcher.container("camera-0").id))

    result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
    assert result.status == "completed", (result.reason, result.kpis.get("log_tail"))
    assert result.kpis["tasks"] >= 2 and result.kpis["ul_packets"] > 0 and result.kpis["dl_packets"] > 0
    host = inspected["HostConfig"]
    profile = sc.nodes.camera
    assert host["CpuPeriod"] == 10_000
    # A cpu-timed node (the default) gets whole cores: its durations come from CPU time.
    assert profile.timing == "cpu"
    assert host["CpuQuota"] == math.ceil(profile.cpus) * 10_000
    assert host["Memory"] == profile.mem_mb * MIB
    assert not host["CapAdd"] and host["CapDrop"] == ["ALL"]
    assert host["Privileged"] is False and host["ReadonlyRootfs"] is True
    assert inspected["Config"]["Labels"][LABEL_RUN] == result.run_id
    assert not leftovers(docker_client, result.run_id)


def test_killing_a_run_container_fails_the_run_within_15_s(docker_client: Any, tmp_path: Path) -> None:
    sc = load_scenario(SMOKE, ["runtime=docker", "duration_s=30"])
    launcher = DockerLauncher(docker_client)
    struck: dict[str, float] = {}

    def on_progress(p: Progress) -> None:
        if p.t_us > 300_000 and not struck:
            launcher.container("edge").kill()
            struck["at"] = time.monotonic()

    result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
    elapsed = time.monotonic() - struck["at"]
    assert result.status == "failed" and result.kpis["failed_federate"] == "edge"
    assert elapsed < 15
    assert not leftovers(docker_client, result.run_id)
