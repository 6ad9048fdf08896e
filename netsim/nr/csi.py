"""What the gNB knows of each UE's channel when it schedules (ideal CSI): the effective SINR of an
allocation, the wideband MCS and rate the scheduler ranks and sizes by, the UL power headroom,
and the PRBs a size needs."""

from __future__ import annotations

import math
from itertools import repeat

import numpy as np

from netsim.nr.channel import SubbandGains
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.nr.phy import PhyAbstraction
from scenario.nr import NrConfig

POWER_LIMIT_MARGIN_DB = 3.0  # SNR per PRB kept above the MCS-0 threshold by this much
# EESMs cached a cell: a slot looks up a few hundred, and with fading the cache is emptied at
# every channel update; without fading it would grow by a few a slot for as long as a run lasts.
EESM_CACHE_MAX = 16_384


class Csi:
    """Channel knowledge of both links of ``channel`` for the cell configured by ``cfg``, with
    ``phy``'s formats and EESM betas, OLLA offsets from ``la_ul``/``la_dl``, and MCS up to
    ``max_mcs``. Per UE index: ``mcs_wb_ul``/``mcs_wb_dl`` (wideband MCS), ``rate_ul``/
    ``rate_dl`` (bits per PRB at that MCS), ``ul_max_prb`` (power-headroom cap of an UL
    allocation, PRBs); refreshed lazily, when a link schedules after a channel update."""

    def __init__(self, cfg: NrConfig, channel: SubbandGains, phy: PhyAbstraction,
                 la_ul: LinkAdaptation, la_dl: LinkAdaptation, max_mcs: int) -> None:
        n = channel.n_ue
        self.n_ue = n
        self.channel = channel
        self.phy = phy
        self.la_ul = la_ul
        self.la_dl = la_dl
        self.n_prb = cfg.n_prb
        self.sb = cfg.subband_prb
        self.betas = phy.betas
        self.ul_snr = channel.ul_snr_fullband
        self.dl_snr = channel.dl_snr
        self.wb_threshold_db = np.array([
            phy.bler.cb_bler_threshold_db(m, 8448, cfg.bler_target) for m in range(max_mcs + 1)])
        self.max_mcs = max_mcs
        self.beta_arr = np.array(phy.betas)
        sb_edges = np.minimum(np.arange(channel.n_subbands + 1) * cfg.subband_prb, cfg.n_prb)
        self.subband_weights = np.diff(sb_edges) / cfg.n_prb  # share of the PRBs per subband
        self.rate_by_mcs_ul = [phy.bits_per_prb(m, cfg.ul_re_per_prb) for m in range(max_mcs + 1)]
        self.rate_by_mcs_dl = [phy.bits_per_prb(m, cfg.dl_re_per_prb) for m in range(max_mcs + 1)]
        self.ul_snr_arr = np.array(self.ul_snr)
        self.dl_snr_arr = np.array(self.dl_snr)
        self.rate_ul = [0.0] * n
        self.rate_dl = [0.0] * n
        self.mcs_wb_ul = [0] * n
        self.mcs_wb_dl = [0] * n
        self.ul_max_prb = [cfg.n_prb] * n
        self.stale_ul = self.stale_dl = True
        # EESM of (ue, first PRB, n PRB, MCS, link) under the current channel: allocations
        # repeat from slot to slot (a backlogged UE gets the same PRBs), the gains change only
        # every channel_update_period_slots.
        # Without fading the gains never change and nothing clears it: bounded by EESM_CACHE_MAX.
        self.eesm_cache: dict[tuple[int, int, int, int, bool], float] = {}

    def channel_changed(self) -> None:
        """The channel's gains moved: every estimate is stale."""
        self.stale_ul = self.stale_dl = True
        self.eesm_cache.clear()

    def move(self, u: int, ul_snr: float, dl_snr: float, ul_pc_snr: float) -> None:
        """UE index ``u`` moved: its mean SNRs per PRB (linear; ``ul_pc_snr`` at its power-control
        target, read by ``InterferenceCsi``) are now these; every estimate is stale."""
        self.ul_snr[u] = ul_snr  # the channel's own lists where it shares them: no harm
        self.dl_snr[u] = dl_snr
        self.ul_snr_arr[u] = ul_snr
        self.dl_snr_arr[u] = dl_snr
        self.channel_changed()

    def eesm(self, u: int, p0: int, n: int, mcs: int, ul: bool) -> float:
        """Effective SINR (linear) of UE index ``u`` on PRBs [``p0``, ``p0`` + ``n``) with the
        EESM beta of ``mcs`` (subband gains weighted by the PRBs each contributes), uplink if
        ``ul``. In UL the UE's power is spread over the n PRBs, in DL the gNB's over the whole
        carrier."""
        key = (u, p0, n, mcs, ul)
        cached = self.eesm_cache.get(key)
        if cached is not None:
            return cached
        value = self.eesm_scaled(u, p0, n, mcs,
                                 self.ul_snr[u] * self.n_prb / n if ul else self.dl_snr[u])
        self._keep(key, value)
        return value

    def _keep(self, key: tuple[int, int, int, int, bool], value: float) -> None:
        """Cache an EESM; a full cache starts again."""
        if len(self.eesm_cache) >= EESM_CACHE_MAX:
            self.eesm_cache.clear()
        self.eesm_cache[key] = value

    def eesm_scaled(self, u: int, p0: int, n: int, mcs: int, scale: float) -> float:
        """Effective SINR (linear) of UE index ``u`` on PRBs [``p0``, ``p0`` + ``n``) with the
        EESM beta of ``mcs``, when its mean SINR per PRB before fading is ``scale`` (linear)."""
        size = self.sb
        row = self.channel.gain_row(u)
        sb0 = p0 // size
        sb1 = (p0 + n - 1) // size
        if sb0 == sb1:
            value = scale * row[sb0]
        else:
            beta = self.betas[mcs]
            # The smallest gain by a plain loop (min's own order of comparisons): compiled
            # (fabric.native), it compares C doubles.
            gmin = row[sb0]
            for sb in range(sb0 + 1, sb1 + 1):
                if row[sb] < gmin:
                    gmin = row[sb]
            c = scale / beta
            end = p0 + n
            acc = 0.0
            # math.exp itself, not a local alias: compiled (fabric.native), that is a C call.
            for sb in range(sb0, sb1 + 1):
                lo = sb * size
                hi = lo + size
                acc += ((hi if hi < end else end) - (lo if lo > p0 else p0)) * math.exp(
                    (gmin - row[sb]) * c)
            value = scale * gmin - beta * math.log(acc / n)
        return value

    def update_wideband(self, ul: bool) -> None:
        """Refresh the wideband MCS and rate per UE of the uplink if ``ul``, else the downlink
        (EESM over the whole carrier, OLLA applied), and in UL the power-headroom cap."""
        g = self.channel.gain
        la = self.la_ul if ul else self.la_dl
        snr = (self.ul_snr_arr if ul else self.dl_snr_arr)[:, None] * g
        last_mcs = la.last_mcs
        eff = self.wideband_eesm(snr, last_mcs)
        # The same numbers as eesm for a full-carrier allocation: a backlogged UE usually
        # gets exactly that, so the per-slot EESM becomes a cache hit.
        n_ue, n_prb = self.n_ue, self.n_prb
        keys = zip(range(n_ue), repeat(0, n_ue), repeat(n_prb, n_ue), last_mcs, repeat(ul, n_ue),
                   strict=True)
        self.eesm_cache.update(zip(keys, eff.tolist(), strict=True))
        snr_db = 10 * np.log10(np.maximum(eff, 1e-12)) - np.array(la.offset_db)
        mcs = self.wideband_mcs(snr_db)
        if ul:
            # Power headroom: spreading the UE's power over more PRBs than this would push the
            # SNR per PRB below what MCS 0 needs (plus a margin), wasting the extra PRBs.
            self.set_uplink(mcs, n_prb * 10 ** ((snr_db - self.power_floor_db()) / 10))
        else:
            self.set_downlink(mcs)

    def wideband_eesm(self, snr: np.ndarray, last_mcs: list[int]) -> np.ndarray:
        """EESM (linear) over the whole carrier of each UE's subband SINRs ``snr`` (n_ue,
        n_subbands; linear), with the beta of its MCS in ``last_mcs``."""
        beta = self.beta_arr[last_mcs][:, None]
        smin = snr.min(axis=1, keepdims=True)
        return smin[:, 0] - beta[:, 0] * np.log(
            np.exp((smin - snr) / beta) @ self.subband_weights)

    def wideband_mcs(self, snr_db: np.ndarray) -> list[int]:
        """The highest MCS per UE whose long-block threshold lies under ``snr_db`` (dB, OLLA
        offset already taken off), within 0..max_mcs."""
        top = self.max_mcs
        return [0 if m < 0 else (top if m > top else m) for m in (
            np.searchsorted(self.wb_threshold_db, snr_db, side="right") - 1).tolist()]

    def power_floor_db(self) -> float:
        """SNR per PRB (dB) an UL allocation keeps: the MCS-0 threshold plus a margin."""
        return float(self.wb_threshold_db[0]) + POWER_LIMIT_MARGIN_DB

    def set_uplink(self, mcs: list[int], max_prb: np.ndarray) -> None:
        """The UL wideband MCS per UE, its rate, and the power-headroom cap from ``max_prb``
        (PRBs, real, per UE; at least 1, at most the carrier)."""
        n_prb = self.n_prb
        table = self.rate_by_mcs_ul
        self.mcs_wb_ul, self.rate_ul = mcs, [table[m] for m in mcs]
        self.ul_max_prb = [n_prb if x >= n_prb else max(1, int(x)) for x in max_prb.tolist()]
        self.stale_ul = False

    def set_downlink(self, mcs: list[int]) -> None:
        """The DL wideband MCS per UE and its rate."""
        table = self.rate_by_mcs_dl
        self.mcs_wb_dl, self.rate_dl = mcs, [table[m] for m in mcs]
        self.stale_dl = False

    def prbs_for(self, need_bits: int, mcs: int, n_re: int, available: int) -> int:
        """Fewest PRBs whose TBS at ``mcs`` with ``n_re`` data RE per PRB carries ``need_bits``
        bits, at most ``available`` PRBs."""
        n = max(1, math.ceil(need_bits / self.phy.bits_per_prb(mcs, n_re)))
        if n >= available:
            return available
        fmt = self.phy.tb_format
        while n < available and fmt(n, mcs, n_re).tbs_bits < need_bits:
            n += 1
        return n


# Weight of the newest measurement in a UE's interference estimate (an exponential average over
# its transmissions). A power of two: with no interference the estimate stays exactly 1.
INTERFERENCE_FILTER = 0.25


class InterferenceCsi(Csi):
    """Channel knowledge of a gNB among several on one carrier (``netsim.nr.multicell``): the
    ``Csi`` of ``channel`` (the links to its own UEs) with UL open-loop power control and an
    estimate of the interference per UE and link.

    ``ul_pc_snr[u]``: the mean SNR per PRB (linear) of UE index ``u`` at its power-control target
    P0 + alpha PL (TS 38.213 7.1.1), met on as many PRBs as P_CMAX allows; beyond, the UE's
    P_CMAX spreads over its PRBs as in one cell (``ul_scale``). ``ipn_ul``/``ipn_dl``: per UE,
    interference plus noise over noise (linear, >= 1), the starting estimates; each
    transmission's measured value then moves them (``measured``). Link adaptation, the
    wideband MCS and the power cap divide the SNR by the estimates of the last ``report`` (a
    periodic CSI report), so that allocations repeating between reports hit the EESM cache.
    """

    def __init__(self, cfg: NrConfig, channel: SubbandGains, phy: PhyAbstraction,
                 la_ul: LinkAdaptation, la_dl: LinkAdaptation, max_mcs: int,
                 ul_pc_snr: list[float], ipn_ul: list[float], ipn_dl: list[float]) -> None:
        super().__init__(cfg, channel, phy, la_ul, la_dl, max_mcs)
        self.ul_pc_snr = ul_pc_snr
        self.ipn_ul = ipn_ul
        self.ipn_dl = ipn_dl
        self._reported_ul: list[float] = []
        self._reported_dl: list[float] = []
        self._pc_over_ipn: list[float] = []
        self._full_over_ipn: list[float] = []
        self._dl_over_ipn: list[float] = []
        # The UL wideband MCS and power caps ``prepare_uplink`` computed with other cells', for
        # the next ``update_wideband(True)`` of this slot (None: compute them here).
        self.prepared_ul: tuple[list[int], np.ndarray] | None = None
        self.report()

    def report(self) -> None:
        """A CSI report: from now on link adaptation and the wideband MCS see the interference
        estimates as they are now (nothing changes if they have not moved)."""
        if self.ipn_ul == self._reported_ul and self.ipn_dl == self._reported_dl:
            return
        self._reported_ul = ul = list(self.ipn_ul)
        self._reported_dl = dl = list(self.ipn_dl)
        # Indexed loops rather than zips: compiled (fabric.native), they divide C doubles.
        pc, full, dls = self.ul_pc_snr, self.ul_snr, self.dl_snr
        n = self.n_ue
        if not len(pc) == len(full) == len(dls) == len(ul) == len(dl) == n:
            raise ValueError(f"CSI of {n} UEs: per-UE lists of other lengths")
        self._pc_over_ipn = [pc[u] / ul[u] for u in range(n)]
        self._full_over_ipn = [full[u] / ul[u] for u in range(n)]
        self._dl_over_ipn = [dls[u] / dl[u] for u in range(n)]
        self.channel_changed()

    def move(self, u: int, ul_snr: float, dl_snr: float, ul_pc_snr: float) -> None:
        """``Csi.move``, with the power-control target, over the interference estimates last
        reported (the other UEs' CSI unchanged)."""
        self.ul_pc_snr[u] = ul_pc_snr
        super().move(u, ul_snr, dl_snr, ul_pc_snr)
        self._pc_over_ipn[u] = ul_pc_snr / self._reported_ul[u]
        self._full_over_ipn[u] = ul_snr / self._reported_ul[u]
        self._dl_over_ipn[u] = dl_snr / self._reported_dl[u]

    def ul_scale(self, u: int, n: int) -> float:
        """Mean SNR per PRB (linear, before fading and interference) of UE index ``u``'s PUSCH
        on ``n`` PRBs: its power-control target, or P_CMAX spread over the n PRBs if lower."""
        full = self.ul_snr[u] * self.n_prb / n
        pc = self.ul_pc_snr[u]
        return pc if pc < full else full

    def eesm(self, u: int, p0: int, n: int, mcs: int, ul: bool) -> float:
        """``Csi.eesm`` with UL power control and the reported interference estimate."""
        key = (u, p0, n, mcs, ul)
        cached = self.eesm_cache.get(key)
        if cached is not None:
            return cached
        if ul:
            full = self._full_over_ipn[u] * self.n_prb / n
            pc = self._pc_over_ipn[u]
            scale = pc if pc < full else full
        else:
            scale = self._dl_over_ipn[u]
        value = self.eesm_scaled(u, p0, n, mcs, scale)
        self._keep(key, value)
        return value

    def measured(self, u: int, ul: bool, inr: float) -> None:
        """A transmission of UE index ``u`` (uplink if ``ul``) met a mean interference over
        noise ``inr`` (linear) on its PRBs: the UE's estimate moves towards 1 + ``inr``."""
        ipn = self.ipn_ul if ul else self.ipn_dl
        ipn[u] += INTERFERENCE_FILTER * (1.0 + inr - ipn[u])

    def update_wideband(self, ul: bool) -> None:
        """``Csi.update_wideband`` with UL power control and the reported interference. The UL
        power cap: the SNR per PRB stays at the power-control target up to where P_CMAX binds,
        then falls as the power spreads; the cap is where it falls below the floor (1 PRB when
        the target itself is below it)."""
        if ul and self.prepared_ul is not None:
            mcs_ul, max_prb = self.prepared_ul
            self.prepared_ul = None
            self.set_uplink(mcs_ul, max_prb)
            return
        la = self.la_ul if ul else self.la_dl
        if ul:
            pc = np.array(self._pc_over_ipn)
            full = np.array(self._full_over_ipn)
            base = np.minimum(pc, full)
        else:
            base = np.array(self._dl_over_ipn)
        eff = self.wideband_eesm(base[:, None] * self.channel.gain, la.last_mcs)
        snr_db = 10 * np.log10(np.maximum(eff, 1e-12)) - np.array(la.offset_db)
        mcs = self.wideband_mcs(snr_db)
        if not ul:
            self.set_downlink(mcs)
            return
        floor_db = self.power_floor_db()
        target_db = snr_db + 10 * np.log10(pc / base)
        spread_db = snr_db + 10 * np.log10(full / base)
        self.set_uplink(mcs, np.where(target_db < floor_db, 1.0,
                                      self.n_prb * 10 ** ((spread_db - floor_db) / 10)))


def prepare_uplink(csis: list[InterferenceCsi]) -> None:
    """``InterferenceCsi.update_wideband(True)`` of several cells of one configuration at once
    (each UE's numbers are those of its cell's own call: the same element-wise operations, and
    the EESM's weighted sum per cell), kept in each one's ``prepared_ul`` for its call in this
    slot. The caller drops those a cell did not use (``prepared_ul = None``) before its inputs
    (channel, OLLA, last MCS, interference report) move."""
    first = csis[0]
    pc_list: list[float] = []
    full_list: list[float] = []
    last_mcs: list[int] = []
    offset_db: list[float] = []
    gains: list[np.ndarray] = []
    bounds = [0]
    for csi in csis:
        pc_list += csi._pc_over_ipn
        full_list += csi._full_over_ipn
        last_mcs += csi.la_ul.last_mcs
        offset_db += csi.la_ul.offset_db
        gains.append(csi.channel.gain)
        bounds.append(bounds[-1] + csi.n_ue)
    pc = np.array(pc_list)
    full = np.array(full_list)
    base = np.minimum(pc, full)
    snr = base[:, None] * np.concatenate(gains)
    # Csi.wideband_eesm over every cell's UEs, its weighted sum cell by cell.
    beta = first.beta_arr[last_mcs][:, None]
    smin = snr.min(axis=1, keepdims=True)
    terms = np.exp((smin - snr) / beta)
    weights = first.subband_weights
    acc = np.concatenate([terms[a:b] @ weights
                          for a, b in zip(bounds[:-1], bounds[1:], strict=True)])
    eff = smin[:, 0] - beta[:, 0] * np.log(acc)
    snr_db = 10 * np.log10(np.maximum(eff, 1e-12)) - np.array(offset_db)
    mcs = first.wideband_mcs(snr_db)
    floor_db = first.power_floor_db()
    target_db = snr_db + 10 * np.log10(pc / base)
    spread_db = snr_db + 10 * np.log10(full / base)
    max_prb = np.where(target_db < floor_db, 1.0,
                       first.n_prb * 10 ** ((spread_db - floor_db) / 10))
    for i, csi in enumerate(csis):
        a, b = bounds[i], bounds[i + 1]
        csi.prepared_ul = (mcs[a:b], max_prb[a:b])
