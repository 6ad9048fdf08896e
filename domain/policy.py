"""Co-design policies: from a loop's control state (``LoopState``) to its dynamic QoS (PDP_r,
L_r), one interface swapped by name: ``none``, ``fixed``, ``heuristic`` and ``learned`` (a small
network trained with deep RL, run with ONNX Runtime) (docs/policy.md)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
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
            self.input_name = self.session.get_inputs()[0].name
        except Exception as exc:  # a corrupt or incompatible file, a network of no input
            raise ValueError(f"learned policy model {path} cannot be loaded ({type(exc).__name__}: {exc}); "
                             f"retrain it: {TRAIN_COMMAND}") from None
        self._observe = ((lambda state: F.features(F.idle_load(state))) if cfg.load_feature == "idle"
                         else F.features)
        self.pdp_levels = tuple(float(p) for p in self.info["pdp_levels"])
        self.budget_levels_ms = tuple(float(b) for b in self.info["budget_levels_ms"])
        self._probe()

    def _probe(self) -> None:
        """One inference of two rows of features, so that a network that does not fit its card
        (input width, a batch fixed at one, output width against the card's levels) is refused
        here, naming the file, and not at the first policy period of a run."""
        width = len(F.FEATURE_NAMES)
        want = len(self.pdp_levels) + len(self.budget_levels_ms)
        try:
            out = self.session.run(None, {self.input_name: np.zeros((2, width), np.float32)})[0]
        except Exception as exc:
            shape = self.session.get_inputs()[0].shape
            raise ValueError(f"learned policy model {self.path} does not take a batch of {width} features "
                             f"(its input {self.input_name!r} has shape {shape}): {exc}; retrain it: "
                             f"{TRAIN_COMMAND}") from None
        if np.shape(out) != (2, want):
            raise ValueError(f"learned policy model {self.path} gives {np.shape(out)[1:]} outputs a state where "
                             f"its card {self.path.with_suffix('.json')} names {len(self.pdp_levels)} PDP and "
                             f"{len(self.budget_levels_ms)} budget levels ({want}); retrain it: {TRAIN_COMMAND}")

    def logits(self, state: LoopState) -> np.ndarray:
        """The network's output for ``state``: PDP logits then budget logits."""
        x = self._observe(state)[None]
        return np.asarray(self.session.run(None, {self.input_name: x})[0][0])

    def decide(self, state: LoopState) -> Qos:
        return decode(self.logits(state), self.pdp_levels, self.budget_levels_ms)

    def decide_many(self, states: list[LoopState]) -> list[Qos]:
        # One inference for all: the network's rows are the same to the bit as one at a time
        # (tests/unit/test_policy_learning.py), and the call's overhead is most of a small network's cost.
        if not states:
            return []
        x = np.stack([self._observe(state) for state in states])
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
        lo, hi = family[field]  # a pair of numbers, as load_model_card checked
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

    def bad(what: str) -> ValueError:
        return ValueError(f"learned policy model card {card}: {what}; retrain: {TRAIN_COMMAND}")

    try:
        info = json.loads(card.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise bad(f"not JSON ({exc})") from None
    if not isinstance(info, dict):
        raise bad(f"a JSON object was expected, it holds a {type(info).__name__}")
    if "features" not in info:
        raise bad("lacks 'features' (the observation the model was trained on)")
    # The cards of the first observation named no set: that set is "v1".
    trained, names = info.get("feature_set", "v1"), info["features"]
    if trained != F.FEATURE_SET:
        raise ValueError(f"learned policy {path} was trained on feature set {trained!r}, but "
                         f"domain/policy_features.py computes set {F.FEATURE_SET!r}; retrain it: {TRAIN_COMMAND}")
    if not isinstance(names, list) or tuple(names) != F.FEATURE_NAMES:
        given = names if isinstance(names, list) else []
        i = next((i for i, (a, b) in enumerate(zip(given, F.FEATURE_NAMES, strict=False)) if a != b),
                 min(len(given), len(F.FEATURE_NAMES)))
        raise bad(f"its features differ from set {F.FEATURE_SET!r} of domain/policy_features.py from feature "
                  f"{i} on ({given[i] if i < len(given) else 'none'!r} where the set has "
                  f"{F.FEATURE_NAMES[i] if i < len(F.FEATURE_NAMES) else 'none'!r})")
    for key in ("pdp_levels", "budget_levels_ms"):
        levels = info.get(key)
        if not isinstance(levels, list) or not levels or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in levels):
            raise bad(f"{key!r} must be a non-empty list of positive numbers, it is {levels!r}")
    if not all(v <= 1 for v in info["pdp_levels"]):
        raise bad(f"'pdp_levels' must lie in (0, 1], they are {info['pdp_levels']!r}")
    family = info.get("family")
    if family is not None:
        for field in ("belt_speed_m_s", "object_period_s"):
            pair = family.get(field) if isinstance(family, dict) else None
            if not (isinstance(pair, list) and len(pair) == 2 and all(
                    isinstance(v, int | float) and not isinstance(v, bool) for v in pair) and pair[0] <= pair[1]):
                raise bad(f"family.{field} must be a range [low, high], it is {pair!r}")
    return info


def policy_errors(cfg: PolicyConfig, cell: Any) -> list[tuple[str, str]]:
    """(field, message) of what keeps the policy ``cfg`` names from serving work cell ``cell``
    (a WorkCellConfig), found as an Edge would find it when it builds the policy: a learned model
    missing, corrupt, of another feature set, whose network does not fit its card, or trained on
    a family that does not hold the cell. Checked before a run starts; empty if it can serve."""
    if cfg.name != LearnedPolicy.name:
        return []
    path = Path(cfg.learned_model) if cfg.learned_model else DEFAULT_POLICY_MODEL
    try:
        info = _checked_model(str(path), *_stamp(path))
    except (ValueError, OSError) as exc:
        return [("policy.learned_model", str(exc))]
    try:
        check_family(info, path, cell)
    except ValueError as exc:
        return [("work_cell", str(exc))]
    return []


def _stamp(path: Path) -> tuple[float, int]:
    """When the model and its card last changed: a model retrained in place is checked again."""
    try:
        return max(path.stat().st_mtime, path.with_suffix(".json").stat().st_mtime), path.stat().st_size
    except OSError:
        return 0.0, -1


@lru_cache(maxsize=8)
def _checked_model(path: str, mtime: float, size: int) -> dict[str, Any]:
    """The card of the learned model at ``path``, once the model is built and probed (once per
    version of the files: every point of a sweep checks the same model)."""
    del mtime, size  # the cache key
    return LearnedPolicy(PolicyConfig(name="learned", learned_model=path)).info


POLICIES: dict[str, type[Policy]] = {
    p.name: p for p in (NonePolicy, FixedPolicy, HeuristicPolicy, LearnedPolicy)
}


def make_policy(cfg: PolicyConfig) -> Policy:
    """The policy a scenario's policy section ``cfg`` names, configured by it."""
    return POLICIES[cfg.name](cfg)
