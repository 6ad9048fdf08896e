"""The randomised family of cells the learned policy is trained and evaluated on (issue 14):
belt speed 0.1-0.5 m/s, object period 2-6 s, spawn jitter, yaw, size and mass spreads, and the
number of loops sharing the radio cell, all within the scenario schema's ranges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenario.schema import CellConfig


@dataclass(frozen=True)
class CellFamily:
    """Ranges of the cells drawn (uniform in each)."""

    belt_speed_m_s: tuple[float, float] = (0.1, 0.5)
    object_period_s: tuple[float, float] = (2.0, 6.0)
    jitter_fraction: tuple[float, float] = (0.0, 0.3)  # of the period (the schema allows < 0.5)
    yaw_spread_deg: tuple[float, float] = (0.0, 90.0)
    size_spread_m: tuple[float, float] = (0.0, 0.02)  # around the nominal 6 cm edge
    mass_spread_kg: tuple[float, float] = (0.0, 0.1)  # around the nominal 0.3 kg
    loops: tuple[int, int] = (1, 40)  # loops sharing the radio cell (inclusive)

    def draw(self, rng: np.random.Generator) -> tuple[CellConfig, int]:
        """A cell and the number of loops in its radio cell."""
        period = float(rng.uniform(*self.object_period_s))
        cell = CellConfig(
            belt_speed_m_s=round(float(rng.uniform(*self.belt_speed_m_s)), 4),
            object_period_s=round(period, 3),
            object_jitter_s=round(period * float(rng.uniform(*self.jitter_fraction)), 3),
            object_yaw_spread_deg=round(float(rng.uniform(*self.yaw_spread_deg)), 2),
            object_size_spread_m=round(float(rng.uniform(*self.size_spread_m)), 4),
            object_mass_spread_kg=round(float(rng.uniform(*self.mass_spread_kg)), 3),
        )
        loops = int(rng.integers(self.loops[0], self.loops[1] + 1))
        return cell, loops


DEFAULT_FAMILY = CellFamily()
