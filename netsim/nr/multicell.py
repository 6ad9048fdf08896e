"""MultiCell: the NR cells of every gNB of a hall's InF layout in one radio model, each with its own
scheduler, HARQ and link adaptation (``GnbCell``), on one carrier (reuse 1) or a third of it per
frequency group (reuse 3). Each slot every cell first decides its transmissions, then the SINR of
each is computed per PRB from the other co-channel cells' transmissions of that slot
(``sinr.slot_sinr``), then each cell decodes (docs/netsim.md, "Several cells")."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from netsim.nr.gnb_cell import GnbCell
from netsim.nr.interference import serving_gnb
from netsim.nr.large_scale import InfLinks
from netsim.nr.layout import InfLayout
from netsim.nr.link_fading import LinkFading, ServingLinks
from netsim.nr.sinr import slot_sinr
from netsim.radio_cell import FlowQos, Packet, PacketOutcome, RadioCell
from scenario.nr import NrConfig

# SINR histogram of the transmissions per link: 0.5 dB bins from -30 dB to 70 dB (clamped).
SINR_HIST_MIN_DB = -30.0
SINR_HIST_STEP_DB = 0.5
SINR_HIST_BINS = 200


class MultiCell(RadioCell):
    """The cells of the gNBs of ``layout`` serving ``ue_positions_m`` (UE id -> (x, y, z), m),
    each UE by the gNB of strongest RSRP, fixed for the run. ``config`` is every cell's NrConfig
    (a reuse-3 cell takes n_prb // 3 of its PRBs); the sub-scenario of ``layout`` sets the path
    loss, LOS probability and shadowing of every (UE, gNB) link (``large_scale.InfLinks``), and
    ``config`` the powers, noise figures, fading and MAC. Streams: ``stream_prefix`` then
    ``/inf/...`` (large scale), ``/fading/<ue>/<gnb id>`` and ``/<gnb id>/...`` (a cell's MAC),
    so the same seed gives the same outcomes and a gNB's streams do not depend on the others.
    With ``record``, each transmission is kept for ``transmissions()``.

    ``serving_gnb_index`` maps each UE id to its gNB's index in ``layout``; ``cells`` holds the
    cells of the gNBs that serve a UE (a gNB serving none sends nothing and is left out).
    """

    def __init__(self, config: NrConfig, layout: InfLayout,
                 ue_positions_m: Mapping[str, tuple[float, float, float]], seed: int,
                 stream_prefix: str = "netsim/nr", record: bool = False) -> None:
        cfg = config
        if not ue_positions_m:
            raise ValueError("ue_positions_m is empty: a cell needs at least one UE")
        n_cell_prb = cfg.n_prb // layout.reuse
        if n_cell_prb < 1:
            raise ValueError(f"n_prb = {cfg.n_prb} leaves no PRB per cell with reuse "
                             f"{layout.reuse}")
        self.config = cell_cfg = cfg.model_copy(update={"n_prb": n_cell_prb})
        self.slot_us = cfg.slot_us
        self.n_cell_prb = n_cell_prb
        self.layout = layout
        ue_ids = list(ue_positions_m)
        pos = np.array([ue_positions_m[u] for u in ue_ids], dtype=float).reshape(-1, 3)
        n_ue, n_gnb = len(ue_ids), layout.n_gnb
        self.n_gnb = n_gnb
        links = InfLinks(layout, pos, cfg.carrier_frequency_hz, seed, f"{stream_prefix}/inf",
                         cfg.gnb_antenna_gain_dbi, cfg.ue_antenna_gain_dbi, cfg.los_mode,
                         cfg.shadowing_enabled)
        self.links = links
        serving = serving_gnb(links.coupling_loss_db)
        rows = np.arange(n_ue)
        # Mean SNR per PRB of every link with the whole power over the cell's carrier, as the
        # single cell computes it (InfSlChannel); the interference margin counts as noise.
        prb_bw_hz = 12 * cfg.subcarrier_spacing_hz
        noise_prb_dbm = cfg.noise_psd_dbm_per_hz + 10 * math.log10(prb_bw_hz)
        coupling_db = (cfg.gnb_antenna_gain_dbi + cfg.ue_antenna_gain_dbi - links.pathloss_db
                       - links.shadowing_db - cfg.interference_margin_db
                       - 10 * math.log10(n_cell_prb))
        ul_db = cfg.ue_tx_power_dbm + coupling_db - noise_prb_dbm - cfg.gnb_noise_figure_db
        dl_db = cfg.gnb_tx_power_dbm + coupling_db - noise_prb_dbm - cfg.ue_noise_figure_db
        self.ul_snr = 10 ** (ul_db / 10)  # (n_ue, n_gnb): at gNB g from UE u
        self.dl_snr = 10 ** (dl_db / 10)  # (n_ue, n_gnb): at UE u from gNB g
        # UL open-loop power control (TS 38.213 7.1.1): P0 + 10 log10(2^mu) + alpha PL per PRB,
        # PL the coupling loss to the serving gNB; capped at P_CMAX by GnbCell's CSI.
        mu = round(math.log2(cfg.subcarrier_spacing_hz / 15000))
        cl_serving = links.coupling_loss_db[rows, serving]
        pc_db = (layout.ul_p0_dbm + 10 * math.log10(2**mu) + layout.ul_alpha * cl_serving
                 - cl_serving - cfg.interference_margin_db - noise_prb_dbm
                 - cfg.gnb_noise_figure_db)
        pc_snr = 10 ** (pc_db / 10)
        groups = layout.groups
        has_ues = np.bincount(serving, minlength=n_gnb) > 0
        ipn_ul, ipn_dl = _geometry_ipn(serving, groups, has_ues, self.ul_snr, self.dl_snr,
                                       pc_snr)
        # The links that can carry a signal or interference: to the serving gNB, and to every
        # other gNB of its frequency group that serves UEs.
        used = (groups[None, :] == groups[serving][:, None]) & has_ues[None, :]
        self.fading = fading = LinkFading(
            ue_ids, list(layout.gnb_ids), links.los, math.ceil(n_cell_prb / cfg.subband_prb),
            cell_cfg, seed, stream_prefix, used)
        self.serving_gnb_index: dict[str, int] = {ue: int(g) for ue, g in zip(ue_ids, serving,
                                                                               strict=True)}
        self.cells: list[GnbCell] = []
        self.cell_gnb: list[int] = []  # layout index of each cell's gNB
        self.cell_ues: list[list[int]] = []  # the hall's UE index of each cell's UEs, in order
        self._cell_of: dict[str, GnbCell] = {}
        self._serving_links: list[np.ndarray] = []
        self._no_links = np.zeros(0, dtype=np.int64)
        self._update = -1
        for g in range(n_gnb):
            members = np.flatnonzero(serving == g)
            if not members.size:
                continue
            ch = ServingLinks(fading, members * n_gnb + g, ul_db[members, g], dl_db[members, g],
                              links.los[members, g], links.d3d_m[members, g])
            x, y, z = (float(v) for v in layout.gnb_positions_m[g])
            cell = GnbCell(cell_cfg, (x, y, z), {ue_ids[m]: ue_positions_m[ue_ids[m]]
                                                  for m in members.tolist()},
                           seed, f"{stream_prefix}/{layout.gnb_ids[g]}", ch,
                           pc_snr[members].tolist(), ipn_ul[members].tolist(),
                           ipn_dl[members].tolist())
            self.cells.append(cell)
            self._serving_links.append(ch.links)
            self.cell_gnb.append(g)
            self.cell_ues.append(members.tolist())
            for m in members.tolist():
                self._cell_of[ue_ids[m]] = cell
        self.ue_ids = ue_ids
        self._groups = groups
        self._subband_prb = cfg.subband_prb
        self._period = cell_cfg.channel_update_period_slots
        self._last_slot: int | None = None
        self.next_slot_us = 0
        self.slots = 0
        self.sinr_hist = {"ul": np.zeros(SINR_HIST_BINS, dtype=np.int64),
                          "dl": np.zeros(SINR_HIST_BINS, dtype=np.int64)}
        self._sinr_pending: dict[str, list[float]] = {"ul": [], "dl": []}
        self.record = record
        self._records: dict[str, list[Any]] = _empty_records()

    # ------------------------------------------------------------------ interface
    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        """Put ``packet`` in its UE's cell (``NrCell.enqueue``)."""
        return self._cell(packet).enqueue(packet)

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``enqueue`` each of ``packets`` in order, runs of one UE at a time; the outcomes of
        those refused at once."""
        batch = packets if isinstance(packets, list) else list(packets)
        refused: list[PacketOutcome] = []
        i, n = 0, len(batch)
        while i < n:
            ue = batch[i].ue
            j = i + 1
            while j < n and batch[j].ue == ue:
                j += 1
            refused += self._cell(batch[i]).enqueue_many(batch if j - i == n else batch[i:j])
            i = j
        return refused

    def _cell(self, packet: Packet) -> GnbCell:
        cell = self._cell_of.get(packet.ue)
        if cell is None:
            raise ValueError(f"packet {packet.packet_id}: unknown UE {packet.ue!r}")
        return cell

    def run_slot(self, slot_start_us: int) -> list[PacketOutcome]:
        """Simulate the slot at ``slot_start_us`` (us, a multiple of ``slot_us``, later than the
        last) in every cell with work: each decides its transmissions, then each transmission's
        SINR is computed, then each cell decodes. The outcomes, cell by cell."""
        slot_us = self.slot_us
        if slot_start_us % slot_us:
            raise ValueError(f"slot_start_us={slot_start_us} is not a multiple of the slot "
                             f"({slot_us} us)")
        s = slot_start_us // slot_us
        if self._last_slot is not None and s <= self._last_slot:
            raise ValueError(f"slot_start_us={slot_start_us} does not advance past the last "
                             f"slot ({self._last_slot * slot_us} us)")
        self._last_slot = s
        self.next_slot_us = slot_start_us + slot_us
        self.slots += 1
        active = [k for k, cell in enumerate(self.cells) if cell.has_pending()]
        cells = self.cells
        update = s // self._period
        if update != self._update:
            # The serving links of every cell with work, in one step (each cell's channel then
            # finds them up to date).
            self._update = update
            self.fading.refresh(np.concatenate([self._serving_links[k] for k in active])
                                if active else self._no_links, update)
        for k in active:
            cells[k].open_slot(slot_start_us)
        plans = [cells[k].plan_slot(s) for k in active]
        dl_sinr, dl_inr = self._sinr(active, [p[0] for p in plans], False, update)
        ul_sinr, ul_inr = self._sinr(active, [p[1] for p in plans], True, update)
        out: list[PacketOutcome] = []
        i_dl = i_ul = 0
        for k, (pdsch, pusch) in zip(active, plans, strict=True):
            cell = cells[k]
            n_dl, n_ul = len(pdsch), len(pusch)
            decoded: list[bool] = []
            out += cell.finish_slot(s, pdsch, dl_sinr[i_dl:i_dl + n_dl], pusch,
                                    ul_sinr[i_ul:i_ul + n_ul], decoded)
            csi = cell.csi
            for j, (tb, _) in enumerate(pdsch):
                csi.measured(tb.ue, False, dl_inr[i_dl + j])
            for j, (_, tb) in enumerate(pusch):
                csi.measured(tb.ue, True, ul_inr[i_ul + j])
            if self.record:
                self._record(slot_start_us, k, [tb for tb, _ in pdsch], dl_sinr[i_dl:i_dl + n_dl],
                             [tb for _, tb in pusch], ul_sinr[i_ul:i_ul + n_ul], decoded)
            i_dl += n_dl
            i_ul += n_ul
        self._histogram("dl", dl_sinr)
        self._histogram("ul", ul_sinr)
        return out

    def _sinr(self, active: list[int], per_cell: list[Any], ul: bool, update: int
              ) -> tuple[list[float], list[float]]:
        """Effective SINR and mean interference over noise (linear) of the transmissions of
        one link of the active cells (``per_cell``: each cell's PDSCH or PUSCH list, in the
        order of ``active``), in that order."""
        cell_of_tx: list[int] = []
        ue_of_tx: list[int] = []
        p0: list[int] = []
        n: list[int] = []
        scale: list[float] = []
        beta: list[float] = []
        for k, txs in zip(active, per_cell, strict=True):
            if not txs:
                continue
            cell = self.cells[k]
            csi = cell.csi
            ues = self.cell_ues[k]
            g = self.cell_gnb[k]
            betas = cell.betas
            for a, b in txs:
                if ul:
                    tb, first, size = b, a.prb_start, a.n_prb
                    scale.append(csi.ul_scale(tb.ue, size))
                else:
                    tb, first, size = a, b, a.n_prb
                    scale.append(csi.dl_snr[tb.ue])
                cell_of_tx.append(g)
                ue_of_tx.append(ues[tb.ue])
                p0.append(first)
                n.append(size)
                beta.append(betas[tb.mcs])
        if not cell_of_tx:
            return [], []
        c = np.array(cell_of_tx)
        u = np.array(ue_of_tx)
        scale_arr = np.array(scale)
        groups = self._groups[c]
        co_channel = (groups[:, None] == groups[None, :]) & (c[:, None] != c[None, :])
        n_gnb = self.n_gnb
        if ul:
            # Transmission j reaches gNB c[i] with its own power: its power-control power per
            # PRB relative to the whole power spread over the carrier.
            factor = scale_arr / self.ul_snr[u, c]
            cross = self.ul_snr[u[None, :], c[:, None]] * factor[None, :]
            cross_links = u[None, :] * n_gnb + c[:, None]
        else:
            cross = self.dl_snr[u[:, None], c[None, :]]
            cross_links = u[:, None] * n_gnb + c[None, :]
        eff, inr = slot_sinr(np.array(p0), np.array(n), scale_arr, np.array(beta),
                             u * n_gnb + c, np.where(co_channel, cross, 0.0), cross_links,
                             self.fading, update, self._subband_prb)
        return eff.tolist(), inr.tolist()

    def _histogram(self, link: str, sinr: list[float]) -> None:
        """Count the effective SINRs ``sinr`` (linear) of ``link`` in its histogram, binned a
        few thousand at a time."""
        pending = self._sinr_pending[link]
        pending += sinr
        if len(pending) >= 4096:
            self._bin(link)

    def _bin(self, link: str) -> None:
        pending = self._sinr_pending[link]
        if not pending:
            return
        db = 10 * np.log10(np.maximum(np.array(pending), 1e-30))
        bins = np.clip(((db - SINR_HIST_MIN_DB) / SINR_HIST_STEP_DB).astype(np.int64), 0,
                       SINR_HIST_BINS - 1)
        self.sinr_hist[link] += np.bincount(bins, minlength=SINR_HIST_BINS)
        pending.clear()

    def _record(self, t_us: int, k: int, pdsch: list[Any], pdsch_sinr: list[float],
                pusch: list[Any], pusch_sinr: list[float], decoded: list[bool]) -> None:
        """Keep the transmissions of cell ``k`` in the slot at ``t_us`` (us)."""
        rec = self._records
        ids = self.cells[k].ue_ids
        g = self.cell_gnb[k]
        i = 0
        for link, tbs, sinrs in (("dl", pdsch, pdsch_sinr), ("ul", pusch, pusch_sinr)):
            for tb, sinr in zip(tbs, sinrs, strict=True):
                rec["t_us"].append(t_us)
                rec["gnb"].append(g)
                rec["dir"].append(link)
                rec["ue"].append(ids[tb.ue])
                rec["n_prb"].append(tb.n_prb)
                rec["cell_prb"].append(self.n_cell_prb)
                rec["mcs"].append(tb.mcs)
                rec["tx"].append(tb.tx_count)
                rec["sinr_db"].append(10 * math.log10(sinr) if sinr > 0 else -300.0)
                rec["ok"].append(decoded[i])
                i += 1

    def transmissions(self) -> dict[str, list[Any]] | None:
        """The transmissions since the last call, as the columns of the ``transmissions`` table
        (None without ``record``)."""
        if not self.record:
            return None
        rec, self._records = self._records, _empty_records()
        return rec

    def serving(self) -> dict[str, int]:
        """UE id -> the layout index of its serving gNB."""
        return self.serving_gnb_index

    def has_pending(self) -> bool:
        """True while a cell has work (``NrCell.has_pending``)."""
        return any(cell.has_pending() for cell in self.cells)

    def earliest_delivery_us(self, ue: str, direction: str) -> int | None:
        """``NrCell.earliest_delivery_us`` of the UE's cell, not before the next slot the hall
        runs (a cell without work skips slots); None for an unknown UE."""
        cell = self._cell_of.get(ue)
        if cell is None:
            return None
        at = cell.earliest_delivery_us(ue, direction)
        return None if at is None else max(at, self.next_slot_us)

    def set_flow_qos(self, flow: str, qos: FlowQos, ue: str | None = None) -> None:
        """``NrCell.set_flow_qos`` in the UE's cell, or in every cell without ``ue``."""
        if ue is None:
            for cell in self.cells:
                cell.set_flow_qos(flow, qos)
            return
        served = self._cell_of.get(ue)
        if served is None:
            raise ValueError(f"flow {flow!r}: unknown UE {ue!r}")
        served.set_flow_qos(flow, qos, ue)

    def stats(self) -> dict[str, Any]:
        """The hall's totals in the form of ``NrCell.stats`` (PRB utilisation over every cell's
        carrier), per gNB ``gnb<index>`` its PRB utilisation, delivered bytes, BLER and UE count, the
        SINR percentiles of the transmissions, and per UE what its cell reports."""
        slots = max(1, self.slots)
        per_cell = [cell.stats() for cell in self.cells]
        out: dict[str, Any] = {"slots": self.slots, "slot_us": self.slot_us,
                               "n_prb": self.n_cell_prb, "gnbs": len(self.cells),
                               "reuse": self.layout.reuse}
        lost: dict[str, int] = {}
        for st in per_cell:
            for cause, count in st["lost_packets"].items():
                lost[cause] = lost.get(cause, 0) + count
        out["lost_packets"] = lost
        out["pdcch_missed"] = sum(st["pdcch_missed"] for st in per_cell)
        prb_slots = slots * self.n_cell_prb
        for link in ("ul", "dl"):
            used = [cell.prb_used(link == "ul") for cell in self.cells]
            first = sum(st[link]["first_transmissions"] for st in per_cell)
            failed = sum(st[link]["bler_first_transmission"] * st[link]["first_transmissions"]
                         for st in per_cell)
            self._bin(link)
            hist = self.sinr_hist[link].tolist()
            out[link] = {
                "delivered_bytes": sum(st[link]["delivered_bytes"] for st in per_cell),
                "delivered_packets": sum(st[link]["delivered_packets"] for st in per_cell),
                "prb_utilisation": sum(used) / (prb_slots * max(1, len(per_cell))),
                "first_transmissions": first,
                "bler_first_transmission": failed / first if first else 0.0,
                "harq_retransmissions": sum(st[link]["harq_retransmissions"] for st in per_cell),
                "harq_residual_failures": sum(st[link]["harq_residual_failures"]
                                              for st in per_cell),
                "sinr_db_p5": _hist_percentile(hist, 5),
                "sinr_db_p50": _hist_percentile(hist, 50),
                "sinr_db_p95": _hist_percentile(hist, 95),
            }
            for k, st in enumerate(per_cell):
                gnb = out.setdefault(f"gnb{self.cell_gnb[k]}", {"ue_count": len(self.cell_ues[k])})
                gnb[link] = {"prb_utilisation": used[k] / prb_slots,
                             "delivered_bytes": st[link]["delivered_bytes"],
                             "bler_first_transmission": st[link]["bler_first_transmission"]}
        ues: dict[str, Any] = {}
        for k, st in enumerate(per_cell):
            for ue, row in st["ues"].items():
                ues[ue] = {**row, "gnb": self.cell_gnb[k]}
        out["ues"] = ues
        return out


def _geometry_ipn(serving: np.ndarray, groups: np.ndarray, has_ues: np.ndarray,
                  ul_snr: np.ndarray, dl_snr: np.ndarray, pc_snr: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The starting interference estimates of each UE, interference plus noise over noise per
    link (linear), from the geometry at full load: in DL every other co-channel gNB serving UEs
    sends on every PRB; in UL every such cell has one UE on every PRB, the mean of its UEs at
    their power-control power over the whole carrier."""
    n_ue, n_gnb = ul_snr.shape
    rows = np.arange(n_ue)
    other = (groups[None, :] == groups[serving][:, None]) & has_ues[None, :]
    other[rows, serving] = False
    ipn_dl = 1.0 + np.where(other, dl_snr, 0.0).sum(axis=1)
    # A UE's power relative to P_CMAX over the carrier when it has the whole carrier.
    factor = np.minimum(pc_snr, ul_snr[rows, serving]) / ul_snr[rows, serving]
    mean_at = np.zeros((n_gnb, n_gnb))  # [c, g]: mean received at g from a UE of cell c
    for c in range(n_gnb):
        members = serving == c
        if members.any():
            mean_at[c] = (ul_snr[members] * factor[members, None]).mean(axis=0)
    ipn_ul = 1.0 + np.where(other, mean_at.T[serving], 0.0).sum(axis=1)
    return ipn_ul, ipn_dl


def _hist_percentile(hist: list[int], q: float) -> float | None:
    """The q-th percentile (dB) of an SINR histogram (the bin's centre); None if empty."""
    total = sum(hist)
    if not total:
        return None
    target = q / 100 * total
    acc = 0
    for b, count in enumerate(hist):
        acc += count
        if acc >= target:
            return SINR_HIST_MIN_DB + (b + 0.5) * SINR_HIST_STEP_DB
    return None


def _empty_records() -> dict[str, list[Any]]:
    return {name: [] for name in ("t_us", "gnb", "dir", "ue", "n_prb", "cell_prb", "mcs", "tx",
                                  "sinr_db", "ok")}
