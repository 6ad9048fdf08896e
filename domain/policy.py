"""Co-design policies (DESIGN 7): from a loop's control state to its dynamic QoS (PDP_r, L_r).

All policies share one interface so the Edge, the abstract loops and the benchmarks swap them by
name: ``none`` (PDP 1, conventional URLLC), ``fixed`` (constant PDP), ``heuristic`` (thresholds on
the state).
"""

from __future__ import annotations

from dataclasses import dataclass

from scenario.schema import PolicyConfig
from domain import cell_geometry as g


@dataclass(frozen=True)
class LoopState:
    """What the Edge knows of a loop when the policy runs."""

    now_us: int
    tracks: list[dict]  # tracker report: id, t_us, p, v, sd
    last_frame_us: int | None  # capture time of the last frame that arrived
    belt_speed_m_s: float


@dataclass(frozen=True)
class Qos:
    pdp: float
    pdb_us: int | None


class Policy:
    name = "base"

    def __init__(self, cfg: PolicyConfig) -> None:
        self.cfg = cfg

    def decide(self, state: LoopState) -> Qos:
        raise NotImplementedError


class NonePolicy(Policy):
    """Every frame matters: PDP 1, no delay budget."""

    name = "none"

    def decide(self, state: LoopState) -> Qos:
        return Qos(1.0, None)


class FixedPolicy(Policy):
    name = "fixed"

    def decide(self, state: LoopState) -> Qos:
        return Qos(self.cfg.pdp, int(self.cfg.latency_budget_ms * 1000))


class HeuristicPolicy(Policy):
    """Full PDP when the estimate is stale or a part is near or inside the pick window; a low PDP
    while the belt is empty; a middle PDP while a fresh track is still far upstream."""

    name = "heuristic"

    def decide(self, state: LoopState) -> Qos:
        c = self.cfg
        pdb = int(c.latency_budget_ms * 1000)
        if not state.tracks:
            return Qos(c.idle_pdp, pdb)
        lead_m = c.approach_s * state.belt_speed_m_s
        for tr in state.tracks:
            age_ms = (state.now_us - tr["t_us"]) / 1000
            x = tr["p"][0] + tr["v"][0] * (state.now_us - tr["t_us"]) / 1e6
            if age_ms > c.stale_ms or x >= g.PICK_X_RANGE[0] - lead_m:
                return Qos(1.0, pdb)
        return Qos(c.track_pdp, pdb)


POLICIES: dict[str, type[Policy]] = {p.name: p for p in (NonePolicy, FixedPolicy, HeuristicPolicy)}


def make_policy(cfg: PolicyConfig) -> Policy:
    return POLICIES[cfg.name](cfg)
