"""What a pose estimator reports for one part; shared by the classical and the learned estimator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Detection:
    """A part's centre (cell frame, m) and the area (px) it covers in the frame."""

    p: np.ndarray
    area_px: int
