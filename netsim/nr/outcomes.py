"""What the end of a transmission means for its packets: delivered at the slot end, a
retransmission queued, or, after the last HARQ attempt, every packet with bytes in the TB lost."""

from __future__ import annotations

from netsim.nr.buffers import SenderBuffer
from netsim.nr.counters import CellCounters
from netsim.nr.harq import HarqEntity, TransportBlock
from netsim.radio_cell import LOSS_CHANNEL, PacketOutcome


class Outcomes:
    """The outcomes of the slot being run (``out``, delivered at ``slot_end_us``), which the
    cell sets at the start of each slot; ``ul_buf``/``dl_buf`` are the sender buffers by UE
    index, ``counters`` the cell's counters."""

    def __init__(self, ul_buf: list[SenderBuffer], dl_buf: list[SenderBuffer],
                 counters: CellCounters) -> None:
        self.out: list[PacketOutcome] = []
        self.slot_end_us = 0
        self.ul_buf = ul_buf
        self.dl_buf = dl_buf
        self.counters = counters

    def deliver(self, tb: TransportBlock, ul: bool) -> None:
        """The receiver decoded ``tb`` (uplink if ``ul``): packets whose last missing bytes it
        carries arrive at the slot end."""
        end = self.slot_end_us
        out = self.out
        append = out.append
        n_out = len(out)
        delivered = 0
        for e, nb in tb.segments:
            if e.lost:
                continue
            delivered += nb
            left = e.undelivered - nb
            e.undelivered = left
            if not left:
                append(PacketOutcome(e.packet, end))
        done = len(out) - n_out
        counters = self.counters
        if ul:
            counters.ul_bytes[tb.ue] += delivered
            counters.delivered["ul"] += done
        else:
            counters.dl_bytes[tb.ue] += delivered
            counters.delivered["dl"] += done

    def lose(self, tb: TransportBlock, ul: bool) -> None:
        """Residual HARQ failure of ``tb`` (uplink if ``ul``): every packet with bytes in it is
        lost (RLC UM does not recover it); its bytes still queued are dropped rather than sent
        for nothing."""
        buf = self.ul_buf[tb.ue] if ul else self.dl_buf[tb.ue]
        out = self.out
        lost = self.counters.lost
        for e, _ in tb.segments:
            if e.lost:
                continue
            e.lost = True
            buf.drop_unsent(e, e.packet.flow)
            lost[LOSS_CHANNEL] += 1
            out.append(PacketOutcome(e.packet, None, LOSS_CHANNEL))

    def after_failure(self, tb: TransportBlock, ready_slot: int, harq: HarqEntity,
                      ul: bool) -> None:
        """A transmission of ``tb`` (uplink if ``ul``, its link's ``harq``) failed: queue a
        retransmission from the PDCCH of slot index ``ready_slot`` or, out of attempts, lose the
        TB and free its process (in DL at ``ready_slot``, when the gNB has read the NACK)."""
        if harq.exhausted(tb):
            self.counters.residual["ul" if ul else "dl"] += 1
            self.lose(tb, ul)
            if ul:
                harq.release(tb.ue)
            else:
                harq.release_later(tb.ue, ready_slot)
        else:
            harq.queue_retx(tb, ready_slot)
