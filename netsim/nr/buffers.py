"""Sender buffers: per-flow FIFO queues of IP packets, filled into transport blocks by priority
(logical channel prioritisation; docs/netsim.md, "MAC"). One ``SenderBuffer`` per UE and link:
the UE's in UL, the gNB's for that UE in DL."""

from __future__ import annotations

from collections import deque

from netsim.radio_cell import Packet


class PacketEntry:
    """IP packet ``packet`` inside the cell: bytes still to send and bytes not yet delivered.
    ``deadline_us``: when it is discarded unless under way (us; None: no delay budget). It stays
    tracked by the TB segments carrying it until every byte is delivered or it is lost."""

    __slots__ = ("packet", "to_send", "undelivered", "lost", "deadline_us")

    def __init__(self, packet: Packet, deadline_us: int | None) -> None:
        self.packet = packet
        self.to_send = packet.size_bytes
        self.undelivered = packet.size_bytes
        self.lost = False
        # Discard deadline at the sender (PDCP discard timer); None: no budget.
        self.deadline_us = deadline_us


class FlowQueue:
    """The packets of QoS flow ``name`` in one sender buffer, served at ``priority`` (lower
    first); ``bytes`` counts the bytes still to send."""

    __slots__ = ("name", "priority", "entries", "bytes")

    def __init__(self, name: str, priority: int) -> None:
        self.name = name
        self.priority = priority
        self.entries: deque[PacketEntry] = deque()
        self.bytes = 0


# One TB segment: (packet entry, bytes of that packet carried).
Segment = tuple[PacketEntry, int]


class SenderBuffer:
    """The transmit buffer of one UE in one direction: at most ``limit_bytes`` of IP bytes still
    to send, and ``header_bytes`` of L2 header paid by each segment of a packet in a TB."""

    __slots__ = ("flows", "by_name", "bytes", "packets", "limit_bytes", "header_bytes")

    def __init__(self, limit_bytes: int, header_bytes: int) -> None:
        self.flows: list[FlowQueue] = []  # sorted by (priority, name)
        self.by_name: dict[str, FlowQueue] = {}
        self.bytes = 0  # bytes still to send
        self.packets = 0  # packets with bytes still to send
        self.limit_bytes = limit_bytes
        self.header_bytes = header_bytes

    def fits(self, size_bytes: int) -> bool:
        """Whether a packet of ``size_bytes`` bytes fits under the limit."""
        return self.bytes + size_bytes <= self.limit_bytes

    def flow(self, name: str, priority: int) -> FlowQueue:
        """The queue of flow ``name``, made with ``priority`` (lower first) if it is new."""
        fq = self.by_name.get(name)
        if fq is None:
            fq = FlowQueue(name, priority)
            self.by_name[name] = fq
            self.flows.append(fq)
            self.flows.sort(key=lambda f: (f.priority, f.name))
        return fq

    def set_priority(self, name: str, priority: int) -> None:
        """Serve flow ``name`` (if it has a queue) at ``priority`` (lower first) from now on."""
        fq = self.by_name.get(name)
        if fq is not None and fq.priority != priority:
            fq.priority = priority
            self.flows.sort(key=lambda f: (f.priority, f.name))

    def add(self, fq: FlowQueue, entry: PacketEntry) -> None:
        """Append ``entry`` to flow queue ``fq`` of this buffer (the limit is the caller's)."""
        fq.entries.append(entry)
        fq.bytes += entry.to_send
        self.bytes += entry.to_send
        self.packets += 1

    def report_bytes(self) -> int:
        """Buffer status as the MAC sees it, bytes: data plus the L2 headers it will need."""
        return self.bytes + self.packets * self.header_bytes

    def best_priority(self) -> int:
        """Priority of the most important non-empty flow (large if empty)."""
        for fq in self.flows:
            if fq.bytes:
                return fq.priority
        return 1 << 30

    def fill(self, payload_bytes: int) -> list[Segment]:
        """Take up to ``payload_bytes`` bytes (headers included) from the head of the flows, in
        priority order; the segments taken, as (packet entry, bytes of it carried)."""
        segments: list[Segment] = []
        append = segments.append
        room = payload_bytes
        h = self.header_bytes
        taken_total = 0
        finished = 0  # packets whose last byte was taken
        for fq in self.flows:
            if not fq.bytes:
                continue
            q = fq.entries
            taken = 0
            # The counters are written back once per flow: the same totals, fewer attribute
            # updates on the per-packet path.
            while q and room > h:
                e = q[0]
                to_send = e.to_send
                if to_send == 0:  # discarded or lost while queued, removed lazily
                    q.popleft()
                    continue
                take = room - h
                if take >= to_send:
                    take = to_send
                    q.popleft()
                    finished += 1
                e.to_send = to_send - take
                taken += take
                room -= take + h
                append((e, take))
            fq.bytes -= taken
            taken_total += taken
            if room <= h:
                break
        self.bytes -= taken_total
        self.packets -= finished
        return segments

    def drop_unsent(self, entry: PacketEntry, flow_name: str) -> None:
        """Forget the bytes of ``entry``, of flow ``flow_name``, not yet sent (discarded or
        already lost).

        The entry leaves its queue lazily: ``fill`` skips entries with nothing to send.
        """
        if entry.to_send:
            self.by_name[flow_name].bytes -= entry.to_send
            self.bytes -= entry.to_send
            self.packets -= 1
            entry.to_send = 0
