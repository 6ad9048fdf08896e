"""Edges in a hall of several gNBs, end to end: factory_small with an Edge per gNB and with one
central Edge behind a backhaul, in the process runtime with model timing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support import MODEL_TIMING_SETS

from coordinator.run import execute_run
from domain.edges import EDGE_FILE
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
FACTORY_SMALL = Path(__file__).parents[2] / "configs" / "scenarios" / "factory_small.yaml"
SMOKE = FACTORY_SMALL.with_name("smoke.yaml")


def run_factory(tmp_path: Path, placement: str) -> tuple[dict, dict]:
    sc = load_scenario(FACTORY_SMALL, ["duration_s=2", f"edge.placement={placement}",
                                       *MODEL_TIMING_SETS])
    result = execute_run(sc, tmp_path / placement)
    assert result.status == "completed", result.reason
    plan = json.loads((result.run_dir / EDGE_FILE).read_text())
    return result.kpis["federates"]["loops"]["edges"], plan


def test_factory_small_runs_with_an_edge_per_gnb_and_with_a_central_edge(tmp_path: Path) -> None:
    per, plan = run_factory(tmp_path, "per_gnb")
    # One Edge per gNB serving cameras, each with the loops whose camera it serves and levels
    # of its own: the gNBs carry different loads, so their Edges see different queueing delays.
    assert per["placement"] == "per_gnb" and per["backhaul_ms"] == 0
    assert set(per["edges"]) == set(plan["edges"]) and len(per["edges"]) == 4
    for name, edge in per["edges"].items():
        assert edge["loops_here"] == plan["edges"][name] and edge["loops"] == len(plan["edges"][name])
        assert edge["gnbs"] == [int(name.removeprefix("gnb"))]
        assert edge["mean_pdp"] is not None
    assert len({e["mean_queueing_delay_s"] for e in per["edges"].values()}) > 1
    assert set(per["gnbs"]) == set(per["edges"])

    central, plan = run_factory(tmp_path, "central")
    assert central["placement"] == "central" and central["backhaul_ms"] == 1.0
    assert list(central["edges"]) == ["central"] and plan["edges"] == {"central": list(range(40))}
    assert central["edges"]["central"]["gnbs"] == [0, 1, 2, 3]
    assert set(central["gnbs"]) == set(per["gnbs"])  # the PDP is still reported per gNB


def test_the_detailed_and_the_abstract_loops_of_one_edge_see_one_load_control(tmp_path: Path) -> None:
    # One detailed loop beside five abstract ones, all at gNB 0's Edge: its two federates fold
    # the same counts every period, so they report the same levels over the run.
    sc = load_scenario(Path(__file__).parents[2] / "configs" / "scenarios" / "co_design.yaml",
                       ["duration_s=2", "loops=6", "detailed_loops=1", *MODEL_TIMING_SETS])
    result = execute_run(sc, tmp_path / "shared")
    assert result.status == "completed", result.reason
    feds = result.kpis["federates"]
    detailed, abstract = feds["edge"]["edges"]["edges"]["gnb0"], feds["loops"]["edges"]["edges"]["gnb0"]
    assert (detailed["loops_here"], abstract["loops_here"]) == ([0], [1, 2, 3, 4, 5])
    levels = ("mean_fill", "mean_cap", "mean_queueing_delay_s", "mean_served", "fill", "cap",
              "queueing_delay_s", "frame_loss", "served")
    assert {k: detailed[k] for k in levels} == {k: abstract[k] for k in levels}
    assert detailed["mean_cap"] < 1.0  # the slow start: levels that moved


def test_the_abstract_loops_of_an_edge_queue_on_one_node_when_its_compute_is_shared(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    # Eight loops at PDP 1 on an Edge of half a reference core: each loop's poses (8.3 ms, 30 a
    # second) fit a node of its own, the eight together (2 cores' worth) do not fit one.
    base = ["loops=8", "detailed_loops=0", "duration_s=2", "policy.name=none", "nodes.edge.cpus=0.5",
            *MODEL_TIMING_SETS]
    queues = {}
    for compute in ("per_loop", "shared"):
        result = execute_run(load_scenario(SMOKE, [*base, f"edge.abstract_compute={compute}"]), tmp_path)
        assert result.status == "completed", result.reason
        jobs = pq.read_table(result.run_dir / "jobs.parquet").to_pylist()
        poses = [j for j in jobs if j["kind"] == "pose"]
        queues[compute] = ({j["node"] for j in poses}, max(j["queue_us"] for j in poses))
    assert queues["per_loop"][0] == {"edge"} and queues["per_loop"][1] < 1_000
    [node] = queues["shared"][0]
    assert node.startswith("edge-") and queues["shared"][1] > 100_000, queues


def test_an_edge_keeping_each_loops_newest_frame_never_falls_behind(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    # The eight loops above at PDP 1 (240 frames a second for a node that estimates 120): with
    # `newest` a frame waits for the frames of the other loops in line at most, and the older
    # frame of a loop still waiting is dropped.
    sets = ["loops=8", "detailed_loops=0", "duration_s=2", "policy.name=none", "nodes.edge.cpus=0.5",
            "edge.abstract_compute=shared", "edge.pose_queue=newest", *MODEL_TIMING_SETS]
    result = execute_run(load_scenario(SMOKE, sets), tmp_path)
    assert result.status == "completed", result.reason
    jobs = pq.read_table(result.run_dir / "jobs.parquet").to_pylist()
    poses = [j for j in jobs if j["kind"] == "pose"]
    busy = sum(j["duration_us"] for j in poses) / 2e6
    assert max(j["queue_us"] for j in poses) < 8 * 8_300 + 2_000, max(j["queue_us"] for j in poses)
    assert busy > 0.9, busy  # the node estimates without pause
    loops = result.kpis["federates"]["loops"]
    # About half the frames are dropped: what arrives beyond the node's 120 a second.
    assert 0.3 < loops["frames_superseded"] / loops["frames_kept"] < 0.7, loops


def test_the_load_control_reads_a_shared_edges_compute_queue(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    # The eight loops above with a co-design policy: their frames count for the load as their
    # estimates are ready, so the pose queue shows as queueing delay and the cap comes down until
    # the node keeps up, where PDP 1 lets the queue grow for the whole run.
    sets = ["loops=8", "detailed_loops=0", "duration_s=3", "policy.name=heuristic", "nodes.edge.cpus=0.5",
            "edge.abstract_compute=shared", *MODEL_TIMING_SETS]
    result = execute_run(load_scenario(SMOKE, sets), tmp_path)
    assert result.status == "completed", result.reason
    edge = result.kpis["federates"]["loops"]["edges"]["edges"]["gnb0"]
    jobs = pq.read_table(result.run_dir / "jobs.parquet").to_pylist()
    late = [j["queue_us"] for j in jobs if j["kind"] == "pose" and j["start_us"] > 2_000_000]
    assert edge["cap"] < 0.8, edge
    assert late and max(late) < 100_000, max(late)
