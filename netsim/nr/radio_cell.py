"""NrCell: a 5G NR system-level cell (TDD self-contained slot, MAC scheduling, HARQ, LA), the one
entry of ``netsim.nr``. It builds the parts once and runs them in air order each slot; what a slot
does and what the model simplifies is in docs/netsim.md ("The slot", "Simplifications")."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from fabric.seeding import rng as named_rng
from netsim.nr.arrivals import Arrivals
from netsim.nr.buffers import SenderBuffer
from netsim.nr.channel import InfSlChannel, SubbandGains
from netsim.nr.counters import CellCounters
from netsim.nr.csi import Csi
from netsim.nr.downlink import Downlink
from netsim.nr.draws import Uniforms
from netsim.nr.harq import HarqEntity
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.nr.outcomes import Outcomes
from netsim.nr.phy import PhyAbstraction
from netsim.nr.scheduler import make_scheduler
from netsim.nr.uplink import Uplink
from netsim.radio_cell import FlowQos, Packet, PacketOutcome, RadioCell
from scenario.nr import NrConfig


class NrCell(RadioCell):
    """A single NR cell: one gNB, fixed UEs, uplink and downlink, stepped slot by slot.

    ``config`` is the cell's NrConfig; ``gnb_position_m`` and ``ue_positions_m`` (UE id ->
    position) are (x, y, z) in metres inside the hall of ``config`` (``hall_length_m`` x
    ``hall_width_m`` x ``hall_height_m``); the UE ids are the ``Packet.ue`` values. ``seed`` is
    the run's root seed: every random stream is derived from it by name, ``stream_prefix``
    then ``/<component>``, so the same seed gives the same outcomes. ``channel``: the UEs'
    channel, in ``ue_positions_m`` order (None: the InF-SL channel of ``config``, drawn here).
    """

    def __init__(self, config: NrConfig, gnb_position_m: tuple[float, float, float],
                 ue_positions_m: Mapping[str, tuple[float, float, float]], seed: int,
                 stream_prefix: str = "netsim/nr", channel: SubbandGains | None = None) -> None:
        cfg = config
        self.config = cfg
        self.slot_us = cfg.slot_us
        if not ue_positions_m:
            raise ValueError("ue_positions_m is empty: a cell needs at least one UE")
        self._check_position("gnb_position_m", gnb_position_m)
        for ue, p in ue_positions_m.items():
            self._check_position(f"ue_positions_m[{ue!r}]", p)
        self.ue_ids: list[str] = list(ue_positions_m)
        self._index = {ue: i for i, ue in enumerate(self.ue_ids)}
        n = len(self.ue_ids)
        self.n_ue = n
        self.channel: SubbandGains = channel if channel is not None else InfSlChannel(
            cfg, gnb_position_m, self.ue_ids,
            np.array([ue_positions_m[u] for u in self.ue_ids], dtype=float), seed, stream_prefix)
        self.phy = phy = PhyAbstraction(cfg.mcs_table)
        max_mcs = phy.max_mcs if cfg.max_mcs is None else cfg.max_mcs

        def la() -> LinkAdaptation:
            return LinkAdaptation(phy, n, cfg.bler_target, cfg.olla_nack_step_db,
                                  cfg.olla_min_offset_db, cfg.olla_max_offset_db, max_mcs)

        self._la_ul, self._la_dl = la(), la()
        chase = cfg.harq_combining == "chase"
        self._harq_ul = HarqEntity(n, cfg.harq_processes, cfg.harq_max_transmissions, chase)
        self._harq_dl = HarqEntity(n, cfg.harq_processes, cfg.harq_max_transmissions, chase)
        header = cfg.l2_header_bytes_per_segment
        self._ul_buf = [SenderBuffer(cfg.ul_buffer_limit_bytes, header) for _ in range(n)]
        self._dl_buf = [SenderBuffer(cfg.dl_buffer_limit_bytes, header) for _ in range(n)]
        # Urgency weights of the UEs' dynamic delay budgets, as signalled to the gNB (1: none);
        # one weight per UE, for both links.
        self._urgency = [1.0] * n
        rand_ctrl = Uniforms(named_rng(seed, f"{stream_prefix}/control"))
        self._counters = counters = CellCounters(n, phy.max_mcs)
        self._csi = csi = self._make_csi(phy, max_mcs)
        self._outcomes = outcomes = Outcomes(self._ul_buf, self._dl_buf, counters)
        self._ul = Uplink(
            cfg, phy, self._harq_ul, self._la_ul,
            make_scheduler(cfg.scheduler, n, cfg.pf_forgetting_factor), self._ul_buf, csi,
            outcomes, counters, self._urgency,
            Uniforms(named_rng(seed, f"{stream_prefix}/harq-ul")), rand_ctrl)
        self._dl = Downlink(
            cfg, phy, self._harq_dl, self._la_dl,
            make_scheduler(cfg.scheduler, n, cfg.pf_forgetting_factor), self._dl_buf, csi,
            outcomes, counters, self._urgency,
            Uniforms(named_rng(seed, f"{stream_prefix}/harq-dl")), rand_ctrl)
        self._arrivals = Arrivals(self._index, self.slot_us, self._ul_buf, self._dl_buf,
                                  self._ul, self._dl, counters)
        self._k2 = cfg.k2_slots
        self._last_slot: int | None = None

    def _make_csi(self, phy: PhyAbstraction, max_mcs: int) -> Csi:
        """The cell's channel knowledge (ideal CSI of its channel, no interference)."""
        return Csi(self.config, self.channel, phy, self._la_ul, self._la_dl, max_mcs)

    # ------------------------------------------------------------------ interface
    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        """Put ``packet`` in its sender buffer (UL: its UE's, DL: the gNB's for its UE) from its
        ``enqueue_us`` (us, a slot boundary) on; its outcome at once if it is refused."""
        refused = self._arrivals.enqueue_many((packet,))
        return refused[0] if refused else None

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``enqueue`` each of ``packets`` in order; the outcomes of those refused at once."""
        return self._arrivals.enqueue_many(packets)

    def run_slot(self, slot_start_us: int) -> list[PacketOutcome]:
        """Simulate the slot starting at ``slot_start_us`` (us, a multiple of ``slot_us``, later
        than the last slot run); the outcomes decided in it (deliveries at its end, losses)."""
        s = self._open_slot(slot_start_us)
        out = self._outcomes.out
        ul = self._ul
        # PDCCH, then the data symbols in air order: PDSCH, PUSCH, PUCCH.
        if ul.known or self._harq_ul.pending():
            ul.schedule(s, s + self._k2)
        if self._dl.active or self._harq_dl.pending():
            self._dl.run(s)
        ul.run_pusch(s)
        self._close_slot(s)
        return out

    def _open_slot(self, slot_start_us: int) -> int:
        """The start of the slot at ``slot_start_us`` (us; checked as ``run_slot`` says), before
        its PDCCH: packets entering, the channel moving, discards, HARQ processes freed. Its
        outcomes go to a new list, ``self._outcomes.out``; returns the slot index."""
        slot_us = self.slot_us
        if slot_start_us % slot_us:
            raise ValueError(f"slot_start_us={slot_start_us} is not a multiple of the slot "
                             f"({slot_us} us)")
        s = slot_start_us // slot_us
        ul = self._ul
        if self._last_slot is not None:
            if s <= self._last_slot:
                raise ValueError(f"slot_start_us={slot_start_us} does not advance past the last "
                                 f"slot ({self._last_slot * slot_us} us)")
            if s > self._last_slot + 1 and ul.pipeline:
                ul.drop_skipped_grants(s)
        self._last_slot = s
        end = slot_start_us + slot_us
        out: list[PacketOutcome] = []
        outcomes = self._outcomes
        outcomes.out = out
        outcomes.slot_end_us = end
        arrivals = self._arrivals
        if arrivals.staged and arrivals.staged[0][0] <= slot_start_us:
            arrivals.admit_staged(slot_start_us)
        if self.channel.advance(s):
            self._csi.channel_changed()
        if arrivals.deadlines and arrivals.deadlines[0][0] < end:
            arrivals.discard_expired(end, out)
        self._harq_dl.release_due(s)
        return s

    def _close_slot(self, s: int) -> None:
        """The end of slot index ``s``, after its data symbols: the PUCCH and the counters."""
        ul = self._ul
        if ul.sr_candidates:
            ul.run_pucch(s)
        self._counters.slots += 1
        self._arrivals.next_slot_us = (s + 1) * self.slot_us

    def has_pending(self) -> bool:
        """True while any buffer, grant or HARQ process holds data, i.e. the next slot has work."""
        ul = self._ul
        return bool(
            self._arrivals.staged or ul.pipeline or self._harq_ul.pending()
            or self._harq_dl.pending() or ul.known or ul.sr_candidates or self._dl.active
            or any(b.bytes for b in self._ul_buf))

    def earliest_delivery_us(self, ue: str, direction: str) -> int | None:
        """A lower bound on the start (us) of the slot at whose end a packet of UE ``ue`` in
        ``direction`` (``ul``/``dl``) held now may arrive; None for an unknown UE. DL: a PDSCH is
        assigned in its own slot (K0 = 0), so the next slot may deliver. UL: a PUSCH needs a
        grant made K2 slots before (a configured grant needs none): ``Uplink.earliest_slot``."""
        u = self._index.get(ue)
        if u is None:
            return None
        slot = self.slot_us
        nxt = self._arrivals.next_slot_us
        n0 = 0 if nxt is None else nxt // slot
        if direction != "ul" or self._ul.configured_grant:
            return n0 * slot
        # A packet entering or a discard may put a whole packet first.
        whole = self._arrivals.whole_packet_may_lead(u)
        return self._ul.earliest_slot(u, n0, whole) * slot

    def set_flow_qos(self, flow: str, qos: FlowQos, ue: str | None = None) -> None:
        """Set ``flow``'s priority and delay budget (``qos``, budget in us); the budget also
        applies to its packets already queued (their discard deadline is recomputed from their
        enqueue time). With ``ue`` (a UE id), the flow's urgency weighs that UE in the PF
        ranking of both links."""
        if qos.delay_budget_us is not None and qos.delay_budget_us <= 0:
            raise ValueError(f"flow {flow!r}: delay_budget_us={qos.delay_budget_us} must be > 0")
        if qos.urgency <= 0:
            raise ValueError(f"flow {flow!r}: urgency={qos.urgency} must be > 0")
        self._arrivals.qos[flow] = qos
        if ue is not None:
            u = self._index.get(ue)
            if u is None:
                raise ValueError(f"flow {flow!r}: unknown UE {ue!r}")
            self._urgency[u] = qos.urgency
        self._arrivals.apply_qos(flow, qos)

    def stats(self) -> dict[str, Any]:
        """Counters: cell totals, per-link HARQ/LA figures and per-UE bytes and buffers
        (docs/netsim.md, "Counters")."""
        return self._counters.report(self.slot_us, self.config.n_prb, self.ue_ids, self._ul_buf,
                                     self._dl_buf, self._la_ul, self._la_dl, self.channel)

    def _check_position(self, what: str, p: Sequence[float]) -> None:
        cfg = self.config
        if len(p) != 3 or not all(math.isfinite(float(v)) for v in p):
            raise ValueError(f"{what}={p!r} must be three finite numbers (x, y, z) in metres")
        x, y, z = (float(v) for v in p)
        if not (0 <= x <= cfg.hall_length_m and 0 <= y <= cfg.hall_width_m
                and 0 <= z <= cfg.hall_height_m):
            raise ValueError(
                f"{what}={p!r} is outside the hall [0, {cfg.hall_length_m:g}] x "
                f"[0, {cfg.hall_width_m:g}] x [0, {cfg.hall_height_m:g}] m (hall_*_m fields)")
