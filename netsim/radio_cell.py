"""The interface every radio cell model implements, and the packet records it produces: a cell
sees IP packets entering sender buffers and is stepped one slot at a time (the netsim federate
owns the clock). Implementations: ``netsim.simple.SimpleCell``, ``netsim.nr.NrCell``."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal

Direction = Literal["ul", "dl"]

# Why a packet never arrived.
LOSS_CHANNEL = "channel"  # residual error after HARQ (or the simple cell's loss draw)
LOSS_DELAY_BUDGET = "delay_budget"  # older than its flow's packet delay budget at the sender
LOSS_BUFFER = "buffer_overflow"  # sender buffer full on arrival
LOSS_HANDOVER = "handover"  # held for a UE during its handover, not forwarded to the target cell


# Packets and outcomes are made by the ten thousand a simulated second: plain classes with an
# __init__ of their own, which the compiled build (fabric.native) compiles; a dataclass's
# generated __init__ would run as interpreted code even there.
class Packet:
    """One IP packet handed to a sender's modem.

    ``packet_id`` identifies it in the run; ``flow`` names its QoS flow; ``ue`` is the UE it
    belongs to (the sender in uplink, the receiver in downlink); ``direction`` is ``ul`` or
    ``dl``; ``size_bytes`` its IP size; ``enqueue_us`` the slot boundary (us) at which it enters
    the sender buffer; ``ref`` whatever the caller routes it by (the cell never reads it).
    """

    __slots__ = ("packet_id", "flow", "ue", "direction", "size_bytes", "enqueue_us", "ref")

    def __init__(self, packet_id: int, flow: str, ue: str, direction: Direction, size_bytes: int,
                 enqueue_us: int, ref: Any = None) -> None:
        self.packet_id = packet_id
        self.flow = flow
        self.ue = ue
        self.direction = direction
        self.size_bytes = size_bytes
        self.enqueue_us = enqueue_us
        self.ref = ref  # opaque to the cell: the netsim federate's routing data

    def __repr__(self) -> str:
        return (f"Packet({self.packet_id}, {self.flow!r}, {self.ue!r}, {self.direction!r}, "
                f"{self.size_bytes}, {self.enqueue_us}, ref={self.ref!r})")


class PacketOutcome:
    """The fate of ``packet``: delivered at ``deliver_us`` (us, a slot end) or lost (None) with
    ``cause`` (one of the ``LOSS_*`` values)."""

    __slots__ = ("packet", "deliver_us", "cause")

    def __init__(self, packet: Packet, deliver_us: int | None, cause: str | None = None) -> None:
        self.packet = packet
        self.deliver_us = deliver_us
        self.cause = cause

    def __repr__(self) -> str:
        return f"PacketOutcome({self.packet!r}, {self.deliver_us}, {self.cause!r})"

    @property
    def delivered(self) -> bool:
        """Whether the packet arrived."""
        return self.deliver_us is not None


@dataclass(slots=True)
class FlowQos:
    """Per-flow QoS: lower ``priority`` is served first; packets older than ``delay_budget_us``
    (us) are discarded at the sender (None: no budget). ``urgency`` weighs the flow's UE in a
    proportional-fair ranking among UEs of equal priority (1: plain PF); the gNB sets it from a
    budget it was told through lower-layer signalling."""

    priority: int = 10
    delay_budget_us: int | None = None
    urgency: float = 1.0


class RadioCell(ABC):
    """A radio cell stepped slot by slot of ``slot_us`` (us)."""

    slot_us: int

    @abstractmethod
    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        """Put ``packet`` in its sender buffer from its ``enqueue_us`` on; its outcome at once if
        it is refused."""

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``enqueue`` each of ``packets`` in order; the outcomes of those refused at once."""
        refused = []
        for packet in packets:
            outcome = self.enqueue(packet)
            if outcome is not None:
                refused.append(outcome)
        return refused

    @abstractmethod
    def run_slot(self, slot_start_us: int) -> list[PacketOutcome]:
        """Simulate the slot starting at ``slot_start_us`` (us, a multiple of ``slot_us``);
        outcomes decided in it (deliveries at ``slot_start_us + slot_us``, losses)."""

    @abstractmethod
    def has_pending(self) -> bool:
        """True while any buffer or HARQ process holds data, i.e. the next slot has work."""

    def earliest_delivery_us(self, ue: str, direction: str) -> int | None:
        """A lower bound on the start (us) of the slot at whose end this cell may next deliver a
        packet of UE ``ue`` in ``direction`` (``ul``/``dl``) that it holds now, were nothing more enqueued; None: no bound
        (the next slot may). A federate promises from it when it sends its next delivery."""
        return None

    @abstractmethod
    def set_flow_qos(self, flow: str, qos: FlowQos, ue: str | None = None) -> None:
        """Change ``flow``'s QoS to ``qos`` (e.g. the co-design policy's latency budget L_r);
        ``ue`` names the flow's UE where the QoS weighs its scheduling."""

    def stats(self) -> dict[str, Any]:
        """Counters for metrics and KPIs (free-form, numbers only)."""
        return {}

    def serving(self) -> dict[str, int] | None:
        """UE id -> the index of the gNB serving it, for a model of several gNBs (None: one)."""
        return None

    def transmissions(self) -> dict[str, list[Any]] | None:
        """The radio transmissions made since the last call, as the columns of the
        ``transmissions`` table (None: the model keeps none)."""
        return None

    def handovers(self) -> dict[str, list[Any]] | None:
        """The handovers of moving radios completed since the last call, as the columns of the
        ``handovers`` table (None: the model moves no radio)."""
        return None
