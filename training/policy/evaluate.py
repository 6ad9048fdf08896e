"""Evaluation of co-design policies in the training environment: any ``domain.policy`` policy
(``learned`` through ONNX Runtime, as the Edge runs it) on the same cells of the family for all.
Task success, tasks missed or dropped, mean PDP and camera traffic per loop, mean latency budget,
mean cost and reward.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from domain.loop_state import LoopState
from domain.policy import Policy, Qos, make_policy
from scenario.schema import PolicyConfig
from training.policy.env import DEFAULT_LAMBDA, PickLoopEnv

EVAL_SEED = 100_000  # evaluation cells: episodes EVAL_SEED, EVAL_SEED + 1, ... (never trained on:
# training episodes are seeded from the training seed's own stream)
EVAL_EPISODES = 20


def policy_for(name: str, model: str | None = None, **cfg: Any) -> Policy:
    """A domain policy by name (``learned`` from ``model``, default domain/models/policy.onnx),
    with any other ``PolicyConfig`` fields in ``cfg``."""
    return make_policy(PolicyConfig(name=name, learned_model=model, **cfg))  # type: ignore[arg-type]


def run_episodes(decide: Callable[[LoopState], Qos], episodes: int = EVAL_EPISODES,
                 seed0: int = EVAL_SEED, lam: float = DEFAULT_LAMBDA, bounded: bool = True,
                 floor: bool | None = None, **env_kw: Any) -> dict[str, Any]:
    """Run ``decide`` on ``episodes`` cells; the pooled results and one row per episode.
    ``bounded``: the safety floor and the load control bound its PDP, as they bound every
    co-design policy at the Edge (not PDP 1, the reference); ``floor`` alone overrides the floor's."""
    env = PickLoopEnv(lam=lam, floor=bounded if floor is None else floor, load_control=bounded, **env_kw)
    rows = []
    for i in range(episodes):
        _, info = env.reset(seed=seed0 + i)
        ret = 0.0
        while True:
            _, r, _, truncated, step_info = env.step_qos(decide(env.loop_state()))
            ret += r
            if truncated:
                break
        s = step_info["summary"]
        rows.append({"seed": seed0 + i, "loops": info["loops"],
                     "belt_speed_m_s": info["work_cell"]["belt_speed_m_s"],
                     "object_period_s": info["work_cell"]["object_period_s"], "return": ret, **s})
    return {"episodes": episodes, "lambda": lam, **pool(rows), "rows": rows}


def at_lambda(result: dict[str, Any], lam: float) -> dict[str, Any]:
    """``result`` of ``run_episodes`` with its returns as the reward of ``lam`` prices them: a
    return is ``lam`` x (placed - missed - dropped) - cost, and only ``lam`` differs. A result of
    that lambda already (or of none named: a policy's own evaluation) keeps its returns as summed."""
    if result.get("lambda", lam) == lam:
        return {**result, "lambda": lam}
    rows = [{**r, "return": lam * (r["placed"] - r["missed"] - r["dropped"]) - r["cost"]} for r in result["rows"]]
    return {**result, "lambda": lam, **pool(rows), "rows": rows}


def pool(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Pooled numbers over episode rows."""
    tasks = sum(r["tasks"] for r in rows)
    placed = sum(r["placed"] for r in rows)
    return {
        "tasks": tasks, "placed": placed, "missed": sum(r["missed"] for r in rows),
        "dropped": sum(r["dropped"] for r in rows), "success": placed / tasks if tasks else 1.0,
        "mean_pdp": float(np.mean([r["mean_pdp"] for r in rows])),
        "injected_mbps": float(np.mean([r["injected_mbps"] for r in rows])),
        "mean_budget_ms": float(np.mean([r["mean_budget_ms"] for r in rows])),
        "cost": float(np.mean([r["cost"] for r in rows])),
        "return": float(np.mean([r["return"] for r in rows])),
    }


def lost_to_policy(rows: list[dict[str, Any]], reference: list[dict[str, Any]]) -> int:
    """Tasks a policy lost (missed or dropped) beyond those the reference (``none``) lost on the
    same cells, summed over the episodes where it lost more. Failures, not placements, are
    compared: a part still on its way when an episode ends counts for neither."""
    ref = {r["seed"]: r["missed"] + r["dropped"] for r in reference}
    return sum(max(0, r["missed"] + r["dropped"] - ref[r["seed"]]) for r in rows if r["seed"] in ref)
