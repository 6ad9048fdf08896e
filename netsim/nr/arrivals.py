"""Packets entering the NR cell's sender buffers: refusal when full, staging until their slot
boundary, admission under their flow's QoS, and discard at their delay budget."""

from __future__ import annotations

import heapq
from collections.abc import Iterable

from netsim.nr.buffers import PacketEntry, SenderBuffer
from netsim.nr.counters import CellCounters
from netsim.nr.downlink import Downlink
from netsim.nr.uplink import Uplink
from netsim.radio_cell import LOSS_BUFFER, LOSS_DELAY_BUDGET, FlowQos, Packet, PacketOutcome

DEFAULT_QOS = FlowQos()


class Arrivals:
    """Where packets enter: ``index`` maps UE name -> UE index, ``slot_us`` is the slot (us),
    ``ul_buf``/``dl_buf`` the sender buffers by UE index, ``ul``/``dl`` the links (told when a
    buffer gets data), ``counters`` the cell's counters. ``next_slot_us`` (us, None before the
    first slot) is the start of the next slot the cell will run, set by the cell."""

    def __init__(self, index: dict[str, int], slot_us: int, ul_buf: list[SenderBuffer],
                 dl_buf: list[SenderBuffer], ul: Uplink, dl: Downlink,
                 counters: CellCounters) -> None:
        self.index = index
        self.slot_us = slot_us
        self.ul_buf = ul_buf
        self.dl_buf = dl_buf
        self.ul = ul
        self.dl = dl
        self.lost = counters.lost
        self.ul_peak = counters.ul_peak
        self.dl_peak = counters.dl_peak
        self.qos: dict[str, FlowQos] = {}
        self.staged: list[tuple[int, int, PacketEntry, int, bool]] = []  # future arrivals
        self.deadlines: list[tuple[int, int, PacketEntry, int, bool]] = []
        self.seq = 0
        self.next_slot_us: int | None = None

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``NrCell.enqueue_many``: each of ``packets`` in order; the outcomes of those refused
        at once.

        This runs once per IP packet and dominates the cost of a loaded cell. Packets come in
        runs that share UE, flow and direction (a frame's): a run that joins its non-empty UL
        queue whole (no delay budget, every packet fits, none staged) is appended in one go;
        any other run goes packet by packet through ``_enqueue_each``.
        """
        refused: list[PacketOutcome] = []
        batch = packets if isinstance(packets, list) else list(packets)
        n = len(batch)
        i = 0
        while i < n:  # runs found by plain comparisons: compiled, they cost a few instructions
            first = batch[i]
            ue, flow, direction = first.ue, first.flow, first.direction
            j = i + 1
            while j < n:
                p = batch[j]
                if p.ue != ue or p.flow != flow or p.direction != direction:
                    break
                j += 1
            run = batch if j - i == n else batch[i:j]
            if not (direction == "ul" and self._append_run(run, ue, flow)):
                self._enqueue_each(run, refused)
            i = j
        return refused

    def _append_run(self, run: list[Packet], ue: str, flow: str) -> bool:
        """Append a run of UL packets of one UE and flow to its non-empty queue, if the packets
        would all be taken that way one by one (then True); else change nothing (False)."""
        qos = self.qos.get(flow, DEFAULT_QOS)
        u = self.index.get(ue, -1)
        if u < 0 or qos.delay_budget_us is not None or self.staged:
            return False
        buf = self.ul_buf[u]
        queued = buf.bytes
        fq = buf.by_name.get(flow)
        if not queued or fq is None or fq.priority != qos.priority:
            return False
        # Plain loops: compiled (fabric.native), they read the packets' fields directly.
        nxt = self.next_slot_us
        total = 0
        for p in run:
            size = p.size_bytes
            if size <= 0 or (nxt is not None and p.enqueue_us > nxt):
                return False
            total += size
        if queued + total > buf.limit_bytes:
            return False
        entries = fq.entries
        for p in run:
            entries.append(PacketEntry(p, None))
        fq.bytes += total
        buf.bytes = queued = queued + total
        buf.packets += len(run)
        # The occupancy only grows along the run: its peak is the final one.
        if queued > self.ul_peak[u]:
            self.ul_peak[u] = queued
        return True

    def _enqueue_each(self, packets: Iterable[Packet], refused: list[PacketOutcome]) -> None:
        """``enqueue`` each packet, adding the refused ones' outcomes to ``refused``. The common
        case (an UL packet of a flow without delay budget, joining its non-empty queue at the
        next slot) is inlined, with the UE and flow looked up once per run of packets that
        share them; anything else takes ``_enqueue``."""
        nxt = self.next_slot_us
        ue = flow = direction = None
        fast = False
        u = 0
        buf = self.ul_buf[0]
        limit = buf.limit_bytes
        fq = None  # the run's flow queue once it has been checked usable
        peak = self.ul_peak
        priority = DEFAULT_QOS.priority
        for packet in packets:
            if packet.ue != ue or packet.flow != flow or packet.direction != direction:
                ue, flow, direction = packet.ue, packet.flow, packet.direction
                qos = self.qos.get(flow, DEFAULT_QOS)
                priority = qos.priority
                u = self.index.get(ue, -1)
                fast = direction == "ul" and u >= 0 and qos.delay_budget_us is None
                fq = None
                if fast:
                    buf = self.ul_buf[u]
                    limit = buf.limit_bytes
            size = packet.size_bytes
            if (not fast or size <= 0 or self.staged
                    or (nxt is not None and packet.enqueue_us > nxt)):
                outcome = self._enqueue(packet)
                if outcome is not None:
                    refused.append(outcome)
                fq = None
                continue
            queued = buf.bytes
            if queued + size > limit:
                self.lost[LOSS_BUFFER] += 1
                refused.append(PacketOutcome(packet, None, LOSS_BUFFER))
                continue
            if fq is None or not queued:
                fq = buf.by_name.get(flow)
                if not queued or fq is None or fq.priority != priority:
                    self._admit(PacketEntry(packet, None), u, True, priority)
                    fq = None
                    continue
            fq.entries.append(PacketEntry(packet, None))
            fq.bytes += size
            buf.bytes = queued = queued + size
            buf.packets += 1
            if queued > peak[u]:
                peak[u] = queued

    def _enqueue(self, packet: Packet) -> PacketOutcome | None:
        """``enqueue`` of one packet, every case: validation, buffer limit, staging, admission."""
        u = self.index.get(packet.ue)
        if u is None:
            raise ValueError(f"packet {packet.packet_id}: unknown UE {packet.ue!r}")
        direction = packet.direction
        if direction == "ul":
            ul = True
            buf = self.ul_buf[u]
        elif direction == "dl":
            ul = False
            buf = self.dl_buf[u]
        else:
            raise ValueError(f"packet {packet.packet_id}: direction {direction!r} is not "
                             "'ul' or 'dl'")
        size = packet.size_bytes
        if size <= 0:
            raise ValueError(f"packet {packet.packet_id}: size_bytes={size} must be > 0")
        staged = 0
        if self.staged:
            staged = sum(e.to_send for _, _, e, su, sul in self.staged if su == u and sul == ul)
        if buf.bytes + staged + size > buf.limit_bytes:
            self.lost[LOSS_BUFFER] += 1
            return PacketOutcome(packet, None, LOSS_BUFFER)
        qos = self.qos.get(packet.flow, DEFAULT_QOS)
        budget = qos.delay_budget_us
        entry = PacketEntry(packet, None if budget is None else packet.enqueue_us + budget)
        nxt = self.next_slot_us
        if nxt is not None and packet.enqueue_us > nxt:
            # Enters at a later slot boundary than the next slot: hold it until then.
            slot = self.slot_us
            self.seq += 1
            heapq.heappush(self.staged, (-(-packet.enqueue_us // slot) * slot, self.seq,
                                         entry, u, ul))
            return None
        self._admit(entry, u, ul, qos.priority)
        return None

    def _admit(self, entry: PacketEntry, u: int, ul: bool, priority: int) -> None:
        pkt = entry.packet
        if ul:
            buf = self.ul_buf[u]
            if buf.bytes == 0 and not self.ul.configured_grant:
                self.ul.sr_candidates.add(u)  # regular BSR triggered: data into an empty buffer
        else:
            buf = self.dl_buf[u]
            dl = self.dl
            dl.active.add(u)
            if priority < dl.prio[u]:
                dl.prio[u] = priority
        buf.add(buf.flow(pkt.flow, priority), entry)
        peak = self.ul_peak if ul else self.dl_peak
        if buf.bytes > peak[u]:
            peak[u] = buf.bytes
        if entry.deadline_us is not None:
            self.seq += 1
            heapq.heappush(self.deadlines, (entry.deadline_us, self.seq, entry, u, ul))

    def admit_staged(self, now_us: int) -> None:
        """Admit the staged packets whose slot boundary is at or before ``now_us`` (us)."""
        staged = self.staged
        while staged and staged[0][0] <= now_us:
            _, _, entry, u, ul = heapq.heappop(staged)
            qos = self.qos.get(entry.packet.flow, DEFAULT_QOS)
            self._admit(entry, u, ul, qos.priority)

    def discard_expired(self, slot_end_us: int, out: list[PacketOutcome]) -> None:
        """Drop queued packets that can no longer arrive within their delay budget by the end
        of the slot ending at ``slot_end_us`` (us), adding their outcomes to ``out``.

        A packet is discarded at the start of the first slot whose end is past its deadline
        (enqueue + budget), and only if none of its bytes has been sent (TS 38.322: an SDU
        already partly submitted to lower layers is not discarded).
        """
        heap = self.deadlines
        while heap and heap[0][0] < slot_end_us:
            deadline, _, e, u, ul = heapq.heappop(heap)
            if e.deadline_us != deadline or e.lost or e.to_send != e.packet.size_bytes:
                continue  # stale deadline, already gone, or under way
            e.lost = True
            (self.ul_buf[u] if ul else self.dl_buf[u]).drop_unsent(e, e.packet.flow)
            self.lost[LOSS_DELAY_BUDGET] += 1
            out.append(PacketOutcome(e.packet, None, LOSS_DELAY_BUDGET))

    def apply_qos(self, flow: str, qos: FlowQos) -> None:
        """``flow``'s new ``qos`` (already in ``self.qos``) for its packets already queued: their
        flow's priority, the best priority each link knows per UE, and their discard deadline,
        recomputed from their enqueue time."""
        for bufs, ul in ((self.ul_buf, True), (self.dl_buf, False)):
            prio = self.ul.prio if ul else self.dl.prio
            for u, buf in enumerate(bufs):
                fq = buf.by_name.get(flow)
                if fq is None:
                    continue
                buf.set_priority(flow, qos.priority)
                prio[u] = buf.best_priority()
                for e in fq.entries:
                    e.deadline_us = (None if qos.delay_budget_us is None
                                     else e.packet.enqueue_us + qos.delay_budget_us)
                    if e.deadline_us is not None and e.to_send:
                        self.seq += 1
                        heapq.heappush(self.deadlines, (e.deadline_us, self.seq, e, u, ul))

    def whole_packet_may_lead(self, u: int) -> bool:
        """Whether a packet still staged for UE index ``u``'s uplink, or a discard in one of its
        flows with a delay budget, may put a whole packet first in its UL buffer."""
        return any(su == u and sul for _, _, _, su, sul in self.staged) or any(
            self.qos.get(name, DEFAULT_QOS).delay_budget_us is not None
            for name in self.ul_buf[u].by_name)
