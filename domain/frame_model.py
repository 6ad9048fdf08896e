"""The abstract loops' model of a detailed loop's camera and estimator: compressed frame sizes
and the estimator's error and misses, measured on real frames for one camera's settings
(``CAMERA_KEYS``), shipped, cached or kept in a run's directory, and only ever used for those
settings (docs/perception.md)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fabric.settings import settings as platform_settings
from wire.bodies import Part

PATH = Path(__file__).parent / "data" / "frame_model.json"
RUN_FILE = "frame_model.json"  # in a run's directory: the model its abstract loops use
# The camera settings that shape a compressed frame or what the estimator sees in it.
CAMERA_KEYS = ("width_px", "height_px", "fovy_deg", "jpeg_quality", "depth_codec", "depth_decimation",
               "sensor_model", "depth_subpixel_px", "depth_noise_mm")


class FrameModelMissing(LookupError):
    """No frame model has been measured for a camera's settings."""


@dataclass(frozen=True)
class FrameModel:
    """The measured model; ``data`` is the whole record (settings, sizes, error statistics)."""

    frame_bytes: np.ndarray  # compressed frame sizes, bytes
    error_sd_m: float  # per-axis sd of the estimator's position error
    miss_rate: float  # share of visible parts the estimator misses
    data: dict[str, Any]

    def estimate(self, objects: Sequence[Part], rng: np.random.Generator) -> list[np.ndarray]:
        """The parts at capture (``objects``: ground truth, ``p`` each, m) as the estimator
        reports them: each missed with the measured rate, the others off by the measured error
        (drawn from ``rng``)."""
        out = []
        for obj in objects:
            if rng.random() < self.miss_rate:
                continue
            out.append(np.asarray(obj["p"]) + rng.normal(0.0, self.error_sd_m, 3))
        return out


def load_frame_model(path: Path = PATH) -> FrameModel:
    """The frame model shipped with the platform (or the one at ``path``)."""
    data = json.loads(path.read_text())
    return FrameModel(np.asarray(data["frame_bytes"], dtype=np.int64), float(data["estimator_error_sd_m"]),
                      float(data["estimator_miss_rate"]), data)


def camera_settings(camera: Any) -> dict[str, Any]:
    """The settings of ``camera`` (a scenario's ``camera`` section) a frame model is measured for."""
    return {k: getattr(camera, k) for k in CAMERA_KEYS}


def settings_match(model: FrameModel, settings: dict[str, Any]) -> bool:
    """Whether ``model`` was measured with ``settings``."""
    recorded = model.data.get("settings", {})
    return all(k in recorded and recorded[k] == v for k, v in settings.items())


def cache_path(settings: dict[str, Any], root: Path | None = None) -> Path:
    """Where the model measured for ``settings`` (``camera_settings``) is cached (under
    ``root``, default $COSIM5G_CACHE_DIR or ~/.cache/cosim5g)."""
    root = root or platform_settings().cache_dir or Path.home() / ".cache" / "cosim5g"
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    return root / "frame-models" / f"{digest}.json"


def find_model(settings: dict[str, Any], *candidates: Path) -> Path:
    """The file of the frame model measured for ``settings`` (``camera_settings``): the first of
    the files ``candidates``, the cache and the shipped model that exists and matches;
    FrameModelMissing (naming the settings) if none does."""
    for path in (*candidates, cache_path(settings), PATH):
        if path.exists() and settings_match(load_frame_model(path), settings):
            return path
    shipped = {k: v for k, v in load_frame_model().data["settings"].items() if k in CAMERA_KEYS}
    raise FrameModelMissing(f"no frame model measured for the camera settings {settings} (the shipped "
                            f"one is for {shipped}); a run measures one on first use")


def miss_rate_for(camera: Any, run_file: Path) -> float:
    """The estimator's miss rate behind a scenario's ``camera`` section: that of the run's own
    frame model (``run_file``, measured for the camera: the abstract loops' federate reads the
    same), else the shipped model's (a run of detailed loops only gets none), never one a cache
    happens to hold: the same scenario must run the same on any host."""
    if run_file.is_file():
        model = load_frame_model(run_file)
        if settings_match(model, camera_settings(camera)):
            return model.miss_rate
    return load_frame_model().miss_rate


def model_for(settings: dict[str, Any], *candidates: Path) -> FrameModel:
    """The frame model measured for ``settings``, looked for in ``candidates`` first (see
    ``find_model``)."""
    return load_frame_model(find_model(settings, *candidates))
