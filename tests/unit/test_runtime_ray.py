"""The ray runtime's refusals of bad input, without a Ray cluster: Ray missing, a placement the
cluster cannot hold, an address without the ray runtime."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from coordinator.launcher import FederateSpec, NodeLimits
from coordinator.runtime_ray import (
    RayLauncher,
    RayRuntimeError,
    _what,
    bundle_cpus,
    check_placement,
    check_reachable,
)
from interfaces.cli import build_parser
from scenario.schema import load_scenario

ROOT = Path(__file__).parents[2]
SMOKE = ROOT / "configs" / "scenarios" / "smoke.yaml"


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return int(args.fn(args))


def test_the_scenario_takes_runtime_ray() -> None:
    assert load_scenario(SMOKE, ["runtime=ray"]).runtime == "ray"


def test_runtime_ray_without_ray_names_the_extra_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(RayRuntimeError, match=r"pip install -e '\.\[ray\]'"):
        RayLauncher()


def test_cli_run_without_ray_says_which_extra_and_starts_nothing(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)
    code = main(["run", str(SMOKE), "--set", "runtime=ray", "--results", str(tmp_path), "--quiet"])
    assert code == 2
    assert "the `ray` extra" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [], "no run directory for a refused run"


def test_address_without_runtime_ray_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(SMOKE), "--address", "auto", "--results", str(tmp_path), "--quiet"])
    assert code == 2
    assert "--set runtime=ray" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_cpus_round_up_to_rays_step() -> None:
    assert bundle_cpus(None) is None
    assert bundle_cpus(0.25) == pytest.approx(0.25)
    assert bundle_cpus(1.0) == pytest.approx(1.0)
    assert bundle_cpus(0.33333) == pytest.approx(0.3334)
    assert bundle_cpus(0.00001) == pytest.approx(0.0001)


def test_a_process_larger_than_every_node_is_refused_naming_it() -> None:
    edge = FederateSpec("edge", "edge", NodeLimits(cpus=4.0))
    with pytest.raises(RayRuntimeError, match=r"edge \(nodes\.edge\.cpus = 4\) asks 4 CPUs.*largest Ray node has 2"):
        check_placement({_what(edge): 4.0}, {"node-a": 2.0, "node-b": 2.0}, 4.0)


def test_more_cpus_than_the_cluster_has_free_are_refused_naming_the_shortfall() -> None:
    asked = {"edge": 1.0, "camera-0": 0.25, "camera-1": 0.25, "robot-0": 1.0}
    with pytest.raises(RayRuntimeError, match=r"ask 2\.5 CPUs .* has 2 free .* 0\.5 CPUs missing"):
        check_placement(asked, {"node-a": 2.0}, 2.0)
    with pytest.raises(RayRuntimeError, match="has 1.5 free"):  # other work holds the rest
        check_placement({"edge": 1.0, "camera-0": 0.5, "camera-1": 0.5}, {"node-a": 2.0}, 1.5)
    check_placement({"edge": 1.0, "camera-0": 0.25, "camera-1": 0.25}, {"node-a": 2.0}, 1.5)


def test_strict_strategies_are_checked_against_the_nodes() -> None:
    asked = {"edge": 1.0, "camera-0": 0.5}
    with pytest.raises(RayRuntimeError, match="STRICT_PACK .* largest has 1"):
        check_placement(asked, {"a": 1.0, "b": 1.0}, 2.0, "STRICT_PACK")
    check_placement(asked, {"a": 1.0, "b": 1.0}, 2.0, "SPREAD")
    with pytest.raises(RayRuntimeError, match="STRICT_SPREAD .* 2 federate processes .* 1 nodes"):
        check_placement(asked, {"a": 4.0}, 4.0, "STRICT_SPREAD")
    with pytest.raises(RayRuntimeError, match="expected one of PACK"):
        check_placement(asked, {"a": 4.0}, 4.0, "CLOSE")


def test_an_address_nobody_answers_at_is_refused_at_once() -> None:
    with pytest.raises(RayRuntimeError, match=r"cannot reach the Ray cluster at 127.0.0.1:1 .*ray start --head"):
        check_reachable("127.0.0.1:1")
    check_reachable("auto")  # Ray's own forms are left to Ray


def test_a_point_directory_of_a_worker_that_is_gone_is_removed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from experiments.ray_executor import POINT_DIR_PREFIX, remove_stale_point_dirs

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead, alive = tmp_path / f"{POINT_DIR_PREFIX}a", tmp_path / f"{POINT_DIR_PREFIX}b"
    for path, pid in ((dead, gone.stdout.strip()), (alive, str(os.getpid()))):
        (path / "runs").mkdir(parents=True)
        (path / "owner").write_text(pid)
    remove_stale_point_dirs()
    assert not dead.exists() and alive.exists()


def test_a_ray_sweep_takes_at_least_one_point_at_a_time() -> None:
    from experiments.executors import make_executor

    with pytest.raises(ValueError, match="jobs must be >= 1, got -1"):
        make_executor("ray", -1)
