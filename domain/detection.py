"""What a pose estimator reports for one part; shared by the classical and the learned estimator."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Detection:
    """Centre of a part's top face (cell frame, metres) and its pixel area."""

    p: np.ndarray
    area_px: int
