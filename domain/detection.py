"""What a pose estimator reports for one part; shared by the classical and the learned estimator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The parts' orange in OpenCV HSV (hue 0..180: orange ~ 8..22), low and high bounds.
PART_HSV_LOW, PART_HSV_HIGH = np.array([5, 120, 80]), np.array([25, 255, 255])


@dataclass(frozen=True)
class Detection:
    """A part's centre (cell frame, m) and the area (px) it covers in the frame."""

    p: np.ndarray
    area_px: int
