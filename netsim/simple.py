"""A shared-capacity cell, the platform's first cell model: per direction, a fixed number of
bytes served per slot to queues ordered by flow priority then arrival, with seeded losses,
bounded sender buffers and delay-budget discards as in the NR model."""

from __future__ import annotations

import heapq
from collections import defaultdict
from typing import Any

import numpy as np

from netsim.radio_cell import (
    LOSS_BUFFER,
    LOSS_CHANNEL,
    LOSS_DELAY_BUDGET,
    FlowQos,
    Packet,
    PacketOutcome,
    RadioCell,
)


class SimpleCell(RadioCell):
    """Slots of ``slot_us`` (us) serving ``ul_rate_mbps`` and ``dl_rate_mbps`` (Mbit/s) of
    packet bytes; the head packet takes the slot's remaining bytes and is delivered at the end
    of the slot carrying its last byte, unless a draw from ``rng`` loses it (probability
    ``loss_probability``); at most ``buffer_bytes`` queued per UE and direction."""

    def __init__(self, slot_us: int, ul_rate_mbps: float, dl_rate_mbps: float, loss_probability: float,
                 buffer_bytes: int, rng: np.random.Generator) -> None:
        self.slot_us = slot_us
        self.capacity = {
            "ul": int(ul_rate_mbps * 1e6 / 8 * slot_us / 1e6),
            "dl": int(dl_rate_mbps * 1e6 / 8 * slot_us / 1e6),
        }
        self.loss_probability = loss_probability
        self.buffer_bytes = buffer_bytes
        self.rng = rng
        self.qos: dict[str, FlowQos] = {}
        # heap of (priority, enqueue_us, packet_id, packet) per direction
        self.queues: dict[str, list[tuple[int, int, int, Packet]]] = {"ul": [], "dl": []}
        # Bytes left of each packet begun and not finished, by packet id: a packet that arrives
        # with a higher priority goes first, and the one it overtook keeps its count.
        self.left: dict[int, int] = {}
        self.buffered: dict[tuple[str, str], int] = defaultdict(int)  # (ue, dir) -> bytes
        self.served_bytes = {"ul": 0, "dl": 0}
        self.busy_slots = {"ul": 0, "dl": 0}
        self.slots = 0

    def set_flow_qos(self, flow: str, qos: FlowQos, ue: str | None = None) -> None:
        """``flow``'s priority and delay budget from ``qos`` for its next packets; ``ue`` and the
        urgency are ignored."""
        self.qos[flow] = qos  # strict priority only: the simple cell has no per-UE ranking

    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        """Queue ``packet``; refused (``buffer_overflow``) if its UE's bytes queued in its
        direction would exceed ``buffer_bytes``."""
        key = (packet.ue, packet.direction)
        if self.buffered[key] + packet.size_bytes > self.buffer_bytes:
            return PacketOutcome(packet, None, LOSS_BUFFER)
        self.buffered[key] += packet.size_bytes
        prio = self.qos.get(packet.flow, FlowQos()).priority
        heapq.heappush(self.queues[packet.direction], (prio, packet.enqueue_us, packet.packet_id, packet))
        return None

    def has_pending(self) -> bool:
        """Whether a packet is queued."""
        return bool(self.queues["ul"] or self.queues["dl"])

    def run_slot(self, slot_start_us: int) -> list[PacketOutcome]:
        """Serve the slot starting at ``slot_start_us`` (us); the outcomes of the packets whose
        last byte it carries (delivered at its end, or lost by the draw) and of the head packets
        found past their delay budget (discarded)."""
        self.slots += 1
        end = slot_start_us + self.slot_us
        out: list[PacketOutcome] = []
        for direction in ("ul", "dl"):
            q = self.queues[direction]
            budget = self.capacity[direction]
            if q:
                self.busy_slots[direction] += 1
            while q and budget > 0:
                packet = q[0][3]
                left = self.left.get(packet.packet_id)
                if left is None:
                    pdb = self.qos.get(packet.flow, FlowQos()).delay_budget_us
                    if pdb is not None and slot_start_us - packet.enqueue_us > pdb:
                        self._pop(direction)
                        out.append(PacketOutcome(packet, None, LOSS_DELAY_BUDGET))
                        continue
                    left = packet.size_bytes
                take = min(left, budget)
                budget -= take
                self.served_bytes[direction] += take
                if take < left:
                    self.left[packet.packet_id] = left - take
                    break
                self._pop(direction)
                if self.loss_probability and self.rng.random() < self.loss_probability:
                    out.append(PacketOutcome(packet, None, LOSS_CHANNEL))
                else:
                    out.append(PacketOutcome(packet, end))
        return out

    def _pop(self, direction: str) -> None:
        packet = heapq.heappop(self.queues[direction])[3]
        self.buffered[(packet.ue, direction)] -= packet.size_bytes
        self.left.pop(packet.packet_id, None)

    def stats(self) -> dict[str, Any]:
        """Slots run, bytes served and busy slots per direction."""
        return {
            "slots": self.slots,
            "ul_bytes": self.served_bytes["ul"],
            "dl_bytes": self.served_bytes["dl"],
            "ul_busy_slots": self.busy_slots["ul"],
            "dl_busy_slots": self.busy_slots["dl"],
        }
