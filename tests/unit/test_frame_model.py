"""The abstract loops' frame model follows the scenario's camera: the shipped one serves the
default camera only, a model is used only for the settings it was measured with, and a run
gets the one for its camera in its directory."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from coordinator.provision import provide_frame_model
from domain.edge_side import Edges
from domain.edges import load_plan
from domain.frame_model import (
    PATH,
    RUN_FILE,
    FrameModelMissing,
    cache_path,
    camera_settings,
    find_model,
    miss_rate_for,
    model_for,
)
from scenario.schema import parse_scenario


@pytest.fixture(autouse=True)
def empty_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    cache = tmp_path / "cache"
    monkeypatch.setenv("COSIM5G_CACHE_DIR", str(cache))
    return cache


def measured_for(settings: dict, path: Path, frame_bytes: list[int]) -> Path:
    """A model file as ``training.measure_frames`` writes it, for ``settings``."""
    data = json.loads(PATH.read_text())
    data["settings"].update(settings)
    data["frame_bytes"] = frame_bytes
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def test_the_default_camera_uses_the_shipped_model() -> None:
    assert find_model(camera_settings(parse_scenario({}).camera)) == PATH


def test_another_camera_never_gets_the_shipped_model_silently() -> None:
    settings = camera_settings(parse_scenario({"camera": {"jpeg_quality": 60}}).camera)
    with pytest.raises(FrameModelMissing, match="'jpeg_quality': 60"):
        model_for(settings)


def test_a_model_is_used_only_for_the_settings_it_was_measured_with(tmp_path: Path) -> None:
    settings = camera_settings(parse_scenario({"camera": {"depth_decimation": 2}}).camera)
    wrong = measured_for({"depth_decimation": 4}, tmp_path / "wrong.json", [1, 2, 3])
    with pytest.raises(FrameModelMissing):
        model_for(settings, wrong)
    measured_for(settings, cache_path(settings), [7, 8, 9])
    assert model_for(settings, wrong).frame_bytes.tolist() == [7, 8, 9]


def test_a_run_gets_the_model_of_its_camera_in_its_directory(tmp_path: Path) -> None:
    sc = parse_scenario({"loops": 3, "detailed_loops": 1, "camera": {"width_px": 320, "height_px": 180}})
    settings = camera_settings(sc.camera)
    measured_for(settings, cache_path(settings), [5, 6])
    path = provide_frame_model(sc, tmp_path / "config.yaml", tmp_path)
    assert path == tmp_path / RUN_FILE
    assert model_for(settings, path).frame_bytes.tolist() == [5, 6]
    assert provide_frame_model(parse_scenario({"loops": 1, "detailed_loops": 1}), tmp_path / "c.yaml",
                               tmp_path / "none") is None  # no abstract loop, no model


def test_the_safety_floor_assumes_the_miss_rate_measured_for_the_runs_camera(tmp_path: Path) -> None:
    sc = parse_scenario({"loops": 4, "detailed_loops": 1, "camera": {"jpeg_quality": 70},
                         "policy": {"name": "heuristic"}})
    path = measured_for(camera_settings(sc.camera), tmp_path / RUN_FILE, [30_000])
    data = json.loads(path.read_text())
    data["estimator_miss_rate"] = 0.2
    path.write_text(json.dumps(data))
    assert miss_rate_for(sc.camera, path) == 0.2
    # With none in the run's directory (detailed loops only), the shipped model's, whatever a
    # cache holds for this camera.
    cached = measured_for(camera_settings(sc.camera), cache_path(camera_settings(sc.camera)), [30_000])
    assert cached.is_file()
    shipped = json.loads(PATH.read_text())["estimator_miss_rate"]
    assert miss_rate_for(sc.camera, tmp_path / "none" / RUN_FILE) == shipped
    edges = Edges(sc, load_plan(sc, tmp_path), range(1, 4), miss_rate_for(sc.camera, path))
    limits = edges[1].limits
    assert limits is not None and limits.miss_rate == 0.2
