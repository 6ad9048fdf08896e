"""Frames sent and never received count as lost: the sent-frame sequence in the frame bodies,
the Edge's monitor counting its gaps, and the cap it drives past capacity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_conformance import CASES, Input, drive, tiny_scenario

from domain.congestion import (
    CELL_ALPHA,
    CUT,
    DEEPEST_CUT,
    HOLD_US,
    LOOP_ALPHA,
    LOSS_LAG_US,
    LOSS_TARGET,
    LOST_AFTER_US,
    SHED_LOSS_TARGET,
    STALL_US,
    Level,
    LoadControl,
    UplinkMonitor,
    served_rank,
)

PERIOD_US = 50_000
FRAME_US = 33_333


def test_a_gap_in_the_sequence_counts_as_lost_once_its_timeout_passes() -> None:
    mon = UplinkMonitor()
    mon.frame(0, 0, 20_000, 0)
    mon.frame(0, 33_000, 53_000, 1)
    mon.frame(0, 133_000, 153_000, 4)  # 2 and 3 were sent and are missing from now
    assert mon.period(153_000 + LOST_AFTER_US - 1) == (0.0, 0.0)
    _, loss = mon.period(153_000 + LOST_AFTER_US)
    assert loss == pytest.approx(CELL_ALPHA * 1.0)  # two lost, no frame complete this period
    assert mon.estimate(0).loss == pytest.approx(1 - (1 - LOOP_ALPHA) ** 2)
    assert mon.period(153_000 + 2 * LOST_AFTER_US)[1] == pytest.approx(loss)  # counted once


def test_a_frame_shown_sent_by_a_gap_has_its_timeout_from_its_first_packet() -> None:
    mon = UplinkMonitor()
    mon.started(0, 1, 0)
    mon.frame(0, -20_000, 10_000, 1)  # frame 0 expected from 10 ms: sent before frame 1
    mon.started(0, 0, 200_000)  # it starts to arrive within the timeout ...
    assert mon.close(10_000 + LOST_AFTER_US).lost == 0  # ... and has the timeout from then on
    assert mon.close(200_000 + LOST_AFTER_US).lost == 1
    never = UplinkMonitor()
    never.frame(0, 0, 10_000, 1)
    assert never.close(10_000 + LOST_AFTER_US).lost == 1  # never started: lost from the gap


def test_frames_the_camera_dropped_for_its_pdp_take_no_number_and_count_nothing() -> None:
    mon = UplinkMonitor()
    # Captures 0-9, every third kept (PDP 1/3): the sent frames are numbered 0, 1, 2, 3.
    for seq, capture in enumerate(range(0, 10, 3)):
        t = capture * FRAME_US
        mon.started(0, seq, t + 15_000)
        mon.frame(0, t, t + 20_000, seq)
    assert mon.period(10 * FRAME_US + LOST_AFTER_US) == (0.0, 0.0)
    assert mon.estimate(0).loss == 0.0


def test_reordered_frames_duplicates_and_late_frames_count_once() -> None:
    mon = UplinkMonitor()
    mon.started(0, 0, 10_000)
    mon.started(0, 2, 12_000)  # frame 1 overtaken in HARQ: expected from now
    mon.frame(0, 0, 15_000, 2)
    mon.started(0, 1, 20_000)
    mon.frame(0, 0, 25_000, 1)
    mon.frame(0, 0, 26_000, 0)
    mon.started(0, 2, 30_000)  # a packet of a frame already complete: no new frame expected
    mon.started(1, 0, 30_000)  # another loop numbers its own frames
    mon.frame(1, 0, 35_000, 0)
    assert mon.period(30_000 + 2 * LOST_AFTER_US)[1] == 0.0
    mon.started(0, 3, 600_000)  # never completes: lost by its timeout ...
    mon.frame(0, 600_000, 610_000, 4)
    _, loss = mon.period(600_000 + LOST_AFTER_US)
    assert loss == pytest.approx(CELL_ALPHA * 0.5)
    mon.started(0, 3, 900_000)  # ... and a packet of it arriving later starts nothing
    mon.frame(0, 900_000, 910_000, 5)
    assert mon.period(900_000 + 2 * LOST_AFTER_US)[1] == pytest.approx(loss * (1 - CELL_ALPHA))


def test_frames_that_never_started_and_one_left_incomplete_are_both_lost() -> None:
    mon = UplinkMonitor()
    mon.frame(0, 0, 20_000, 0)
    mon.period(40_000)
    mon.started(0, 1, 50_000)  # incomplete
    mon.frame(0, 0, 120_000, 3)  # 2 discarded whole at the UE
    _, loss = mon.period(120_000 + LOST_AFTER_US)
    assert loss == pytest.approx(CELL_ALPHA * 2 / 3)  # 1 and 2 lost, 3 complete


def test_a_frame_the_edge_drops_for_a_newer_one_is_lost_at_once_and_once() -> None:
    mon = UplinkMonitor()
    mon.started(0, 0, 10_000)
    mon.started(0, 1, 43_000)
    mon.dropped(0, 0)  # complete, waiting for the CPU, replaced by frame 1
    mon.frame(0, 33_000, 60_000, 1)
    counts = mon.close(60_000)
    assert (counts.frames, counts.lost) == (1, 1)
    assert mon.estimate(0).loss == pytest.approx(LOOP_ALPHA * (1 - LOOP_ALPHA))
    mon.dropped(0, 0)  # already counted: nothing more
    assert mon.close(10_000 + LOST_AFTER_US).lost == 0


def test_a_frame_incomplete_stall_us_after_its_first_packet_has_stalled() -> None:
    mon = UplinkMonitor()
    mon.started(0, 0, 10_000)
    mon.frame(1, 0, 20_000, 0)
    mon.period(10_000 + STALL_US - 1)
    assert mon.stalled == 0.0
    mon.frame(1, 33_000, 55_000, 1)
    mon.period(10_000 + STALL_US)  # one stalled, one complete since the last period
    assert mon.stalled == pytest.approx(0.5)
    mon.frame(0, 0, 70_000, 0)  # complete at last, late
    mon.period(100_000)
    assert mon.stalled == 0.0


def test_the_detailed_camera_numbers_the_frames_it_sends_only(tmp_path: Path) -> None:
    camera = next(c for c in CASES if c.name == "camera-0")
    images = [i for i in camera.inputs(tiny_scenario()) if i.kind == "image"]
    # PDP 0 from 20 ms (the second capture dropped), 1 again from 50 ms.
    inputs = images + [Input(t, "netsim", "net", "qos", {"type": "qos", "loop": 0, "pdp": pdp, "pdb_us": None,
                                                         "packet_id": k})
                       for k, (t, pdp) in enumerate([(20_000, 0.0), (50_000, 1.0)])]
    result = drive(camera, tmp_path, arrival_seed=1, jump=False, inputs=inputs)
    assert result.error is None, result.error
    sent = {o[6]["app"]["frame_id"]: o[6]["app"]["seq"] for o in result.outputs if o[5] == "packet"}
    captures = sorted(sent)
    assert captures != list(range(len(captures))), "the script's PDP dropped no frame"
    assert [sent[f] for f in captures] == list(range(len(captures)))


def cell(loops: int, capacity: int, periods: int, seq: bool, start: float = 1.0) -> tuple[LoadControl, list[float]]:
    """``loops`` cameras at 30 frame/s sending at the cap of a load control whose Edge sees a
    cell that carries ``capacity`` frames a policy period, drawn at random, with a constant
    20 ms delay and discards the rest whole at the UEs (the PDB); ``seq``: the Edge knows the
    sent sequence; ``start``: the cap's slow start. The load control and the injected frames,
    period by period."""
    mon, load = UplinkMonitor(), LoadControl(0.025, 0.06, 0.1, start)
    rng = np.random.default_rng(1)
    sent = [0] * loops
    credit = [i / loops for i in range(loops)]  # the cameras' captures are not aligned
    injected = []
    for k in range(periods):
        now = k * PERIOD_US
        load.update(now, *mon.period(now))
        frames = []
        for i in range(loops):  # 1.5 frames a period at the cap (a policy asking PDP 1), if served
            credit[i] += 1.5 * load.cap * load.serves(i)
            while credit[i] >= 1.0:
                credit[i] -= 1.0
                frames.append((i, sent[i]))
                sent[i] += 1
        injected.append(len(frames))
        for j in sorted(rng.permutation(len(frames))[:capacity]):
            i, s = frames[j]
            mon.frame(i, now, now + 20_000, s if seq else None)
    return load, injected


@pytest.mark.parametrize(("loops", "capacity"), [(100, 60), (128, 29)])
def test_past_capacity_the_cap_holds_the_injected_traffic_near_what_the_cell_delivers(loops: int,
                                                                                        capacity: int) -> None:
    # 1.5 frames a loop a period offered: 2.5x and 6.6x what the cell carries (a cap of 0.4, 0.15)
    _, injected = cell(loops, capacity, 300, seq=True)
    late = injected[100:]  # the cap cycles around a loss of LOSS_TARGET
    assert 0.9 * capacity < sum(late) / len(late) < capacity / (1 - LOSS_TARGET)
    assert max(late) < 1.5 * capacity
    # Without the sequence the Edge sees only frames that arrive, on time: the cap never moves.
    blind, injected = cell(loops, capacity, 200, seq=False)
    assert blind.cap == 1.0 and min(injected[100:]) == 1.5 * loops


def test_deep_past_capacity_the_cap_comes_down_within_a_second() -> None:
    # 6.6x what the cell carries: cut to the delivered share, a dozen cuts by CUT took 3 s.
    _, injected = cell(128, 29, 100, seq=True)
    assert max(injected[20:]) < 1.5 * 29


def test_a_cut_follows_the_delivered_share_of_the_level_the_lost_frames_were_sent_at() -> None:
    near = Level(0.06, 0.1, LOSS_TARGET, proportional=True)
    near.update(0, 0.0, 0.12)  # just past capacity: 88 % arrive, the cut is CUT as ever
    assert near.value == pytest.approx(CUT)
    deep = Level(0.06, 0.1, LOSS_TARGET, proportional=True)
    deep.update(0, 0.0, 0.7)  # 30 % arrive: never more than DEEPEST_CUT at once
    assert deep.value == pytest.approx(DEEPEST_CUT)
    for t in range(50_000, LOSS_LAG_US, 50_000):  # a period each, no loss: up by STEP of it
        deep.update(t, 0.0, 0.0)
    deep.update(LOSS_LAG_US + HOLD_US, 0.0, 0.4)  # 60 % of the frames sent HOLD_US in arrive
    assert deep.value == pytest.approx(DEEPEST_CUT * 1.01 ** (HOLD_US // 50_000) * 0.6)
    delay = Level(0.025, 0.0)  # a level steered by the delay alone is cut by CUT whatever the loss
    delay.update(0, 0.1, 1.0)
    assert delay.value == pytest.approx(CUT)


def test_a_level_keeps_what_was_in_force_a_loss_lag_ago_over_irregular_periods() -> None:
    level = Level(0.06, 0.1, LOSS_TARGET, proportional=True)
    times = [0, 30_000, 110_000, 170_000, 400_000, 420_000, 700_000, 1_300_000, 1_310_000, 1_900_000]
    seen = []
    for t in times:  # climbing from 1 (capped): cut once at 400 ms, then climbing again
        level.update(t, 0.1 if t == 400_000 else 0.0, 0.0)
        seen.append((t, level.value))
        in_force = [v for u, v in seen if u <= t - LOSS_LAG_US]
        assert level._value_at(t - LOSS_LAG_US) == (in_force[-1] if in_force else 1.0)
    assert len(level._past) <= 3  # only the last LOSS_LAG_US, and what was in force before them
    rising = Level(0.06, 0.1, LOSS_TARGET, proportional=True)
    rising.value = 0.2
    for k in range(1, 13):  # 12 periods up by 1 %: the cap of LOSS_LAG_US ago was 0.2 x 1.01
        rising.update(k * 50_000, 0.0, 0.0)
    rising.update(13 * 50_000, 0.0, 0.12)  # 88 % of those arrived: below CUT of today's cap
    assert rising.value == pytest.approx(0.2 * 1.01 * 0.88)
    for bad in (float("nan"), 1.5):  # nothing known to arrive: never more than DEEPEST_CUT at once
        odd = Level(0.06, 0.1, LOSS_TARGET, proportional=True)
        odd.update(0, 0.1, bad)
        assert odd.value == pytest.approx(DEEPEST_CUT)


def test_where_every_loop_at_the_least_cap_overloads_the_cell_the_cap_sheds_loops() -> None:
    # 400 loops at the least cap, 0.1, offer 60 frames a period to a cell that carries 29: shed
    # loops send nothing, the others stay at 0.1, and the injected traffic stays near what is
    # carried, within what a loss of SHED_LOSS_TARGET allows (in bursts: a served loop sends a
    # frame every 7 periods, so what a share injects is lumpy).
    load, injected = cell(400, 29, 500, seq=True)
    late = injected[200:]  # from 20x what the cell carries, the first cuts undershoot
    assert 0.8 * 29 < sum(late) / len(late) < 29 / (1 - SHED_LOSS_TARGET) and max(late) < 2 * 29
    assert load.cap == 0.1 and 0.35 < load.served < 0.65
    served = [i for i in range(400) if load.serves(i)]
    assert abs(len(served) - load.served * 400) <= 3  # the share, spread over the loops:
    assert all(abs(sum(1 for i in served if 100 * q <= i < 100 * (q + 1)) - load.served * 100) <= 3
               for q in range(4))


def test_a_loop_served_at_a_share_is_served_at_every_larger_share() -> None:
    ranks = [served_rank(i) for i in range(1000)]
    assert ranks[0] == 0.0 and all(0.0 <= r < 1.0 for r in ranks)  # loop 0 is always served
    for share in (0.05, 0.1, 0.3, 0.5, 0.9):
        assert abs(sum(r < share for r in ranks) - 1000 * share) <= 3
    shares = [0.1, 0.2, 0.5, 0.8]  # nested: a rising share adds loops, never swaps them
    sets = [{i for i, r in enumerate(ranks) if r < s} for s in shares]
    assert all(a < b for a, b in zip(sets, sets[1:], strict=False))


def test_below_capacity_the_sequence_changes_nothing() -> None:
    load, injected = cell(20, 60, 100, seq=True)  # 20 or 40 frames a period, all carried
    assert load.cap == 1.0 and load.fill == 1.0 and max(injected) <= 60


def test_the_slow_start_reaches_pdp_1_below_capacity_and_stops_at_the_first_loss_past_it() -> None:
    load, injected = cell(20, 60, 100, seq=True, start=0.1)  # PDP 1 carried: up in four periods
    assert load.cap == 1.0 and injected[4:] == [30] * 96
    _, started = cell(100, 60, 100, seq=True, start=0.1)  # 2.5x what the cell carries
    _, cold = cell(100, 60, 100, seq=True)
    assert started[:3] == [30, 60, 120] and cold[:3] == [150] * 3  # doubling from 0.1 (0.2 first)
    assert max(started[10:]) < 1.5 * 60 <= max(cold[10:])  # and in hand sooner
