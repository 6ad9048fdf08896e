"""GnbCell: one gNB's NR cell in a hall with several (``netsim.nr.multicell``): NrCell's MAC, HARQ
and link adaptation on the links to its own UEs, with UL power control and interference-aware
CSI, and its slot split in the phases the hall interleaves with the other cells' (every cell
decides its transmissions before any is decoded)."""

from __future__ import annotations

from collections.abc import Mapping

from netsim.nr.csi import Csi, InterferenceCsi
from netsim.nr.harq import TransportBlock
from netsim.nr.link_fading import ServingLinks
from netsim.nr.phy import PhyAbstraction
from netsim.nr.radio_cell import NrCell
from netsim.nr.uplink import Grant
from netsim.radio_cell import PacketOutcome
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
        """The PDCCH of slot index ``s`` (UL grants for s + K2, DL assignments for s) and the
        UEs' PUSCHs of s: the PDSCH transmissions, each TB with its first PRB, and the PUSCH
        ones, each grant with its TB, in the order the cell alone would decode them."""
        ul = self._ul
        if ul.known or self._harq_ul.pending():
            ul.schedule(s, s + self._k2)
        dl = self._dl
        pdsch = list(dl.assign(s)) if dl.active or self._harq_dl.pending() else []
        return pdsch, ul.take_pusch(s)

    def finish_slot(self, s: int, pdsch: list[tuple[TransportBlock, int]], pdsch_sinr: list[float],
                    pusch: list[tuple[Grant, TransportBlock]], pusch_sinr: list[float],
                    decoded: list[bool]) -> list[PacketOutcome]:
        """Decode the transmissions ``plan_slot`` gave for slot index ``s`` at their effective
        SINRs (linear, in the same order), appending to ``decoded`` whether each was, then the
        PUCCH; the slot's outcomes."""
        dl = self._dl
        for (tb, p0), sinr in zip(pdsch, pdsch_sinr, strict=True):
            decoded.append(dl.transmit(s, tb, p0, sinr))
        ul = self._ul
        for (_, tb), sinr in zip(pusch, pusch_sinr, strict=True):
            decoded.append(ul.decode(s, tb, sinr))
        self._close_slot(s)
        return self._outcomes.out
