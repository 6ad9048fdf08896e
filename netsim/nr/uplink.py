"""The uplink data path: the gNB's view of each UE's buffer (BSR, SR), the grants its PDCCH makes
for slot s + K2, the PUSCH that uses them and the PUCCH that carries SRs (docs/netsim.md, "The
slot")."""

from __future__ import annotations

import math

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


class Grant:
    """An UL grant: PRBs and format of one PUSCH, decided K2 slots before it is sent."""

    __slots__ = ("ue", "prb_start", "n_prb", "mcs", "tbs_bits", "cbs_bits", "n_cb",
                 "payload_bytes", "tb", "missed", "from_sr", "configured")

    def __init__(self, ue: int, prb_start: int, n_prb: int, mcs: int, tbs_bits: int,
                 cbs_bits: int, n_cb: int, payload_bytes: int, tb: TransportBlock | None,
                 missed: bool, from_sr: bool, configured: bool) -> None:
        self.ue = ue
        self.prb_start = prb_start
        self.n_prb = n_prb
        self.mcs = mcs
        self.tbs_bits = tbs_bits
        self.cbs_bits = cbs_bits
        self.n_cb = n_cb
        self.payload_bytes = payload_bytes  # room for MAC SDUs and their headers
        self.tb = tb  # the TB to retransmit, None for a new transmission
        self.missed = missed  # the UE missed the DCI: nothing is sent
        self.from_sr = from_sr
        self.configured = configured


class Uplink:
    """The uplink of a cell configured by ``cfg``, with ``phy``'s formats: its ``harq`` entity, link adaptation ``la``,
    scheduler ``sched``, the UEs' buffers ``bufs`` (by UE index), the shared ``csi``,
    ``outcomes`` and ``counters``, the UEs' ``urgency`` weights (shared with the downlink), the
    decoding draws ``rand`` and the control-channel draws ``rand_ctrl``."""

    def __init__(self, cfg: NrConfig, phy: PhyAbstraction, harq: HarqEntity, la: LinkAdaptation,
                 sched: Scheduler, bufs: list[SenderBuffer], csi: Csi, outcomes: Outcomes,
                 counters: CellCounters, urgency: list[float], rand: Uniforms,
                 rand_ctrl: Uniforms) -> None:
        n = len(bufs)
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
        self.n_ue = n
        self.n_prb = cfg.n_prb
        self.re = cfg.ul_re_per_prb
        self.configured_grant = cfg.ul_access == "configured_grant"
        # gNB side: what it believes each UE has (from BSRs, minus what it has granted since),
        # SRs received. UE side: grants announced but not yet used.
        self.gnb_bytes = [0] * n
        self.gnb_sr = [False] * n
        self.known: set[int] = set()  # UEs the gNB would schedule (bytes > 0 or SR)
        self.prio = [1 << 30] * n  # QoS priority the gNB knows per UE (from BSR / SR)
        self.ue_grants = [0] * n  # new-transmission grants in the pipeline, per UE
        self.ue_grant_bytes = [0] * n
        self.sr_candidates: set[int] = set()  # UEs with a triggered BSR and no grant yet
        self.absent: set[int] = set()  # UEs served by another cell now (moving radios): no occasions
        self.pipeline: dict[int, list[Grant]] = {}  # PUSCH slot -> grants

    def schedule(self, s: int, target: int) -> None:
        """PDCCH of slot index ``s``: grants for the PUSCH of slot index ``target``."""
        cfg = self.config
        n_prb = self.n_prb
        harq = self.harq
        csi = self.csi
        grants: list[Grant] = []
        pos = 0
        taken: set[int] = set()
        if self.configured_grant:
            # Configured-grant occasions need no DCI: their PRBs come first in every slot.
            pos = len(self._cg_occasions(target)) * cfg.cg_prb
        max_ues = cfg.max_ul_ues_per_slot
        count = 0
        for tb, start in harq.take_due(s, max_ues, pos, n_prb, taken):
            grants.append(Grant(tb.ue, start, tb.n_prb, tb.mcs, tb.tbs_bits, tb.cbs_bits,
                                tb.n_cb, 0, tb, self.rand_ctrl() < cfg.pdcch_miss_prob,
                                False, False))
            pos = start + tb.n_prb
            count += 1
        if self.known and count < max_ues and pos < n_prb:
            if csi.stale_ul:
                csi.update_wideband(True)
            # Set order is fine: every scheduler's ranking ends with a total order on the UE.
            candidates = [u for u in self.known if u not in taken and harq.has_free_process(u)]
            gnb_bytes = self.gnb_bytes
            extra = 8 * cfg.bsr_bytes
            for u in self.sched.ranked(candidates, self.prio, csi.rate_ul, s, self.urgency):
                if count >= max_ues or pos >= n_prb:
                    break
                from_sr = gnb_bytes[u] == 0
                need_bits = 8 * (cfg.sr_grant_bytes if from_sr else gnb_bytes[u]) + extra
                room = n_prb - pos
                cap = csi.ul_max_prb[u]
                n = csi.prbs_for(need_bits, csi.mcs_wb_ul[u], self.re, cap if cap < room else room)
                mcs = self._mcs(u, pos, n)
                fmt = self.phy.tb_format(n, mcs, self.re)
                payload = fmt.tbs_bits // 8 - cfg.bsr_bytes
                if payload <= 0:
                    continue
                grants.append(Grant(u, pos, n, mcs, fmt.tbs_bits, fmt.cbs_bits, fmt.n_cb,
                                    payload, None, self.rand_ctrl() < cfg.pdcch_miss_prob,
                                    from_sr, False))
                gnb_bytes[u] = max(0, gnb_bytes[u] - payload)
                self.gnb_sr[u] = False
                if gnb_bytes[u] == 0:
                    self.known.discard(u)
                self.ue_grants[u] += 1
                self.ue_grant_bytes[u] += payload
                harq.occupy(u)  # the process is reserved by the grant
                self.sched.served(u, fmt.tbs_bits, s)
                pos += n
                count += 1
        if grants:
            self.pipeline.setdefault(target, []).extend(grants)

    def _cg_occasions(self, slot: int) -> list[int]:
        """UEs with a configured-grant occasion in ``slot`` (staggered over the period), as
        many as fit in the carrier; where more share the slot than fit, they take turns from one
        period to the next (the same first ones every period would starve the rest, which send
        no scheduling request)."""
        cfg = self.config
        period = cfg.cg_period_slots
        fit = self.n_prb // cfg.cg_prb
        absent = self.absent
        due = [u for u in range(self.n_ue) if (slot + u) % period == 0 and u not in absent]
        if len(due) <= fit:
            return due
        k = (slot // period) * fit % len(due)
        return (due[k:] + due[:k])[:fit]

    def _configured_grants(self, s: int) -> list[Grant]:
        """The configured-grant PUSCHs of slot ``s``, for UEs with data to send (an unused
        occasion stays empty); MCS by link adaptation, as if the gNB kept reconfiguring it."""
        cfg = self.config
        grants = []
        occasions = self._cg_occasions(s)
        for i, u in enumerate(occasions):
            if not self.buf[u].bytes:
                continue
            pos = i * cfg.cg_prb
            mcs = self._mcs(u, pos, cfg.cg_prb)
            fmt = self.phy.tb_format(cfg.cg_prb, mcs, self.re)
            grants.append(Grant(u, pos, cfg.cg_prb, mcs, fmt.tbs_bits, fmt.cbs_bits, fmt.n_cb,
                                fmt.tbs_bits // 8 - cfg.bsr_bytes, None, False, False, True))
        # Unused occasions still occupy their PRBs (used ones are counted with the PUSCH).
        self.counters.ul_prb_used += (len(occasions) - len(grants)) * cfg.cg_prb
        return grants

    def _mcs(self, u: int, p0: int, n: int) -> int:
        """Link adaptation for a PUSCH of n PRBs: the UE's power is spread over them."""
        la = self.la
        est = self.csi.eesm(u, p0, n, la.last_mcs[u], True)
        mcs = la.select(u, est, n, self.re)
        la.last_mcs[u] = mcs
        return mcs

    def run_pusch(self, s: int) -> None:
        """The PUSCH of slot index ``s``: the grants made for it K2 slots ago (after the
        configured-grant occasions) are used, decoded and answered."""
        grants = self.pipeline.pop(s, None)
        if self.configured_grant:
            grants = self._configured_grants(s) + (grants or [])
        if grants:
            csi = self.csi
            for g in grants:
                tb = self.open_grant(s, g)
                if tb is not None:
                    self.decode(s, tb, csi.eesm(g.ue, g.prb_start, g.n_prb, tb.mcs, True))

    def take_pusch(self, s: int) -> list[tuple[Grant, TransportBlock]]:
        """The PUSCH transmissions of slot index ``s``, each grant with the TB its UE sends on
        it, before any is decoded: a cell among several needs them all for the interference.
        Grants that send nothing (missed DCI, nothing to send) are settled here."""
        grants = self.pipeline.pop(s, None)
        if self.configured_grant:
            grants = self._configured_grants(s) + (grants or [])
        out: list[tuple[Grant, TransportBlock]] = []
        if grants:
            for g in grants:
                tb = self.open_grant(s, g)
                if tb is not None:
                    out.append((g, tb))
        return out

    def open_grant(self, s: int, g: Grant) -> TransportBlock | None:
        """The UE's side of grant ``g`` in slot index ``s``: the TB it sends (a new one filled
        from its buffer with its BSR, or the one to retransmit), or None when it sends nothing
        (it missed the DCI, or has nothing but padding)."""
        harq = self.harq
        counters = self.counters
        u = g.ue
        counters.ul_prb_used += g.n_prb
        tb = g.tb
        if tb is None:
            if not g.configured:
                self.ue_grants[u] -= 1
                self.ue_grant_bytes[u] -= g.payload_bytes
            if g.missed:
                # DTX seen by the gNB: it knows nothing came and restores its view.
                counters.pdcch_missed += 1
                self._restore_request(u, g)
                return None
            buf = self.buf[u]
            if g.configured and not (buf.bytes and harq.has_free_process(u)):
                return None  # unused configured-grant occasion
            queued = buf.bytes
            segments = buf.fill(g.payload_bytes) if queued else []
            # The BSR rides with the PUSCH: the gNB now knows the rest of the buffer.
            self.sr_candidates.discard(u)
            known = buf.report_bytes() - self.ue_grant_bytes[u]
            self.gnb_bytes[u] = known if known > 0 else 0
            self.prio[u] = buf.best_priority()
            if known > 0:
                self.known.add(u)
            elif not self.gnb_sr[u]:
                self.known.discard(u)
            if not segments:
                if not g.configured:
                    harq.release(u)  # padding only: no HARQ process needed
                return None
            if g.configured:
                harq.occupy(u)
            # fill takes exactly the bytes it puts in segments out of the buffer.
            return TransportBlock(u, segments, g.tbs_bits, g.mcs, g.n_prb, g.cbs_bits, g.n_cb,
                                  queued - buf.bytes)
        if g.missed:
            counters.pdcch_missed += 1
            harq.missed(tb)
            counters.retx["ul"] += 1
            self.outcomes.after_failure(tb, s + 1, harq, True)
            return None
        return tb

    def decode(self, s: int, tb: TransportBlock, sinr: float) -> bool:
        """The gNB decodes ``tb``, received in slot index ``s`` at effective SINR ``sinr``
        (linear); whether it succeeded (a failure queues a retransmission or loses the TB)."""
        harq = self.harq
        u = tb.ue
        eff = harq.combine(tb, sinr)
        ok = self.rand() >= self.phy.bler.tb_bler(
            tb.mcs, tb.cbs_bits, tb.n_cb, 10.0 * math.log10(eff))
        self.counters.account("ul", u, tb, ok, self.la, ok)
        if ok:
            self.outcomes.deliver(tb, True)
            harq.release(u)
        else:
            self.outcomes.after_failure(tb, s + 1, harq, True)
        return ok

    def _restore_request(self, u: int, g: Grant) -> None:
        """A grant that carried nothing: free its HARQ process and give the gNB back what it
        knew of the UE's request (a pending SR, or the bytes the grant was sized for)."""
        self.harq.release(u)
        if g.from_sr:
            self.gnb_sr[u] = True
        else:
            self.gnb_bytes[u] += g.payload_bytes
        self.known.add(u)

    def run_pucch(self, s: int) -> None:
        """The PUCCH of slot index ``s``: SRs of UEs with a triggered BSR and no grant on its
        way, at their SR occasions."""
        period = self.config.sr_period_slots
        for u in sorted(self.sr_candidates):
            if self.ue_grants[u]:
                continue  # a grant is coming; its PUSCH carries the BSR
            buf = self.buf[u]
            if not buf.bytes:
                self.sr_candidates.discard(u)
                continue
            if (s + u) % period:
                continue
            self.sr_candidates.discard(u)
            self.gnb_sr[u] = True
            self.prio[u] = buf.best_priority()
            self.known.add(u)

    def drop_skipped_grants(self, s: int) -> None:
        """The caller skipped slots before slot index ``s`` with grants pending (it should not,
        has_pending() was True): undo those grants as if the UEs had missed them."""
        harq = self.harq
        for slot in sorted(k for k in self.pipeline if k < s):
            for g in self.pipeline.pop(slot):
                u = g.ue
                if g.tb is not None:
                    harq.queue_retx(g.tb, s)
                    continue
                self.ue_grants[u] -= 1
                self.ue_grant_bytes[u] -= g.payload_bytes
                self._restore_request(u, g)

    def earliest_slot(self, u: int, n0: int, whole_packet_first: bool) -> int:
        """A lower bound on the slot index whose PUSCH may complete a packet now in UE index
        ``u``'s buffer, from slot index ``n0`` (the next slot) on; ``whole_packet_first``: a
        whole packet may come before the rest of the first one queued (NrCell's
        ``earliest_delivery_us`` says when). Of the UE's grants already in the pipeline, a
        retransmission may complete a packet; a new one only once the grants up to it have room
        for the rest of a flow's first packet. Without such a grant, the slot the next PDCCH
        grants for."""
        buf = self.buf[u]
        rest = 0 if whole_packet_first else _first_packet_rest(buf)
        room = 0
        h = buf.header_bytes
        for k in sorted(k for k in self.pipeline if k >= n0):
            for g in self.pipeline[k]:
                if g.ue != u:
                    continue
                if g.tb is not None:
                    return k
                room += max(0, g.payload_bytes - h)  # a grant below one header carries nothing
                if rest is not None and rest <= room:
                    return k
                if self.harq.max_tx == 1:
                    rest = 0  # a failed TB loses its packets at once: a whole one may come first
        return n0 + self.config.k2_slots


def _first_packet_rest(buf: SenderBuffer) -> int | None:
    """Fewest bytes still to send of a flow's first packet in ``buf`` (None: nothing to send)."""
    rest = None
    for fq in buf.flows:
        if fq.bytes:
            for e in fq.entries:
                if e.to_send:  # entries with nothing to send leave their queue lazily
                    rest = e.to_send if rest is None else min(rest, e.to_send)
                    break
    return rest
