"""A slot's packet outcomes as the columns of the ``packets`` table and as counts per fate.
Compiled with the cell (``fabric.native``): tens of thousands of packets a simulated second pass
through here, a field at a time."""

from __future__ import annotations

from typing import Any

from netsim.radio_cell import PacketOutcome


class OutcomeColumns:
    """The ``packets`` table's columns (``fabric.tables.PACKETS``, in its order) of
    ``outcomes``; times and latencies in us, sizes in bytes. ``serving`` (UE id -> index of its
    gNB) fills the ``gnb`` column; without it the column is null (one gNB)."""

    def __init__(self, outcomes: list[PacketOutcome], serving: dict[str, int] | None = None) -> None:
        self.packet_id: list[int] = []
        self.flow: list[str] = []
        self.ue: list[str] = []
        self.dir: list[str] = []
        self.size_bytes: list[int] = []
        self.enqueue_us: list[int] = []
        self.deliver_us: list[int | None] = []
        self.latency_us: list[int | None] = []
        self.lost_cause: list[str | None] = []
        for o in outcomes:
            p = o.packet
            self.packet_id.append(p.packet_id)
            self.flow.append(p.flow)
            self.ue.append(p.ue)
            self.dir.append(p.direction)
            self.size_bytes.append(p.size_bytes)
            self.enqueue_us.append(p.enqueue_us)
            t = o.deliver_us
            self.deliver_us.append(t)
            self.latency_us.append(None if t is None else t - p.enqueue_us)
            self.lost_cause.append(o.cause)
        self.gnb: list[int | None] = ([None] * len(self.ue) if serving is None
                                      else [serving[u] for u in self.ue])

    def as_dict(self) -> dict[str, list[Any]]:
        """The columns by name."""
        return {"packet_id": self.packet_id, "flow": self.flow, "ue": self.ue, "dir": self.dir,
                "size_bytes": self.size_bytes, "enqueue_us": self.enqueue_us,
                "deliver_us": self.deliver_us, "latency_us": self.latency_us,
                "lost_cause": self.lost_cause, "gnb": self.gnb}

    def tally(self, fates: dict[tuple[str, str], int], bits: dict[str, int],
              latencies: dict[str, dict[int, int]]) -> None:
        """Add the outcomes to ``fates`` (count per direction and fate: ``delivered`` or the loss
        cause), to ``bits`` (delivered bits per direction) and to ``latencies`` (count of each
        latency in us, per direction)."""
        for k in range(len(self.dir)):
            d = self.dir[k]
            latency = self.latency_us[k]
            if latency is None:
                cause = self.lost_cause[k]
                key = (d, cause if cause is not None else "lost")
                fates[key] = fates.get(key, 0) + 1
            else:
                bits[d] += 8 * self.size_bytes[k]
                counts = latencies[d]
                counts[latency] = counts.get(latency, 0) + 1
                key = (d, "delivered")
                fates[key] = fates.get(key, 0) + 1
