"""AGVs as moving radios: closed routes of waypoints over the hall floor driven at constant
speed, positions as a pure function of simulated time (one AGV or many at once), and aisle loops
around the rows of work cells for a scenario that gives no route.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from netsim.nr.layout import UT_HEIGHT_M
from scenario.schema import HallConfig, Scenario


def _closed_route(waypoints_m: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    """The waypoints as an (n, 2) array without repeated consecutive points (the closing segment,
    last to first, included in the check)."""
    pts = np.asarray(waypoints_m, dtype=float).reshape(-1, 2)
    keep = np.any(pts != np.roll(pts, -1, axis=0), axis=1)
    pts = pts[keep]
    if len(pts) < 2:
        raise ValueError("a route needs at least two different waypoints")
    return pts


class AgvRoute:
    """One AGV: it drives the closed polyline ``waypoints_m`` ((n, 2), metres on the hall floor;
    after the last point it drives back to the first; repeated consecutive points are dropped)
    at ``speed_m_s``, starting ``start_offset_m`` metres along the route at t = 0, its radio
    ``height_m`` above the floor."""

    def __init__(self, waypoints_m: np.ndarray | Sequence[Sequence[float]], speed_m_s: float,
                 start_offset_m: float = 0.0, height_m: float = UT_HEIGHT_M) -> None:
        if not speed_m_s > 0:
            raise ValueError(f"speed_m_s {speed_m_s} must be positive")
        pts = _closed_route(waypoints_m)
        seg = np.hypot(*(np.roll(pts, -1, axis=0) - pts).T)
        self.waypoints_m = pts
        self.speed_m_s = float(speed_m_s)
        self.start_offset_m = float(start_offset_m)
        self.height_m = float(height_m)
        # Distance from the first point to point i; the last entry is the lap.
        self.cumulative_m = np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length_m(self) -> float:
        """Length of one lap, metres."""
        return float(self.cumulative_m[-1])

    @property
    def lap_us(self) -> float:
        """Duration of one lap, microseconds."""
        return self.length_m / self.speed_m_s * 1e6

    def distance_m(self, t_us: int) -> float:
        """Distance along the route at ``t_us`` from the first waypoint, in [0, length)."""
        return (self.start_offset_m + self.speed_m_s * t_us * 1e-6) % self.length_m

    def position_m(self, t_us: int) -> np.ndarray:
        """Position (x, y, z) at simulated time ``t_us`` (integer microseconds), metres."""
        s = self.distance_m(t_us)
        i = int(np.searchsorted(self.cumulative_m, s, side="right")) - 1
        a = self.waypoints_m[i]
        b = self.waypoints_m[(i + 1) % len(self.waypoints_m)]
        f = (s - self.cumulative_m[i]) / (self.cumulative_m[i + 1] - self.cumulative_m[i])
        x, y = a + f * (b - a)
        return np.array([x, y, self.height_m])


class Fleet:
    """Many AGV routes, positioned together: ``positions_m(t_us)`` is ``route.position_m(t_us)``
    of every route as one (n, 3) array, computed without a Python loop over the AGVs."""

    def __init__(self, routes: Sequence[AgvRoute]) -> None:
        self.routes = tuple(routes)
        n = len(self.routes)
        k = max((len(r.waypoints_m) for r in self.routes), default=1)
        # Padded per AGV: points (with the first repeated after the last), cumulative distances
        # (inf past the end, so the segment search never lands there).
        self._points = np.zeros((n, k + 1, 2))
        self._cumulative = np.full((n, k + 1), np.inf)
        for j, r in enumerate(self.routes):
            m = len(r.waypoints_m)
            self._points[j, :m] = r.waypoints_m
            self._points[j, m] = r.waypoints_m[0]
            self._cumulative[j, : m + 1] = r.cumulative_m
        self._length = np.array([r.length_m for r in self.routes])
        self._speed = np.array([r.speed_m_s for r in self.routes])
        self._offset = np.array([r.start_offset_m for r in self.routes])
        self._height = np.array([r.height_m for r in self.routes])

    def __len__(self) -> int:
        return len(self.routes)

    def positions_m(self, t_us: int) -> np.ndarray:
        """Positions (x, y, z) of every AGV at simulated time ``t_us``, shape (n, 3), metres."""
        n = len(self.routes)
        if n == 0:
            return np.empty((0, 3))
        s = (self._offset + self._speed * t_us * 1e-6) % self._length
        i = (self._cumulative[:, 1:] <= s[:, None]).sum(axis=1)
        rows = np.arange(n)
        a, b = self._points[rows, i], self._points[rows, i + 1]
        c0, c1 = self._cumulative[rows, i], self._cumulative[rows, i + 1]
        f = ((s - c0) / (c1 - c0))[:, None]
        return np.column_stack([a + f * (b - a), self._height])


def aisle_loops(hall: HallConfig, work_cells: int) -> list[np.ndarray]:
    """Rectangular loops along the aisles, one per row of work cells: each drives around its
    row, half a pitch from the work-cell centres (on the aisles between rows and outside the
    outer ones), clipped to the hall floor. Rows and pitch are those of
    ``hall.work_cell_origins(work_cells)``; loops are (4, 2) arrays of corners, metres,
    counter-clockwise from the lower left, first row (lowest y) first.
    """
    origins = np.asarray(hall.work_cell_origins(max(work_cells, 1)), dtype=float)
    px, py = hall.work_cell_pitch_m
    x0 = max(origins[:, 0].min() - px / 2, 0.0)
    x1 = min(origins[:, 0].max() + px / 2, hall.length_m)
    loops = []
    for y in np.unique(origins[:, 1]):
        y0, y1 = max(y - py / 2, 0.0), min(y + py / 2, hall.width_m)
        loops.append(np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]))
    return loops


def agv_routes(scenario: Scenario) -> list[AgvRoute]:
    """The routes of the scenario's ``agvs``: every AGV on ``agvs.waypoints_m``, or, without
    them, on the aisle loops of its work cells (AGV i on loop i mod the number of loops), at
    ``agvs.speed_m_s`` and ``hall.ue_height_m``; the AGVs of one route start evenly spaced
    along it."""
    cfg, hall = scenario.agvs, scenario.hall
    loops = ([np.asarray(cfg.waypoints_m, dtype=float)] if cfg.waypoints_m
             else aisle_loops(hall, scenario.loops))
    sharing = [len(range(j, cfg.count, len(loops))) for j in range(len(loops))]
    routes = []
    for i in range(cfg.count):
        j = i % len(loops)
        base = AgvRoute(loops[j], cfg.speed_m_s, 0.0, hall.ue_height_m)
        offset = base.length_m * (i // len(loops)) / sharing[j]
        routes.append(AgvRoute(loops[j], cfg.speed_m_s, offset, hall.ue_height_m))
    return routes


def agv_ids(count: int) -> list[str]:
    """The UE names of the AGVs: ``agv-0`` .. ``agv-<count - 1>``."""
    return [f"agv-{i}" for i in range(count)]

