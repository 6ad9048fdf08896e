"""The ray runtime on a local Ray cluster (a head and a worker node on this machine): the same trace
hash as the process runtime, also for a run split into netsim partitions spread over both nodes;
a federate whose actor dies, or a node lost with its raylet, fails the run naming it and leaves
no actor, placement group or federate process behind."""

from __future__ import annotations

import os
import signal
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support import MODEL_TIMING_SETS, local_ray_cluster, processes_with

from coordinator.conductor import Progress
from coordinator.run import execute_run, federate_specs, free_port
from interfaces.cli import build_parser
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
SMOKE = ROOT / "configs" / "scenarios" / "smoke.yaml"
FACTORY_SMALL = ROOT / "configs" / "scenarios" / "factory_small.yaml"


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[str]:
    pytest.importorskip("ray")
    # Two CPUs per node: the smoke run's node profiles ask for 2 (edge 1, cameras and robots 0.25).
    with local_ray_cluster(free_port(), 2) as address:
        yield address


@pytest.fixture
def on_cluster(ray_cluster: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """This test process joined to the cluster (the run's launcher then leaves the session open,
    so that what the run left can be looked at); federates spread over both nodes."""
    import ray

    monkeypatch.setenv("COSIM5G_RAY_PLACEMENT", "SPREAD")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ray.init(address=ray_cluster, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def leftovers(ray: Any, run_id: str) -> dict[str, Any]:
    """What of the run is still on the cluster or this host."""
    return {
        "actors": [a for a in ray.util.list_named_actors(all_namespaces=True) if run_id in a["name"]],
        "placement_groups": [pg for pg in ray.util.placement_group_table().values() if pg["state"] != "REMOVED"],
        "processes": processes_with(run_id),
    }


def wait_for_nothing_left(ray: Any, run_id: str, timeout_s: float = 10.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    left = leftovers(ray, run_id)
    while any(left.values()) and time.monotonic() < deadline:
        time.sleep(0.2)
        left = leftovers(ray, run_id)
    return left


def process_then_ray(scenario: Path, sets: list[str], tmp_path: Path) -> tuple[Any, Any]:
    """``scenario`` with ``sets`` run in the process runtime, then on Ray: both completed, with
    one trace hash and one results hash."""
    local = execute_run(load_scenario(scenario, sets), tmp_path / "process")
    assert local.status == "completed", local.reason
    on_ray = execute_run(load_scenario(scenario, [*sets, "runtime=ray"]), tmp_path / "ray")
    assert on_ray.status == "completed", on_ray.reason
    assert on_ray.kpis["trace_hash"] == local.kpis["trace_hash"]
    assert on_ray.kpis["results_hash"] == local.kpis["results_hash"]
    return local, on_ray


def test_ray_runtime_gives_the_process_runtimes_trace_hash(tmp_path: Path, on_cluster: Any) -> None:
    local, on_ray = process_then_ray(SMOKE, ["duration_s=1.5", *MODEL_TIMING_SETS], tmp_path)
    assert on_ray.kpis["tasks"] == local.kpis["tasks"]
    placement = on_ray.kpis["placement"]
    names = {n for s in federate_specs(load_scenario(SMOKE)) for n in s.names}
    assert set(placement) == names, "every federate says where it ran"
    assert placement["physics"]["process"] == "core" and placement["edge"]["cpus_reserved"] == 1.0
    assert len({p["node_id"] for p in placement.values()}) == 2, "SPREAD uses both nodes"
    assert "netsim.federate" in (on_ray.run_dir / "logs" / "core.log").read_text(), "logs in the run directory"
    assert wait_for_nothing_left(on_cluster, on_ray.run_id) == {"actors": [], "placement_groups": [],
                                                                "processes": []}


def test_a_federate_whose_actor_dies_fails_the_run_naming_it_and_leaves_nothing(
        tmp_path: Path, on_cluster: Any) -> None:
    from coordinator.runtime_ray import RayLauncher

    sc = load_scenario(SMOKE, ["duration_s=60", *MODEL_TIMING_SETS, "runtime=ray"])
    launcher = RayLauncher()
    struck: dict[str, float] = {}

    def on_progress(p: Progress) -> None:
        if p.t_us > 300_000 and not struck:
            os.kill(launcher.placement()["edge"]["actor_pid"], signal.SIGKILL)
            struck["at"] = time.monotonic()

    result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
    ended = time.monotonic()
    assert struck, "the run ended before the kill"
    assert result.status == "failed" and result.kpis["failed_federate"] == "edge", result.reason
    assert "edge" in (result.reason or "") and "Ray actor" in (result.reason or "")
    assert ended - struck["at"] < 15.0, "a lost actor fails the run within seconds"
    assert wait_for_nothing_left(on_cluster, result.run_id) == {"actors": [], "placement_groups": [],
                                                                "processes": []}


def test_a_run_the_cluster_cannot_hold_is_refused_before_it_starts(
        tmp_path: Path, ray_cluster: str, on_cluster: Any, capsys: pytest.CaptureFixture[str]) -> None:
    def run(*sets: str) -> tuple[int, str]:
        args = build_parser().parse_args(["run", str(SMOKE), "--set", "runtime=ray", "--address", ray_cluster,
                                          "--results", str(tmp_path), "--quiet",
                                          *(a for s in sets for a in ("--set", s))])
        return int(args.fn(args)), capsys.readouterr().err

    code, err = run("nodes.edge.cpus=3")  # more than any node has
    assert code == 2 and "edge (nodes.edge.cpus = 3) asks 3 CPUs" in err and "largest Ray node has 2" in err
    code, err = run("nodes.camera.cpus=2")  # 5.5 CPUs in all, 4 in the cluster
    assert code == 2 and "ask 5.5 CPUs" in err and "1.5 CPUs missing" in err
    assert list(tmp_path.iterdir()) == [], "no run directory, no federate started"
    assert [pg for pg in on_cluster.util.placement_group_table().values() if pg["state"] != "REMOVED"] == []


def test_a_partitioned_run_spreads_over_the_nodes_with_the_process_runtimes_results(
        tmp_path: Path, on_cluster: Any) -> None:
    _, on_ray = process_then_ray(FACTORY_SMALL, ["duration_s=1", "partitions=2", *MODEL_TIMING_SETS], tmp_path)
    placement = on_ray.kpis["placement"]
    assert placement["netsim-00"]["cpus_reserved"] == placement["netsim-01"]["cpus_reserved"] == 1.0
    assert len({placement[n]["node_id"] for n in ("edge", "netsim-00", "netsim-01")}) == 2, "SPREAD"
    assert wait_for_nothing_left(on_cluster, on_ray.run_id) == {"actors": [], "placement_groups": [],
                                                                "processes": []}


def test_a_lost_node_fails_the_run_within_seconds_naming_it_and_what_it_held(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ray = pytest.importorskip("ray")
    from coordinator.runtime_ray import RayLauncher

    monkeypatch.setenv("COSIM5G_RAY_PLACEMENT", "SPREAD")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    # As on nodes that do not see the run directory: what the lost node streamed is kept.
    monkeypatch.setenv("COSIM5G_RAY_RECORDS", "stream")
    # A cluster of its own: the node lost here does not come back.
    with local_ray_cluster(free_port(), 2) as address:
        ray.init(address=address, log_to_driver=False)
        try:
            head = ray.get_runtime_context().get_node_id()
            sc = load_scenario(FACTORY_SMALL, ["duration_s=60", "partitions=2", *MODEL_TIMING_SETS, "runtime=ray"])
            launcher = RayLauncher()
            struck: dict[str, Any] = {}

            def on_progress(p: Progress) -> None:
                if p.t_us > 2_500_000 and not struck:
                    victim = next(n for n, w in launcher.placement().items() if w["node_id"] != head)
                    node = launcher.placement()[victim]["node_id"]
                    raylets = [pid for pid in processes_with(f"--node_id={node}")
                               if "raylet" in Path(f"/proc/{pid}/cmdline").read_text()]
                    for pid in raylets:
                        os.kill(pid, signal.SIGKILL)
                    struck.update(at=time.monotonic(), node=node, victim=victim, raylets=raylets)

            result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
            ended = time.monotonic()
            assert struck and struck["raylets"], "the run ended before the node was lost"
            assert result.status == "failed", result.reason
            reason = result.reason or ""
            assert struck["node"][:12] in reason and "which held" in reason, reason
            held = [n for n, w in (result.kpis.get("placement") or {}).items() if w["node_id"] == struck["node"]]
            assert held and all(n in reason for n in held), reason
            # Noticed within seconds (lost liveliness tokens, then up to 3 s for the runtime's
            # word); neither the conductor nor the runtime waits on the lost node's federates.
            assert ended - struck["at"] < 10.0, "a lost node fails and ends the run within 10 s"
            # What the lost node streamed before the loss (batches every 2 simulated s) is kept:
            # the run's tables hold it.
            kept = [p for p in result.kpis["recorded"]["parts"] if p["federate"] in held and p["rows"]]
            assert kept and all(p["upto_s"] >= 2.0 and not p["complete"] for p in kept), kept
            left = wait_for_nothing_left(ray, result.run_id)
            assert left["processes"] == [] and left["placement_groups"] == [], left
        finally:
            ray.shutdown()


def test_records_written_on_the_nodes_come_back_through_ray(
        tmp_path: Path, on_cluster: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # As on nodes that do not see the run directory: each federate streams its table parts to the
    # coordinator and writes the rest into a folder of its node, shipped back when the run stops;
    # the run's results are those of the process runtime.
    monkeypatch.setenv("COSIM5G_RAY_RECORDS", "stream")
    local, shipped = process_then_ray(SMOKE, ["duration_s=1.5", *MODEL_TIMING_SETS], tmp_path)
    assert {w["records"] for w in shipped.kpis["placement"].values()} == {"streamed"}
    assert shipped.kpis["recorded"]["rows"] == local.kpis["recorded"]["rows"]
    logs = shipped.run_dir / "logs"
    assert "netsim.federate" in (logs / "core.log").read_text(), "the logs came back too"
    assert not list(Path(tempfile.gettempdir()).glob("cosim5g-run-*")), "the nodes' folders are removed"
    assert wait_for_nothing_left(on_cluster, shipped.run_id) == {"actors": [], "placement_groups": [],
                                                                 "processes": []}
