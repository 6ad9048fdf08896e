"""Co-design policies: from a loop's control state (``LoopState``) to its dynamic QoS (PDP_r,
L_r), one interface swapped by name: ``none``, ``fixed``, ``heuristic`` and ``learned`` (a small
network trained with deep RL, run with ONNX Runtime) (docs/policy.md)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from domain import policy_features as F
from domain import work_cell as g
from domain.loop_state import LoopState
from domain.tracker import ACCEL_SD, GATE_M
from scenario.schema import PolicyConfig
from wire.bodies import Track

MODEL_DIR = Path(__file__).parent / "models"
DEFAULT_POLICY_MODEL = MODEL_DIR / "policy.onnx"
TRAIN_COMMAND = "make train-policy (python tools/train_policy.py)"


@dataclass(frozen=True)
class Qos:
    """A loop's QoS: ``pdp`` the probability (0-1) that the camera keeps a frame, ``pdb_us`` the
    latency budget (us; None: none)."""

    pdp: float
    pdb_us: int | None


class Policy:
    """A co-design policy configured by a scenario's policy section ``cfg``."""

    name = "base"

    def __init__(self, cfg: PolicyConfig) -> None:
        self.cfg = cfg

    def decide(self, state: LoopState) -> Qos:
        """The QoS of the loop in ``state``."""
        raise NotImplementedError

    def decide_many(self, states: list[LoopState]) -> list[Qos]:
        """``decide`` for each of ``states`` (loops decided at once: no policy keeps state
        between decisions, so their order does not matter)."""
        return [self.decide(state) for state in states]


class NonePolicy(Policy):
    """Every frame matters: PDP 1, no delay budget."""

    name = "none"

    def decide(self, state: LoopState) -> Qos:
        return Qos(1.0, None)


class FixedPolicy(Policy):
    """The configured PDP and latency budget, whatever the state."""

    name = "fixed"

    def decide(self, state: LoopState) -> Qos:
        return Qos(self.cfg.pdp, int(self.cfg.latency_budget_ms * 1000))


# PDPs computed on a continuum are signalled in steps of this: a QoS message goes to the camera
# whenever the QoS changes, and a change below a step would make no difference to the loop.
PDP_STEP = 0.05

# Heuristic constants. A frame kept with probability p arrives, frame after frame, as a Bernoulli
# stream: the chance that none comes within n frames is (1 - p)^n.
MISS_RISK = 0.01  # accepted chance that no frame comes before a deadline
PICK_TIME_S = 0.5  # the arm's alignment to sealed grip (the controller's GRASP_TIME_S)
SD_LIMIT_M = GATE_M / 2  # a prediction this uncertain may match the wrong part


def gate_time_s(track: Track, age_s: float) -> float:
    """Time left (s) before the tracker's prediction of ``track``, its sd grown by the tracker's
    motion model over the estimate's age ``age_s``, leaves half the association gate."""
    return math.sqrt(2 * max(0.0, SD_LIMIT_M - track.get("sd", 0.0)) / ACCEL_SD) - age_s


def step_up(pdp: float) -> float:
    """``pdp`` rounded up to PDP_STEP, at most 1 (a QoS is signalled in those steps)."""
    return round(min(1.0, math.ceil(round(pdp / PDP_STEP, 6)) * PDP_STEP), 4)


def pdp_for_deadline(deadline_s: float, fps: float, useful: float = 1.0, risk: float = MISS_RISK) -> float:
    """The lowest PDP that brings a useful frame within ``deadline_s`` (s) with probability
    1 - ``risk``, when a kept frame is useful (arrives and shows the part) with probability
    ``useful``: each of the ``deadline_s * fps`` captures (``fps`` in frame/s) is useful with
    PDP x useful, independently."""
    n = deadline_s * fps
    if n <= 1.0:
        return 1.0
    return min(1.0, (1.0 - risk ** (1.0 / n)) / max(useful, 1e-6))


class HeuristicPolicy(Policy):
    """Rules on the cell's kinematics, the same on any belt:

    - a part within ``approach_s`` of the pick window (in belt travel time), or inside it:
      PDP 1, the arm is about to work on it;
    - a part further upstream: ``track_pdp``, raised when its estimate is older than
      ``stale_ms`` so that a frame comes before the part's approach starts, and raised as the
      tracker's prediction of it (its sd grown by the tracker's own motion model over the
      estimate's age) nears the association gate, so that the track is kept; upstream parts
      never force PDP 1 by their age alone (under load every estimate is old, and PDP 1 for
      all would only load the cell more);
    - an empty belt: ``idle_pdp`` while the next part cannot have landed yet (the schema keeps
      spawn jitter under half the object period), then the PDP that sees a new part, 99 times in
      100, while the arm still has time to pick it in the window.

    The latency budget is ``latency_budget_ms`` throughout; the PDP is rounded up to PDP_STEP."""

    name = "heuristic"

    def decide(self, state: LoopState) -> Qos:
        c = self.cfg
        pdb = int(c.latency_budget_ms * 1000)
        v = max(state.belt_speed_m_s, F.MIN_SPEED_M_S)
        x0, x1 = g.PICK_X_RANGE
        parts = F.belt_tracks(state)
        pdp = c.idle_pdp
        for x, tr in parts:
            t_reach = (x0 - x) / v  # time until the part reaches the pick window
            if t_reach <= c.approach_s:
                return Qos(1.0, pdb)
            age_s = max(0.0, (state.now_us - tr["t_us"]) / 1e6)
            slack_s = t_reach - c.approach_s  # until the arm needs a fresh estimate
            need = c.track_pdp
            if age_s * 1000 > c.stale_ms:
                need = max(need, pdp_for_deadline(slack_s, state.fps))
            gate_s = gate_time_s(tr, age_s)
            need = max(need, pdp_for_deadline(gate_s, state.fps))
            pdp = max(pdp, need)
        if not parts and not self._next_part_unlikely(state):
            # A new part: seen early enough that the arm can still pick it in the window.
            window_s = (x1 - x0) / v
            reach_s = (x0 - g.SPAWN_X) / v
            deadline = (reach_s + window_s - c.approach_s - PICK_TIME_S) / 2
            pdp = max(pdp, pdp_for_deadline(deadline, state.fps))
        return Qos(step_up(pdp), pdb)

    @staticmethod
    def _next_part_unlikely(state: LoopState) -> bool:
        """True while the next part cannot have landed yet: spawn jitter is under half the
        object period, so the next part lands at least half a period after the last one."""
        if state.last_spawn_us is None or state.object_period_s is None:
            return False
        return state.now_us < state.last_spawn_us + state.object_period_s * 1e6 / 2


class LearnedPolicy(Policy):
    """A small network trained with PPO in the single-loop environment of training/policy/, run
    with ONNX Runtime on one thread, loaded from ``cfg.learned_model`` (default: the shipped
    model). It maps ``policy_features.features(state)`` to one logit per PDP level and per
    latency budget.

    The PDP is the mean level under the network's distribution (softmax of the PDP logits): the
    trained policy draws a level every period and the camera keeps each frame with that level,
    so each frame is kept with the mean level's probability; the argmax would instead round
    every mixed decision to one level (mostly the lowest, where the policy hedges). The budget
    is the most likely level."""

    name = "learned"

    def __init__(self, cfg: PolicyConfig) -> None:
        super().__init__(cfg)
        path = Path(cfg.learned_model) if cfg.learned_model else DEFAULT_POLICY_MODEL
        self.path = path
        self.info = load_model_card(path)
        import onnxruntime as ort  # imported here: the other policies must not need it

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1  # the Edge runs the policy on one emulated core
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # a corrupt or incompatible file
            raise ValueError(f"learned policy model {path} cannot be loaded ({exc}); "
                             f"retrain it: {TRAIN_COMMAND}") from None
        self.input_name = self.session.get_inputs()[0].name
        self.pdp_levels = tuple(float(p) for p in self.info["pdp_levels"])
        self.budget_levels_ms = tuple(float(b) for b in self.info["budget_levels_ms"])

    def logits(self, state: LoopState) -> np.ndarray:
        """The network's output for ``state``: PDP logits then budget logits."""
        x = F.features(state)[None]
        return np.asarray(self.session.run(None, {self.input_name: x})[0][0])

    def decide(self, state: LoopState) -> Qos:
        return decode(self.logits(state), self.pdp_levels, self.budget_levels_ms)

    def decide_many(self, states: list[LoopState]) -> list[Qos]:
        # One inference for all: the network's rows are the same to the bit as one at a time
        # (tests/unit/test_policy_learning.py), and the call's overhead is most of a small network's cost.
        if not states:
            return []
        x = np.stack([F.features(state) for state in states])
        out = self.session.run(None, {self.input_name: x})[0]
        return [decode(row, self.pdp_levels, self.budget_levels_ms) for row in out]


def decode(logits: np.ndarray, pdp_levels: tuple[float, ...], budget_levels_ms: tuple[float, ...]) -> Qos:
    """The QoS of the learned policy's output ``logits`` (PDP logits, then budget logits) over
    the levels ``pdp_levels`` and ``budget_levels_ms`` (ms): mean PDP level, most likely budget."""
    n = len(pdp_levels)
    e = np.exp(logits[:n] - np.max(logits[:n]))
    prob = e / e.sum()
    pdp = round(float(prob @ np.asarray(pdp_levels)) / PDP_STEP) * PDP_STEP
    budget_ms = budget_levels_ms[int(np.argmax(logits[n:]))]
    return Qos(round(float(np.clip(pdp, min(pdp_levels), 1.0)), 4), int(budget_ms * 1000))


def check_family(info: dict[str, Any], path: Path, cell: Any) -> None:
    """Refuse a work cell ``cell`` (a WorkCellConfig) outside the family the learned policy at
    ``path`` was trained on (the ``family`` ranges of its card ``info``), naming the field, the
    cell's value and the family's range."""
    family = info.get("family")
    if not family:
        raise ValueError(f"learned policy model card {path.with_suffix('.json')} names no training "
                         f"family; retrain: {TRAIN_COMMAND}")
    for field in ("belt_speed_m_s", "object_period_s"):
        lo, hi = family[field]
        value = getattr(cell, field)
        if not lo <= value <= hi:
            raise ValueError(f"work_cell.{field} = {value} is outside the family the learned policy {path} "
                             f"was trained on ({field} {lo}-{hi}); use a cell of that family or "
                             f"retrain over one that holds it: {TRAIN_COMMAND}")


def load_model_card(path: Path) -> dict[str, Any]:
    """The model card beside the learned policy at ``path`` (``policy.json`` for
    ``policy.onnx``), checked against this code's observation; errors name the file and how to
    make it."""
    if not path.is_file():
        raise FileNotFoundError(f"learned policy model {path} not found; train it: {TRAIN_COMMAND}, "
                                f"or set policy.learned_model to an exported model")
    card = path.with_suffix(".json")
    if not card.is_file():
        raise FileNotFoundError(f"learned policy model card {card} (beside {path}) not found; "
                                f"retrain: {TRAIN_COMMAND}")
    info = json.loads(card.read_text())
    trained = info.get("feature_set", "v1")
    if trained != F.FEATURE_SET or tuple(info.get("features", ())) != F.FEATURE_NAMES:
        raise ValueError(f"learned policy {path} was trained on feature set {trained!r} "
                         f"({', '.join(info.get('features', ())[-2:])}, ...), but domain/policy_features.py "
                         f"computes set {F.FEATURE_SET!r} ({', '.join(F.FEATURE_NAMES[-2:])}, ...); "
                         f"retrain it: {TRAIN_COMMAND}")
    for key in ("pdp_levels", "budget_levels_ms"):
        if not info.get(key):
            raise ValueError(f"learned policy model card {card} lacks {key!r}; retrain: {TRAIN_COMMAND}")
    return info


POLICIES: dict[str, type[Policy]] = {
    p.name: p for p in (NonePolicy, FixedPolicy, HeuristicPolicy, LearnedPolicy)
}


def make_policy(cfg: PolicyConfig) -> Policy:
    """The policy a scenario's policy section ``cfg`` names, configured by it."""
    return POLICIES[cfg.name](cfg)
