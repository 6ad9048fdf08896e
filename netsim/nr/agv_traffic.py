"""AGV traffic: each AGV's uplink video and downlink control stream as constant-rate packet
sources inside netsim (no federate sends or receives them), and what became of their packets:
latency and loss per AGV and link, for the run's KPIs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from netsim.radio_cell import Direction, Packet, PacketOutcome


class AgvTraffic:
    """The streams of the AGVs ``agv_ids``: every ``ul_packet_bytes`` IP packet of a
    ``ul_rate_mbps`` uplink and every ``dl_packet_bytes`` packet of a ``dl_rate_mbps`` downlink,
    at a constant interval, AGV i's first one i/n of an interval after t = 0 (so they do not all
    burst in one slot). A packet made during a slot enters its buffer at the next slot boundary,
    as a federate's would (DESIGN sec. 3). Packet ids count down from -1: the federates' count
    up from 0, so the two never meet. Flows: ``<agv id>/video`` and ``<agv id>/control``, with
    the delay budget ``delay_budget_us`` (None: none)."""

    def __init__(self, agv_ids: Sequence[str], ul_rate_mbps: float, dl_rate_mbps: float,
                 ul_packet_bytes: int, dl_packet_bytes: int,
                 delay_budget_us: int | None = None) -> None:
        if not ul_rate_mbps > 0 or not dl_rate_mbps > 0:
            raise ValueError(f"AGV rates must be positive: ul {ul_rate_mbps}, dl {dl_rate_mbps} "
                             "Mbit/s")
        self.agv_ids = list(agv_ids)
        n = max(1, len(self.agv_ids))
        # (ue, direction, flow, size, interval us, next packet time us) per stream.
        self._streams: list[list[Any]] = []
        for i, ue in enumerate(self.agv_ids):
            for direction, rate, size, flow in (("ul", ul_rate_mbps, ul_packet_bytes, "video"),
                                                ("dl", dl_rate_mbps, dl_packet_bytes, "control")):
                interval = size * 8 / rate  # us: bits over Mbit/s
                self._streams.append([ue, direction, f"{ue}/{flow}", size, interval,
                                      interval * i / n])
        self._next_id = -1
        self.delay_budget_us = delay_budget_us
        self.index = {ue: i for i, ue in enumerate(self.agv_ids)}
        # Per AGV and link: packets delivered, lost, and the count of each latency (us).
        self.delivered = {d: [0] * len(self.agv_ids) for d in ("ul", "dl")}
        self.lost = {d: [0] * len(self.agv_ids) for d in ("ul", "dl")}
        self.latency = {d: [dict[int, int]() for _ in self.agv_ids] for d in ("ul", "dl")}

    def flows(self) -> list[tuple[str, Direction]]:
        """Every stream's flow name and direction."""
        return [(stream[2], stream[1]) for stream in self._streams]

    def due(self, slot_start_us: int) -> list[Packet]:
        """The packets made before ``slot_start_us`` (us) and not yet given out, entering at
        ``slot_start_us``, stream by stream."""
        out: list[Packet] = []
        for stream in self._streams:
            ue, direction, flow, size, interval, t = stream
            while t < slot_start_us:
                out.append(Packet(self._next_id, flow, ue, direction, size, slot_start_us))
                self._next_id -= 1
                t += interval
            stream[5] = t
        return out

    def count(self, outcomes: Sequence[PacketOutcome]) -> None:
        """Count the fates of the AGV packets among ``outcomes`` (others are skipped)."""
        index = self.index
        for o in outcomes:
            p = o.packet
            a = index.get(p.ue)
            if a is None or p.packet_id >= 0:
                continue
            d: Direction = p.direction
            if o.deliver_us is None:
                self.lost[d][a] += 1
            else:
                self.delivered[d][a] += 1
                lat = self.latency[d][a]
                key = o.deliver_us - p.enqueue_us
                lat[key] = lat.get(key, 0) + 1

    def summary(self) -> dict[str, Any]:
        """Per link the hall's AGV packets delivered and lost, loss share and latency
        percentiles (ms) over every AGV; per AGV the same under ``per_agv``."""
        out: dict[str, Any] = {}
        per_agv: dict[str, dict[str, Any]] = {ue: {} for ue in self.agv_ids}
        for d in ("ul", "dl"):
            hall: dict[int, int] = {}
            for a, ue in enumerate(self.agv_ids):
                lat = self.latency[d][a]
                for k, v in lat.items():
                    hall[k] = hall.get(k, 0) + v
                per_agv[ue][d] = _link_summary(self.delivered[d][a], self.lost[d][a], lat)
            out[d] = _link_summary(sum(self.delivered[d]), sum(self.lost[d]), hall)
        out["per_agv"] = per_agv
        return out


def _link_summary(delivered: int, lost: int, latency: dict[int, int]) -> dict[str, Any]:
    total = delivered + lost
    return {"delivered_packets": delivered, "lost_packets": lost,
            "loss": lost / total if total else 0.0,
            "latency_ms_p50": _percentile_ms(latency, 50),
            "latency_ms_p95": _percentile_ms(latency, 95),
            "latency_ms_p99": _percentile_ms(latency, 99)}


def _percentile_ms(counts: dict[int, int], q: float) -> float | None:
    """The q-th percentile (ms, nearest rank) of latencies given as us -> count; None if none."""
    total = sum(counts.values())
    if not total:
        return None
    rank = max(1, math.ceil(q / 100 * total))
    acc = 0
    for value in sorted(counts):
        acc += counts[value]
        if acc >= rank:
            return value / 1000
    return max(counts) / 1000
