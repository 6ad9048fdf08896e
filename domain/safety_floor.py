"""The safety floor every co-design policy's PDP is bounded by: the PDP below which, from the
work cell's kinematics, the tracker's state and the uplink's current delay and loss, a new part
would not be seen in time, a tracked part's estimate would be too old when the arm works on it,
or its track would be lost (docs/policy.md, "Safety floor").
"""

from __future__ import annotations

from dataclasses import dataclass

from domain import policy_features as F
from domain import work_cell as g
from domain.loop_state import LoopState
from domain.policy import PICK_TIME_S, gate_time_s, pdp_for_deadline, step_up

# How long before a part reaches the pick window the arm may start working on it (it waits at
# the window's entry): from then on its estimate must stay fresh.
LEAD_S = 1.0
# Share of the time a part can be picked in (from its landing) within which it must be seen: the
# sooner the arm knows it, the sooner it can start, and on a dense belt the next part waits.
DETECT_SHARE = 0.25


@dataclass(frozen=True)
class FloorLimits:
    """What the floor protects. ``max_estimate_age_s``: the robot holds back on older estimates
    (RobotConfig.max_estimate_age_ms); ``miss_rate``: share of visible parts the estimator misses
    (the frame model's); ``risk``: accepted chance that no useful frame comes before a deadline;
    ``period_s``: the policy period (a PDP holds that long before the next decision)."""

    max_estimate_age_s: float
    miss_rate: float
    risk: float
    period_s: float


def next_part_earliest_us(state: LoopState) -> int | None:
    """The earliest time (us) the next part can land in the loop of ``state``: the newest part's
    landing plus the object period less its jitter (spawn times are drawn uniformly within +-
    jitter of the plan); None when unknown."""
    if state.last_spawn_us is None or state.object_period_s is None:
        return None
    return state.last_spawn_us + int((state.object_period_s - state.object_jitter_s) * 1e6)


def safety_floor(state: LoopState, limits: FloorLimits) -> float:
    """The floor on the PDP of the loop in ``state``, protecting ``limits``, rounded up to
    PDP_STEP.

    - every part the arm may work on within LEAD_S (and inside the window): a useful frame
      before its estimate's age would pass ``max_estimate_age_s``, counting the uplink delay and
      the policy period the PDP holds;
    - every tracked part: a useful frame before the tracker's prediction of it (its sd grown by
      the tracker's motion model) leaves half the association gate, or the track is lost;
    - when a new part may have landed (not before ``next_part_earliest_us``): a useful frame
      within DETECT_SHARE of the time the arm has to pick a part from its landing (to the last
      grasp start in the window), less the uplink delay and the policy period."""
    link = state.link
    useful = (1.0 - min(link.loss, 0.9)) * (1.0 - limits.miss_rate)
    fps, risk = state.fps, limits.risk
    delay_s = link.delay_s
    v = max(state.belt_speed_m_s, F.MIN_SPEED_M_S)
    x0, x1 = g.PICK_X_RANGE
    floor = 0.0
    parts = F.belt_tracks(state)
    for x, tr in parts:
        age_s = max(0.0, (state.now_us - tr["t_us"]) / 1e6)
        if (x0 - x) / v <= LEAD_S:
            fresh_s = limits.max_estimate_age_s - delay_s - limits.period_s
            floor = max(floor, pdp_for_deadline(fresh_s, fps, useful, risk))
        floor = max(floor, pdp_for_deadline(gate_time_s(tr, age_s) - delay_s, fps, useful, risk))
    earliest = next_part_earliest_us(state)
    if earliest is None or state.now_us >= earliest:
        window_s = (x1 - x0) / v
        reach_s = max(0.0, (x0 - g.SPAWN_X) / v)
        deadline = (reach_s + window_s - PICK_TIME_S) * DETECT_SHARE - delay_s - limits.period_s
        floor = max(floor, pdp_for_deadline(deadline, fps, useful, risk))
    return step_up(floor)
