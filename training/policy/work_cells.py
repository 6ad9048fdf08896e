"""The randomised family of work cells the learned policy is trained and evaluated on: belt
speed 0.1-0.5 m/s, object period 2-6 s, spawn jitter, yaw, size and mass spreads, and the number
of loops sharing the radio cell, all within the scenario schema's ranges; a share of the draws
comes from the fast, dense corner (the hardest cells) so that it is sampled enough.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenario.schema import WorkCellConfig


@dataclass(frozen=True)
class WorkCellFamily:
    """Ranges of the cells drawn (uniform in each)."""

    belt_speed_m_s: tuple[float, float] = (0.1, 0.5)
    object_period_s: tuple[float, float] = (2.0, 6.0)
    jitter_fraction: tuple[float, float] = (0.0, 0.3)  # of the period (the schema allows < 0.5)
    yaw_spread_deg: tuple[float, float] = (0.0, 90.0)
    size_spread_m: tuple[float, float] = (0.0, 0.02)  # around the nominal 6 cm edge
    mass_spread_kg: tuple[float, float] = (0.0, 0.1)  # around the nominal 0.3 kg
    loops: tuple[int, int] = (1, 40)  # loops sharing the radio cell (inclusive)
    # Share of the draws from the fast, dense corner: the top quarter of the belt speeds and the
    # bottom quarter of the object periods (uniform draws put 1/16 of the cells there).
    corner_share: float = 0.25

    def draw(self, rng: np.random.Generator) -> tuple[WorkCellConfig, int]:
        """A cell and the number of loops in its radio cell."""
        speed_range, period_range = self.belt_speed_m_s, self.object_period_s
        if rng.random() < self.corner_share:
            lo, hi = speed_range
            speed_range = (hi - (hi - lo) / 4, hi)
            lo, hi = period_range
            period_range = (lo, lo + (hi - lo) / 4)
        period = float(rng.uniform(*period_range))
        cell = WorkCellConfig(
            belt_speed_m_s=round(float(rng.uniform(*speed_range)), 4),
            object_period_s=round(period, 3),
            object_jitter_s=round(period * float(rng.uniform(*self.jitter_fraction)), 3),
            object_yaw_spread_deg=round(float(rng.uniform(*self.yaw_spread_deg)), 2),
            object_size_spread_m=round(float(rng.uniform(*self.size_spread_m)), 4),
            object_mass_spread_kg=round(float(rng.uniform(*self.mass_spread_kg)), 3),
        )
        loops = int(rng.integers(self.loops[0], self.loops[1] + 1))
        return cell, loops

    def card(self) -> dict[str, object]:
        """The family as a model card records it: every range and the corner sampling."""
        return {"belt_speed_m_s": list(self.belt_speed_m_s), "object_period_s": list(self.object_period_s),
                "jitter_fraction": list(self.jitter_fraction), "yaw_spread_deg": list(self.yaw_spread_deg),
                "size_spread_m": list(self.size_spread_m), "mass_spread_kg": list(self.mass_spread_kg),
                "loops": list(self.loops),
                "sampling": f"uniform in each range; {self.corner_share:.0%} of the cells from the fast, "
                            "dense corner (top quarter of belt speeds x bottom quarter of periods)"}


DEFAULT_FAMILY = WorkCellFamily()

