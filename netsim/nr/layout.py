"""Several gNBs in one factory hall: the TR 38.901 InF calibration layouts as data, the 6 x 3 gNB
lattice and its subsets, the reuse-3 frequency plan and uniform UE drops over the floor.
Positions are metres in the hall frame of ``scenario.schema.HallConfig`` (x along the length).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from netsim.nr.channel import INF_LOS_SHADOWING_STD_DB, INF_NLOS_SHADOWING_STD_DB
from scenario.lattice import lattice_points_m, lattice_subset
from scenario.schema import HallConfig

UT_HEIGHT_M = 1.5  # Table 7.8-7: UTs at 1.5 m
# A UT closer than this (2D) to a BS is dropped again: the minimum BS-UT distance the public
# Table 7.8-7 implementations use (Sionna's calibration driver and the MATLAB InF model cited in
# docs/netsim.md, "Several gNBs in one hall"); the path loss clamps d_3D at 1 m anyway.
MIN_UT_BS_DISTANCE_M = 1.0


@dataclass(frozen=True)
class InfSubScenario:
    """One InF sub-scenario of the TR 38.901 large-scale calibration (Table 7.8-7; the
    sub-scenarios of Table 7.2-4): hall, BS lattice spacing and height, clutter."""

    name: str  # SL, DL, SH or DH
    hall_length_m: float
    hall_width_m: float
    hall_height_m: float
    bs_spacing_m: float  # D: 18 BSs on a 6 x 3 lattice, D/2 from the walls
    bs_height_m: float
    clutter_density: float  # r
    clutter_size_m: float  # d_clutter
    clutter_height_m: float  # h_c

    @property
    def los_shadowing_std_db(self) -> float:
        """Shadow fading sigma in LOS, dB (TR 38.901 Table 7.4.1-1)."""
        return INF_LOS_SHADOWING_STD_DB

    @property
    def nlos_shadowing_std_db(self) -> float:
        """Shadow fading sigma in NLOS, dB (TR 38.901 Table 7.4.1-1)."""
        return INF_NLOS_SHADOWING_STD_DB[self.name]

    @property
    def los_correlation_m(self) -> float:
        """Correlation distance of the LOS state, d_clutter / 2 (TR 38.901 7.6.3.1)."""
        return self.clutter_size_m / 2

    @property
    def shadowing_decorrelation_m(self) -> float:
        """Shadowing correlation distance, 10 m in LOS and NLOS for InF (TR 38.901 Table 7.5-6)."""
        return 10.0


# TR 38.901 Table 7.8-7. Sparse clutter: r = 20 %, 10 m pieces 2 m high; dense: r = 60 %, 2 m
# pieces 6 m high. Low BS at 1.5 m, high BS at 8 m; 120 x 60 m halls with D = 20 m for SL and DH,
# 300 x 150 m halls with D = 50 m for DL and SH; 10 m high.
SUB_SCENARIOS: dict[str, InfSubScenario] = {
    "SL": InfSubScenario("SL", 120.0, 60.0, 10.0, 20.0, 1.5, 0.2, 10.0, 2.0),
    "DL": InfSubScenario("DL", 300.0, 150.0, 10.0, 50.0, 1.5, 0.6, 2.0, 6.0),
    "SH": InfSubScenario("SH", 300.0, 150.0, 10.0, 50.0, 8.0, 0.2, 10.0, 2.0),
    "DH": InfSubScenario("DH", 120.0, 60.0, 10.0, 20.0, 8.0, 0.6, 2.0, 6.0),
}

def lattice_positions_m(hall_length_m: float, hall_width_m: float, bs_height_m: float
                        ) -> np.ndarray:
    """The 18 lattice points, shape (18, 3), metres, in ``lattice_index`` order
    (``scenario.lattice.lattice_points_m``)."""
    return np.array(lattice_points_m(hall_length_m, hall_width_m, bs_height_m))


def reuse_groups(gnb_positions_m: np.ndarray, reuse: int) -> np.ndarray:
    """Frequency group (0 .. reuse - 1) of each gNB; gNBs of one group share the same PRBs.

    Reuse 1: one group. Reuse 3: greedy in gNB order, each gNB takes the group whose nearest
    member is farthest away (ties: the lowest group). On the full 6 x 3 lattice this gives group
    (column - row) mod 3: six gNBs per group, co-channel gNBs at least sqrt(2) pitches apart.
    """
    if reuse not in (1, 3):
        raise ValueError(f"reuse {reuse} is not 1 or 3")
    xy = np.asarray(gnb_positions_m, dtype=float)[:, :2]
    groups = np.zeros(len(xy), dtype=int)
    if reuse == 1:
        return groups
    for i in range(len(xy)):
        best, best_d = 0, -1.0
        for g in range(reuse):
            members = xy[:i][groups[:i] == g]
            d = (math.inf if len(members) == 0
                 else float(np.min(np.hypot(*(members - xy[i]).T))))
            if d > best_d + 1e-9:
                best, best_d = g, d
        groups[i] = best
    return groups


@dataclass(frozen=True, eq=False)
class InfLayout:
    """The gNBs of a hall: sub-scenario (propagation), positions, frequency plan, UL power
    control. ``gnb_ids`` name each gNB's random streams: a lattice point keeps its streams (its
    LOS and shadowing maps) in every subset."""

    sub_scenario: InfSubScenario
    hall_length_m: float
    hall_width_m: float
    hall_height_m: float
    gnb_positions_m: np.ndarray  # (n_gnb, 3)
    gnb_ids: tuple[str, ...]
    reuse: int = 1
    ul_p0_dbm: float = -90.0
    ul_alpha: float = 1.0
    groups: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        pos = np.asarray(self.gnb_positions_m, dtype=float).reshape(-1, 3)
        if len(self.gnb_ids) != len(pos):
            raise ValueError(f"{len(self.gnb_ids)} gNB ids for {len(pos)} positions")
        object.__setattr__(self, "gnb_positions_m", pos)
        object.__setattr__(self, "groups", reuse_groups(pos, self.reuse))

    @property
    def n_gnb(self) -> int:
        return len(self.gnb_positions_m)

    @classmethod
    def lattice(cls, sub_scenario: str, hall_length_m: float, hall_width_m: float,
                hall_height_m: float, count: int = 18, reuse: int = 1,
                ul_p0_dbm: float = -90.0, ul_alpha: float = 1.0) -> InfLayout:
        """``count`` gNBs of the hall's lattice at the sub-scenario's BS height."""
        sub = SUB_SCENARIOS[sub_scenario]
        points = lattice_positions_m(hall_length_m, hall_width_m, sub.bs_height_m)
        subset = lattice_subset(count)
        return cls(sub, hall_length_m, hall_width_m, hall_height_m, points[list(subset)],
                   tuple(f"lattice-{k}" for k in subset), reuse, ul_p0_dbm, ul_alpha)

    @classmethod
    def calibration(cls, sub_scenario: str, reuse: int = 1) -> InfLayout:
        """The Table 7.8-7 layout: the sub-scenario's own hall with all 18 BSs."""
        sub = SUB_SCENARIOS[sub_scenario]
        return cls.lattice(sub_scenario, sub.hall_length_m, sub.hall_width_m,
                           sub.hall_height_m, 18, reuse)

    @classmethod
    def explicit(cls, sub_scenario: str, hall_length_m: float, hall_width_m: float,
                 hall_height_m: float, positions_m: Sequence[Sequence[float]], reuse: int = 1,
                 ul_p0_dbm: float = -90.0, ul_alpha: float = 1.0) -> InfLayout:
        """gNBs at explicit (x, y, z) positions, metres."""
        pos = np.asarray(positions_m, dtype=float).reshape(-1, 3)
        return cls(SUB_SCENARIOS[sub_scenario], hall_length_m, hall_width_m, hall_height_m,
                   pos, tuple(f"gnb-{i}" for i in range(len(pos))), reuse, ul_p0_dbm, ul_alpha)


def layout_from_hall(hall: HallConfig) -> InfLayout | None:
    """The layout a scenario's hall asks for, or None for the single gNB at
    ``hall.gnb_position_m`` (no ``hall.inf_layout``)."""
    cfg = hall.inf_layout
    if cfg is None:
        return None
    dims = (hall.length_m, hall.width_m, hall.height_m)
    if cfg.gnb_positions_m is not None:
        return InfLayout.explicit(cfg.sub_scenario, *dims, cfg.gnb_positions_m, cfg.reuse,
                                  cfg.ul_p0_dbm, cfg.ul_alpha)
    return InfLayout.lattice(cfg.sub_scenario, *dims, cfg.gnb_count, cfg.reuse, cfg.ul_p0_dbm,
                             cfg.ul_alpha)


def drop_ues(n: int, hall_length_m: float, hall_width_m: float, gen: np.random.Generator,
             gnb_positions_m: np.ndarray | None = None, height_m: float = UT_HEIGHT_M,
             min_distance_m: float = MIN_UT_BS_DISTANCE_M) -> np.ndarray:
    """``n`` positions uniform over the floor at ``height_m``, shape (n, 3), metres, none closer
    than ``min_distance_m`` (2D) to a gNB (UTs of the calibration, or work-cell centres)."""
    out = np.empty((0, 2))
    gnb_xy = None if gnb_positions_m is None else np.asarray(gnb_positions_m, float)[:, :2]
    while len(out) < n:
        xy = gen.uniform((0.0, 0.0), (hall_length_m, hall_width_m), size=(n - len(out), 2))
        if gnb_xy is not None and len(gnb_xy):
            d = np.hypot(xy[:, None, 0] - gnb_xy[None, :, 0], xy[:, None, 1] - gnb_xy[None, :, 1])
            xy = xy[d.min(axis=1) >= min_distance_m]
        out = np.vstack([out, xy])
    return np.column_stack([out[:n], np.full(n, height_m)])
