"""Edges in a hall of several gNBs: which Edge serves each loop (per gNB or central), the
association resolved with netsim's numbers, each Edge's own load control, and the backhaul delay
of a central Edge on the uplink and the downlink (docs/architecture.md sec. 7, "Edges")."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from coordinator.edges import provide_edge_plan, resolve_plan, serving_gnbs
from domain.edge_side import CoDesign, Edges
from domain.edges import EDGE_FILE, load_plan, make_plan, single_gnb_plan, write_plan
from domain.frame_model import RUN_FILE, camera_settings
from domain.tracker import Tracker
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.federate import NEVER_US, FederateContext
from fabric.messages import Advance, Message
from netsim.federate import make_cell
from scenario.schema import Scenario, ScenarioError, load_scenario, parse_scenario
from services.loops.federate import LOST_FRAME_US, LoopsFederate
from wire.bodies import Aframe, Packet, Packets, Truth

FACTORY_SMALL = Path(__file__).resolve().parents[2] / "configs" / "scenarios" / "factory_small.yaml"
FRAME_MODEL = Path(__file__).resolve().parents[2] / "domain" / "data" / "frame_model.json"
MODEL = {"cpus": 0.5, "timing": "model"}
W = 1000


def hall_scenario(**edge: Any) -> Scenario:
    """Four abstract loops in a hall of two gNBs (model timing, the heuristic policy, no slow
    start: the Edges' mean levels then tell their cells' loads apart)."""
    return parse_scenario({
        "name": "edges", "seed": 2, "duration_s": 0.5, "loops": 4, "detailed_loops": 0,
        "hall": {"work_cells_per_row": 4, "work_cell_pitch_m": [4.0, 8.0],
                 "inf_layout": {"gnb_count": 2}},
        "policy": {"name": "heuristic", "guard_start_pdp": 1.0}, "edge": edge,
        "nodes": {"camera": MODEL, "edge": MODEL, "robot": MODEL},
    })


# ---- the setting -----------------------------------------------------------------------------------
def test_placement_defaults_to_an_edge_per_gnb_and_the_backhaul_is_checked() -> None:
    sc = parse_scenario({})
    assert (sc.edge.placement, sc.edge.backhaul_ms) == ("per_gnb", 1.0)
    with pytest.raises(ScenarioError) as bad:
        parse_scenario({"edge": {"placement": "central", "backhaul_ms": -1}})
    assert [f for f, _ in bad.value.errors] == ["edge.backhaul_ms"]
    assert "greater than or equal to 0" in bad.value.errors[0][1]
    with pytest.raises(ScenarioError) as bad:
        parse_scenario({"edge": {"placement": "cloud"}})
    assert [f for f, _ in bad.value.errors] == ["edge.placement"]


# ---- grouping ---------------------------------------------------------------------------------------
def test_loops_are_grouped_by_their_cameras_gnb_or_all_at_the_central_edge() -> None:
    per = make_plan(hall_scenario(), [1, 0, 0, 1])
    assert per.groups() == {"gnb1": [0, 3], "gnb0": [1, 2]}
    assert per.groups([2, 3]) == {"gnb0": [2], "gnb1": [3]}
    assert per.backhaul_us == 0  # an Edge at its gNB: no backhaul, whatever backhaul_ms says
    central = make_plan(hall_scenario(placement="central", backhaul_ms=2.5), [1, 0, 0, 1])
    assert central.groups() == {"central": [0, 1, 2, 3]}
    assert central.backhaul_us == 2500
    with pytest.raises(ValueError, match="3 loops"):
        make_plan(hall_scenario(), [0, 1, 0])


def test_one_gnb_gives_one_edge_for_every_loop_without_a_file(tmp_path: Path) -> None:
    sc = parse_scenario({"loops": 3})
    plan = load_plan(sc, tmp_path)  # nothing written: one gNB needs no association
    assert plan == single_gnb_plan(sc) and plan.groups() == {"gnb0": [0, 1, 2]}
    assert plan.backhaul_us == 0
    edges = Edges(sc, plan, range(3))
    assert list(edges.by_edge) == ["gnb0"] and edges[0] is edges[2]
    assert edges[0].loops == CoDesign.for_scenario(sc).loops == 3


def test_several_gnbs_need_the_coordinators_association(tmp_path: Path) -> None:
    sc = hall_scenario()
    with pytest.raises(ValueError, match=EDGE_FILE):
        load_plan(sc, tmp_path)
    write_plan(make_plan(sc, [0, 0, 1, 1]), tmp_path)
    assert load_plan(sc, tmp_path).gnb_of_loop == (0, 0, 1, 1)
    (tmp_path / EDGE_FILE).write_text(json.dumps({"gnb_of_loop": [0, 1]}))
    with pytest.raises(ValueError, match="2 loops"):
        load_plan(sc, tmp_path)


# ---- the association: netsim's own ----------------------------------------------------------------
@pytest.mark.parametrize("seed", [1, 7])
def test_the_association_is_the_one_netsim_makes(seed: int, tmp_path: Path) -> None:
    sc = load_scenario(FACTORY_SMALL, [f"seed={seed}"])
    cell = make_cell(SimpleNamespace(scenario=sc, name="netsim", rng=None))  # type: ignore[arg-type]
    serving = cell.serving()
    assert serving is not None and serving_gnbs(sc) == serving
    plan = provide_edge_plan(sc, tmp_path)
    assert list(plan.gnb_of_loop) == [serving[f"camera-{i}"] for i in range(sc.loops)]
    assert load_plan(sc, tmp_path) == plan == resolve_plan(sc)
    assert len(plan.groups()) > 1  # factory_small's cameras are spread over its gNBs


# ---- one load control per Edge ---------------------------------------------------------------------
def policy_periods(edges: Edges) -> None:
    """Two seconds of policy periods in which loop 0's frames queue 100 ms (above its first's)
    and no other loop's frame arrives."""
    edges[0].monitor.frame(0, 0, 20_000)
    for t in range(50_000, 2_000_000, 50_000):
        edges[0].monitor.frame(0, t - 40_000, t - 40_000 + 120_000)
        for loop in range(4):
            edges[loop].decide(loop, t, Tracker((0.2, 0.0, 0.0)), None)


def test_a_gnbs_congestion_throttles_its_own_loops_only() -> None:
    sc = hall_scenario()
    per = Edges(sc, make_plan(sc, [0, 0, 1, 1]), range(4))
    assert list(per.by_edge) == ["gnb0", "gnb1"] and per[0] is per[1] and per[1] is not per[2]
    one = hall_scenario(placement="central")
    central = Edges(one, make_plan(one, [0, 0, 1, 1]), range(4))
    assert list(central.by_edge) == ["central"] and central[0] is central[3]
    for edges in (per, central):
        policy_periods(edges)
    loaded, calm = per.by_edge["gnb0"].levels(), per.by_edge["gnb1"].levels()
    assert loaded[2] > 0.06 and calm[2] == 0.0  # queueing delay, s
    assert loaded[1] < 1.0 and calm[1] == 1.0  # cap: gNB 0's loops only
    assert central.by_edge["central"].levels()[1] < 1.0  # one Edge: every loop capped
    summary = per.summary()
    assert set(summary["edges"]) == {"gnb0", "gnb1"} and set(summary["gnbs"]) == {"gnb0", "gnb1"}
    assert summary["gnbs"]["gnb0"]["mean_pdp"] < summary["gnbs"]["gnb1"]["mean_pdp"] == 1.0
    assert summary["edges"]["gnb1"]["mean_cap"] == 1.0 > summary["edges"]["gnb0"]["mean_cap"]
    assert central.summary()["edges"]["central"]["loops_here"] == [0, 1, 2, 3]


# ---- the backhaul of a central Edge, on the abstract loops' federate ------------------------------
def loops_federate(sc: Scenario, results_dir: Path, gnbs: list[int]) -> LoopsFederate:
    """The loops federate of ``sc`` on an in-memory bus, set up (frame model and Edge plan in
    ``results_dir``)."""
    model = json.loads(FRAME_MODEL.read_text())
    model["settings"].update(camera_settings(sc.camera))
    results_dir.mkdir(parents=True)
    (results_dir / RUN_FILE).write_text(json.dumps(model))
    write_plan(make_plan(sc, gnbs), results_dir)
    fed = LoopsFederate(FederateContext("loops", "t1", sc, results_dir), InMemoryBus(InMemoryHub()))
    fed.setup()
    return fed


def run_loops(sc: Scenario, results_dir: Path, gnbs: list[int], frame_at_us: int
              ) -> tuple[LoopsFederate, list[tuple[int, str, int, Any]]]:
    """The loops federate of ``sc`` on an in-memory bus: loop 0 captures a frame at 0, netsim
    delivers all its packets at ``frame_at_us``; every message it sends (now, to, at, body) until
    0.2 s."""
    fed = loops_federate(sc, results_dir, gnbs)
    sent: list[tuple[int, str, int, Any]] = []
    send = fed.send

    def recorded(dst: str, t_us: int, body: Any, blob: bytes | None = None) -> None:
        sent.append((fed.now, dst, t_us, body))
        send(dst, t_us, body, blob)

    fed.send = recorded  # type: ignore[method-assign]
    fed.accept(Message(2000, "physics", "loops", 1, "sense", "truth",
                       Truth(loop=0, capture_us=0, objects=[]), None, 1))
    for k in range(200):
        if k * W == frame_at_us:
            n = next(len(b.sizes) for _, _, _, b in sent if isinstance(b, Packets))
            fed.accept(Message(frame_at_us, "netsim", "loops", 1, "net", "aframe",
                               Aframe(loop=0, frame_id=0, n=n, idx=list(range(n))), None, k - 1))
        fed.process_window(Advance(window=k, t_start_us=k * W, t_end_us=(k + 1) * W, expected_in={}))
    return fed, sent


def test_a_loop_none_of_whose_frames_gets_through_keeps_a_bounded_record_of_them(tmp_path: Path) -> None:
    sc = hall_scenario().model_copy(update={"duration_s": 8.0})
    fed = loops_federate(sc, tmp_path / "r", [0, 0, 0, 0])  # netsim never delivers a frame
    lp, largest = fed.loops[0], 0
    for k in range(8000):  # a frame from physics every 33 ms (readout 2 ms), for 8 s
        if k % 33 == 2:
            fed.accept(Message(k * W, "physics", "loops", k, "sense", "truth",
                               Truth(loop=0, capture_us=(k - 2) * W, objects=[]), None, k))
        fed.process_window(Advance(window=k, t_start_us=k * W, t_end_us=(k + 1) * W, expected_in={}))
        largest = max(largest, len(lp.truth))
    assert lp.frames_kept > 200 and largest <= LOST_FRAME_US // 33_000 + 2


def downlinks(sent: list[tuple[int, str, int, Any]], flow: str) -> list[int]:
    return [t for _, dst, t, b in sent if dst == "netsim" and isinstance(b, Packet) and b.flow == flow]


def test_a_central_edge_gets_each_frame_and_sends_each_packet_a_backhaul_later(tmp_path: Path) -> None:
    # Every loop on gNB 0: the two placements differ by the backhaul only.
    gnbs = [0, 0, 0, 0]
    per, per_sent = run_loops(hall_scenario(), tmp_path / "per", gnbs, 60_000)
    central, central_sent = run_loops(hall_scenario(placement="central", backhaul_ms=1.0),
                                      tmp_path / "central", gnbs, 60_000)
    # Uplink: the frame reaches the central Edge 1 ms after netsim delivered it at 60 ms; it
    # counts for the load as its estimate is ready, the pose job (the same draw) later.
    delay_s = per.edges[0].monitor.delay_s[0]
    assert 0.060 < delay_s < 0.080
    assert central.edges[0].monitor.delay_s[0] == pytest.approx(delay_s + 0.001)
    # Downlink: the policy's first QoS (decided at 0) enters the gNB 1 ms later; the pose,
    # estimated 1 ms later, enters 2 ms later.
    qos = downlinks(per_sent, "camera-0/qos")
    assert qos and [t + 1000 for t in qos] == downlinks(central_sent, "camera-0/qos")
    (pose_per,), (pose_central,) = downlinks(per_sent, "robot-0/pose"), downlinks(central_sent, "robot-0/pose")
    assert pose_central == pose_per + 2000
    # The camera's uplink is the camera's: no backhaul on it.
    ul = [[t for _, _, t, b in s if isinstance(b, Packets)] for s in (per_sent, central_sent)]
    assert ul[0] == ul[1]
    # The window rule: every message is delivered at or after the end of the window it was sent in.
    for now, _, t, _ in per_sent + central_sent:
        assert t >= (now // W + 1) * W
    assert central.finish("completed")["edges"]["backhaul_ms"] == 1.0


# ---- one Edge served by two federates --------------------------------------------------------------
def test_an_edge_two_federates_serve_folds_what_one_serving_every_loop_folds() -> None:
    # Loops 0 and 1 detailed (the Edge federate), 2 and 3 abstract (the loops federate), all at
    # gNB 0's Edge; loop 0's frames queue, the others' do not.
    sc = parse_scenario({"loops": 4, "detailed_loops": 2, "policy": {"name": "heuristic"}})
    plan = single_gnb_plan(sc)
    whole, detailed, abstract = Edges(sc, plan, range(4)), Edges(sc, plan, range(2)), Edges(sc, plan, range(2, 4))
    assert detailed.share(range(2, 4)) == ["gnb0"] and abstract.share(range(2)) == ["gnb0"]
    assert whole.share([]) == [] and not whole.by_edge["gnb0"].shared
    period, ahead = sc.edge.policy_period_ms * 1000, detailed.close_ahead_us
    assert ahead == 2 * sc.window_us
    tracker = Tracker((0.2, 0.0, 0.0))
    for t in range(0, 3_000_000, period):
        if t:
            # Frames complete between the closes only: the counts closed ahead hold them all.
            for loop in range(4):
                delay = 100_000 + t // 20 if loop == 0 else 20_000
                for side in (whole, detailed if loop < 2 else abstract):
                    side[loop].monitor.started(loop, t // period, t - ahead - 10_000)
                    side[loop].monitor.frame(loop, t - ahead - 10_000 - delay, t - ahead - 5_000, t // period)
            (due_d, sent_d), (due_a, sent_a) = detailed.close(t - ahead), abstract.close(t - ahead)
            assert due_d == due_a == t - ahead + sc.window_us < t  # in before the period ends
            for counts in sent_d:
                abstract.peer(counts)
            for counts in sent_a:
                detailed.peer(counts)
        for loop in range(4):
            whole[loop].decide(loop, t, tracker, None)
            (detailed if loop < 2 else abstract)[loop].decide(loop, t, tracker, None)
    one, d, a = whole.by_edge["gnb0"], detailed.by_edge["gnb0"], abstract.by_edge["gnb0"]
    assert one.levels()[2] > 0.025  # queued: the fill fell from PDP 1
    assert d.levels() == a.levels() == one.levels()
    assert d.load is not None and a.load is not None and one.load is not None
    assert (d.load.fill, d.load.cap, d.monitor.stalled) == (a.load.fill, a.load.cap, a.monitor.stalled) \
        == (one.load.fill, one.load.cap, one.monitor.stalled)
    assert d.load.fill < 1.0


def test_only_a_co_design_edge_is_shared_and_its_period_must_hold_two_windows() -> None:
    sc = parse_scenario({"loops": 4, "detailed_loops": 2, "policy": {"name": "none"}})
    assert Edges(sc, single_gnb_plan(sc), range(2)).share(range(2, 4)) == []  # PDP 1: nothing to steer
    two = hall_scenario()
    plan = make_plan(two, [0, 1, 1, 1])
    assert Edges(two, plan, range(2)).share(range(2, 4)) == ["gnb1"]  # gNB 0's Edge is the Edge federate's alone
    with pytest.raises(ScenarioError, match="edge.policy_period_ms = 2 ms must exceed two windows"):
        parse_scenario({"loops": 4, "detailed_loops": 1, "policy": {"name": "heuristic"},
                        "edge": {"policy_period_ms": 2}})
    parse_scenario({"loops": 4, "detailed_loops": 4, "policy": {"name": "heuristic"},
                    "edge": {"policy_period_ms": 2}})  # every loop detailed: no Edge shared


def test_the_loops_federate_sends_its_counts_to_the_edge_federate_by_its_horizon(tmp_path: Path) -> None:
    sc = parse_scenario({"loops": 3, "detailed_loops": 1, "policy": {"name": "heuristic"},
                         "nodes": {"camera": MODEL, "edge": MODEL, "robot": MODEL}})
    model = json.loads(FRAME_MODEL.read_text())
    model["settings"].update(camera_settings(sc.camera))
    (tmp_path / RUN_FILE).write_text(json.dumps(model))
    fed = LoopsFederate(FederateContext("loops", "t1", sc, tmp_path), InMemoryBus(InMemoryHub()))
    fed.setup()
    fed.cohosted = frozenset({"physics", "netsim", "loops"})  # a group holding physics and netsim
    sent: list[tuple[int, str, int, Any]] = []
    bundle = fed.send_bundle

    def recorded(dst: str, t_us: int, bodies: Any) -> None:
        sent.append((fed.now, dst, t_us, bodies))
        bundle(dst, t_us, bodies)

    fed.send_bundle = recorded  # type: ignore[method-assign]
    period = sc.edge.policy_period_ms * 1000
    fed.process_window(Advance(window=0, t_start_us=0, t_end_us=W, expected_in={}))
    close = period - 2 * W
    assert fed.external_horizon_us() == close  # the group may not run past the close's window
    for k in range(1, close // W + 1):
        fed.process_window(Advance(window=k, t_start_us=k * W, t_end_us=(k + 1) * W, expected_in={}))
    ((now, dst, due, bodies),) = sent
    assert (now, dst, due) == (close, "edge", close + W) and [b.edge for b in bodies] == ["gnb0"]
    assert fed.external_horizon_us() == NEVER_US  # nothing more to send before the next period
