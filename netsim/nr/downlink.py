"""The downlink data path: the PDSCH assignments of a slot (K0 = 0) from the gNB's per-UE buffers,
their decoding and the gNB's reading of the HARQ-ACK that comes back K1 slots later."""

from __future__ import annotations

import math
from collections.abc import Iterator

from netsim.nr.buffers import SenderBuffer
from netsim.nr.counters import CellCounters
from netsim.nr.csi import Csi
from netsim.nr.draws import Uniforms
from netsim.nr.harq import HarqEntity, TransportBlock
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.nr.outcomes import Outcomes
from netsim.nr.phy import PhyAbstraction
from netsim.nr.scheduler import Scheduler
from scenario.nr import NrConfig


class Downlink:
    """The downlink of a cell configured by ``cfg``, with ``phy``'s formats: its ``harq``
    entity, link adaptation ``la``, scheduler ``sched``, the gNB's buffers ``bufs`` (by UE index), the shared ``csi``,
    ``outcomes`` and ``counters``, the UEs' ``urgency`` weights (shared with the uplink), the
    decoding draws ``rand`` and the control-channel draws ``rand_ctrl``."""

    def __init__(self, cfg: NrConfig, phy: PhyAbstraction, harq: HarqEntity, la: LinkAdaptation,
                 sched: Scheduler, bufs: list[SenderBuffer], csi: Csi, outcomes: Outcomes,
                 counters: CellCounters, urgency: list[float], rand: Uniforms,
                 rand_ctrl: Uniforms) -> None:
        self.config = cfg
        self.phy = phy
        self.harq = harq
        self.la = la
        self.sched = sched
        self.buf = bufs
        self.csi = csi
        self.outcomes = outcomes
        self.counters = counters
        self.urgency = urgency
        self.rand = rand
        self.rand_ctrl = rand_ctrl
        self.n_prb = cfg.n_prb
        self.re = cfg.dl_re_per_prb
        self.k1 = cfg.k1_slots
        self.active: set[int] = set()  # UEs with bytes in the gNB's buffer (lazily cleared)
        self.prio = [1 << 30] * len(bufs)  # best QoS priority queued per UE

    def run(self, s: int) -> None:
        """Assign, send and decode the PDSCH of slot index ``s`` (K0 = 0)."""
        for tb, start in self.assign(s):
            self.transmit(s, tb, start)

    def assign(self, s: int) -> Iterator[tuple[TransportBlock, int]]:
        """The PDSCH assignments of slot index ``s`` (K0 = 0), retransmissions first: each TB
        with its first PRB. Taken one at a time, ``run`` sends each before the next is made, as
        the slot goes; a cell among several takes them all before any is decoded."""
        cfg = self.config
        n_prb = self.n_prb
        harq = self.harq
        max_ues = cfg.max_dl_ues_per_slot
        pos = 0
        count = 0
        taken: set[int] = set()
        for tb, start in harq.take_due(s, max_ues, pos, n_prb, taken):
            yield tb, start
            pos = start + tb.n_prb
            count += 1
        if not self.active or count >= max_ues or pos >= n_prb:
            return
        csi = self.csi
        if csi.stale_dl:
            csi.update_wideband(False)
        candidates = []
        for u in sorted(self.active):
            if not self.buf[u].bytes:
                self.active.discard(u)
                self.prio[u] = 1 << 30
            elif u not in taken and harq.has_free_process(u):
                candidates.append(u)
        la = self.la
        for u in self.sched.ranked(candidates, self.prio, csi.rate_dl, s, self.urgency):
            if count >= max_ues or pos >= n_prb:
                break
            buf = self.buf[u]
            n = csi.prbs_for(8 * buf.report_bytes(), csi.mcs_wb_dl[u], self.re, n_prb - pos)
            est = csi.eesm(u, pos, n, la.last_mcs[u], False)
            mcs = la.select(u, est, n, self.re)
            la.last_mcs[u] = mcs
            fmt = self.phy.tb_format(n, mcs, self.re)
            queued = buf.bytes
            segments = buf.fill(fmt.tbs_bits // 8)
            self.prio[u] = buf.best_priority()
            if not buf.bytes:
                self.active.discard(u)
            if not segments:
                continue
            tb = TransportBlock(u, segments, fmt.tbs_bits, mcs, n, fmt.cbs_bits, fmt.n_cb,
                                queued - buf.bytes)
            harq.occupy(u)
            self.sched.served(u, fmt.tbs_bits, s)
            yield tb, pos
            pos += n
            count += 1

    def transmit(self, s: int, tb: TransportBlock, p0: int, sinr: float | None = None) -> bool:
        """One PDSCH transmission of ``tb`` at PRB ``p0`` in slot index ``s`` and the gNB's
        reading of its ACK; ``sinr``: its effective SINR (linear), None for the one the CSI
        gives (no interference). Whether the UE decoded it."""
        cfg = self.config
        harq = self.harq
        counters = self.counters
        u = tb.ue
        counters.dl_prb_used += tb.n_prb
        ready = s + self.k1 + 1
        if self.rand_ctrl() < cfg.pdcch_miss_prob:
            # The UE never saw the assignment: no soft bits, the gNB reads DTX as a NACK.
            counters.pdcch_missed += 1
            harq.missed(tb)
            if tb.tx_count > 1:
                counters.retx["dl"] += 1
            if harq.exhausted(tb) and tb.decoded:
                harq.release_later(u, ready)
            else:
                self.outcomes.after_failure(tb, ready, harq, False)
            return False
        if sinr is None:
            sinr = self.csi.eesm(u, p0, tb.n_prb, tb.mcs, False)
        eff = harq.combine(tb, sinr)
        if tb.decoded:
            ok = True  # a retransmission caused by a lost ACK: the UE already has the TB
        else:
            ok = self.rand() >= self.phy.bler.tb_bler(
                tb.mcs, tb.cbs_bits, tb.n_cb, 10.0 * math.log10(eff))
            if ok:
                tb.decoded = True
                self.outcomes.deliver(tb, False)
        r = self.rand_ctrl()
        gnb_ack = r >= cfg.ack_miss_prob if ok else r < cfg.nack_to_ack_prob
        counters.account("dl", u, tb, ok, self.la, gnb_ack)
        if gnb_ack:
            if not tb.decoded:
                counters.residual["dl"] += 1
                self.outcomes.lose(tb, False)  # NACK read as ACK: the gNB drops data the UE lacks
            harq.release_later(u, ready)
        elif harq.exhausted(tb) and tb.decoded:
            harq.release_later(u, ready)
        else:
            self.outcomes.after_failure(tb, ready, harq, False)
        return ok
