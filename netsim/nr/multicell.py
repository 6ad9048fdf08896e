"""MultiCell: the NR cells of every gNB of a hall's InF layout in one radio model, each with its own
scheduler, HARQ and link adaptation (``GnbCell``), on one carrier (reuse 1) or a third of it per
frequency group (reuse 3). Each slot every cell first decides its transmissions, then the SINR of
each is computed per PRB from the other co-channel cells' transmissions of that slot
(``sinr.slot_sinr``), then each cell decodes (docs/netsim.md, "Several cells")."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from netsim.nr.agv_traffic import AgvTraffic
from netsim.nr.csi import prepare_uplink
from netsim.nr.gnb_cell import GnbCell
from netsim.nr.handover import HandoverControl, HandoverParams, ping_pongs
from netsim.nr.interference import serving_gnb
from netsim.nr.large_scale import InfLinks, InfMaps, hall_links
from netsim.nr.layout import InfLayout
from netsim.nr.link_fading import LinkFading, ServingLinks
from netsim.nr.mobility import Fleet
from netsim.nr.sinr import slot_sinr
from netsim.radio_cell import LOSS_HANDOVER, FlowQos, Packet, PacketOutcome, RadioCell
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

    A partition of the hall holds the cells of ``own_gnbs`` only (None: every gNB), seeing the
    whole hall's large scale; each slot it takes the other partitions' transmissions of the
    slot before (``run_slot``'s ``remote``) and gives its own (``slot_transmissions``): with the
    same seed the partitions' outcomes are the whole hall's.

    Moving radios (docs/netsim.md, "Mobility and handover"): ``fleet`` drives the AGVs of
    ``agv_traffic`` (its UE ids, in order), whose streams enter every slot. Each AGV is a UE of
    every gNB's cell (then every gNB has a cell), attached to one at a time; its large scale
    follows its position (``large_scale.InfMaps``, read every measurement period) and
    ``handover`` moves it between cells on the A3 event (``handover.HandoverControl``, streams
    ``<stream_prefix>/handover/<ue>``). The fading of a link keeps the LOS state of the AGV's
    start.
    """

    def __init__(self, config: NrConfig, layout: InfLayout,
                 ue_positions_m: Mapping[str, tuple[float, float, float]], seed: int,
                 stream_prefix: str = "netsim/nr", record: bool = False,
                 fleet: Fleet | None = None, agv_traffic: AgvTraffic | None = None,
                 handover: HandoverParams | None = None,
                 own_gnbs: Sequence[int] | None = None) -> None:
        cfg = config
        if not ue_positions_m:
            raise ValueError("ue_positions_m is empty: a cell needs at least one UE")
        agv_ids = [] if agv_traffic is None else list(agv_traffic.agv_ids)
        if agv_ids and (fleet is None or len(fleet) != len(agv_ids) or handover is None):
            raise ValueError(f"{len(agv_ids)} AGVs need a fleet of as many routes and handover "
                             "settings")
        own = set(range(layout.n_gnb) if own_gnbs is None else own_gnbs)
        if not own <= set(range(layout.n_gnb)):
            raise ValueError(f"own_gnbs {sorted(own)} must be gNB indices 0..{layout.n_gnb - 1}")
        if agv_ids and own_gnbs is not None and handover is not None and not handover.interruption_us:
            raise ValueError("a partition of the hall (own_gnbs) with AGVs needs a handover "
                             "interruption of at least 1 us (netsim.handover.interruption_ms): the "
                             "packets a handover takes from one partition's gNB reach another's a "
                             "slot later")
        self.own = own
        n_cell_prb = cfg.n_prb // layout.reuse
        if n_cell_prb < 1:
            raise ValueError(f"n_prb = {cfg.n_prb} leaves no PRB per cell with reuse "
                             f"{layout.reuse}")
        self.config = cell_cfg = cfg.model_copy(update={"n_prb": n_cell_prb})
        self.slot_us = cfg.slot_us
        self.n_cell_prb = n_cell_prb
        self.layout = layout
        ue_ids = list(ue_positions_m)
        n_static = len(ue_ids)
        pos = np.array([ue_positions_m[u] for u in ue_ids], dtype=float).reshape(-1, 3)
        n_gnb = layout.n_gnb
        self.n_gnb = n_gnb
        self.fleet = fleet
        self.agv_traffic = agv_traffic
        self.maps: InfMaps | None = None
        if agv_ids:
            assert fleet is not None
            # The maps read at the static UEs give InfLinks' values (the same streams).
            self.maps = InfMaps(layout, cfg.carrier_frequency_hz, seed, f"{stream_prefix}/inf",
                                cfg.gnb_antenna_gain_dbi, cfg.ue_antenna_gain_dbi, cfg.los_mode,
                                cfg.shadowing_enabled)
            ue_ids += agv_ids
            pos = np.vstack([pos, fleet.positions_m(0)])
            links: InfLinks | Any = self.maps.links(pos)
        else:
            links = hall_links(layout, pos, cfg, seed, stream_prefix)
        n_ue = len(ue_ids)
        self.links = links
        serving = serving_gnb(links.coupling_loss_db)
        rows = np.arange(n_ue)
        # Mean SNR per PRB of every link with the whole power over the cell's carrier, as the
        # single cell computes it (InfSlChannel); the interference margin counts as noise.
        prb_bw_hz = 12 * cfg.subcarrier_spacing_hz
        self._noise_prb_dbm = cfg.noise_psd_dbm_per_hz + 10 * math.log10(prb_bw_hz)
        ul_db, dl_db, pc_all_db = self._link_snr_db(links.pathloss_db, links.shadowing_db,
                                                    links.coupling_loss_db)
        self.ul_snr = 10 ** (ul_db / 10)  # (n_ue, n_gnb): at gNB g from UE u
        self.dl_snr = 10 ** (dl_db / 10)  # (n_ue, n_gnb): at UE u from gNB g
        pc_all = 10 ** (pc_all_db / 10)
        pc_snr = pc_all[rows, serving]
        groups = layout.groups
        # With AGVs every gNB may serve one: each has a cell.
        has_ues = (np.bincount(serving, minlength=n_gnb) > 0) | bool(agv_ids)
        ipn_ul, ipn_dl = _geometry_ipn(serving, groups, has_ues, self.ul_snr, self.dl_snr,
                                       pc_snr)
        # The links that can carry a signal or interference: to the serving gNB, and to every
        # other gNB of its frequency group that serves UEs; every link of an AGV.
        used = (groups[None, :] == groups[serving][:, None]) & has_ues[None, :]
        used[n_static:] = True
        # An AGV's starting interference estimates in each cell, as if that cell served it.
        agv_rows = np.arange(n_static, n_ue)
        agv_ipn: list[tuple[np.ndarray, np.ndarray]] = []
        for g in range(n_gnb if agv_ids else 0):
            at_g = serving.copy()
            at_g[agv_rows] = g
            agv_pc = pc_snr.copy()
            agv_pc[agv_rows] = pc_all[agv_rows, g]
            agv_ipn.append(_geometry_ipn(at_g, groups, has_ues, self.ul_snr, self.dl_snr,
                                         agv_pc))
        # Downlink interference at a UE from a gNB not serving it: processes of their own.
        used_dl = used.copy()
        used_dl[np.arange(n_static), serving[:n_static]] = False
        self.fading = fading = LinkFading(
            ue_ids, list(layout.gnb_ids), links.los, math.ceil(n_cell_prb / cfg.subband_prb),
            cell_cfg, seed, stream_prefix, used, used_dl)
        self.serving_gnb_index: dict[str, int] = {ue: int(g) for ue, g in zip(ue_ids, serving,
                                                                               strict=True)}
        self.cells: list[GnbCell] = []
        self.cell_gnb: list[int] = []  # layout index of each cell's gNB
        self.cell_ues: list[list[int]] = []  # the hall's UE index of each cell's UEs, in order
        self._cell_of: dict[str, GnbCell] = {}
        self._serving_links: list[np.ndarray] = []
        self._no_links = np.zeros(0, dtype=np.int64)
        self._update = -1
        self.cell_static: list[int] = []  # the number of static UEs of each cell
        self.cell_of_gnb: list[GnbCell | None] = [None] * n_gnb
        positions = {ue: (float(p[0]), float(p[1]), float(p[2])) for ue, p in zip(ue_ids, pos,
                                                                                   strict=True)}
        for g in range(n_gnb):
            members = np.flatnonzero(serving[:n_static] == g)
            static = members.size
            if g not in own or (not static and not agv_ids):
                continue
            members = np.concatenate([members, agv_rows]).astype(np.int64)
            ch = ServingLinks(fading, members * n_gnb + g, ul_db[members, g], dl_db[members, g],
                              links.los[members, g], links.d3d_m[members, g])
            pc = pc_snr[members]
            ipn = (ipn_ul[members], ipn_dl[members])
            if agv_ids:
                pc[static:] = pc_all[agv_rows, g]
                ipn[0][static:] = agv_ipn[g][0][agv_rows]
                ipn[1][static:] = agv_ipn[g][1][agv_rows]
            x, y, z = (float(v) for v in layout.gnb_positions_m[g])
            cell = GnbCell(cell_cfg, (x, y, z), {ue_ids[m]: positions[ue_ids[m]]
                                                  for m in members.tolist()},
                           seed, f"{stream_prefix}/{layout.gnb_ids[g]}", ch,
                           pc.tolist(), ipn[0].tolist(), ipn[1].tolist())
            self.cells.append(cell)
            self._serving_links.append(ch.links)
            self.cell_gnb.append(g)
            self.cell_ues.append(members.tolist())
            self.cell_static.append(static)
            self.cell_of_gnb[g] = cell
            for m in members.tolist():
                if serving[m] == g:
                    self._cell_of[ue_ids[m]] = cell
                else:
                    cell.detach(ue_ids[m], 0)  # an AGV served elsewhere
        self.ue_ids = ue_ids
        self._hall_index = {ue: i for i, ue in enumerate(ue_ids)}
        self.agv_ids = agv_ids
        self._agv_set = set(agv_ids)
        self._n_static = n_static
        self.handover: HandoverControl | None = None
        # Per AGV, the held packets its target cell refused at its attach (a full buffer).
        self._attach_refused: dict[str, list[PacketOutcome]] = {}
        self._agv_db: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0),
                                                                    np.zeros(0))
        self._move_period_us = 0
        self._rs_dbm = 0.0
        self._queues: list[_GnbQueues] = []
        self._next_move_us = 0
        self._handover_lost = 0
        self._handover_rows: list[Any] = []
        # Handovers from one of this partition's gNBs to another's, with the packets they took
        # from the source cell, for ``held_out``.
        self._held_out: list[tuple[int, str, int, list[Packet], dict[str, Any]]] = []
        if agv_ids:
            assert handover is not None
            self.handover = HandoverControl(handover, agv_ids, serving[agv_rows], n_gnb, seed,
                                            f"{stream_prefix}/handover")
            self._move_period_us = handover.measurement_period_us
            # RSRP per RE: the gNB's power over every subcarrier of its carrier, less the
            # coupling loss (TS 38.215 5.1.1); only differences between gNBs matter to A3.
            self._rs_dbm = cfg.gnb_tx_power_dbm - 10 * math.log10(12 * n_cell_prb)
            self._queues = [_GnbQueues(self, g) for g in range(n_gnb)]
            assert agv_traffic is not None
            budget = agv_traffic.delay_budget_us
            for flow, direction in agv_traffic.flows():
                # The loops' priorities: DL before UL.
                qos = FlowQos(priority=5 if direction == "dl" else 10, delay_budget_us=budget)
                for c in self.cells:
                    c.set_flow_qos(flow, qos)
        self._groups = groups
        self._one_group = bool((groups == groups[0]).all())
        self._subband_prb = cfg.subband_prb
        self._period = cell_cfg.channel_update_period_slots
        self._last_slot: int | None = None
        self._planned: _Planned | None = None
        self.next_slot_us = 0
        self.slots = 0
        self.sinr_hist = {"ul": np.zeros(SINR_HIST_BINS, dtype=np.int64),
                          "dl": np.zeros(SINR_HIST_BINS, dtype=np.int64)}
        self._sinr_pending: dict[str, list[float]] = {"ul": [], "dl": []}
        self.record = record
        self._records: dict[str, list[Any]] = _empty_records()

    def _link_snr_db(self, pathloss_db: np.ndarray, shadowing_db: np.ndarray,
                     coupling_loss_db: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per link (n_ue, n_gnb), dB: the mean SNR per PRB with the whole power over the
        cell's carrier, UL and DL, as the single cell computes it (InfSlChannel, the
        interference margin counting as noise), and the UL SNR per PRB at the power-control
        target if that gNB served the UE (TS 38.213 7.1.1: P0 + 10 log10(2^mu) + alpha PL per
        PRB, PL the coupling loss; GnbCell's CSI caps it at P_CMAX)."""
        cfg, layout = self.config, self.layout
        noise = self._noise_prb_dbm
        coupling_db = (cfg.gnb_antenna_gain_dbi + cfg.ue_antenna_gain_dbi - pathloss_db
                       - shadowing_db - cfg.interference_margin_db
                       - 10 * math.log10(self.n_cell_prb))
        ul_db = cfg.ue_tx_power_dbm + coupling_db - noise - cfg.gnb_noise_figure_db
        dl_db = cfg.gnb_tx_power_dbm + coupling_db - noise - cfg.ue_noise_figure_db
        mu = round(math.log2(cfg.subcarrier_spacing_hz / 15000))
        pc_db = (layout.ul_p0_dbm + 10 * math.log10(2**mu) + layout.ul_alpha * coupling_loss_db
                 - coupling_loss_db - cfg.interference_margin_db - noise
                 - cfg.gnb_noise_figure_db)
        return ul_db, dl_db, pc_db

    # ------------------------------------------------------------------ moving radios
    def _agv_slot(self, t_us: int, out: list[PacketOutcome]) -> None:
        """The AGVs at the start of the slot at ``t_us`` (us): handovers ending and starting,
        their large scale moved to where they are, and their streams' new packets in."""
        control = self.handover
        fleet = self.fleet
        maps = self.maps
        assert control is not None and fleet is not None and maps is not None
        if t_us >= self._next_move_us:
            self._move_agvs(t_us)
            self._next_move_us = t_us - t_us % self._move_period_us + self._move_period_us
        if control.next_event_us() <= t_us:
            rs = self._rs_dbm

            def rsrp_dbm(t: int) -> np.ndarray:
                return rs - maps.coupling_loss_db(fleet.positions_m(t))

            tick = control.tick(t_us, rsrp_dbm, self._queues)
            own = self.own
            for h in tick.started:
                if h.source in own and h.target not in own:
                    # What the source cell gave up leaves now (what reaches the UE from now on
                    # is held by the target's partition too), and so do the fading processes of
                    # the interference at the UE, which the serving partition steps.
                    self._held_out.append((h.target, h.ue, h.start_us, h.held,
                                           self.fading.export(self._dl_interference_links(h.ue))))
                    h.held = []
            for h in tick.completed:
                if h.target not in own:
                    continue  # its target's partition forwards or loses the held packets
                self._handover_rows.append(h)
                for p in h.lost:
                    out.append(PacketOutcome(p, None, LOSS_HANDOVER))
                self._handover_lost += len(h.lost)
                refused = self._attach_refused.pop(h.ue, [])
                h.forwarded -= len(refused)
                out += refused
        traffic = self.agv_traffic
        assert traffic is not None
        due = traffic.due(t_us)
        if due:
            out += self.enqueue_many(due)

    def _move_agvs(self, t_us: int) -> None:
        """Read every AGV's large scale at its position at ``t_us`` (us): the hall's link SNRs
        (which the interference reads) and its serving cell's channel."""
        maps, fleet = self.maps, self.fleet
        assert maps is not None and fleet is not None
        state = maps.links(fleet.positions_m(t_us))
        ul_db, dl_db, pc_db = self._link_snr_db(state.pathloss_db, state.shadowing_db,
                                                state.coupling_loss_db)
        rows = slice(self._n_static, len(self.ue_ids))
        self.ul_snr[rows] = 10 ** (ul_db / 10)
        self.dl_snr[rows] = 10 ** (dl_db / 10)
        self._agv_db = (ul_db, dl_db, 10 ** (pc_db / 10))
        for a, ue in enumerate(self.agv_ids):
            cell = self._cell_of.get(ue)
            if cell is not None:
                self._move_in(cell, a)

    def _move_in(self, cell: GnbCell, a: int) -> None:
        """Give AGV ``a``'s current link to ``cell``'s gNB to that cell."""
        k = self.cells.index(cell)
        g = self.cell_gnb[k]
        ul_db, dl_db, pc = self._agv_db
        cell.move(self.cell_static[k] + a, float(ul_db[a, g]), float(dl_db[a, g]),
                  float(pc[a, g]))

    def _detach(self, g: int, ue: str, t_us: int) -> list[Packet]:
        cell = self.cell_of_gnb[g]
        if cell is None:  # another partition's gNB: that partition holds the UE's packets
            return []
        self._cell_of.pop(ue, None)
        return cell.detach(ue, t_us)

    def _attach(self, g: int, ue: str, t_us: int, packets: list[Packet]) -> None:
        self.serving_gnb_index[ue] = g
        cell = self.cell_of_gnb[g]
        if cell is None:  # another partition's gNB: that partition attaches the UE
            return
        self._move_in(cell, self.agv_ids.index(ue))
        self._cell_of[ue] = cell
        self._attach_refused[ue] = cell.attach(ue, t_us, packets)

    def held_out(self) -> list[tuple[int, str, int, list[Packet], dict[str, Any]]]:
        """The handovers started since the last call from one of this partition's gNBs to
        another partition's: (target gNB, UE, start us, the packets taken from the source cell,
        oldest first, the fading of the interference at the UE: ``LinkFading.export``), for the
        target's partition (``take_held``). They leave this partition."""
        out, self._held_out = self._held_out, []
        return out

    def take_held(self, ue: str, start_us: int, packets: list[Packet],
                  fading: dict[str, Any]) -> None:
        """What another partition gave up when ``ue``'s handover from its gNB into one of this
        partition's started at ``start_us`` (``held_out``): the packets, first among those
        held for the target cell, as in the whole hall, and the fading processes of the
        interference at the UE. They arrive a slot later, before the handover ends (the UE
        receives nothing meanwhile)."""
        control = self.handover
        h = None if control is None else control.running(ue)
        if h is None or h.start_us != start_us or h.target not in self.own:
            raise ValueError(f"held packets of {ue}'s handover started at {start_us} us: no such "
                             f"handover into this partition is running")
        if sorted(fading["links"]) != sorted(self._dl_interference_links(ue)):
            raise ValueError(f"{ue}'s fading processes: links {fading['links']} are not its "
                             f"interference links")
        h.held[:0] = packets
        self.fading.load(fading)

    def _dl_interference_links(self, ue: str) -> list[int]:
        """The fading processes of the downlink interference at ``ue`` from each gNB."""
        base = self.fading.dl_interference_offset + self._hall_index[ue] * self.n_gnb
        return list(range(base, base + self.n_gnb))

    def handovers(self) -> dict[str, list[Any]] | None:
        """The handovers completed since the last call, as the columns of the ``handovers``
        table (None without moving radios)."""
        if self.handover is None:
            return None
        rows, self._handover_rows = self._handover_rows, []
        return {"ue": [h.ue for h in rows], "source": [h.source for h in rows],
                "target": [h.target for h in rows], "start_us": [h.start_us for h in rows],
                "end_us": [h.end_us for h in rows], "forwarded": [h.forwarded for h in rows],
                "lost": [len(h.lost) for h in rows]}

    # ------------------------------------------------------------------ interface
    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        """Put ``packet`` in its UE's cell (``NrCell.enqueue``); a moving radio's during its
        handover is held for the target cell."""
        cell = self._cell_of.get(packet.ue)
        if cell is None and self.handover is not None and packet.ue in self.handover.index:
            if self.handover.in_handover(packet.ue):
                self.handover.hold(packet.ue, [packet])
            return None  # else served by another partition's gNB: that partition takes it
        return self._cell(packet).enqueue(packet)

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``enqueue`` each of ``packets`` in order, runs of one UE at a time; the outcomes of
        those refused at once."""
        batch = packets if isinstance(packets, list) else list(packets)
        refused: list[PacketOutcome] = []
        i, n = 0, len(batch)
        control = self.handover
        while i < n:
            ue = batch[i].ue
            j = i + 1
            while j < n and batch[j].ue == ue:
                j += 1
            run = batch if j - i == n else batch[i:j]
            if control is not None and ue not in self._cell_of and ue in control.index:
                if control.in_handover(ue):
                    control.hold(ue, run)
                # else served by another partition's gNB: that partition takes them
            else:
                refused += self._cell(batch[i]).enqueue_many(run)
            i = j
        return refused

    def _cell(self, packet: Packet) -> GnbCell:
        cell = self._cell_of.get(packet.ue)
        if cell is None:
            raise ValueError(f"packet {packet.packet_id}: unknown UE {packet.ue!r}")
        return cell

    def run_slot(self, slot_start_us: int, remote: Mapping[str, list[Tx]] | None = None
                 ) -> list[PacketOutcome]:
        """Simulate the slot at ``slot_start_us`` (us, a multiple of ``slot_us``, later than the
        last) in every cell with work, one slot late (docs/architecture.md sec. 13, "Decode one
        slot late"): first the transmissions planned at the last call are decoded, each at its
        SINR against every co-channel transmission of that slot, this hall's and ``remote``'s
        (the other partitions' of that slot, per link; ``slot_transmissions`` gave them there),
        and their packets delivered at the end of this slot; then each cell with work decides
        this slot's transmissions (``slot_transmissions``). The outcomes, cell by cell."""
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
        out: list[PacketOutcome] = []
        planned = self._planned
        if planned is not None:  # else nothing of this hall's to interfere with
            self._planned = None
            self._decode(planned, remote or {}, out, slot_start_us + slot_us)
        if self.handover is not None:
            self._agv_slot(slot_start_us, out)
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
        # The UL wideband CSI of every cell due to refresh it, in one step; a cell that does not
        # schedule its uplink in this slot drops it (its inputs may move before it does).
        prepared = [cells[k].csi for k in active if cells[k].csi.stale_ul]
        if len(prepared) > 1:
            prepare_uplink(prepared)
        plans = [cells[k].plan_slot(s) for k in active]
        for csi in prepared:
            csi.prepared_ul = None
        if active:
            self._planned = _Planned(s, update, active, plans,
                                     self._tx_rows(active, [p[0] for p in plans], False),
                                     self._tx_rows(active, [p[1] for p in plans], True))
        if self.agv_traffic is not None:
            self.agv_traffic.count(out)
        return out

    def slot_transmissions(self) -> dict[str, list[Tx]]:
        """The transmissions the last ``run_slot`` decided, per link, as the other partitions'
        ``run_slot`` takes them (``remote``): (gNB index, the transmitting radio's hall index
        in UL or the receiving one's in DL, first PRB, PRBs, mean SNR per PRB before fading)."""
        planned = self._planned
        if planned is None:
            return {"dl": [], "ul": []}
        return {"dl": planned.dl.txs, "ul": planned.ul.txs}

    def _decode(self, planned: _Planned, remote: Mapping[str, list[Tx]],
                out: list[PacketOutcome], deliver_us: int) -> None:
        """Decode the transmissions of ``planned`` against them and ``remote``'s, adding the
        outcomes to ``out``, the delivered ones at ``deliver_us`` (us: the end of the slot in
        which they are decoded, the one after theirs)."""
        s, update, active, plans = planned.slot, planned.update, planned.active, planned.plans
        slot_us = self.slot_us
        dl_sinr, dl_inr = self._sinr(planned.dl, remote.get("dl", []), False, update)
        ul_sinr, ul_inr = self._sinr(planned.ul, remote.get("ul", []), True, update)
        cells = self.cells
        i_dl = i_ul = 0
        first = len(out)
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
                self._record(s * slot_us, k, [tb for tb, _ in pdsch], dl_sinr[i_dl:i_dl + n_dl],
                             [tb for _, tb in pusch], ul_sinr[i_ul:i_ul + n_ul], decoded)
            i_dl += n_dl
            i_ul += n_ul
        for o in out[first:]:
            if o.deliver_us is not None:
                o.deliver_us = deliver_us
        self._histogram("dl", dl_sinr)
        self._histogram("ul", ul_sinr)

    def _tx_rows(self, active: list[int], per_cell: list[Any], ul: bool) -> _TxRows:
        """The transmissions of one link of the active cells (``per_cell``: each cell's PDSCH or
        PUSCH list, in the order of ``active``), in that order, as rows: ``txs`` (``Tx``) and
        each one's EESM beta."""
        rows = _TxRows()
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
                    scale = csi.ul_scale(tb.ue, size)
                else:
                    tb, first, size = a, b, a.n_prb
                    scale = csi.dl_snr[tb.ue]
                rows.txs.append((g, ues[tb.ue], first, size, scale))
                rows.beta.append(betas[tb.mcs])
        return rows

    def _sinr(self, own: _TxRows, remote: list[Tx], ul: bool, update: int
              ) -> tuple[list[float], list[float]]:
        """Effective SINR and mean interference over noise (linear) of the transmissions
        ``own`` of one link, against ``own`` and ``remote``'s (another partition's, their
        results unused), in ``own``'s order."""
        if not own.txs:
            return [], []
        n_own = len(own.txs)
        txs = own.txs
        beta = own.beta
        if remote:
            # One order whatever the partitioning: by gNB, each cell's own order kept, so
            # every victim sums its interferers in the same order.
            merged = sorted([(t[0], 0, i) for i, t in enumerate(own.txs)]
                            + [(t[0], 1, i) for i, t in enumerate(remote)])
            txs = [own.txs[i] if side == 0 else remote[i] for _, side, i in merged]
            beta = [own.beta[i] if side == 0 else 1.0 for _, side, i in merged]
            mine = np.array([i for i, (_, side, _) in enumerate(merged) if side == 0])
        # Column by column, each with its type: numpy need not discover one from the tuples.
        cols = list(zip(*txs, strict=True))
        c = np.array(cols[0], dtype=np.int64)
        u = np.array(cols[1], dtype=np.int64)
        p0 = np.array(cols[2], dtype=np.int64)
        n = np.array(cols[3], dtype=np.int64)
        scale_arr = np.array(cols[4], dtype=float)
        co_channel = c[:, None] != c[None, :]
        if not self._one_group:
            groups = self._groups.take(c)
            co_channel &= groups[:, None] == groups[None, :]
        n_gnb = self.n_gnb
        links = u * n_gnb + c
        if ul:
            # Transmission j reaches gNB c[i] with its own power: its power-control power per
            # PRB relative to the whole power spread over the carrier.
            at = self.ul_snr.take(u, axis=0)  # [j, g]: from transmission j's UE at gNB g
            factor = scale_arr / at.ravel().take(np.arange(u.size) * n_gnb + c)
            cross = at.take(c, axis=1).T * factor[None, :]
            cross_links = u[None, :] * n_gnb + c[:, None]
        else:
            cross = self.dl_snr.take(u, axis=0).take(c, axis=1)
            # The downlink interference's own fading processes (one owner each).
            cross_links = (self.fading.dl_interference_offset + u[:, None] * n_gnb
                           + c[None, :])
        eff, inr = slot_sinr(p0, n, scale_arr, np.array(beta), links,
                             np.where(co_channel, cross, 0.0), cross_links, self.fading, update,
                             self._subband_prb)
        if remote:
            eff, inr = eff[mine], inr[mine]
        assert len(eff) == n_own
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
        """True while a slot waits to be decoded or a cell has work (``NrCell.has_pending``);
        always with AGVs, whose streams never stop."""
        return (self._planned is not None or self.agv_traffic is not None
                or any(cell.has_pending() for cell in self.cells))

    def earliest_delivery_us(self, ue: str, direction: str) -> int | None:
        """A lower bound on the time (us) the hall may deliver, and so its federate send, a
        packet of UE ``ue`` in ``direction`` held now; None for an unknown UE. A slot is decoded
        at the start of the next one: the next slot the hall runs if the UE has a transmission
        in the air, else a slot after the cell's own bound (``NrCell.earliest_delivery_us``, not
        before the next slot the hall runs: a cell without work skips slots)."""
        cell = self._cell_of.get(ue)
        if cell is None:
            return None
        planned = self._planned
        if planned is not None:
            u = self._hall_index[ue]
            if u in (planned.ul_ues if direction == "ul" else planned.dl_ues):
                return self.next_slot_us
        at = cell.earliest_delivery_us(ue, direction)
        return None if at is None else max(at, self.next_slot_us) + self.slot_us

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
        if self.handover is not None:
            lost[LOSS_HANDOVER] = self._handover_lost
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
                gnb = out.setdefault(f"gnb{self.cell_gnb[k]}", {"ue_count": self.cell_static[k]})
                gnb[link] = {"prb_utilisation": used[k] / prb_slots,
                             "delivered_bytes": st[link]["delivered_bytes"],
                             "bler_first_transmission": st[link]["bler_first_transmission"]}
        ues: dict[str, Any] = {}
        for k, st in enumerate(per_cell):
            for ue, row in st["ues"].items():
                # An AGV is a UE of every cell, each counting its time there only: its row is
                # the AGV's own (below).
                if ue not in self._agv_set:
                    ues[ue] = {**row, "gnb": self.cell_gnb[k]}
        out["ues"] = ues
        if self.handover is not None and self.agv_traffic is not None:
            out["agvs"] = self._agv_stats(ues)
        return out

    def _agv_stats(self, ues: dict[str, Any]) -> dict[str, Any]:
        """The AGVs' KPIs: handovers (started, completed, ping-pongs within 1 s), interruption
        time, held packets forwarded and lost, and per link their packets' loss and latency
        percentiles; per AGV the same in its ``ues`` row."""
        control = self.handover
        traffic = self.agv_traffic
        assert control is not None and traffic is not None
        # A partition counts the handovers into its gNBs (their packets are its own).
        into = [h for h in control.handovers if h.target in self.own]
        done = [h for h in into if h.done]
        summary = traffic.summary()
        per_agv = summary.pop("per_agv")
        for ue, row in per_agv.items():
            mine = [h for h in into if h.ue == ue]
            ues[ue] = {"gnb": self.serving_gnb_index[ue], **row, "handovers": len(mine)}
        return {"count": len(self.agv_ids), "handovers": len(into),
                "handovers_completed": len(done),
                "ping_pongs": ping_pongs(control.handovers, into=self.own),
                "interruption_s": sum((h.end_us - h.start_us) for h in done) / 1e6,
                "forwarded_packets": sum(h.forwarded for h in done),
                "lost_packets_handover": self._handover_lost, **summary}


# One transmission as the partitions exchange it: gNB index, radio's hall UE index, first PRB,
# PRBs, mean SNR per PRB before fading (linear).
Tx = tuple[int, int, int, int, float]


class _TxRows:
    """The transmissions of one link of a slot and their EESM betas, in decoding order."""

    def __init__(self) -> None:
        self.txs: list[Tx] = []
        self.beta: list[float] = []


class _Planned:
    """A slot whose transmissions are decided and not yet decoded: its index, fading grid
    update, active cells (indices into ``MultiCell.cells``), their plans and the rows of each
    link."""

    def __init__(self, slot: int, update: int, active: list[int], plans: list[Any],
                 dl: _TxRows, ul: _TxRows) -> None:
        self.slot = slot
        self.update = update
        self.active = active
        self.plans = plans
        self.dl = dl
        self.ul = ul
        # The radios (hall UE indices) with a transmission in the slot, per link.
        self.dl_ues = {tx[1] for tx in dl.txs}
        self.ul_ues = {tx[1] for tx in ul.txs}


class _GnbQueues:
    """gNB ``g`` of a ``MultiCell`` as the handover control sees it (``handover.CellQueues``)."""

    def __init__(self, hall: MultiCell, g: int) -> None:
        self.hall = hall
        self.g = g

    def detach(self, ue: str, t_us: int) -> list[Any]:
        return self.hall._detach(self.g, ue, t_us)

    def attach(self, ue: str, t_us: int, packets: list[Any]) -> None:
        self.hall._attach(self.g, ue, t_us, packets)


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
