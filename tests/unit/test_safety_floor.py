"""The safety floor on the kinematics of fast and slow belts, spawn jitter and the uplink's
delay and loss; the load control (headroom fill, cap) and the uplink monitor it reads."""

from __future__ import annotations

import math

import pytest

from domain import work_cell as g
from domain.congestion import (
    CELL_ALPHA,
    CUT,
    HOLD_US,
    IDLE_LINK,
    LEAST_SERVED,
    LOOP_ALPHA,
    LOSS_LAG_US,
    LOSS_TARGET,
    LOST_AFTER_US,
    SHED_AFTER_US,
    SHED_LOSS_TARGET,
    START_WATCH_US,
    STEP,
    LinkEstimate,
    LoadControl,
    UplinkMonitor,
)
from domain.edge_side import CoDesign, bounded_pdp
from domain.loop_state import LoopState
from domain.policy import Qos, pdp_for_deadline
from domain.safety_floor import FloorLimits, next_part_earliest_us, safety_floor
from domain.tracker import Tracker
from scenario.schema import PolicyConfig, WorkCellConfig

LIMITS = FloorLimits(max_estimate_age_s=0.4, miss_rate=0.0, risk=0.01, period_s=0.05)
NOW = 10_000_000


def state(speed: float, tracks: list[dict] | None = None, last_spawn_us: int | None = None,
          period_s: float = 4.0, jitter_s: float = 0.0, link: LinkEstimate = IDLE_LINK) -> LoopState:
    return LoopState(NOW, tracks or [], None, speed, period_s, 8, 30.0, last_spawn_us, jitter_s, link)


def part(x: float, speed: float, age_us: int = 0, sd: float = 0.004) -> dict:
    return {"id": 1, "t_us": NOW - age_us, "p": [x - speed * age_us / 1e6, 0.0, g.BELT_TOP_Z + 0.03],
            "v": [speed, 0.0, 0.0], "sd": sd}


def test_pdp_for_deadline_brings_a_useful_frame_with_the_accepted_risk() -> None:
    for deadline, useful in [(0.3, 1.0), (0.5, 0.8), (1.2, 0.5)]:
        p = pdp_for_deadline(deadline, 30.0, useful, 0.01)
        assert (1 - p * useful) ** (deadline * 30) == pytest.approx(0.01)
    assert pdp_for_deadline(0.02, 30.0) == 1.0  # under one frame: every frame


def test_a_faster_belt_needs_a_higher_floor_to_see_a_new_part_in_time() -> None:
    slow, fast = safety_floor(state(0.1), LIMITS), safety_floor(state(0.5), LIMITS)
    assert 0 < slow < fast <= 1.0
    # At 0.5 m/s a part spends 0.3 s before the window and 1.7 s in it: seen (99 %) within a
    # quarter of (0.3 + 1.7 - 0.5) s less a period, 0.325 s, 9.75 frames: PDP 0.38 -> 0.4.
    assert fast == pytest.approx(0.4)
    # At 0.1 m/s: within 2.325 s, 70 frames: PDP 0.064 -> 0.1.
    assert slow == pytest.approx(0.1)


def test_no_new_part_can_have_landed_before_the_period_less_the_jitter() -> None:
    spawn = NOW - 3_500_000  # the newest part landed 3.5 s ago; the period is 4 s
    assert next_part_earliest_us(state(0.3, last_spawn_us=spawn)) == spawn + 4_000_000
    assert safety_floor(state(0.3, last_spawn_us=spawn), LIMITS) == 0.0
    # With 1 s of jitter the next part may already be on the belt.
    jittered = state(0.3, last_spawn_us=spawn, jitter_s=1.0)
    assert safety_floor(jittered, LIMITS) == safety_floor(state(0.3), LIMITS) > 0


def test_a_part_at_the_pick_window_keeps_its_estimate_fresh() -> None:
    # 0.4 s age limit less a period: a useful frame within 0.35 s, 10.5 frames: PDP 0.36 -> 0.4.
    spawn = NOW - 1_000_000
    near = state(0.3, [part(-0.45, 0.3)], last_spawn_us=spawn)
    assert safety_floor(near, LIMITS) == pytest.approx(0.4)
    # 1.5 s upstream of the window on a slow belt only the track must be kept: its prediction
    # leaves half the gate after sqrt(2 x 0.036 / 0.5) = 0.38 s, 11.4 frames: PDP 0.33 -> 0.35.
    far = state(0.1, [part(-0.55, 0.1)], last_spawn_us=spawn)
    assert safety_floor(far, LIMITS) == pytest.approx(0.35)


def test_the_floor_counts_the_uplink_delay_and_loss() -> None:
    base = state(0.3, [part(-0.45, 0.3)], last_spawn_us=NOW - 1_000_000)
    lossy = state(0.3, [part(-0.45, 0.3)], last_spawn_us=NOW - 1_000_000, link=LinkEstimate(0.0, 0.5))
    slow = state(0.3, [part(-0.45, 0.3)], last_spawn_us=NOW - 1_000_000, link=LinkEstimate(0.2, 0.0))
    assert safety_floor(lossy, LIMITS) > safety_floor(base, LIMITS)
    assert safety_floor(slow, LIMITS) > safety_floor(base, LIMITS)


def test_a_track_about_to_leave_its_gate_asks_for_every_frame() -> None:
    stale = state(0.3, [part(-0.2, 0.3, age_us=500_000, sd=0.03)], last_spawn_us=NOW - 1_000_000)
    assert safety_floor(stale, LIMITS) == 1.0


def test_the_cap_cuts_once_per_hold_never_below_its_minimum_then_sheds_loops_and_recovers() -> None:
    load = LoadControl(None, 0.04, 0.1)
    assert load.fill == 0.0 and load.served == 1.0
    load.update(0, 0.02, 0.0)
    assert load.cap == 1.0  # under the target: nothing changes
    load.update(50_000, 0.08, 0.0)
    assert load.cap == pytest.approx(CUT)
    load.update(100_000, 0.08, 0.0)
    assert load.cap == pytest.approx(CUT)  # within the hold
    load.update(50_000 + HOLD_US, 0.01, 0.1 + 1e-9)
    assert load.cap == pytest.approx(CUT * CUT)  # the loss counts too
    load.update(50_000 + 2 * HOLD_US, 0.01, 0.3)  # 70 % of the frames sent under the cap of then
    assert load.cap == pytest.approx(CUT * 0.7)  # (CUT, 600 ms ago) arrived: the cut goes there
    t = 50_000 + 2 * HOLD_US
    for _ in range(40):
        t += HOLD_US
        load.update(t, 1.0, 1.0)
    assert load.cap == 0.1 and load.served == pytest.approx(LEAST_SERVED)  # loops shed instead
    t += 50_000
    load.update(t, 0.01, 0.0)
    assert load.cap == 0.1 and load.served == pytest.approx(LEAST_SERVED * (1 + STEP))  # back first
    while load.served < 1.0:
        t += 50_000
        load.update(t, 0.01, 0.0)
    load.update(t + 50_000, 0.01, 0.0)
    assert load.cap == pytest.approx(0.1 * (1 + STEP), rel=0.02)  # then the cap, by STEP of its value


def test_the_cap_starts_low_and_doubles_until_the_first_sign_of_congestion() -> None:
    load = LoadControl(None, 0.04, 0.1, start_cap=0.1)
    assert load.cap == 0.1
    caps = []
    for k in range(5):  # an idle cell: 0.2, 0.4, 0.8, then 1 (at 150 ms)
        load.update(50_000 * k, 0.0, 0.0)
        caps.append(load.cap)
    assert caps == pytest.approx([0.2, 0.4, 0.8, 1.0, 1.0])
    load.update(250_000, 0.0, 0.0, stalled=LOSS_TARGET)  # a few frames stalled: nothing
    assert load.cap == 1.0
    # Frames sent past capacity stall before their loss shows: while the start watches (the cap
    # 1 for less than START_WATCH_US), the cap is cut to half what it was START_LAG_US before.
    load.update(150_000 + START_WATCH_US - 50_000, 0.0, 0.0, stalled=0.5)
    assert load.cap == pytest.approx(0.5)
    load.update(150_000 + START_WATCH_US, 0.0, 0.0)
    assert load.cap == pytest.approx(0.5 * (1 + STEP))  # the start is over: the usual climb
    watched = LoadControl(None, 0.04, 0.1, start_cap=0.1)
    for k in range(4 + START_WATCH_US // 50_000):
        watched.update(50_000 * k, 0.0, 0.0)
    watched.update(50_000 * (4 + START_WATCH_US // 50_000), 0.0, 0.0, stalled=1.0)
    assert watched.cap == 1.0  # past the start, stalled frames alone cut nothing
    load = LoadControl(None, 0.04, 0.05, start_cap=0.1)
    load.update(0, 0.0, 0.0)
    load.update(50_000, 0.0, 0.0)  # 0.4
    load.update(100_000, 0.0, 0.5)  # half the frames lost: the start ends in a cut ...
    assert load.cap == pytest.approx(0.1)  # ... to half the 0.2 of START_LAG_US before
    load.update(150_000, 0.0, 0.0)
    assert load.cap == pytest.approx(0.1 * (1 + STEP))  # then the usual climb


def _cut_by_the_start() -> LoadControl:
    """A load control whose slow start (0.2, 0.4, 0.8) ended at 150 ms on stalled frames."""
    load = LoadControl(None, 0.04, 0.05, start_cap=0.1)
    for k in range(3):
        load.update(50_000 * k, 0.0, 0.0)
    load.update(150_000, 0.0, 0.0, stalled=0.5)  # the start overshot: half the 0.4 of 100 ms before
    return load


def test_the_loss_of_the_frames_sent_before_the_starts_cut_cuts_nothing_more() -> None:
    load = _cut_by_the_start()
    assert load.cap == pytest.approx(0.2)
    load.update(150_000 + HOLD_US, 0.0, 0.5)  # the overload's loss shows: those frames were sent before the cut
    assert load.cap == pytest.approx(0.2 * (1 + STEP))
    load.update(150_000 + LOSS_LAG_US - 50_000, 0.0, 0.5)
    assert load.cap > 0.2
    load.update(150_000 + LOSS_LAG_US, 0.0, 0.5)  # a loss read LOSS_LAG_US after the cut is new
    assert load.cap < 0.2
    delayed = _cut_by_the_start()
    delayed.update(150_000 + HOLD_US, 0.1, 0.0)  # the queueing delay still cuts, after HOLD_US
    assert delayed.cap < 0.2


def test_the_slow_start_is_a_setting_at_least_the_least_cap() -> None:
    assert PolicyConfig(name="heuristic").guard_start_pdp == 0.1
    assert CoDesign(PolicyConfig(name="heuristic"), 0.3).load.cap == 0.1
    assert CoDesign(PolicyConfig(name="heuristic", guard_start_pdp=1.0), 0.3).load.cap == 1.0
    with pytest.raises(ValueError, match="guard_start_pdp .* must be at least guard_min_pdp"):
        PolicyConfig(name="heuristic", guard_start_pdp=0.1, guard_min_pdp=0.2)


def test_loops_are_shed_only_once_the_cap_has_sat_at_its_least_and_many_frames_are_still_lost() -> None:
    load = LoadControl(None, 0.04, 0.1)
    t = 0
    while load.cap > 0.1:  # the delay alone brings the cap down
        load.update(t, 1.0, 0.0)
        t += HOLD_US
    for _ in range(10):
        load.update(t, 1.0, 0.0)
        t += HOLD_US
    assert load.served == 1.0  # and sheds nothing: the cell carries what it is sent
    load.update(t, 1.0, SHED_LOSS_TARGET)  # a loss spread over every loop: still none shed
    assert load.served == 1.0
    load.update(t + 50_000, 1.0, 0.5)  # half the frames sent at the least cap are lost
    assert load.cap == 0.1 and load.served == pytest.approx(0.5)
    fresh = LoadControl(None, 0.04, 0.1)
    t = 0
    while fresh.cap > 0.1:
        fresh.update(t, 1.0, 1.0)
        t += HOLD_US
    least = t - HOLD_US
    while t < least + SHED_AFTER_US:  # the loss read is of the start's, not of the least cap
        fresh.update(t, 1.0, 1.0)
        assert fresh.served == 1.0
        t += 50_000
    fresh.update(t, 1.0, 1.0)
    assert fresh.served < 1.0


def test_the_fill_gives_pdp_1_while_the_cell_has_headroom_and_yields_near_saturation() -> None:
    load = LoadControl(0.01, 0.04, 0.1)
    st = state(0.3, [part(-0.45, 0.3)], last_spawn_us=NOW - 1_000_000)
    load.update(0, 0.002, 0.0)
    assert bounded_pdp(0, st, 0.1, LIMITS, load) == 1.0
    load.update(50_000, 0.02, 0.0)  # past the headroom target, under the cap's
    assert load.fill == pytest.approx(CUT) and load.cap == 1.0
    for k in range(2, 12):
        load.update(k * HOLD_US, 0.02, 0.0)
    assert bounded_pdp(0, st, 0.1, LIMITS, load) == pytest.approx(0.4)  # the floor's, no more


def test_the_monitor_measures_queueing_above_each_loops_base_delay_and_loss_by_timeout() -> None:
    mon = UplinkMonitor()
    mon.frame(0, 0, 20_000, 0)  # base delays: 20 ms and 40 ms
    mon.frame(1, 0, 40_000, 0)
    assert mon.period(50_000) == (0.0, 0.0)
    mon.started(0, 1, 120_000)
    mon.frame(0, 100_000, 130_000, 1)  # 10 ms of queueing
    mon.frame(1, 100_000, 170_000, 1)  # 30 ms
    mon.started(1, 2, 180_000)  # never completes
    queueing, loss = mon.period(180_000 + LOST_AFTER_US - 1)
    assert queueing == pytest.approx(CELL_ALPHA * 0.02) and loss == 0.0
    assert mon.period(180_000 + LOST_AFTER_US) == (queueing, pytest.approx(CELL_ALPHA))  # one lost
    est = mon.estimate(1)
    assert est.delay_s == pytest.approx(0.04 + LOOP_ALPHA * 0.03) and est.loss == pytest.approx(LOOP_ALPHA)
    assert mon.estimate(0).loss == 0.0


def test_pdp_1_is_never_bounded_and_every_co_design_policy_is() -> None:
    cell = WorkCellConfig(belt_speed_m_s=0.45, object_period_s=2.5)
    none = CoDesign(PolicyConfig(name="none"), cell)
    assert none.limits is None and none.load is None
    started = CoDesign(PolicyConfig(name="fixed", pdp=0.1), cell)
    assert started.decide(0, NOW, Tracker((0.45, 0.0, 0.0)), None).pdp == 0.2  # slow start: 0.1, doubled once
    fixed = CoDesign(PolicyConfig(name="fixed", pdp=0.1, guard_start_pdp=1.0), cell)
    assert fixed.decide(0, NOW, Tracker((0.45, 0.0, 0.0)), None).pdp == 1.0  # headroom: PDP 1
    bare = CoDesign(PolicyConfig(name="fixed", pdp=0.1, headroom=False), cell)
    assert 0.1 < bare.decide(0, NOW, Tracker((0.45, 0.0, 0.0)), None).pdp < 1.0  # the floor's
    off = CoDesign(PolicyConfig(name="fixed", pdp=0.1, headroom=False, floor=False), cell)
    assert off.decide(0, NOW, Tracker((0.45, 0.0, 0.0)), None).pdp == 0.1


def test_past_capacity_the_cap_wins_over_the_floor() -> None:
    st = state(0.3, [part(-0.45, 0.3)], last_spawn_us=NOW - 1_000_000)
    load = LoadControl(0.01, 0.04, 0.1)
    t = 0
    while load.cap > 0.3:
        load.update(t, 1.0, 0.0)
        t += HOLD_US
    assert bounded_pdp(0, st, 0.1, LIMITS, None) == pytest.approx(0.4)
    cap = math.ceil(round(load.cap / 0.05, 6)) * 0.05  # signalled in steps of 0.05, rounded up
    assert cap < 0.4
    assert bounded_pdp(0, st, 0.1, LIMITS, load) == pytest.approx(cap)
    assert Qos(bounded_pdp(0, st, 1.0, None, load), None).pdp == pytest.approx(cap)
