"""The environment's network: frame latency and loss of a camera flow vs the cell's offered uplink
load and the flow's latency budget, from data/network_table.json (docs/policy.md, "The
environment", network model).
"""

from __future__ import annotations

import bisect
import json
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

TABLE = "policy/data/network_table.json"


@dataclass(frozen=True)
class Column:
    """One budget's measurements over the loads, arrays indexed like ``loads``."""

    loads: np.ndarray  # offered uplink load, Mbit/s (ascending)
    frame_loss: np.ndarray
    byte_discard: np.ndarray
    latency_q_ms: np.ndarray  # loads x quantiles
    dl_latency_q_ms: np.ndarray


class NetworkModel:
    """Frame-level uplink model of the NR cell, plus the downlink pose latency."""

    def __init__(self, table: dict[str, Any] | None = None) -> None:
        if table is None:
            table = json.loads(resources.files("training").joinpath(TABLE).read_text())
        self.table = table
        self.quantiles = np.asarray(table["quantiles"], float)
        self.loop_rate_mbps = float(table["loop_rate_mbps"])
        self.columns: dict[float | None, Column] = {}
        for budget in table["budgets_ms"]:
            pts = sorted((p for p in table["points"] if p["budget_ms"] == budget),
                         key=lambda p: p["offered_mbps"])
            last_q = [0.0] * len(self.quantiles)
            lat, dl = [], []
            for p in pts:  # a point with no delivered frame keeps its neighbour's latencies
                last_q = p["latency_quantiles_ms"] or last_q
                lat.append(last_q)
                dl.append(p["dl_latency_quantiles_ms"] or [1.0] * len(self.quantiles))
            self.columns[budget] = Column(
                loads=np.array([p["offered_mbps"] for p in pts]),
                frame_loss=np.array([p["frame_loss"] for p in pts]),
                byte_discard=np.array([p["byte_discard"] for p in pts]),
                latency_q_ms=np.array(lat, float), dl_latency_q_ms=np.array(dl, float))
        self._finite = sorted(b for b in self.columns if b is not None)
        # The cell's capacity: the largest offered load, without a budget, that loses under 1 %
        # of the frames (beyond it the queue grows without bound).
        col = self.columns[None]
        self.capacity_mbps = float(max(load for load, loss in zip(col.loads, col.frame_loss, strict=True)
                                       if loss < 0.01))

    def column(self, budget_ms: float | None) -> Column:
        """The measured column nearest to ``budget_ms`` (None: no budget)."""
        if budget_ms is None or not self._finite:
            return self.columns[None]
        i = bisect.bisect_left(self._finite, budget_ms)
        near = [b for b in self._finite[max(0, i - 1):i + 1]]
        return self.columns[min(near, key=lambda b: abs(b - budget_ms))]

    @staticmethod
    def _weights(col: Column, load: float) -> tuple[int, int, float]:
        loads = col.loads
        if load <= loads[0]:
            return 0, 0, 0.0
        if load >= loads[-1]:
            return len(loads) - 1, len(loads) - 1, 0.0
        j = int(np.searchsorted(loads, load))
        return j - 1, j, float((load - loads[j - 1]) / (loads[j] - loads[j - 1]))

    def frame_loss(self, load_mbps: float, budget_ms: float | None) -> float:
        col = self.column(budget_ms)
        i, j, w = self._weights(col, load_mbps)
        return float((1 - w) * col.frame_loss[i] + w * col.frame_loss[j])

    def byte_discard(self, load_mbps: float, budget_ms: float | None) -> float:
        """Fraction of the injected bytes discarded late at the UE (never sent over the air)."""
        col = self.column(budget_ms)
        i, j, w = self._weights(col, load_mbps)
        return float((1 - w) * col.byte_discard[i] + w * col.byte_discard[j])

    def _draw(self, q_ms: np.ndarray, u: float) -> int:
        return int(round(float(np.interp(u, self.quantiles, q_ms)) * 1000))

    def frame(self, load_mbps: float, budget_ms: float | None, rng: np.random.Generator) -> int | None:
        """Latency (us, UE buffer entry to the last packet delivered) of one frame, or None when
        the frame is lost."""
        col = self.column(budget_ms)
        i, j, w = self._weights(col, load_mbps)
        loss = (1 - w) * col.frame_loss[i] + w * col.frame_loss[j]
        u_loss, u = rng.random(), rng.random()
        if u_loss < loss:
            return None
        return self._draw((1 - w) * col.latency_q_ms[i] + w * col.latency_q_ms[j], u)

    def downlink(self, load_mbps: float, rng: np.random.Generator) -> int:
        """Latency (us) of a small downlink packet (a pose or a QoS message)."""
        col = self.columns[None]
        i, j, w = self._weights(col, load_mbps)
        return self._draw((1 - w) * col.dl_latency_q_ms[i] + w * col.dl_latency_q_ms[j], rng.random())
