"""The learned co-design policy: its observation (one function for training and the Edge), the
training environment (Gymnasium's checker, determinism per seed), the network model, the
shipped ONNX model under the ``learned`` policy, the errors when a model is missing, the
kinematic heuristic, and (with torch) the quick training path end to end."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from domain import policy_features as F
from domain import work_cell as g
from domain.congestion import LinkEstimate
from domain.edge_side import CoDesign
from domain.loop_state import LoopState
from domain.policy import DEFAULT_POLICY_MODEL, LearnedPolicy, make_policy
from domain.tracker import Tracker
from scenario.schema import PolicyConfig, Scenario, WorkCellConfig

ROOT = Path(__file__).parents[2]
needs_gym = pytest.mark.skipif(importlib.util.find_spec("gymnasium") is None,
                               reason="the training environment needs gymnasium (pip install gymnasium)")


def track(tid: int, x: float, t_us: int = 0, v: float = 0.2, z: float = 0.78, sd: float = 0.003) -> dict:
    return {"id": tid, "t_us": t_us, "p": [x, 0.0, z], "v": [v, 0.0, 0.0], "sd": sd}


def state(tracks: list[dict], now_us: int = 0, belt: float = 0.2, **kw: object) -> LoopState:
    return LoopState(now_us, tracks, 0, belt, **kw)  # type: ignore[arg-type]


# ---- the observation ----------------------------------------------------------------------------
def test_features_describe_the_most_urgent_parts_first() -> None:
    s = state([track(0, -0.5), track(1, 0.0), track(2, 0.9), track(3, -0.2, z=0.95)], now_us=100_000,
              object_period_s=3.0, loops=10, last_spawn_us=50_000, link=LinkEstimate(cell_queueing_s=0.02))
    x = F.features(s)
    assert x.shape == (F.N_FEATURES,) and x.dtype == np.float32
    assert len(F.FEATURE_NAMES) == F.N_FEATURES == len(set(F.FEATURE_NAMES))
    obs = dict(zip(F.FEATURE_NAMES, x.tolist(), strict=True))
    # Part 2 is past the window and part 3 is lifted: the slots hold part 1 then part 0.
    assert obs["track0_present"] == 1.0 and obs["track1_present"] == 1.0
    x1 = 0.0 + 0.2 * 0.1
    assert obs["track0_window_pos"] == pytest.approx((x1 - g.PICK_X_RANGE[0]) / F.WINDOW_M, abs=1e-5)
    assert obs["track0_t_reach"] < 0 < obs["track1_t_reach"]  # inside the window / upstream
    assert obs["n_parts"] == 1.0 and obs["lifted"] == 1.0
    assert obs["queueing_delay"] == pytest.approx(0.02 / F.DELAY_SCALE_S)
    assert obs["next_part"] == pytest.approx((0.05 - 0.1 + 3.0) / 3.0, abs=1e-5)
    assert np.all(np.abs(x) <= F.OBS_LIMIT)


def test_features_of_an_empty_belt_are_finite_and_bounded() -> None:
    s = LoopState(10**9, [], None, 0.0)  # no frame yet, a stopped belt: nothing divides by zero
    x = F.features(s)
    assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= F.OBS_LIMIT)
    assert x[F.FEATURE_NAMES.index("track0_present")] == 0.0
    # A load past any scale is the scale's end, not an idle cell's 0; an unknown one reads as none.
    delay = F.FEATURE_NAMES.index("queueing_delay")
    assert F.features(LoopState(10**9, [], None, 0.3, link=LinkEstimate(cell_queueing_s=math.inf)))[delay] == F.OBS_LIMIT
    assert F.features(LoopState(10**9, [], None, 0.3, link=LinkEstimate(cell_queueing_s=math.nan)))[delay] == 0.0


def test_codesign_builds_the_state_from_the_cell_and_remembers_spawns() -> None:
    sc = Scenario(loops=12, work_cell=WorkCellConfig(belt_speed_m_s=0.3, object_period_s=3.0))
    cd = CoDesign.for_scenario(sc)
    tracker = Tracker((0.3, 0.0, 0.0))
    tracker.update(400_000, [np.array([-0.4, 0.0, 0.78])])
    s = cd.state(0, 450_000, tracker, 400_000)
    assert (s.belt_speed_m_s, s.object_period_s, s.loops, s.fps) == (0.3, 3.0, 12, 30)
    # Landed at SPAWN_X: 0.15 m of belt at 0.3 m/s before the frame.
    assert s.last_spawn_us == pytest.approx(400_000 - 0.15 / 0.3 * 1e6, abs=1)
    # The old constructor (a belt speed) still works: the cell is then known by its speed.
    old = CoDesign(PolicyConfig(), 0.2)
    assert old.state(0, 0, Tracker(), None).object_period_s is None


# ---- the kinematic heuristic --------------------------------------------------------------------
def test_heuristic_full_pdp_by_time_to_the_window_on_any_belt() -> None:
    h = make_policy(PolicyConfig(name="heuristic", approach_s=1.0))
    x0 = g.PICK_X_RANGE[0]
    for belt in (0.1, 0.2, 0.5):
        near = track(0, x0 - 0.9 * belt, v=belt)  # 0.9 s of belt travel before the window
        far = track(0, x0 - 1.5 * belt, v=belt)
        assert h.decide(state([near], belt=belt)).pdp == 1.0
        assert h.decide(state([far], belt=belt)).pdp < 1.0


def test_heuristic_never_forces_pdp_1_for_an_old_upstream_estimate() -> None:
    """Under load every estimate is old: upstream parts must not push every loop to PDP 1."""
    h = make_policy(PolicyConfig(name="heuristic", approach_s=1.0, stale_ms=150, track_pdp=0.5))
    far = track(0, -1.4, v=0.2, t_us=0)  # 5 s from the window when seen
    assert h.decide(state([far], now_us=200_000)).pdp < 1.0
    # ... but the PDP rises as its prediction leaves the tracker's gate.
    assert h.decide(state([far], now_us=380_000)).pdp > h.decide(state([far], now_us=0)).pdp


def test_heuristic_on_an_empty_belt_waits_for_the_next_part() -> None:
    h = make_policy(PolicyConfig(name="heuristic", idle_pdp=0.1))
    kw = {"object_period_s": 2.0, "last_spawn_us": 0}
    assert h.decide(state([], now_us=500_000, belt=0.5, **kw)).pdp == 0.1  # cannot have landed yet
    fast = h.decide(state([], now_us=1_500_000, belt=0.5, **kw)).pdp  # may land any time
    slow = h.decide(state([], now_us=1_500_000, belt=0.1, **kw)).pdp
    assert fast > slow >= 0.1  # a fast belt leaves less time to see a new part


# ---- the learned policy at run time ------------------------------------------------------------
def test_learned_policy_runs_the_shipped_model() -> None:
    pol = make_policy(PolicyConfig(name="learned"))
    levels_us = {int(b * 1000) for b in F.BUDGET_LEVELS_MS}
    states = [state([]), state([track(0, -0.5)], now_us=30_000, loops=30),
              state([track(0, 0.1), track(1, -0.5)], now_us=60_000, belt=0.4, object_period_s=2.5),
              state([track(0, -0.3, z=0.9)], now_us=10**6, loops=40)]
    for s in states:
        q = pol.decide(s)
        assert min(F.PDP_LEVELS) <= q.pdp <= 1.0
        assert q.pdb_us in levels_us
    card = json.loads(DEFAULT_POLICY_MODEL.with_suffix(".json").read_text())
    assert card["features"] == list(F.FEATURE_NAMES) and "lambda" in card


def test_policies_decide_many_loops_as_one_at_a_time() -> None:
    """One inference for many loops gives each loop the QoS it gets alone, to the bit."""
    rng = np.random.default_rng(7)
    states = [state([track(k, float(rng.uniform(-0.6, 0.2))) for k in range(int(rng.integers(0, 3)))],
                    now_us=int(rng.integers(0, 10**6)), belt=float(rng.uniform(0.1, 0.5)),
                    loops=int(rng.integers(1, 200)), object_period_s=float(rng.uniform(2, 6)),
                    link=LinkEstimate(cell_queueing_s=float(rng.exponential(0.05))))
              for _ in range(300)]
    for name in ("learned", "heuristic", "none"):
        pol = make_policy(PolicyConfig(name=name))
        assert pol.decide_many(states) == [pol.decide(s) for s in states], name
        assert pol.decide_many([]) == []


def test_the_load_feature_frozen_reads_every_state_as_on_an_idle_cell() -> None:
    """``load_feature: idle`` feeds the network the state with no queueing delay, and only that."""
    loaded = state([track(0, -0.3)], now_us=40_000, link=LinkEstimate(cell_queueing_s=0.2, delay_s=0.3))
    idle = F.idle_load(loaded)
    assert idle.link.cell_queueing_s == 0.0 and idle.link.delay_s == 0.3 and idle.tracks == loaded.tracks
    live = make_policy(PolicyConfig(name="learned"))
    frozen = make_policy(PolicyConfig(name="learned", load_feature="idle"))
    assert isinstance(live, LearnedPolicy) and isinstance(frozen, LearnedPolicy)
    assert np.array_equal(frozen.logits(loaded), live.logits(idle))
    assert frozen.decide_many([loaded, idle]) == [live.decide(idle)] * 2
    assert not np.array_equal(live.logits(loaded), live.logits(idle)), "the feature reaches the network"


def test_missing_model_raises_naming_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "policy.onnx"
    with pytest.raises(FileNotFoundError, match=str(missing)) as err:
        make_policy(PolicyConfig(name="learned", learned_model=str(missing)))
    assert "make train-policy" in str(err.value)


def test_model_trained_on_other_features_is_refused(tmp_path: Path) -> None:
    model = tmp_path / "policy.onnx"
    shutil.copyfile(DEFAULT_POLICY_MODEL, model)
    card = json.loads(DEFAULT_POLICY_MODEL.with_suffix(".json").read_text())
    card["features"] = card["features"][:-1]
    model.with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match=rf"features differ from set '{F.FEATURE_SET}' .* from feature "
                                         rf"{len(F.FEATURE_NAMES) - 1} on \('none' where the set has "
                                         rf"'{F.FEATURE_NAMES[-1]}'\)"):
        make_policy(PolicyConfig(name="learned", learned_model=str(model)))
    # A model of the previous observation (no feature_set in its card: "v1") names both sets.
    del card["feature_set"]
    model.with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match=f"'v1'.*'{F.FEATURE_SET}'"):
        make_policy(PolicyConfig(name="learned", learned_model=str(model)))


def doctored(tmp_path: Path, card_edit: dict[str, object] | None = None, onnx: bytes | None = None) -> Path:
    """A copy of the shipped model in ``tmp_path``, its card's fields replaced by ``card_edit``
    (or its text by a string) and its network by ``onnx``."""
    model = tmp_path / "policy.onnx"
    model.write_bytes(onnx if onnx is not None else DEFAULT_POLICY_MODEL.read_bytes())
    card = json.loads(DEFAULT_POLICY_MODEL.with_suffix(".json").read_text())
    model.with_suffix(".json").write_text(json.dumps({**card, **(card_edit or {})}))
    return model


def linear_onnx(width: int, outputs: int, batch: int | str = "n") -> bytes:
    """A one-layer network of ``width`` inputs and ``outputs`` outputs (onnx needed)."""
    pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    w = numpy_helper.from_array(np.zeros((width, outputs), np.float32), "w")
    graph = helper.make_graph([helper.make_node("MatMul", ["obs", "w"], ["logits"])], "p",
                              [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [batch, width])],
                              [helper.make_tensor_value_info("logits", TensorProto.FLOAT, [batch, outputs])], [w])
    return bytes(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString())


@pytest.mark.parametrize("edit,match", [
    ({"pdp_levels": [0.1, 0.2, 0.25, 0.5, 0.75, 1.0]}, r"gives \(9,\) outputs a state .* names 6 PDP and 4 budget"),
    ({"budget_levels_ms": [25, 50]}, r"gives \(9,\) outputs .* 5 PDP and 2 budget levels \(7\)"),
    ({"pdp_levels": ["a", "b"]}, r"'pdp_levels' must be a non-empty list of positive numbers"),
    ({"pdp_levels": [0.5, 2.0]}, r"'pdp_levels' must lie in \(0, 1\]"),
    ({"family": {"belt_speed_m_s": 0.3, "object_period_s": [2, 6]}}, r"family.belt_speed_m_s must be a range"),
    ({"features": None}, r"features differ"),
])
def test_a_card_that_does_not_fit_its_network_or_is_malformed_is_refused_naming_it(
        tmp_path: Path, edit: dict[str, object], match: str) -> None:
    model = doctored(tmp_path, edit)
    with pytest.raises(ValueError, match=match) as err:
        make_policy(PolicyConfig(name="learned", learned_model=str(model)))
    assert str(model.with_suffix(".json")) in str(err.value) or str(model) in str(err.value)


@pytest.mark.parametrize("text,match", [("{not json", "not JSON"), ("[1, 2]", "a JSON object was expected"),
                                        ("", "not JSON")])
def test_a_card_that_is_no_json_object_is_refused_naming_it(tmp_path: Path, text: str, match: str) -> None:
    model = doctored(tmp_path)
    model.with_suffix(".json").write_text(text)
    with pytest.raises(ValueError, match=f"card {model.with_suffix('.json')}: {match}"):
        make_policy(PolicyConfig(name="learned", learned_model=str(model)))


@pytest.mark.parametrize("width,outputs,batch,match", [
    (len(F.FEATURE_NAMES) - 1, 9, "n", "does not take a batch of 21 features"),
    (len(F.FEATURE_NAMES), 9, 1, "does not take a batch of 21 features"),
    (len(F.FEATURE_NAMES), 7, "n", r"gives \(7,\) outputs"),
])
def test_a_network_that_does_not_fit_the_features_or_its_card_is_refused_when_built(
        tmp_path: Path, width: int, outputs: int, batch: int | str, match: str) -> None:
    model = doctored(tmp_path, onnx=linear_onnx(width, outputs, batch))
    with pytest.raises(ValueError, match=match) as err:
        make_policy(PolicyConfig(name="learned", learned_model=str(model)))
    assert str(model) in str(err.value)


def test_a_model_that_cannot_serve_the_scenario_is_refused_before_a_run_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from interfaces.cli import main

    model = doctored(tmp_path, {"budget_levels_ms": [25, 50]})
    scenario = str(ROOT / "configs" / "scenarios" / "co_design.yaml")
    learned = ["--set", "policy.name=learned", "--set", f"policy.learned_model={model}"]
    assert main(["validate", scenario, *learned]) == 2
    assert f"policy.learned_model: learned policy model {model} gives" in capsys.readouterr().err
    assert main(["run", scenario, *learned, "--results", str(tmp_path / "runs")]) == 2
    assert not (tmp_path / "runs").exists(), "refused before any run directory or process"
    assert main(["validate", scenario, "--set", "policy.name=learned", "--set", "work_cell.belt_speed_m_s=0.8"]) == 2
    assert "work_cell: work_cell.belt_speed_m_s = 0.8 is outside the family" in capsys.readouterr().err


def test_a_cell_outside_the_learned_policys_family_is_refused_naming_both() -> None:
    card = json.loads(DEFAULT_POLICY_MODEL.with_suffix(".json").read_text())
    lo, hi = card["family"]["belt_speed_m_s"]
    CoDesign(PolicyConfig(name="learned"), WorkCellConfig(belt_speed_m_s=hi))
    with pytest.raises(ValueError, match=rf"work_cell.belt_speed_m_s = 0.8 .*belt_speed_m_s {lo}-{hi}"):
        CoDesign(PolicyConfig(name="learned"), WorkCellConfig(belt_speed_m_s=0.8))


# ---- the training environment -----------------------------------------------------------------
@needs_gym
def test_environment_passes_gymnasium_checker() -> None:
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    from training.policy.env import ENV_ID, PickLoopEnv

    check_env(PickLoopEnv(episode_s=3.0), skip_render_check=True)
    env = gym.make(ENV_ID, episode_s=1.0)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (F.N_FEATURES,)
    env.close()


@needs_gym
def test_environment_is_deterministic_per_seed() -> None:
    from training.policy.env import PickLoopEnv

    def trace(seed: int) -> tuple[list[np.ndarray], list[float], dict]:
        env = PickLoopEnv(episode_s=4.0)
        obs, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        out, rewards = [obs], []
        truncated = False
        while not truncated:
            obs, r, _, truncated, _ = env.step(env.action_space.sample())
            out.append(obs)
            rewards.append(r)
        return out, rewards, info

    a, b, c = trace(3), trace(3), trace(4)
    assert len(a[0]) == 81  # 4 s of 50 ms policy periods, plus the first observation
    assert all(np.array_equal(x, y) for x, y in zip(a[0], b[0], strict=True)) and a[1] == b[1]
    assert a[2] == b[2] and a[2]["work_cell"] != c[2]["work_cell"]


@needs_gym
def test_observation_is_the_shared_feature_function_and_cells_stay_in_the_schema() -> None:
    from training.policy.env import PickLoopEnv
    from training.policy.work_cells import DEFAULT_FAMILY

    env = PickLoopEnv(episode_s=2.0)
    obs, _ = env.reset(seed=1)
    for _ in range(10):
        obs, *_ = env.step(np.array([4, 2]))
    assert np.array_equal(obs, F.features(env.loop_state()))
    rng = np.random.default_rng(0)
    for _ in range(200):  # the family's draws pass the schema's validators (WorkCellConfig raises)
        cell, loops = DEFAULT_FAMILY.draw(rng)
        assert 0.1 <= cell.belt_speed_m_s <= 0.5 and 2.0 <= cell.object_period_s <= 6.0 and 1 <= loops <= 40


@needs_gym
def test_network_model_follows_the_measured_cell() -> None:
    from training.policy.network import NetworkModel

    net = NetworkModel()
    assert net.frame_loss(50, None) < 0.01 < net.frame_loss(300, None)
    assert net.frame_loss(200, 25) > net.frame_loss(200, 200)  # a tight budget discards more
    rng = np.random.default_rng(0)
    light = [net.frame(50, 100, rng) for _ in range(300)]
    heavy = [x for x in (net.frame(190, 100, rng) for _ in range(300)) if x is not None]
    assert all(x is not None for x in light)
    assert np.median(heavy) > np.median(light)
    # A 100 ms budget bounds what arrives (packets already in HARQ when it expires finish).
    assert max(heavy) <= 120_000


# ---- training ------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.skipif(any(importlib.util.find_spec(m) is None for m in ("torch", "onnx", "stable_baselines3", "gymnasium")),
                    reason="training needs torch, onnx, gymnasium and stable-baselines3 (pip install -e '.[train]')")
def test_quick_training_exports_a_model_the_edge_loads(tmp_path: Path) -> None:
    """PPO on a tiny budget, ONNX export, model card, curve; the ``learned`` policy loads it; the
    same seed trains the same network to the byte."""
    for out in (tmp_path, tmp_path / "again"):
        proc = subprocess.run([sys.executable, str(ROOT / "tools" / "train_policy.py"), "--quick", "--out", str(out)],
                              capture_output=True, text=True, timeout=600, cwd=ROOT)
        assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "policy.onnx").read_bytes() == (tmp_path / "again" / "policy.onnx").read_bytes()
    assert "wrote " in proc.stdout
    card = json.loads((tmp_path / "policy.json").read_text())
    assert card["onnx_check"]["argmax_agreement"] == 1.0 and card["evaluation"]["learned"]["tasks"] > 0
    # What PPO trained (whole rollouts), and the command as given.
    assert card["training"]["steps_trained"] >= card["training"]["steps"]
    assert card["training"]["steps_trained"] % (card["training"]["n_envs"] * card["training"]["n_steps"]) == 0
    assert card["command"] == f"python tools/train_policy.py --quick --out {tmp_path}"
    assert (tmp_path / "training_curve.png").stat().st_size > 0
    pol = make_policy(PolicyConfig(name="learned", learned_model=str(tmp_path / "policy.onnx")))
    assert 0.1 <= pol.decide(state([track(0, -0.5)])).pdp <= 1.0


def test_an_ablation_applies_only_part_of_the_policys_qos() -> None:
    from domain.edge_side import CoDesign
    from domain.tracker import Tracker
    from scenario.schema import PolicyConfig

    cfg = {"name": "fixed", "pdp": 0.5, "latency_budget_ms": 40}
    tracker = Tracker()
    # The floor and the load control off: the ablation alone decides.
    cfg.update(floor=False, headroom=False, guard=False)
    got = {c: CoDesign(PolicyConfig(**cfg, controls=c), 0.2).decide(1, 0, tracker, None)
           for c in ("both", "pdp", "budget")}
    assert (got["both"].pdp, got["both"].pdb_us) == (0.5, 40_000)
    assert (got["pdp"].pdp, got["pdp"].pdb_us) == (0.5, None)
    assert (got["budget"].pdp, got["budget"].pdb_us) == (1.0, 40_000)


def test_lambda_choice_keeps_the_invariant_then_prefers_the_overload_hall() -> None:
    from training.policy.sweep import choose, hall_scenario

    def row(lam: float, lost: int, mbps: float) -> dict:
        return {"policy": f"learned (lambda {lam:g})", "lambda": lam, "success": 0.85, "placed": 140,
                "tasks": 165, "lost_vs_none": lost, "mean_pdp": 0.7, "injected_mbps": mbps}

    rows = [{**row(0, 0, 9.0), "policy": "none", "lambda": None}, row(3, 0, 5.0), row(30, 1, 6.0), row(100, 9, 4.0)]
    hall = {"learned (lambda 3)": {"placed": 600, "tasks": 700, "success": 0.857},
            "learned (lambda 30)": {"placed": 680, "tasks": 700, "success": 0.971},
            "learned (lambda 100)": {"placed": 699, "tasks": 700, "success": 0.999}}
    # Lambda 100 loses tasks PDP 1 places in the environment: never chosen, whatever the hall says.
    assert choose(rows, hall)[0] == 30
    assert "most tasks placed in the overload hall (680 of 700" in choose(rows, hall)[1]
    assert choose(rows)[0] == 3  # without the hall: the least traffic among those that qualify
    # The hall runs are the overload sweep's hall.
    sc = hall_scenario(None, "heuristic", 96, 2)
    assert (sc.loops, sc.seed, sc.duration_s, sc.detailed_loops) == (96, 2, 15.0, 0)
    assert (sc.hall.work_cells_per_row, sc.hall.work_cell_pitch_m, sc.policy.name) == (16, (4.0, 4.0), "heuristic")


def test_returns_are_repriced_at_the_chosen_lambda_from_the_episodes() -> None:
    from training.policy.evaluate import at_lambda, pool

    card = json.loads(DEFAULT_POLICY_MODEL.with_suffix(".json").read_text())
    rows = card["evaluation_rows"]["learned"]  # evaluated at lambda 30, the shipped one
    assert at_lambda({"rows": rows, **pool(rows)}, 30.0)["return"] == pytest.approx(pool(rows)["return"])
    heuristic = at_lambda({"rows": card["evaluation_rows"]["heuristic"]}, 30.0)
    assert heuristic["lambda"] == 30.0 and [r["cost"] for r in heuristic["rows"]] == [
        r["cost"] for r in card["evaluation_rows"]["heuristic"]]


def test_the_policy_sweep_says_what_is_missing_instead_of_a_traceback(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from training.policy import sweep

    monkeypatch.setattr(sweep, "RESULTS", tmp_path)
    assert sweep.main(["--report"]) == 2
    assert "pareto.json does not exist" in capsys.readouterr().err
    if sweep.T.missing_packages():
        pytest.skip("the rest needs the training packages (make install-train)")
    assert sweep.main(["--reuse", "--lambdas", "3,10"]) == 2  # at once, before any evaluation
    assert f"no trained model in {tmp_path / 'lambda-3'}, {tmp_path / 'lambda-10'}" in capsys.readouterr().err
