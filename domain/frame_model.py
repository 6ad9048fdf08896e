"""The abstract loops' model of a detailed loop's camera and estimator (DESIGN 6): compressed
frame sizes and the pose estimator's error and misses, measured on real frames by
``python -m training.frame_model`` into ``domain/data/frame_model.json``.

Read by the abstract loops federate, the co-design policy's training environment and the
benchmark that measures its network table; ``estimate`` applies the measured error to
ground-truth part positions as the real estimator would report them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

PATH = Path(__file__).parent / "data" / "frame_model.json"


@dataclass(frozen=True)
class FrameModel:
    """The measured model; ``data`` is the whole record (settings, sizes, error statistics)."""

    frame_bytes: np.ndarray  # compressed frame sizes, bytes
    error_sd_m: float  # per-axis sd of the estimator's position error
    miss_rate: float  # share of visible parts the estimator misses
    data: dict[str, Any]

    def estimate(self, objects: list[dict[str, Any]], rng: np.random.Generator) -> list[np.ndarray]:
        """The parts at capture (``objects``: ground truth, ``p`` each) as the estimator reports
        them: each missed with the measured rate, the others off by the measured error."""
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
