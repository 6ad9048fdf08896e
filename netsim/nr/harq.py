"""HARQ: transport blocks in flight, their soft combining and the per-UE process budget.

A TB holds a process from its first transmission until it is decoded and the sender knows it, or
until it is dropped after ``harq_max_transmissions`` (docs/netsim.md, "PHY abstraction").
"""

from __future__ import annotations

from collections import deque

from netsim.nr.buffers import Segment


class TransportBlock:
    """One TB and its HARQ state: ``ue`` is the UE index, ``segments`` the packet bytes it
    carries, ``tbs_bits`` its size, ``mcs`` and ``n_prb`` its format (kept by retransmissions;
    the position in frequency may change), ``cbs_bits`` and ``n_cb`` its code blocks' size in
    bits and count, ``payload_bytes`` the IP bytes carried."""

    __slots__ = ("ue", "segments", "tbs_bits", "mcs", "n_prb", "cbs_bits", "n_cb",
                 "sinr_acc", "tx_count", "decoded", "ready_slot", "payload_bytes")

    def __init__(self, ue: int, segments: list[Segment], tbs_bits: int, mcs: int, n_prb: int,
                 cbs_bits: int, n_cb: int, payload_bytes: int) -> None:
        self.ue = ue
        self.segments = segments
        self.tbs_bits = tbs_bits
        self.mcs = mcs
        self.n_prb = n_prb
        self.cbs_bits = cbs_bits
        self.n_cb = n_cb
        self.payload_bytes = payload_bytes  # IP bytes carried
        self.sinr_acc = 0.0  # combined effective SINR (linear) over transmissions so far
        self.tx_count = 0
        self.decoded = False  # receiver has it (DL: may still be retransmitted after a lost ACK)
        self.ready_slot = 0  # first slot whose PDCCH may schedule its retransmission


class HarqEntity:
    """HARQ processes of every UE on one link, and the TBs waiting for a retransmission. Its
    state, and the transmission count of its TBs, change only through these methods.

    ``n_ue`` UEs (indices 0..n_ue - 1) with ``n_processes`` processes each; a TB is sent at most
    ``max_transmissions`` times; ``chase``: chase combining (the receiver sums the effective
    SINRs of identical codewords), else each transmission is decoded alone.
    """

    __slots__ = ("_busy", "n_processes", "max_tx", "chase", "_retx", "_later")

    def __init__(self, n_ue: int, n_processes: int, max_transmissions: int, chase: bool) -> None:
        self._busy = [0] * n_ue
        self.n_processes = n_processes
        self.max_tx = max_transmissions
        self.chase = chase
        self._retx: list[TransportBlock] = []  # in the order they failed
        # (slot, UE): processes to free at that slot's PDCCH, in slot order.
        self._later: deque[tuple[int, int]] = deque()

    def has_free_process(self, ue: int) -> bool:
        """Whether UE index ``ue`` has a process free for a new TB."""
        return self._busy[ue] < self.n_processes

    def occupy(self, ue: int) -> None:
        """A process of UE index ``ue`` is taken (by a grant or a new TB)."""
        self._busy[ue] += 1

    def release(self, ue: int) -> None:
        """A process of UE index ``ue`` is free again (its TB decoded and known, or lost, or the
        grant unused)."""
        self._busy[ue] -= 1

    def release_later(self, ue: int, slot: int) -> None:
        """A process of UE index ``ue`` frees at the PDCCH of slot index ``slot`` (when the
        sender has read the HARQ-ACK); calls come in non-decreasing ``slot`` order."""
        self._later.append((slot, ue))

    def release_due(self, slot: int) -> None:
        """Free the processes ``release_later`` set to free at or before slot index ``slot``."""
        later = self._later
        while later and later[0][0] <= slot:
            self._busy[later.popleft()[1]] -= 1

    def combine(self, tb: TransportBlock, sinr_linear: float) -> float:
        """Register one transmission of ``tb`` received at effective SINR ``sinr_linear``
        (linear, not dB); the SINR (linear) to decode it at."""
        tb.tx_count += 1
        if self.chase:
            tb.sinr_acc += sinr_linear
            return tb.sinr_acc
        return sinr_linear

    def missed(self, tb: TransportBlock) -> None:
        """A transmission of ``tb`` the receiver never saw (it missed the DCI): it uses one of the
        TB's attempts and adds no soft bits."""
        tb.tx_count += 1

    def exhausted(self, tb: TransportBlock) -> bool:
        """Whether ``tb`` has used all its transmissions."""
        return tb.tx_count >= self.max_tx

    def queue_retx(self, tb: TransportBlock, ready_slot: int) -> None:
        """``tb`` is to be sent again, from the PDCCH of slot index ``ready_slot`` on (its process
        stays taken)."""
        tb.ready_slot = ready_slot
        self._retx.append(tb)

    def take_due(self, slot: int, max_ues: int, pos: int, n_prb: int,
                 taken: set[int]) -> list[tuple[TransportBlock, int]]:
        """Retransmissions to send in slot index ``slot``, each with its first PRB: due by now,
        one per UE (UE indices, marked in ``taken``), at most ``max_ues``, fitting in PRBs
        ``pos``..``n_prb`` - 1; the others stay queued in their order."""
        out: list[tuple[TransportBlock, int]] = []
        waiting = []
        for tb in self._retx:
            if tb.ready_slot > slot or len(out) >= max_ues or tb.ue in taken or pos + tb.n_prb > n_prb:
                waiting.append(tb)
                continue
            out.append((tb, pos))
            taken.add(tb.ue)
            pos += tb.n_prb
        self._retx = waiting
        return out

    def pending(self) -> bool:
        """Whether a retransmission is queued."""
        return bool(self._retx)

    def drop(self, ue: int) -> list[TransportBlock]:
        """UE index ``ue`` leaves the cell (a handover): its TBs waiting for a retransmission are
        taken out, in their order, and their processes freed."""
        dropped = [tb for tb in self._retx if tb.ue == ue]
        if dropped:
            self._retx = [tb for tb in self._retx if tb.ue != ue]
            self._busy[ue] -= len(dropped)
        return dropped
