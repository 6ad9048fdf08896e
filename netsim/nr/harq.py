"""HARQ: transport blocks in flight, their soft combining and the per-UE process budget.

A ``TransportBlock`` lives in a HARQ process from its first transmission until it is decoded
(and the sender knows it), or dropped after ``harq_max_transmissions``. Chase combining adds the
per-transmission effective SINRs (the receiver sums the energy of identical codewords); with
combining off each transmission is decoded alone. Retransmissions reuse the TB's size, MCS and
number of PRBs (the position in frequency may change).
"""

from __future__ import annotations

from netsim.nr.buffers import Segment


class TransportBlock:
    """One TB and its HARQ state."""

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
    state changes only through these methods."""

    __slots__ = ("_busy", "n_processes", "max_tx", "chase", "_retx")

    def __init__(self, n_ue: int, n_processes: int, max_transmissions: int, chase: bool) -> None:
        self._busy = [0] * n_ue
        self.n_processes = n_processes
        self.max_tx = max_transmissions
        self.chase = chase
        self._retx: list[TransportBlock] = []  # in the order they failed

    def has_free_process(self, ue: int) -> bool:
        return self._busy[ue] < self.n_processes

    def occupy(self, ue: int) -> None:
        """A process of ``ue`` is taken (by a grant or a new TB)."""
        self._busy[ue] += 1

    def release(self, ue: int) -> None:
        """A process of ``ue`` is free again (its TB decoded and known, or lost, or the grant unused)."""
        self._busy[ue] -= 1

    def combine(self, tb: TransportBlock, sinr_linear: float) -> float:
        """Register one transmission received at ``sinr_linear``; the SINR to decode at."""
        tb.tx_count += 1
        if self.chase:
            tb.sinr_acc += sinr_linear
            return tb.sinr_acc
        return sinr_linear

    def exhausted(self, tb: TransportBlock) -> bool:
        return tb.tx_count >= self.max_tx

    def queue_retx(self, tb: TransportBlock, ready_slot: int) -> None:
        """``tb`` is to be sent again, from the PDCCH of ``ready_slot`` on (its process stays taken)."""
        tb.ready_slot = ready_slot
        self._retx.append(tb)

    def take_due(self, slot: int, max_ues: int, pos: int, n_prb: int,
                 taken: set[int]) -> list[tuple[TransportBlock, int]]:
        """Retransmissions to send in ``slot``, each with its first PRB: due by now, one per UE
        (marked in ``taken``), at most ``max_ues``, fitting from PRB ``pos`` on; the others stay
        queued in their order."""
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
