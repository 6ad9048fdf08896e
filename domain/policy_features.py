"""The learned co-design policy's contract: its observation of a ``LoopState`` (``features``, the
one function the training environment and the Edge both call, in units that carry across cells),
named ``FEATURE_SET`` so that a model trained on another is refused, and its action sets
(docs/policy.md, "Observation")."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from domain import work_cell as g
from domain.loop_state import LoopState
from wire.bodies import Track

TRACK_SLOTS = 2  # parts described, most urgent first
TRACK_FEATURES = ("present", "window_pos", "t_reach", "t_exit", "speed", "sd", "age")
GLOBAL_FEATURES = ("n_parts", "lifted", "frame_age", "next_part", "belt_speed", "object_period",
                   "queueing_delay")
FEATURE_NAMES = tuple(f"track{k}_{f}" for k in range(TRACK_SLOTS) for f in TRACK_FEATURES) + GLOBAL_FEATURES
N_FEATURES = len(FEATURE_NAMES)
OBS_LIMIT = 5.0
# The name of this observation: a model trained on another set is refused. "v1": the load as
# loops / 20; "v2": the load as the uplink queueing delay the Edge sees.
FEATURE_SET = "v2"

# Action sets: the PDP levels and latency budgets the learned policy chooses from.
PDP_LEVELS = (0.1, 0.25, 0.5, 0.75, 1.0)
BUDGET_LEVELS_MS = (25, 50, 100, 200)

WINDOW_M = g.PICK_X_RANGE[1] - g.PICK_X_RANGE[0]
LIFTED_M = 0.09  # a part centre this far above the belt is off it (largest half edge + margin)
DEFAULT_OBJECT_PERIOD_S = 4.0  # assumed when the loop state does not say
DELAY_SCALE_S = 0.05  # queueing delays at the Edge: under 15 ms below the cell's capacity, 100s beyond
TIME_SCALE_S = 2.0
AGE_SCALE_S = 0.5
SD_SCALE_M = 0.01
SPEED_SCALE_M_S = 0.5
PERIOD_SCALE_S = 6.0
MIN_SPEED_M_S = 0.02  # guards divisions by the belt speed


def _clip(x: float) -> float:
    return float(min(OBS_LIMIT, max(-OBS_LIMIT, x)))


def belt_tracks(state: LoopState) -> list[tuple[float, Track]]:
    """Parts on the belt of the loop in ``state`` that the arm can still pick, as (predicted x
    now, m, track), most urgent (furthest downstream) first. Lifted parts and parts past the
    window are left out."""
    out = []
    for tr in state.tracks:
        age_s = (state.now_us - tr["t_us"]) / 1e6
        x = tr["p"][0] + tr["v"][0] * age_s
        if tr["p"][2] > g.BELT_TOP_Z + LIFTED_M or x > g.PICK_X_RANGE[1]:
            continue
        out.append((x, tr))
    out.sort(key=lambda xt: -xt[0])
    return out


def spawn_time_us(track: Track, belt_speed_m_s: float) -> int:
    """When (us) the part of ``track`` landed on the belt, from its position and the belt speed
    ``belt_speed_m_s`` (m/s)."""
    travel_s = (track["p"][0] - g.SPAWN_X) / max(belt_speed_m_s, MIN_SPEED_M_S)
    return int(track["t_us"] - max(0.0, travel_s) * 1e6)


def next_part_s(state: LoopState) -> float:
    """Seconds until the next part is due on the belt of the loop in ``state``, from the newest
    part's spawn time and the object period (negative: overdue; 0 when nothing is known)."""
    if state.last_spawn_us is None:
        return 0.0
    period = state.object_period_s or DEFAULT_OBJECT_PERIOD_S
    return (state.last_spawn_us - state.now_us) / 1e6 + period


def idle_load(state: LoopState) -> LoopState:
    """``state`` as the observation sees it on an idle radio cell: no queueing delay (the load
    feature frozen, an ablation; the floor and the load control read the state itself)."""
    return dataclasses.replace(state, link=dataclasses.replace(state.link, cell_queueing_s=0.0))


def features(state: LoopState) -> np.ndarray:
    """The observation of ``state``: float32, shape (N_FEATURES,), names FEATURE_NAMES."""
    v = max(state.belt_speed_m_s, MIN_SPEED_M_S)
    x0, x1 = g.PICK_X_RANGE
    out: list[float] = []
    parts = belt_tracks(state)
    for k in range(TRACK_SLOTS):
        if k < len(parts):
            x, tr = parts[k]
            age_s = max(0.0, (state.now_us - tr["t_us"]) / 1e6)
            out += [1.0, (x - x0) / WINDOW_M, (x0 - x) / v / TIME_SCALE_S, (x1 - x) / v / TIME_SCALE_S,
                    tr["v"][0] / SPEED_SCALE_M_S, tr.get("sd", 0.0) / SD_SCALE_M, age_s / AGE_SCALE_S]
        else:  # no part: far upstream, plenty of time, nothing to refresh
            out += [0.0, -2.0, OBS_LIMIT, OBS_LIMIT, 0.0, 0.0, 0.0]
    lifted = any(tr["p"][2] > g.BELT_TOP_Z + LIFTED_M and abs(tr["p"][1]) <= g.BELT_HALF_WIDTH
                 for tr in state.tracks)
    frame_age = (OBS_LIMIT if state.last_frame_us is None
                 else (state.now_us - state.last_frame_us) / 1e6 / AGE_SCALE_S)
    period = state.object_period_s or DEFAULT_OBJECT_PERIOD_S
    out += [len(parts) / 2.0, float(lifted), frame_age, next_part_s(state) / period,
            state.belt_speed_m_s / SPEED_SCALE_M_S, period / PERIOD_SCALE_S,
            state.link.cell_queueing_s / DELAY_SCALE_S]
    # An unknown value (NaN) reads as none; an infinite one is as far as the scale goes.
    return np.array([0.0 if math.isnan(x) else _clip(x) for x in out], dtype=np.float32)
