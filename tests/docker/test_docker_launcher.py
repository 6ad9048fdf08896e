"""DockerLauncher against a real daemon: cgroup limits, hardening, deaths, cleanup, routing.

Federates do not exist yet in every checkout, so most tests start containers through
``DockerLauncher._start`` with a stand-in command; ``test_public_start_runs_services_main``
checks the real command line of the public ``start``.
"""

from __future__ import annotations

import json
import shutil
import socket
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from coordinator.docker_limits import container_cpu_throttling
from coordinator.docker_runs import LABEL_RUN, reap_dead_runs
from coordinator.launcher import FederateSpec, NodeLimits
from coordinator.run import free_port
from coordinator.runtime_docker import DockerLauncher, DockerRuntimeError

pytestmark = pytest.mark.docker

SLEEP = ["python", "-c", "import time; time.sleep(600)"]
MiB = 1024 * 1024


def _wait_for(cond: Callable[[], Any], timeout_s: float = 20.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"condition not met within {timeout_s} s")


def _labelled(client: Any, run_id: str) -> dict[str, list[Any]]:
    selector = {"label": f"{LABEL_RUN}={run_id}"}
    return {
        "containers": client.containers.list(all=True, filters=selector),
        "networks": client.networks.list(filters=selector),
        "volumes": client.volumes.list(filters=selector),
    }


@pytest.fixture
def launcher(docker_client: Any) -> Any:
    la = DockerLauncher(client=docker_client)
    yield la
    la.stop(grace_s=0)


def test_cgroup_limits_and_hardening(launcher: DockerLauncher, run_id: str, tmp_path: Path,
                                     docker_client: Any) -> None:
    spec = FederateSpec("camera-0", "camera", NodeLimits(cpus=0.25, mem_mb=512, timing="wall"))
    launcher._start([spec], run_id, tmp_path, lambda s: SLEEP)
    c = docker_client.containers.get(launcher.container("camera-0").id)
    hc = c.attrs["HostConfig"]
    assert hc["CpuQuota"] == 2500
    assert hc["CpuPeriod"] == 10000
    assert hc["Memory"] == 512 * MiB
    assert hc["MemorySwap"] == 512 * MiB  # no swap on top of the limit
    assert not hc["CapAdd"]
    assert hc["CapDrop"] == ["ALL"]
    assert hc["Privileged"] is False
    assert hc["ReadonlyRootfs"] is True
    assert hc["SecurityOpt"] == ["no-new-privileges"]
    assert "/tmp" in hc["Tmpfs"]
    assert hc["Binds"] == [f"{tmp_path.resolve()}:{tmp_path}:rw"]  # the only host mount
    assert c.attrs["Config"]["User"] not in ("", "0", "root", "0:0")
    assert c.labels[LABEL_RUN] == run_id and c.labels["cosim5g.federate"] == "camera-0"
    assert c.attrs["Config"]["Env"].count("MUJOCO_GL=egl") == 1
    assert set(c.attrs["NetworkSettings"]["Networks"]) == {f"cosim5g-{run_id}"}


def test_filesystem_is_read_only_except_tmp_and_run_dir(launcher: DockerLauncher, run_id: str,
                                                        tmp_path: Path) -> None:
    out = tmp_path / "fs.json"
    code = (
        "import json, os\n"
        "def can_write(p):\n"
        "    try:\n"
        "        open(p, 'w').close(); return True\n"
        "    except OSError:\n"
        "        return False\n"
        f"r = {{'root': can_write('/probe'), 'opt': can_write('/opt/venv/probe'),\n"
        f"     'tmp': can_write('/tmp/probe'), 'uid': os.getuid()}}\n"
        f"open({str(out)!r}, 'w').write(json.dumps(r))\n"
    )
    launcher._start([FederateSpec("fs", "camera")], run_id, tmp_path,
                    lambda s: ["python", "-c", code])
    _wait_for(lambda: "fs" in launcher.dead())
    assert launcher.dead()["fs"].startswith("exited with code 0"), launcher.last_log_lines("fs")
    r = json.loads(out.read_text())
    assert r == {"root": False, "opt": False, "tmp": True, "uid": r["uid"]} and r["uid"] != 0


def test_dead_reports_a_killed_container(launcher: DockerLauncher, run_id: str,
                                         tmp_path: Path) -> None:
    specs = [FederateSpec("robot-0", "robot", NodeLimits(cpus=0.25)),
             FederateSpec("robot-1", "robot", NodeLimits(cpus=0.25))]
    launcher._start(specs, run_id, tmp_path, lambda s: SLEEP)
    assert launcher.dead() == {}
    launcher.container("robot-1").kill()
    dead = _wait_for(launcher.dead)
    assert set(dead) == {"robot-1"}
    assert "exited with code 137" in dead["robot-1"] and "SIGKILL" in dead["robot-1"]


def test_dead_reports_an_oom_kill(launcher: DockerLauncher, run_id: str, tmp_path: Path) -> None:
    hog = ["python", "-c", "x = bytearray(400 * 1024 * 1024); import time; time.sleep(60)"]
    launcher._start([FederateSpec("edge", "edge", NodeLimits(cpus=1.0, mem_mb=64))], run_id,
                    tmp_path, lambda s: hog)
    reason = _wait_for(launcher.dead)["edge"]
    assert "OOM-killed" in reason and "64 MiB" in reason


def test_last_log_lines_survive_stop(launcher: DockerLauncher, run_id: str,
                                     tmp_path: Path) -> None:
    # stdout and stderr are separate streams in docker's log: the pause fixes their order.
    code = ("import sys, time\nfor i in range(50): print('line', i)\nsys.stdout.flush()\n"
            "time.sleep(0.5)\nprint('oops', file=sys.stderr)")
    launcher._start([FederateSpec("netsim", "netsim")], run_id, tmp_path,
                    lambda s: ["python", "-c", code])
    _wait_for(lambda: "netsim" in launcher.dead())
    assert launcher.last_log_lines("netsim", 3) == ["line 48", "line 49", "oops"]
    launcher.stop()
    assert launcher.last_log_lines("netsim", 2) == ["line 49", "oops"]
    assert (tmp_path / "logs" / "netsim.container.log").read_text().endswith("oops\n")


def test_stop_leaves_nothing_and_is_idempotent(docker_client: Any, run_id: str,
                                               tmp_path: Path) -> None:
    la = DockerLauncher(client=docker_client)
    specs = [FederateSpec(f"camera-{i}", "camera", NodeLimits(cpus=0.25, mem_mb=128))
             for i in range(3)]
    la._start(specs, run_id, tmp_path, lambda s: SLEEP)
    found = _labelled(docker_client, run_id)
    assert len(found["containers"]) == 3 and len(found["networks"]) == 1
    la.container("camera-0").kill()
    t0 = time.monotonic()
    la.stop(grace_s=5)
    assert time.monotonic() - t0 < 5, "SIGTERM through tini should end python at once"
    assert _labelled(docker_client, run_id) == {"containers": [], "networks": [], "volumes": []}
    la.stop()  # a second call on another exit path is harmless
    assert la.dead() == {"camera-0": la.dead()["camera-0"]}


def test_failed_start_cleans_up(docker_client: Any, run_id: str, tmp_path: Path) -> None:
    la = DockerLauncher(client=docker_client)
    specs = [FederateSpec("ok", "camera"), FederateSpec("bad", "camera")]

    def command(spec: FederateSpec) -> list[str]:
        if spec.name == "bad":
            raise RuntimeError("boom while preparing the second federate")
        return SLEEP

    with pytest.raises(RuntimeError, match="boom"):
        la._start(specs, run_id, tmp_path, command)
    assert _labelled(docker_client, run_id) == {"containers": [], "networks": [], "volumes": []}


def test_missing_image_is_named(docker_client: Any, run_id: str, tmp_path: Path) -> None:
    la = DockerLauncher(client=docker_client, image="cosim5g/absent:none")
    with pytest.raises(DockerRuntimeError, match=r"image cosim5g/absent:none missing: run `make images`"):
        la._start([FederateSpec("x", "camera")], run_id, tmp_path, lambda s: SLEEP)


def test_public_start_runs_services_main(launcher: DockerLauncher, run_id: str,
                                         tmp_path: Path) -> None:
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text("{}\n")
    spec = FederateSpec("camera-0", "camera", NodeLimits(cpus=0.25, mem_mb=256))
    endpoint = launcher.router_endpoint_for_federates(7447)
    launcher.start([spec], run_id, endpoint, scenario, tmp_path)
    cmd = launcher.container("camera-0").attrs["Config"]["Cmd"]
    assert cmd == ["python", *spec.argv(run_id, endpoint, str(scenario), str(tmp_path))]
    assert cmd[:4] == ["python", "-m", "services.main", "camera"]


def test_scenario_outside_run_dir_is_refused(launcher: DockerLauncher, run_id: str,
                                             tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    with pytest.raises(DockerRuntimeError, match="outside the run directory"):
        launcher.start([FederateSpec("x", "camera")], run_id, "tcp/h:1",
                       tmp_path / "scenario.yaml", tmp_path / "run")


def test_federate_reaches_router_on_host(launcher: DockerLauncher, run_id: str,
                                         tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    from fabric.zenoh_bus import session_config

    port = free_port()  # on the host
    router = zenoh.open(session_config("router", launcher.router_listen_endpoint(port)))
    got: list[bytes] = []
    key = f"cosim/{run_id}/ctl/hello"
    sub = router.declare_subscriber(key, lambda sample: got.append(sample.payload.to_bytes()))
    endpoint = launcher.router_endpoint_for_federates(port)
    code = (
        "import json, time, zenoh\n"
        "c = zenoh.Config()\n"
        "c.insert_json5('mode', '\"client\"')\n"
        "c.insert_json5('scouting/multicast/enabled', 'false')\n"
        f"c.insert_json5('connect/endpoints', json.dumps([{endpoint!r}]))\n"
        "s = zenoh.open(c)\n"
        "for _ in range(300):\n"
        f"    s.put({key!r}, b'hello'); time.sleep(0.1)\n"
    )
    try:
        launcher._start([FederateSpec("camera-0", "camera", NodeLimits(cpus=0.5))], run_id,
                        tmp_path, lambda s: ["python", "-c", code])
        _wait_for(lambda: got or launcher.dead(), timeout_s=30)
        assert got and got[0] == b"hello", (launcher.dead(), launcher.last_log_lines("camera-0"))
    finally:
        sub.undeclare()
        router.close()


def test_reap_dead_runs(docker_client: Any, run_id: str, tmp_path: Path,
                        monkeypatch: pytest.MonkeyPatch) -> None:
    import coordinator.runtime_docker as rd

    live = DockerLauncher(client=docker_client)
    live._start([FederateSpec("a", "camera")], run_id, tmp_path, lambda s: SLEEP)
    orphan_id = f"{run_id}-orphan"
    monkeypatch.setattr(rd, "owner_id", lambda: f"{socket.gethostname()}/999999999/0")
    orphan = DockerLauncher(client=docker_client)
    orphan._start([FederateSpec("a", "camera")], orphan_id, tmp_path, lambda s: SLEEP)
    try:
        reaped = reap_dead_runs(docker_client)
        assert orphan_id in reaped and run_id not in reaped
        assert _labelled(docker_client, orphan_id) == {"containers": [], "networks": [],
                                                        "volumes": []}
        assert len(_labelled(docker_client, run_id)["containers"]) == 1
        assert reap_dead_runs(docker_client, alive_run_ids=[run_id]) == []
    finally:
        live.stop(grace_s=0)
        orphan.stop(grace_s=0)


@pytest.mark.slow
@pytest.mark.parametrize("cpus", [0.25, 0.5])
def test_cfs_wall_time_tracks_quota(launcher: DockerLauncher, run_id: str, tmp_path: Path,
                                    cpus: float) -> None:
    """A ~70 ms CPU-bound job takes about cpu_time / cpus of wall time at a 10 ms CFS period."""
    probe = tmp_path / "cfs_probe.py"
    shutil.copy(Path(__file__).with_name("cfs_probe.py"), probe)
    launcher._start([FederateSpec("probe", "edge", NodeLimits(cpus=cpus, timing="wall"))], run_id, tmp_path,
                    lambda s: ["python", str(probe), "10"])
    reason = _wait_for(lambda: launcher.dead().get("probe"), timeout_s=60)
    assert reason.startswith("exited with code 0"), launcher.last_log_lines("probe")
    result = json.loads(launcher.last_log_lines("probe", 1)[0])
    ratios = [w / (c / cpus) for w, c in zip(result["wall_s"], result["cpu_s"], strict=True)]
    # Loose bounds: the host runs other things; the point is ~1/cpus scaling, not 100 ms bursts.
    assert 0.7 < statistics.median(ratios) < 1.5, ratios


def test_cpu_throttling_counters(launcher: DockerLauncher, run_id: str, tmp_path: Path) -> None:
    busy = ["python", "-c", "while True: pass"]
    launcher._start([FederateSpec("busy", "edge", NodeLimits(cpus=0.25, timing="wall"))], run_id, tmp_path,
                    lambda s: busy)
    c = launcher.container("busy")
    first = _wait_for(lambda: (t := container_cpu_throttling(c)).throttled_periods > 10 and t)
    assert first.usage_ns > 0 and first.periods >= first.throttled_periods
    assert first.throttled_ns > 0
    later = _wait_for(lambda: (t := container_cpu_throttling(c)).periods > first.periods and t)
    # At a quarter of a core a spinning loop is throttled in (nearly) every 10 ms period.
    new = later.periods - first.periods
    assert later.throttled_periods - first.throttled_periods >= 0.8 * new
