"""Train the learned co-design policy with PPO (stable-baselines3) and export it for ONNX Runtime.

    python tools/train_policy.py                 # full budget, ships domain/models/policy.onnx
    python tools/train_policy.py --quick         # tiny budget into a temporary directory (CI)

Why PPO, what it needs and what it writes into ``--out``: docs/policy.md, "Training".
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from domain import policy_features as F
from domain.policy import DEFAULT_POLICY_MODEL
from training.policy.network import TABLE

ROOT = Path(__file__).resolve().parents[2]
HYPER = {  # PPO settings (stable-baselines3 names); saved in the model card
    "n_envs": 4, "n_steps": 512, "batch_size": 256, "n_epochs": 10, "learning_rate": 3e-4,
    "gamma": 0.995, "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.01, "vf_coef": 0.5,
    "max_grad_norm": 0.5, "net_arch": [64, 64], "activation": "tanh", "normalize_reward": True,
}
QUICK_HYPER = {"n_envs": 2, "n_steps": 256, "batch_size": 128, "n_epochs": 4}


def missing_packages() -> str | None:
    """None if the training packages import, else which are missing."""
    missing = []
    for mod in ("torch", "onnx", "gymnasium", "stable_baselines3"):
        try:
            __import__(mod)
        except ImportError:
            missing.append(mod)
    return ", ".join(missing) or None


# ---- training ----------------------------------------------------------------------------------
def make_env(lam: float, episode_s: float, load_control: bool = True) -> Any:
    from stable_baselines3.common.monitor import Monitor

    from training.policy.env import PickLoopEnv

    return Monitor(PickLoopEnv(lam=lam, episode_s=episode_s, load_control=load_control),
                   info_keywords=("summary",))


def train(lam: float, steps: int, seed: int, hyper: dict[str, Any], episode_s: float, threads: int,
          log: Any = print, load_control: bool = True) -> tuple[Any, list[dict[str, float]]]:
    """A PPO model trained for ``steps`` environment steps, and its history (one record per
    rollout: steps, mean return, success, mean PDP of the episodes that ended in it)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    torch.set_num_threads(threads)
    venv: Any = DummyVecEnv([lambda: make_env(lam, episode_s, load_control) for _ in range(hyper["n_envs"])])
    venv.seed(seed)
    if hyper["normalize_reward"]:
        # Rewards only: the exported network sees the raw features, as the Edge computes them.
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=hyper["gamma"])
    history: list[dict[str, float]] = []
    t0 = time.time()

    class Curve(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.episodes: list[dict[str, float]] = []

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                ep = info.get("episode")
                if ep is not None:
                    s = info["summary"]
                    self.episodes.append({"return": float(ep["r"]), "success": s["success"],
                                          "mean_pdp": s["mean_pdp"], "tasks": s["tasks"]})
            return True

        def _on_rollout_end(self) -> None:
            eps, self.episodes = self.episodes, []
            if not eps:
                return
            tasks = sum(e["tasks"] for e in eps)
            rec = {"steps": int(self.num_timesteps), "episodes": len(eps),
                   "return": round(float(np.mean([e["return"] for e in eps])), 3),
                   "success": round(sum(e["success"] * e["tasks"] for e in eps) / tasks, 4) if tasks else 1.0,
                   "mean_pdp": round(float(np.mean([e["mean_pdp"] for e in eps])), 4),
                   "seconds": round(time.time() - t0, 1)}
            history.append(rec)
            log(f"{rec['steps']:>7} steps: return {rec['return']:8.2f}, success {rec['success']:.3f}, "
                f"mean PDP {rec['mean_pdp']:.3f} ({rec['seconds']} s)")

    act = {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}[hyper["activation"]]
    model = PPO("MlpPolicy", venv, n_steps=hyper["n_steps"], batch_size=hyper["batch_size"],
                n_epochs=hyper["n_epochs"], learning_rate=hyper["learning_rate"], gamma=hyper["gamma"],
                gae_lambda=hyper["gae_lambda"], clip_range=hyper["clip_range"], ent_coef=hyper["ent_coef"],
                vf_coef=hyper["vf_coef"], max_grad_norm=hyper["max_grad_norm"], seed=seed, device="cpu",
                policy_kwargs={"net_arch": {"pi": list(hyper["net_arch"]), "vf": list(hyper["net_arch"])},
                               "activation_fn": act}, verbose=0)
    model.learn(total_timesteps=steps, callback=Curve())
    venv.close()
    return model, history


# ---- export ------------------------------------------------------------------------------------
def export_onnx(model: Any, path: Path) -> None:
    """The actor of ``model`` as ONNX: input ``obs`` (batch x N_FEATURES, float32), output
    ``logits`` (batch x (PDP levels + budget levels))."""
    import torch

    policy = model.policy

    class Actor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.features = policy.pi_features_extractor
            self.mlp = policy.mlp_extractor.policy_net
            self.head = policy.action_net

        def forward(self, obs: torch.Tensor) -> torch.Tensor:
            return self.head(self.mlp(self.features(obs)))

    actor = Actor().eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".onnx.tmp")
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of torch.export's, which needs the
        # onnxscript package; for an MLP both give the same graph.
        warnings.simplefilter("ignore")
        torch.onnx.export(actor, (torch.zeros(1, F.N_FEATURES),), str(tmp), input_names=["obs"],
                          output_names=["logits"], opset_version=17,
                          dynamic_axes={"obs": {0: "batch"}, "logits": {0: "batch"}}, dynamo=False)
    tmp.replace(path)


def onnx_check(model: Any, path: Path, seed: int, n: int = 2000) -> dict[str, float]:
    """ONNX Runtime against torch on observations a random policy visits in the environment:
    the largest logit difference and how often the most likely levels agree."""
    import onnxruntime as ort
    import torch

    from training.policy.env import PickLoopEnv

    env = PickLoopEnv()
    obs, _ = env.reset(seed=seed)
    xs: list[np.ndarray] = []
    while len(xs) < n:
        xs.append(obs)
        obs, _, _, truncated, _ = env.step(env.action_space.sample())
        if truncated:
            obs, _ = env.reset()
    x = np.stack(xs).astype(np.float32)
    torch_act, _ = model.predict(x, deterministic=True)
    with torch.no_grad():
        dist = model.policy.get_distribution(torch.from_numpy(x))
        torch_logits = torch.cat([d.logits for d in dist.distribution], dim=1).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    logits = sess.run(None, {"obs": x})[0]
    k = len(F.PDP_LEVELS)
    onnx_act = np.stack([logits[:, :k].argmax(1), logits[:, k:].argmax(1)], axis=1)
    # torch's Categorical stores normalised logits (log-probabilities): compare those.
    def logp(z: np.ndarray) -> np.ndarray:
        return z - np.log(np.exp(z - z.max(1, keepdims=True)).sum(1, keepdims=True)) - z.max(1, keepdims=True)

    diff = max(float(np.abs(logp(logits[:, :k]) - torch_logits[:, :k]).max()),
               float(np.abs(logp(logits[:, k:]) - torch_logits[:, k:]).max()))
    return {"observations": n, "max_log_prob_difference": diff,
            "argmax_agreement": float((onnx_act == torch_act).all(axis=1).mean())}


# ---- figure ------------------------------------------------------------------------------------
def curve_figure(history: list[dict[str, float]], title: str) -> Any:
    """Training curve: mean episode return, task success and mean PDP vs environment steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["steps"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, label in zip(axes, ("return", "success", "mean_pdp"),
                              ("episode return", "task success", "mean PDP"), strict=True):
        vals = np.array([h[key] for h in history], float)
        ax.plot(steps, vals, color="0.75", lw=1)
        if len(vals) >= 5:
            k = max(1, len(vals) // 10)
            smooth = np.convolve(vals, np.ones(k) / k, mode="valid")
            ax.plot(steps[k - 1:], smooth, color="C0", lw=2)
        ax.set_xlabel("environment steps (50 ms each)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# ---- the command -------------------------------------------------------------------------------
def run(args: argparse.Namespace, argv: list[str] | None = None) -> dict[str, Any]:
    """Train, export, check and evaluate; returns the model card (also written)."""
    import stable_baselines3
    import torch

    from training.policy.env import DEFAULT_LAMBDA, EPISODE_S, HEADROOM
    from training.policy.evaluate import (
        EVAL_SEED,
        lost_to_policy,
        policy_for,
        run_episodes,
    )
    from training.policy.work_cells import DEFAULT_FAMILY

    t_start = time.time()
    hyper = dict(HYPER)
    if args.quick:
        hyper.update(QUICK_HYPER)
    episode_s = args.episode_s or EPISODE_S
    lam = DEFAULT_LAMBDA if args.lam is None else args.lam
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    onnx_path = out / "policy.onnx"
    print(f"training PPO: lambda {lam}, {args.steps} steps, seed {args.seed}, {hyper['n_envs']} envs",
          flush=True)
    load_control = args.train_bounds == "all"
    model, history = train(lam, args.steps, args.seed, hyper, episode_s, args.threads, load_control=load_control)
    train_s = time.time() - t_start
    export_onnx(model, onnx_path)
    check = onnx_check(model, onnx_path, seed=args.seed + 7, n=500 if args.quick else 2000)
    card: dict[str, Any] = {
        "model": onnx_path.name,
        "architecture": f"MLP {hyper['net_arch']} ({hyper['activation']}), PPO actor: features -> "
                        f"PDP logits ({len(F.PDP_LEVELS)}) then budget logits ({len(F.BUDGET_LEVELS_MS)})",
        "parameters": int(sum(p.numel() for p in model.policy.parameters())),
        "actor_parameters": int(sum(p.numel() for n, p in model.policy.named_parameters()
                                    if n.startswith(("mlp_extractor.policy_net", "action_net")))),
        "input": "obs", "output": "logits",
        "features": list(F.FEATURE_NAMES), "feature_set": F.FEATURE_SET, "pdp_levels": list(F.PDP_LEVELS),
        "budget_levels_ms": list(F.BUDGET_LEVELS_MS),
        "decision": "PDP: mean level under softmax(PDP logits) (the trained stochastic policy's "
                    "per-frame keep probability); budget: argmax of the budget logits "
                    "(domain/policy.py decode)",
        "family": DEFAULT_FAMILY.card(),
        "lambda": lam,
        "reward": {"formula": "r = -Cost + lambda * Perf per 50 ms policy period",
                   "cost": "PDP x price(load / capacity) x (1 - fraction of injected bytes discarded "
                           "late) x 0.05 s: seconds of PDP-1 camera traffic the loop puts on the air, "
                           f"free under {HEADROOM:.0%} of the cell's capacity, price 1 at capacity",
                   "bounds": ("the action's PDP bounded by the safety floor and the load control "
                              "(PDP 1 with headroom, a cap past capacity), as at the Edge" if load_control else
                              "the action's PDP bounded by the safety floor only: the policy itself "
                              "learns what the load costs (the Edge adds the load control at run time)"),
                   "perf": "+1 per part placed, -1 per part missed or dropped, when its task ends"},
        "data": {"environment": "training/policy/env.py (cosim5g/PickLoop-v0)",
                 "cells": "training/policy/work_cells.py DEFAULT_FAMILY",
                 "network_table": f"training/{TABLE} (benchmarks/policy_network_table.py)",
                 "estimator_error": "domain/data/frame_model.json", "episode_s": episode_s,
                 "training_seed": args.seed, "evaluation_seeds": f"{EVAL_SEED}..",
                 },
        "training": {"algorithm": "PPO (stable-baselines3)", "steps": args.steps,
                     # PPO trains whole rollouts (n_envs x n_steps): what it trained, at least ``steps``.
                     "steps_trained": int(model.num_timesteps), **hyper,
                     "threads": args.threads, "train_s": round(train_s, 1), "history": history},
        "onnx_check": check,
        "versions": {"torch": torch.__version__, "stable_baselines3": stable_baselines3.__version__},
        # The arguments it was given (a sweep's worker gives its own, not the sweep's command line).
        "command": "python tools/train_policy.py " + " ".join(argv if argv is not None else sys.argv[1:]),
    }
    # The card must be complete before the learned policy can load the model for evaluation.
    card_path = onnx_path.with_suffix(".json")
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    episodes = args.eval_episodes
    print(f"ONNX vs torch: log-probabilities within {check['max_log_prob_difference']:.1e}, most likely "
          f"levels agree on {check['argmax_agreement']:.1%}; evaluating on {episodes} held-out cells ...",
          flush=True)
    evaluation = {}
    for name in ("none", "heuristic", "learned") if args.baselines else ("learned",):
        pol = policy_for(name, str(onnx_path) if name == "learned" else None)
        res = run_episodes(pol.decide, episodes=episodes, lam=lam, episode_s=episode_s,
                           bounded=name != "none")
        evaluation[name] = res
    # With the floor alone bounding it (the load control would override the policy's own choice),
    # and with its load feature frozen at an idle cell's value: how much of its choice is the load's.
    for name, decide in (("learned, floor only", policy_for("learned", str(onnx_path)).decide),
                         ("learned, floor only, load frozen",
                          policy_for("learned", str(onnx_path), load_feature="idle").decide)):
        evaluation[name] = run_episodes(decide, episodes=episodes, lam=lam, episode_s=episode_s, bounded=False,
                                        floor=True)
    for name, res in evaluation.items():
        if "none" in evaluation:
            res["lost_vs_none"] = lost_to_policy(res["rows"], evaluation["none"]["rows"])
        print(f"  {name:9s}: success {res['success']:.3f} ({res['placed']}/{res['tasks']}, "
              f"{res.get('lost_vs_none', '?')} lost vs none), mean PDP {res['mean_pdp']:.3f}, injected "
              f"{res['injected_mbps']:.2f} Mbit/s per loop, return {res['return']:.1f}")
    card["evaluation"] = {name: {k: v for k, v in res.items() if k != "rows"} for name, res in evaluation.items()}
    card["evaluation_rows"] = {name: res["rows"] for name, res in evaluation.items()}
    card["total_s"] = round(time.time() - t_start, 1)
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    # The shipped model's directory is package data: its curve goes with the other results.
    shipped = out.resolve() == DEFAULT_POLICY_MODEL.parent.resolve()
    curve = (ROOT / "results" / "policy" if shipped else out) / "training_curve.png"
    if history:
        curve.parent.mkdir(parents=True, exist_ok=True)
        curve_figure(history, f"PPO, lambda {lam}, seed {args.seed}").savefig(curve, dpi=110)
    print(f"wrote {onnx_path}, {card_path} and {curve} in {card['total_s']} s")
    return card


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="tiny budget (about a minute), into a temporary directory unless --out is given")
    ap.add_argument("--lambda", dest="lam", type=float, default=None,
                    help="task value lambda, seconds of full-rate traffic per task (default: the env's)")
    ap.add_argument("--seed", type=int, default=1, help="training seed")
    ap.add_argument("--steps", type=int, default=300_000, help="environment steps (50 ms each)")
    ap.add_argument("--episode-s", type=float, default=None, help="simulated seconds per episode")
    ap.add_argument("--eval-episodes", type=int, default=20, help="held-out cells to evaluate on")
    ap.add_argument("--no-baselines", dest="baselines", action="store_false",
                    help="evaluate the learned policy only (not none and heuristic beside it)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--train-bounds", choices=("all", "floor"), default="all",
                    help="what bounds the action in training: the safety floor and the load control "
                    "(all), or the floor only, so that the policy learns what the load costs (floor)")
    ap.add_argument("--out", type=Path, default=None,
                    help=f"output directory (default {DEFAULT_POLICY_MODEL.parent}, the shipped model)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    missing = missing_packages()
    if missing:
        print(f"SKIP: training needs {missing} (pip install -e '.[train]'); the runtime does not. "
              f"Nothing trained.")
        return 0
    if args.quick:
        args.steps, args.eval_episodes = min(args.steps, 3_000), min(args.eval_episodes, 2)
        args.episode_s = args.episode_s or 10.0
        if args.out is None:
            with tempfile.TemporaryDirectory(prefix="policy-quick-") as tmp:
                args.out = Path(tmp)
                run(args, argv)
            return 0
    if args.out is None:
        args.out = DEFAULT_POLICY_MODEL.parent
    run(args, argv)
    return 0
