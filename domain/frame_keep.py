"""Which captured frames a camera keeps at the PDP its Edge signalled: each one independently
(``bernoulli``), or a share PDP of them spread as evenly as the captures allow (``spaced``)."""

from __future__ import annotations

import numpy as np

from scenario.schema import FrameKeepMode


class FrameKeep:
    """A camera's keep decisions, drawn from ``rng`` (the camera's ``pdp`` stream).

    ``bernoulli``: a frame is kept with probability PDP, one draw per frame. ``spaced``: the PDPs
    of the captures add up in a credit and a frame is kept each time it passes a whole frame, so
    between two kept frames lie at most ceil(1 / PDP) captures at a steady PDP; the credit starts
    at a uniform draw, so each frame is still kept with probability PDP over the cameras' phases.
    """

    def __init__(self, mode: FrameKeepMode, rng: np.random.Generator) -> None:
        self.spaced = mode == "spaced"
        self.rng = rng
        # The stream serves the keep alone: the phase is its first draw either way.
        self.credit = float(rng.random()) if self.spaced else 0.0

    def keep(self, pdp: float) -> bool:
        """Whether the frame captured now is kept at ``pdp``."""
        if not self.spaced:
            return bool(self.rng.random() < pdp)
        self.credit += pdp
        if self.credit >= 1.0:
            self.credit -= 1.0
            return True
        return False
