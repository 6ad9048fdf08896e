"""What the gNB knows of each UE's channel when it schedules (ideal CSI): the effective SINR of an
allocation, the wideband MCS and rate the scheduler ranks and sizes by, the UL power headroom,
and the PRBs a size needs."""

from __future__ import annotations

import math
from itertools import repeat

import numpy as np

from netsim.nr.channel import InfSlChannel
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.nr.phy import PhyAbstraction
from scenario.nr import NrConfig

POWER_LIMIT_MARGIN_DB = 3.0  # SNR per PRB kept above the MCS-0 threshold by this much


class Csi:
    """Channel knowledge of both links of ``channel`` for the cell configured by ``cfg``, with
    ``phy``'s formats and EESM betas, OLLA offsets from ``la_ul``/``la_dl``, and MCS up to
    ``max_mcs``. Per UE index: ``mcs_wb_ul``/``mcs_wb_dl`` (wideband MCS), ``rate_ul``/
    ``rate_dl`` (bits per PRB at that MCS), ``ul_max_prb`` (power-headroom cap of an UL
    allocation, PRBs); refreshed lazily, when a link schedules after a channel update."""

    def __init__(self, cfg: NrConfig, channel: InfSlChannel, phy: PhyAbstraction,
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
        self.eesm_cache: dict[tuple[int, int, int, int, bool], float] = {}

    def channel_changed(self) -> None:
        """The channel's gains moved: every estimate is stale."""
        self.stale_ul = self.stale_dl = True
        self.eesm_cache.clear()

    def eesm(self, u: int, p0: int, n: int, mcs: int, ul: bool) -> float:
        """Effective SINR (linear) of UE index ``u`` on PRBs [``p0``, ``p0`` + ``n``) with the
        EESM beta of ``mcs`` (subband gains weighted by the PRBs each contributes), uplink if
        ``ul``. In UL the UE's power is spread over the n PRBs, in DL the gNB's over the whole
        carrier."""
        key = (u, p0, n, mcs, ul)
        cached = self.eesm_cache.get(key)
        if cached is not None:
            return cached
        scale = self.ul_snr[u] * self.n_prb / n if ul else self.dl_snr[u]
        size = self.sb
        row = self.channel.gain_row(u)
        sb0 = p0 // size
        sb1 = (p0 + n - 1) // size
        if sb0 == sb1:
            value = scale * row[sb0]
        else:
            beta = self.betas[mcs]
            gmin = min(row[sb0 : sb1 + 1])
            c = scale / beta
            end = p0 + n
            acc = 0.0
            exp = math.exp
            for sb in range(sb0, sb1 + 1):
                lo = sb * size
                hi = lo + size
                acc += ((hi if hi < end else end) - (lo if lo > p0 else p0)) * exp(
                    (gmin - row[sb]) * c)
            value = scale * gmin - beta * math.log(acc / n)
        self.eesm_cache[key] = value
        return value

    def update_wideband(self, ul: bool) -> None:
        """Refresh the wideband MCS and rate per UE of the uplink if ``ul``, else the downlink
        (EESM over the whole carrier, OLLA applied), and in UL the power-headroom cap."""
        g = self.channel.gain
        la = self.la_ul if ul else self.la_dl
        snr = (self.ul_snr_arr if ul else self.dl_snr_arr)[:, None] * g
        last_mcs = la.last_mcs
        beta = self.beta_arr[last_mcs][:, None]
        smin = snr.min(axis=1, keepdims=True)
        eff = smin[:, 0] - beta[:, 0] * np.log(
            np.exp((smin - snr) / beta) @ self.subband_weights)
        # The same numbers as eesm for a full-carrier allocation: a backlogged UE usually
        # gets exactly that, so the per-slot EESM becomes a cache hit.
        n_ue, n_prb = self.n_ue, self.n_prb
        keys = zip(range(n_ue), repeat(0, n_ue), repeat(n_prb, n_ue), last_mcs, repeat(ul, n_ue),
                   strict=True)
        self.eesm_cache.update(zip(keys, eff.tolist(), strict=True))
        snr_db = 10 * np.log10(np.maximum(eff, 1e-12)) - np.array(la.offset_db)
        top = self.max_mcs
        mcs = [0 if m < 0 else (top if m > top else m) for m in (
            np.searchsorted(self.wb_threshold_db, snr_db, side="right") - 1).tolist()]
        if ul:
            table = self.rate_by_mcs_ul
            self.mcs_wb_ul, self.rate_ul = mcs, [table[m] for m in mcs]
            # Power headroom: spreading the UE's power over more PRBs than this would push the
            # SNR per PRB below what MCS 0 needs (plus a margin), wasting the extra PRBs.
            floor_db = self.wb_threshold_db[0] + POWER_LIMIT_MARGIN_DB
            self.ul_max_prb = [
                n_prb if x >= n_prb else max(1, int(x))
                for x in (n_prb * 10 ** ((snr_db - floor_db) / 10)).tolist()]
            self.stale_ul = False
        else:
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
