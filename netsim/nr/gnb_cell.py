"""GnbCell: one gNB's NR cell in a hall with several (``netsim.nr.multicell``): NrCell's MAC, HARQ
and link adaptation on the links to its own UEs, with UL power control and interference-aware
CSI, and its slot split in the phases the hall interleaves with the other cells' (every cell
decides its transmissions before any is decoded)."""

from __future__ import annotations

import heapq
from collections.abc import Mapping

from netsim.nr.buffers import PacketEntry
from netsim.nr.csi import Csi, InterferenceCsi
from netsim.nr.harq import TransportBlock
from netsim.nr.link_fading import ServingLinks
from netsim.nr.phy import PhyAbstraction
from netsim.nr.radio_cell import NrCell
from netsim.nr.uplink import Grant
from netsim.radio_cell import Packet, PacketOutcome
from scenario.nr import NrConfig


class GnbCell(NrCell):
    """The cell of one gNB at ``gnb_position_m`` serving ``ue_positions_m`` (``NrCell``'s
    arguments; its streams under ``stream_prefix``) over ``channel``, with the UL power-control
    SNR ``ul_pc_snr`` and the starting interference estimates ``ipn_ul``/``ipn_dl`` of each UE
    (``InterferenceCsi``), which ``csi`` holds."""

    def __init__(self, config: NrConfig, gnb_position_m: tuple[float, float, float],
                 ue_positions_m: Mapping[str, tuple[float, float, float]], seed: int,
                 stream_prefix: str, channel: ServingLinks, ul_pc_snr: list[float],
                 ipn_ul: list[float], ipn_dl: list[float]) -> None:
        self._pc_snr = ul_pc_snr
        self._ipn = (ipn_ul, ipn_dl)
        super().__init__(config, gnb_position_m, ue_positions_m, seed, stream_prefix, channel)
        csi = self._csi
        assert isinstance(csi, InterferenceCsi)
        self.csi: InterferenceCsi = csi
        self.betas = self.phy.betas
        self._report_period = config.channel_update_period_slots
        self._last_report = -1

    # ------------------------------------------------------------------ handover
    def detach(self, ue: str, t_us: int) -> list[Packet]:
        """UE ``ue`` leaves the cell at ``t_us`` (a handover, ``handover.CellQueues``): every
        packet of it not yet delivered, queued, staged or in a HARQ process, in both links, is
        taken out (the source forwards what it has not delivered, PDCP-style) and returned oldest
        first; its grants, HARQ processes and what the gNB knew of its buffer are dropped. A UE
        detached sends and receives nothing here until ``attach``. Called between a slot's
        decoding and the next slot's plan (no transmission of the UE in the air)."""
        u = self._index[ue]
        entries: list[PacketEntry] = []
        arrivals = self._arrivals
        if arrivals.staged:
            mine = [item for item in arrivals.staged if item[3] == u]
            if mine:
                arrivals.staged = [item for item in arrivals.staged if item[3] != u]
                heapq.heapify(arrivals.staged)
                entries += [item[2] for item in mine]
        for buf in (self._ul_buf[u], self._dl_buf[u]):
            for fq in buf.flows:
                for e in fq.entries:
                    if e.to_send and not e.lost:
                        entries.append(e)
                        buf.drop_unsent(e, fq.name)
                fq.entries.clear()
        ul = self._ul
        for slot in list(ul.pipeline):
            grants = ul.pipeline[slot]
            kept = [g for g in grants if g.ue != u]
            for g in grants:
                if g.ue != u:
                    continue
                if g.tb is not None:
                    entries += [e for e, _ in g.tb.segments]
                else:
                    ul.ue_grants[u] -= 1
                    ul.ue_grant_bytes[u] -= g.payload_bytes
                self._harq_ul.release(u)  # held by the retransmitted TB, or reserved by the grant
            if kept:
                ul.pipeline[slot] = kept
            else:
                del ul.pipeline[slot]
        for harq in (self._harq_ul, self._harq_dl):
            for tb in harq.drop(u):
                entries += [e for e, _ in tb.segments]
        ul.absent.add(u)
        ul.gnb_bytes[u] = 0
        ul.gnb_sr[u] = False
        ul.known.discard(u)
        ul.sr_candidates.discard(u)
        ul.prio[u] = 1 << 30
        self._dl.active.discard(u)
        self._dl.prio[u] = 1 << 30
        packets: dict[int, Packet] = {}
        for e in entries:
            # An entry under way sits in its queue and in a TB: taken once. Its copies in
            # HARQ no longer deliver or lose anything here.
            if not e.lost and e.undelivered:
                e.lost = True
                packets[e.packet.packet_id] = e.packet
        return sorted(packets.values(), key=lambda p: (p.enqueue_us, p.packet_id))

    def attach(self, ue: str, t_us: int, packets: list[Packet]) -> list[PacketOutcome]:
        """UE ``ue`` joins the cell at ``t_us`` with ``packets`` (oldest first) forwarded to its
        queues: each keeps its enqueue time, so its delay budget and latency run on from it; the
        outcomes of those refused at once (a full buffer)."""
        if ue not in self._index:
            raise ValueError(f"attach: unknown UE {ue!r}")
        self._ul.absent.discard(self._index[ue])
        return self._arrivals.enqueue_many(packets) if packets else []

    def move(self, u: int, ul_snr_fullband_db: float, dl_snr_db: float,
             ul_pc_snr: float) -> None:
        """UE index ``u`` moved: its mean SNR per PRB with the whole power over the carrier, UL
        and DL (dB), and its power-control SNR (linear) are now these; link adaptation sees them
        from now on."""
        channel = self.channel
        assert isinstance(channel, ServingLinks)
        channel.move(u, ul_snr_fullband_db, dl_snr_db)
        self.csi.move(u, channel.ul_snr_fullband[u], channel.dl_snr[u], ul_pc_snr)

    def _make_csi(self, phy: PhyAbstraction, max_mcs: int) -> Csi:
        return InterferenceCsi(self.config, self.channel, phy, self._la_ul, self._la_dl, max_mcs,
                               self._pc_snr, self._ipn[0], self._ipn[1])

    def prb_used(self, ul: bool) -> int:
        """PRB-slots allocated so far on the uplink if ``ul``, else the downlink."""
        counters = self._counters
        return counters.ul_prb_used if ul else counters.dl_prb_used

    def open_slot(self, slot_start_us: int) -> int:
        """Start the slot at ``slot_start_us`` (us; as ``run_slot``): packets entering, the
        channel moving, discards, and a CSI report at every channel update (the interference
        estimates reach link adaptation); returns the slot index."""
        s = self._open_slot(slot_start_us)
        report = s // self._report_period
        if report != self._last_report:
            self._last_report = report
            self.csi.report()
        return s

    def plan_slot(self, s: int) -> tuple[list[tuple[TransportBlock, int]],
                                          list[tuple[Grant, TransportBlock]]]:
        """What the radios do in slot index ``s``: the PDCCH (UL grants for s + K2, DL
        assignments for s), the UEs' PUSCHs and the PUCCH. Returns the PDSCH transmissions, each
        TB with its first PRB, and the PUSCH ones, each grant with its TB, in the order the cell
        alone would decode them. The slot is over: packets entering at the next slot boundary
        join the buffers at once, before this slot is decoded (``finish_slot``)."""
        ul = self._ul
        if ul.known or self._harq_ul.pending():
            ul.schedule(s, s + self._k2)
        dl = self._dl
        pdsch = list(dl.assign(s)) if dl.active or self._harq_dl.pending() else []
        pusch = ul.take_pusch(s)
        # The UEs' scheduling requests go out in the slot, before the gNB has decoded it.
        self._close_slot(s)
        return pdsch, pusch

    def finish_slot(self, s: int, pdsch: list[tuple[TransportBlock, int]], pdsch_sinr: list[float],
                    pusch: list[tuple[Grant, TransportBlock]], pusch_sinr: list[float],
                    decoded: list[bool]) -> list[PacketOutcome]:
        """Decode the transmissions ``plan_slot`` gave for slot index ``s`` at their effective
        SINRs (linear, in the same order), appending to ``decoded`` whether each was; the
        slot's outcomes."""
        dl = self._dl
        for (tb, p0), sinr in zip(pdsch, pdsch_sinr, strict=True):
            decoded.append(dl.transmit(s, tb, p0, sinr))
        ul = self._ul
        for (_, tb), sinr in zip(pusch, pusch_sinr, strict=True):
            decoded.append(ul.decode(s, tb, sinr))
        return self._outcomes.out
