"""NrCell: a 5G NR system-level cell (TDD self-contained slot, MAC scheduling, HARQ, LA).

One slot of ``run_slot``, in the order the symbols go on the air:

1. PDCCH: the gNB decides the UL grants for slot s + K2 (configured-grant occasions, then
   HARQ retransmissions, then new grants ranked by the scheduler over the UEs it knows have data
   from their BSRs or SRs) and the DL assignments of this slot (K0 = 0).
2. PDSCH: DL TBs are built from the gNB's per-UE buffers, decoded (EESM -> BLER), delivered at
   the slot end; HARQ-ACK comes back K1 slots later (retransmission from slot s + K1 + 1).
3. PUSCH: the grants made K2 slots ago are used: each UE fills its TB from its own buffer at
   transmission time (logical channel prioritisation) and appends a BSR; the gNB decodes and
   may schedule a retransmission from the next PDCCH (UL HARQ RTT = K2 + 1 slots).
4. PUCCH: a UE whose buffer went from empty to non-empty and that has no grant coming sends an
   SR at its next SR occasion; the gNB answers with a grant of ``sr_grant_bytes`` at the next
   PDCCH, whose PUSCH carries the BSR that sizes the following grants.

So with K2 = 1 the first byte of an UL burst arriving at slot n is on the air in slot n + 2 and
the bulk, sized by that BSR, from slot n + 4. Simplifications (see docs/netsim.md): the BSR is
exact (no quantisation) and always reaches the gNB with its PUSCH; CSI is ideal but aged by the
grant delay; allocations are contiguous PRBs (no frequency-selective scheduling gain); control
channels fail with fixed probabilities.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from itertools import repeat
from typing import Any

import numpy as np

from fabric.seeding import rng as named_rng
from netsim.nr.buffers import PacketEntry, SenderBuffer
from netsim.nr.channel import InfSlChannel
from netsim.nr.harq import HarqEntity, TransportBlock
from netsim.nr.link_adaptation import LinkAdaptation
from netsim.nr.phy import PhyAbstraction
from netsim.nr.scheduler import make_scheduler
from netsim.radio_cell import (
    LOSS_BUFFER,
    LOSS_CHANNEL,
    LOSS_DELAY_BUDGET,
    FlowQos,
    Packet,
    PacketOutcome,
    RadioCell,
)
from scenario.nr import NrConfig

DEFAULT_QOS = FlowQos()
POWER_LIMIT_MARGIN_DB = 3.0  # SNR per PRB kept above the MCS-0 threshold by this much


class _Uniforms:
    """Uniform draws from one named stream, fetched in blocks (scalar draws are slow)."""

    __slots__ = ("_gen", "_buf", "_i")

    def __init__(self, gen: np.random.Generator) -> None:
        self._gen = gen
        self._buf: list[float] = []
        self._i = 0

    def __call__(self) -> float:
        i = self._i
        if i == len(self._buf):
            self._buf = self._gen.random(4096).tolist()
            i = 0
        self._i = i + 1
        return self._buf[i]


class _Grant:
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


class NrCell(RadioCell):
    """A single NR cell: one gNB, fixed UEs, uplink and downlink, stepped slot by slot.

    ``ue_positions_m`` maps UE id -> (x, y, z) in metres inside the hall of ``config``
    (``hall_length_m`` x ``hall_width_m`` x ``hall_height_m``); the ids are the ``Packet.ue``
    values. ``seed`` is the run's root seed: every random stream is derived from it by name
    (``<stream_prefix>/<component>``), so the same seed gives the same outcomes.
    """

    def __init__(self, config: NrConfig, gnb_position_m: tuple[float, float, float],
                 ue_positions_m: Mapping[str, tuple[float, float, float]], seed: int,
                 stream_prefix: str = "netsim/nr") -> None:
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
        self.channel = InfSlChannel(
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
        self._sched_ul = make_scheduler(cfg.scheduler, n, cfg.pf_forgetting_factor)
        self._sched_dl = make_scheduler(cfg.scheduler, n, cfg.pf_forgetting_factor)
        header = cfg.l2_header_bytes_per_segment
        self._ul_buf = [SenderBuffer(cfg.ul_buffer_limit_bytes, header) for _ in range(n)]
        self._dl_buf = [SenderBuffer(cfg.dl_buffer_limit_bytes, header) for _ in range(n)]
        self._qos: dict[str, FlowQos] = {}
        self._rand_ul = _Uniforms(named_rng(seed, f"{stream_prefix}/harq-ul"))
        self._rand_dl = _Uniforms(named_rng(seed, f"{stream_prefix}/harq-dl"))
        self._rand_ctrl = _Uniforms(named_rng(seed, f"{stream_prefix}/control"))

        # Uplink access state. gNB side: what it believes each UE has (from BSRs, minus what it
        # has granted since), SRs received. UE side: grants announced but not yet used.
        self._gnb_ul_bytes = [0] * n
        self._gnb_sr = [False] * n
        self._ul_known: set[int] = set()  # UEs the gNB would schedule (bytes > 0 or SR)
        self._ul_prio = [1 << 30] * n  # QoS priority the gNB knows per UE (from BSR / SR)
        # Urgency weights of the UEs' dynamic delay budgets, as signalled to the gNB (1: none);
        # one weight per UE, for both links.
        self._urgency = [1.0] * n
        self._ue_grants = [0] * n  # new-transmission grants in the pipeline, per UE
        self._ue_grant_bytes = [0] * n
        self._sr_candidates: set[int] = set()  # UEs with a triggered BSR and no grant yet
        self._ul_pipeline: dict[int, list[_Grant]] = {}  # PUSCH slot -> grants
        self._configured_grant = cfg.ul_access == "configured_grant"
        # Downlink.
        self._dl_active: set[int] = set()
        self._dl_prio = [1 << 30] * n
        self._dl_release: deque[tuple[int, int]] = deque()  # (slot, ue) HARQ process frees
        # Time and arrivals.
        self._last_slot: int | None = None
        self._next_slot_us: int | None = None
        self._slot_end_us = 0
        self._staged: list[tuple[int, int, PacketEntry, int, bool]] = []  # future arrivals
        self._deadlines: list[tuple[int, int, PacketEntry, int, bool]] = []
        self._seq = 0
        self._out: list[PacketOutcome] = []

        # Constants of the hot path.
        self._n_prb = cfg.n_prb
        self._sb = cfg.subband_prb
        self._ul_re = cfg.ul_re_per_prb
        self._dl_re = cfg.dl_re_per_prb
        self._betas = phy.betas
        self._k1 = cfg.k1_slots
        self._k2 = cfg.k2_slots
        self._ul_snr = self.channel.ul_snr_fullband
        self._dl_snr = self.channel.dl_snr
        self._wb_threshold_db = np.array([
            phy.bler.cb_bler_threshold_db(m, 8448, cfg.bler_target) for m in range(max_mcs + 1)])
        self._max_mcs = max_mcs
        self._beta_arr = np.array(phy.betas)
        sb_edges = np.minimum(np.arange(self.channel.n_subbands + 1) * cfg.subband_prb, cfg.n_prb)
        self._subband_weights = np.diff(sb_edges) / cfg.n_prb  # share of the PRBs per subband
        self._rate_by_mcs_ul = [phy.bits_per_prb(m, self._ul_re) for m in range(max_mcs + 1)]
        self._rate_by_mcs_dl = [phy.bits_per_prb(m, self._dl_re) for m in range(max_mcs + 1)]
        self._ul_snr_arr = np.array(self._ul_snr)
        self._dl_snr_arr = np.array(self._dl_snr)
        self._rate_ul = [0.0] * n  # bits per PRB at the wideband MCS
        self._rate_dl = [0.0] * n
        self._mcs_wb_ul = [0] * n
        self._mcs_wb_dl = [0] * n
        self._ul_max_prb = [cfg.n_prb] * n  # power-headroom cap of an UL allocation
        # Wideband estimates are refreshed lazily, when a link schedules after a channel update.
        self._wb_stale_ul = self._wb_stale_dl = True
        # EESM of (ue, first PRB, n PRB, MCS, link) under the current channel: allocations
        # repeat from slot to slot (a backlogged UE gets the same PRBs), the gains change only
        # every channel_update_period_slots.
        self._eesm_cache: dict[tuple[int, int, int, int, bool], float] = {}

        # Counters.
        self._slots = 0
        self._ul_bytes = [0] * n
        self._dl_bytes = [0] * n
        self._ul_prb_used = 0
        self._dl_prb_used = 0
        self._mcs_hist = {"ul": [0] * (phy.max_mcs + 1), "dl": [0] * (phy.max_mcs + 1)}
        self._first_tx = {"ul": 0, "dl": 0}
        self._first_fail = {"ul": 0, "dl": 0}
        self._retx = {"ul": 0, "dl": 0}
        self._residual = {"ul": 0, "dl": 0}
        self._delivered = {"ul": 0, "dl": 0}
        self._lost = {LOSS_BUFFER: 0, LOSS_DELAY_BUDGET: 0, LOSS_CHANNEL: 0}
        self._pdcch_missed = 0
        self._ul_peak = [0] * n  # largest buffer occupancy seen, per UE
        self._dl_peak = [0] * n

    # ------------------------------------------------------------------ interface
    def enqueue(self, packet: Packet) -> PacketOutcome | None:
        refused = self.enqueue_many((packet,))
        return refused[0] if refused else None

    def enqueue_many(self, packets: Iterable[Packet]) -> list[PacketOutcome]:
        """``enqueue`` each packet in order; the outcomes of those refused at once.

        This runs once per IP packet and dominates the cost of a loaded cell. Packets come in
        runs that share UE, flow and direction (a frame's): a run that joins its non-empty UL
        queue whole (no delay budget, every packet fits, none staged) is appended in one go;
        any other run goes packet by packet through ``_enqueue_each``.
        """
        refused: list[PacketOutcome] = []
        batch = packets if isinstance(packets, list) else list(packets)
        n = len(batch)
        i = 0
        while i < n:  # runs found by plain comparisons: compiled, they cost a few instructions
            first = batch[i]
            ue, flow, direction = first.ue, first.flow, first.direction
            j = i + 1
            while j < n:
                p = batch[j]
                if p.ue != ue or p.flow != flow or p.direction != direction:
                    break
                j += 1
            run = batch if j - i == n else batch[i:j]
            if not (direction == "ul" and self._append_run(run, ue, flow)):
                self._enqueue_each(run, refused)
            i = j
        return refused

    def _append_run(self, run: list[Packet], ue: str, flow: str) -> bool:
        """Append a run of UL packets of one UE and flow to its non-empty queue, if the packets
        would all be taken that way one by one (then True); else change nothing (False)."""
        qos = self._qos.get(flow, DEFAULT_QOS)
        u = self._index.get(ue, -1)
        if u < 0 or qos.delay_budget_us is not None or self._staged:
            return False
        buf = self._ul_buf[u]
        queued = buf.bytes
        fq = buf.by_name.get(flow)
        if not queued or fq is None or fq.priority != qos.priority:
            return False
        # Plain loops: compiled (fabric.native), they read the packets' fields directly.
        nxt = self._next_slot_us
        total = 0
        for p in run:
            size = p.size_bytes
            if size <= 0 or (nxt is not None and p.enqueue_us > nxt):
                return False
            total += size
        if queued + total > buf.limit_bytes:
            return False
        entries = fq.entries
        for p in run:
            entries.append(PacketEntry(p, None))
        fq.bytes += total
        buf.bytes = queued = queued + total
        buf.packets += len(run)
        # The occupancy only grows along the run: its peak is the final one.
        if queued > self._ul_peak[u]:
            self._ul_peak[u] = queued
        return True

    def _enqueue_each(self, packets: Iterable[Packet], refused: list[PacketOutcome]) -> None:
        """``enqueue`` each packet, adding the refused ones' outcomes to ``refused``. The common
        case (an UL packet of a flow without delay budget, joining its non-empty queue at the
        next slot) is inlined, with the UE and flow looked up once per run of packets that
        share them; anything else takes ``_enqueue``."""
        nxt = self._next_slot_us
        ue = flow = direction = None
        fast = False
        u = 0
        buf = self._ul_buf[0]
        limit = buf.limit_bytes
        fq = None  # the run's flow queue once it has been checked usable
        peak = self._ul_peak
        priority = DEFAULT_QOS.priority
        for packet in packets:
            if packet.ue != ue or packet.flow != flow or packet.direction != direction:
                ue, flow, direction = packet.ue, packet.flow, packet.direction
                qos = self._qos.get(flow, DEFAULT_QOS)
                priority = qos.priority
                u = self._index.get(ue, -1)
                fast = direction == "ul" and u >= 0 and qos.delay_budget_us is None
                fq = None
                if fast:
                    buf = self._ul_buf[u]
                    limit = buf.limit_bytes
            size = packet.size_bytes
            if (not fast or size <= 0 or self._staged
                    or (nxt is not None and packet.enqueue_us > nxt)):
                outcome = self._enqueue(packet)
                if outcome is not None:
                    refused.append(outcome)
                fq = None
                continue
            queued = buf.bytes
            if queued + size > limit:
                self._lost[LOSS_BUFFER] += 1
                refused.append(PacketOutcome(packet, None, LOSS_BUFFER))
                continue
            if fq is None or not queued:
                fq = buf.by_name.get(flow)
                if not queued or fq is None or fq.priority != priority:
                    self._admit(PacketEntry(packet, None), u, True, priority)
                    fq = None
                    continue
            fq.entries.append(PacketEntry(packet, None))
            fq.bytes += size
            buf.bytes = queued = queued + size
            buf.packets += 1
            if queued > peak[u]:
                peak[u] = queued

    def run_slot(self, slot_start_us: int) -> list[PacketOutcome]:
        slot_us = self.slot_us
        if slot_start_us % slot_us:
            raise ValueError(f"slot_start_us={slot_start_us} is not a multiple of the slot "
                             f"({slot_us} us)")
        s = slot_start_us // slot_us
        if self._last_slot is not None:
            if s <= self._last_slot:
                raise ValueError(f"slot_start_us={slot_start_us} does not advance past the last "
                                 f"slot ({self._last_slot * slot_us} us)")
            if s > self._last_slot + 1 and self._ul_pipeline:
                self._drop_skipped_grants(s)
        self._last_slot = s
        self._slot_end_us = slot_start_us + slot_us
        out: list[PacketOutcome] = []
        self._out = out
        if self._staged and self._staged[0][0] <= slot_start_us:
            self._admit_staged(slot_start_us)
        if self.channel.advance(s):
            self._wb_stale_ul = self._wb_stale_dl = True
            self._eesm_cache.clear()
        if self._deadlines and self._deadlines[0][0] < self._slot_end_us:
            self._discard_expired()
        release = self._dl_release
        while release and release[0][0] <= s:
            self._harq_dl.release(release.popleft()[1])
        # PDCCH, then the data symbols in air order: PDSCH, PUSCH, PUCCH.
        if self._ul_known or self._harq_ul.pending():
            self._schedule_ul(s, s + self._k2)
        if self._dl_active or self._harq_dl.pending():
            self._run_dl(s)
        grants = self._ul_pipeline.pop(s, None)
        if self._configured_grant:
            grants = self._configured_grants(s) + (grants or [])
        if grants:
            self._run_pusch(s, grants)
        if self._sr_candidates:
            self._run_pucch(s)
        self._slots += 1
        self._next_slot_us = self._slot_end_us
        return out

    def has_pending(self) -> bool:
        return bool(
            self._staged or self._ul_pipeline or self._harq_ul.pending() or self._harq_dl.pending()
            or self._ul_known or self._sr_candidates or self._dl_active
            or any(b.bytes for b in self._ul_buf))

    def earliest_delivery_us(self, ue: str, direction: str) -> int | None:
        """A packet arrives at the end of the slot whose PDSCH or PUSCH carries its last bytes.
        DL: a PDSCH is assigned in its own slot (K0 = 0), so the next slot may deliver. UL: a
        PUSCH needs a grant made K2 slots before (a configured grant needs none). Of the UE's
        grants already in the pipeline, a retransmission may complete a packet; a new one only
        once the grants up to it have room for the rest of a flow's first packet. Without such
        a grant, the earliest is the slot that the next PDCCH grants for."""
        u = self._index.get(ue)
        if u is None:
            return None
        slot = self.slot_us
        n0 = 0 if self._next_slot_us is None else self._next_slot_us // slot
        if direction != "ul" or self._configured_grant:
            return n0 * slot
        buf = self._ul_buf[u]
        rest = self._first_packet_rest(buf)
        if any(su == u and sul for _, _, _, su, sul in self._staged) or any(
                self._qos.get(name, DEFAULT_QOS).delay_budget_us is not None for name in buf.by_name):
            rest = 0  # a packet entering or a discard may put a whole packet first
        room = 0
        h = buf.header_bytes
        for k in sorted(k for k in self._ul_pipeline if k >= n0):
            for g in self._ul_pipeline[k]:
                if g.ue != u:
                    continue
                if g.tb is not None:
                    return k * slot
                room += max(0, g.payload_bytes - h)  # a grant below one header carries nothing
                if rest is not None and rest <= room:
                    return k * slot
                if self._harq_ul.max_tx == 1:
                    rest = 0  # a failed TB loses its packets at once: a whole one may come first
        return (n0 + self._k2) * slot

    @staticmethod
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

    def set_flow_qos(self, flow: str, qos: FlowQos, ue: str | None = None) -> None:
        """Set a flow's priority and delay budget; the budget also applies to its packets
        already queued (their discard deadline is recomputed from their enqueue time). With
        ``ue``, the flow's urgency weighs that UE in the PF ranking of both links."""
        if qos.delay_budget_us is not None and qos.delay_budget_us <= 0:
            raise ValueError(f"flow {flow!r}: delay_budget_us={qos.delay_budget_us} must be > 0")
        if qos.urgency <= 0:
            raise ValueError(f"flow {flow!r}: urgency={qos.urgency} must be > 0")
        self._qos[flow] = qos
        if ue is not None:
            u = self._index.get(ue)
            if u is None:
                raise ValueError(f"flow {flow!r}: unknown UE {ue!r}")
            self._urgency[u] = qos.urgency
        for links in ((self._ul_buf, True), (self._dl_buf, False)):
            bufs, ul = links
            for u, buf in enumerate(bufs):
                fq = buf.by_name.get(flow)
                if fq is None:
                    continue
                buf.set_priority(flow, qos.priority)
                if ul:
                    self._ul_prio[u] = buf.best_priority()
                else:
                    self._dl_prio[u] = buf.best_priority()
                for e in fq.entries:
                    e.deadline_us = (None if qos.delay_budget_us is None
                                     else e.packet.enqueue_us + qos.delay_budget_us)
                    if e.deadline_us is not None and e.to_send:
                        self._seq += 1
                        heapq.heappush(self._deadlines, (e.deadline_us, self._seq, e, u, ul))

    def stats(self) -> dict[str, Any]:
        """Counters: cell totals, per-link HARQ/LA figures and per-UE bytes and buffers."""
        slots = max(1, self._slots)
        links: dict[str, Any] = {}
        for link in ("ul", "dl"):
            first = self._first_tx[link]
            bufs = self._ul_buf if link == "ul" else self._dl_buf
            la = self._la_ul if link == "ul" else self._la_dl
            links[link] = {
                "delivered_bytes": sum(self._ul_bytes if link == "ul" else self._dl_bytes),
                "delivered_packets": self._delivered[link],
                "prb_utilisation": (self._ul_prb_used if link == "ul" else self._dl_prb_used)
                / (slots * self._n_prb),
                "mcs_histogram": list(self._mcs_hist[link]),
                "first_transmissions": first,
                "bler_first_transmission": self._first_fail[link] / first if first else 0.0,
                "harq_retransmissions": self._retx[link],
                "harq_residual_failures": self._residual[link],
                "buffer_bytes": sum(b.bytes for b in bufs),
                "buffer_peak_bytes_max_ue": max(self._ul_peak if link == "ul" else self._dl_peak),
                "olla_offset_db_mean": float(np.mean(la.offset_db)),
            }
        return {
            "slots": self._slots,
            "slot_us": self.slot_us,
            "n_prb": self._n_prb,
            "lost_packets": dict(self._lost),
            "pdcch_missed": self._pdcch_missed,
            "ul": links["ul"],
            "dl": links["dl"],
            "ues": {
                ue: {
                    "ul_delivered_bytes": self._ul_bytes[u],
                    "dl_delivered_bytes": self._dl_bytes[u],
                    "ul_buffer_bytes": self._ul_buf[u].bytes,
                    "dl_buffer_bytes": self._dl_buf[u].bytes,
                    "ul_buffer_peak_bytes": self._ul_peak[u],
                    "dl_buffer_peak_bytes": self._dl_peak[u],
                    "los": bool(self.channel.los[u]),
                    "distance_m": float(self.channel.d3d_m[u]),
                    "ul_snr_fullband_db": float(self.channel.ul_snr_fullband_db[u]),
                    "dl_snr_db": float(self.channel.dl_snr_db[u]),
                    "ul_olla_offset_db": self._la_ul.offset_db[u],
                    "dl_olla_offset_db": self._la_dl.offset_db[u],
                }
                for u, ue in enumerate(self.ue_ids)
            },
        }

    # ------------------------------------------------------------------ arrivals and discards
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

    def _enqueue(self, packet: Packet) -> PacketOutcome | None:
        """``enqueue`` of one packet, every case: validation, buffer limit, staging, admission."""
        u = self._index.get(packet.ue)
        if u is None:
            raise ValueError(f"packet {packet.packet_id}: unknown UE {packet.ue!r}")
        direction = packet.direction
        if direction == "ul":
            ul = True
            buf = self._ul_buf[u]
        elif direction == "dl":
            ul = False
            buf = self._dl_buf[u]
        else:
            raise ValueError(f"packet {packet.packet_id}: direction {direction!r} is not "
                             "'ul' or 'dl'")
        size = packet.size_bytes
        if size <= 0:
            raise ValueError(f"packet {packet.packet_id}: size_bytes={size} must be > 0")
        staged = 0
        if self._staged:
            staged = sum(e.to_send for _, _, e, su, sul in self._staged if su == u and sul == ul)
        if buf.bytes + staged + size > buf.limit_bytes:
            self._lost[LOSS_BUFFER] += 1
            return PacketOutcome(packet, None, LOSS_BUFFER)
        qos = self._qos.get(packet.flow, DEFAULT_QOS)
        budget = qos.delay_budget_us
        entry = PacketEntry(packet, None if budget is None else packet.enqueue_us + budget)
        nxt = self._next_slot_us
        if nxt is not None and packet.enqueue_us > nxt:
            # Enters at a later slot boundary than the next slot: hold it until then.
            slot = self.slot_us
            self._seq += 1
            heapq.heappush(self._staged, (-(-packet.enqueue_us // slot) * slot, self._seq,
                                          entry, u, ul))
            return None
        self._admit(entry, u, ul, qos.priority)
        return None

    def _admit(self, entry: PacketEntry, u: int, ul: bool, priority: int) -> None:
        pkt = entry.packet
        if ul:
            buf = self._ul_buf[u]
            if buf.bytes == 0 and not self._configured_grant:
                self._sr_candidates.add(u)  # regular BSR triggered: data into an empty buffer
        else:
            buf = self._dl_buf[u]
            self._dl_active.add(u)
            if priority < self._dl_prio[u]:
                self._dl_prio[u] = priority
        buf.add(buf.flow(pkt.flow, priority), entry)
        peak = self._ul_peak if ul else self._dl_peak
        if buf.bytes > peak[u]:
            peak[u] = buf.bytes
        if entry.deadline_us is not None:
            self._seq += 1
            heapq.heappush(self._deadlines, (entry.deadline_us, self._seq, entry, u, ul))

    def _admit_staged(self, now_us: int) -> None:
        staged = self._staged
        while staged and staged[0][0] <= now_us:
            _, _, entry, u, ul = heapq.heappop(staged)
            qos = self._qos.get(entry.packet.flow, DEFAULT_QOS)
            self._admit(entry, u, ul, qos.priority)

    def _discard_expired(self) -> None:
        """Drop queued packets that can no longer arrive within their delay budget.

        A packet is discarded at the start of the first slot whose end is past its deadline
        (enqueue + budget), and only if none of its bytes has been sent (TS 38.322: an SDU
        already partly submitted to lower layers is not discarded).
        """
        heap = self._deadlines
        end = self._slot_end_us
        out = self._out
        while heap and heap[0][0] < end:
            deadline, _, e, u, ul = heapq.heappop(heap)
            if e.deadline_us != deadline or e.lost or e.to_send != e.packet.size_bytes:
                continue  # stale deadline, already gone, or under way
            e.lost = True
            (self._ul_buf[u] if ul else self._dl_buf[u]).drop_unsent(e, e.packet.flow)
            self._lost[LOSS_DELAY_BUDGET] += 1
            out.append(PacketOutcome(e.packet, None, LOSS_DELAY_BUDGET))

    # ------------------------------------------------------------------ PHY helpers
    def _eesm(self, u: int, p0: int, n: int, mcs: int, ul: bool) -> float:
        """Effective SINR (linear) of UE u on PRBs [p0, p0 + n) with the EESM beta of ``mcs``
        (subband gains weighted by the PRBs each contributes). In UL the UE's power is spread
        over the n PRBs, in DL the gNB's over the whole carrier."""
        key = (u, p0, n, mcs, ul)
        cached = self._eesm_cache.get(key)
        if cached is not None:
            return cached
        scale = self._ul_snr[u] * self._n_prb / n if ul else self._dl_snr[u]
        size = self._sb
        row = self.channel.gain_row(u)
        sb0 = p0 // size
        sb1 = (p0 + n - 1) // size
        if sb0 == sb1:
            value = scale * row[sb0]
        else:
            beta = self._betas[mcs]
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
        self._eesm_cache[key] = value
        return value

    def _update_wideband(self, ul: bool) -> None:
        """Wideband MCS and rate per UE (EESM over the whole carrier, OLLA applied): the rate
        estimate the scheduler ranks by and the MCS it sizes allocations with."""
        g = self.channel.gain
        la = self._la_ul if ul else self._la_dl
        snr = (self._ul_snr_arr if ul else self._dl_snr_arr)[:, None] * g
        last_mcs = la.last_mcs
        beta = self._beta_arr[last_mcs][:, None]
        smin = snr.min(axis=1, keepdims=True)
        eff = smin[:, 0] - beta[:, 0] * np.log(
            np.exp((smin - snr) / beta) @ self._subband_weights)
        # The same numbers as _eesm for a full-carrier allocation: a backlogged UE usually
        # gets exactly that, so the per-slot EESM becomes a cache hit.
        n_ue, n_prb = self.n_ue, self._n_prb
        keys = zip(range(n_ue), repeat(0, n_ue), repeat(n_prb, n_ue), last_mcs, repeat(ul, n_ue),
                   strict=True)
        self._eesm_cache.update(zip(keys, eff.tolist(), strict=True))
        snr_db = 10 * np.log10(np.maximum(eff, 1e-12)) - np.array(la.offset_db)
        top = self._max_mcs
        mcs = [0 if m < 0 else (top if m > top else m) for m in (
            np.searchsorted(self._wb_threshold_db, snr_db, side="right") - 1).tolist()]
        if ul:
            table = self._rate_by_mcs_ul
            self._mcs_wb_ul, self._rate_ul = mcs, [table[m] for m in mcs]
            # Power headroom: spreading the UE's power over more PRBs than this would push the
            # SNR per PRB below what MCS 0 needs (plus a margin), wasting the extra PRBs.
            floor_db = self._wb_threshold_db[0] + POWER_LIMIT_MARGIN_DB
            self._ul_max_prb = [
                n_prb if x >= n_prb else max(1, int(x))
                for x in (n_prb * 10 ** ((snr_db - floor_db) / 10)).tolist()]
            self._wb_stale_ul = False
        else:
            table = self._rate_by_mcs_dl
            self._mcs_wb_dl, self._rate_dl = mcs, [table[m] for m in mcs]
            self._wb_stale_dl = False

    def _prbs_for(self, need_bits: int, mcs: int, n_re: int, available: int) -> int:
        """Fewest PRBs whose TBS at ``mcs`` carries ``need_bits`` (at most ``available``)."""
        n = max(1, math.ceil(need_bits / self.phy.bits_per_prb(mcs, n_re)))
        if n >= available:
            return available
        fmt = self.phy.tb_format
        while n < available and fmt(n, mcs, n_re).tbs_bits < need_bits:
            n += 1
        return n

    # ------------------------------------------------------------------ uplink
    def _schedule_ul(self, s: int, target: int) -> None:
        """PDCCH of slot ``s``: grants for the PUSCH of slot ``target``."""
        cfg = self.config
        n_prb = self._n_prb
        harq = self._harq_ul
        grants: list[_Grant] = []
        pos = 0
        taken: set[int] = set()
        if self._configured_grant:
            # Configured-grant occasions need no DCI: their PRBs come first in every slot.
            pos = len(self._cg_occasions(target)) * cfg.cg_prb
        max_ues = cfg.max_ul_ues_per_slot
        count = 0
        for tb, start in harq.take_due(s, max_ues, pos, n_prb, taken):
            grants.append(_Grant(tb.ue, start, tb.n_prb, tb.mcs, tb.tbs_bits, tb.cbs_bits,
                                 tb.n_cb, 0, tb, self._rand_ctrl() < cfg.pdcch_miss_prob,
                                 False, False))
            pos = start + tb.n_prb
            count += 1
        if self._ul_known and count < max_ues and pos < n_prb:
            if self._wb_stale_ul:
                self._update_wideband(True)
            # Set order is fine: every scheduler's ranking ends with a total order on the UE.
            candidates = [u for u in self._ul_known if u not in taken and harq.has_free_process(u)]
            gnb_bytes = self._gnb_ul_bytes
            extra = 8 * cfg.bsr_bytes
            for u in self._sched_ul.ranked(candidates, self._ul_prio, self._rate_ul, s, self._urgency):
                if count >= max_ues or pos >= n_prb:
                    break
                from_sr = gnb_bytes[u] == 0
                need_bits = 8 * (cfg.sr_grant_bytes if from_sr else gnb_bytes[u]) + extra
                room = n_prb - pos
                cap = self._ul_max_prb[u]
                n = self._prbs_for(need_bits, self._mcs_wb_ul[u], self._ul_re,
                                   cap if cap < room else room)
                mcs = self._ul_mcs(u, pos, n)
                fmt = self.phy.tb_format(n, mcs, self._ul_re)
                payload = fmt.tbs_bits // 8 - cfg.bsr_bytes
                if payload <= 0:
                    continue
                grants.append(_Grant(u, pos, n, mcs, fmt.tbs_bits, fmt.cbs_bits, fmt.n_cb,
                                     payload, None, self._rand_ctrl() < cfg.pdcch_miss_prob,
                                     from_sr, False))
                gnb_bytes[u] = max(0, gnb_bytes[u] - payload)
                self._gnb_sr[u] = False
                if gnb_bytes[u] == 0:
                    self._ul_known.discard(u)
                self._ue_grants[u] += 1
                self._ue_grant_bytes[u] += payload
                harq.occupy(u)  # the process is reserved by the grant
                self._sched_ul.served(u, fmt.tbs_bits, s)
                pos += n
                count += 1
        if grants:
            self._ul_pipeline.setdefault(target, []).extend(grants)

    def _cg_occasions(self, slot: int) -> list[int]:
        """UEs with a configured-grant occasion in ``slot`` (staggered over the period), as
        many as fit in the carrier."""
        cfg = self.config
        period = cfg.cg_period_slots
        fit = self._n_prb // cfg.cg_prb
        return [u for u in range(self.n_ue) if (slot + u) % period == 0][:fit]

    def _configured_grants(self, s: int) -> list[_Grant]:
        """The configured-grant PUSCHs of slot ``s``, for UEs with data to send (an unused
        occasion stays empty); MCS by link adaptation, as if the gNB kept reconfiguring it."""
        cfg = self.config
        grants = []
        occasions = self._cg_occasions(s)
        for i, u in enumerate(occasions):
            if not self._ul_buf[u].bytes:
                continue
            pos = i * cfg.cg_prb
            mcs = self._ul_mcs(u, pos, cfg.cg_prb)
            fmt = self.phy.tb_format(cfg.cg_prb, mcs, self._ul_re)
            grants.append(_Grant(u, pos, cfg.cg_prb, mcs, fmt.tbs_bits, fmt.cbs_bits, fmt.n_cb,
                                 fmt.tbs_bits // 8 - cfg.bsr_bytes, None, False, False, True))
        # Unused occasions still occupy their PRBs (used ones are counted with the PUSCH).
        self._ul_prb_used += (len(occasions) - len(grants)) * cfg.cg_prb
        return grants

    def _ul_mcs(self, u: int, p0: int, n: int) -> int:
        """Link adaptation for a PUSCH of n PRBs: the UE's power is spread over them."""
        la = self._la_ul
        est = self._eesm(u, p0, n, la.last_mcs[u], True)
        mcs = la.select(u, est, n, self._ul_re)
        la.last_mcs[u] = mcs
        return mcs

    def _run_pusch(self, s: int, grants: list[_Grant]) -> None:
        harq = self._harq_ul
        for g in grants:
            u = g.ue
            self._ul_prb_used += g.n_prb
            tb = g.tb
            if tb is None:
                if not g.configured:
                    self._ue_grants[u] -= 1
                    self._ue_grant_bytes[u] -= g.payload_bytes
                if g.missed:
                    # DTX seen by the gNB: it knows nothing came and restores its view.
                    self._pdcch_missed += 1
                    self._restore_ul_request(u, g)
                    continue
                buf = self._ul_buf[u]
                if g.configured and not (buf.bytes and harq.has_free_process(u)):
                    continue  # unused configured-grant occasion
                queued = buf.bytes
                segments = buf.fill(g.payload_bytes) if queued else []
                # The BSR rides with the PUSCH: the gNB now knows the rest of the buffer.
                self._sr_candidates.discard(u)
                known = buf.report_bytes() - self._ue_grant_bytes[u]
                self._gnb_ul_bytes[u] = known if known > 0 else 0
                self._ul_prio[u] = buf.best_priority()
                if known > 0:
                    self._ul_known.add(u)
                elif not self._gnb_sr[u]:
                    self._ul_known.discard(u)
                if not segments:
                    if not g.configured:
                        harq.release(u)  # padding only: no HARQ process needed
                    continue
                if g.configured:
                    harq.occupy(u)
                # fill takes exactly the bytes it puts in segments out of the buffer.
                tb = TransportBlock(u, segments, g.tbs_bits, g.mcs, g.n_prb, g.cbs_bits, g.n_cb,
                                    queued - buf.bytes)
            elif g.missed:
                self._pdcch_missed += 1
                tb.tx_count += 1
                self._retx["ul"] += 1
                self._after_failure(tb, s + 1, harq, True)
                continue
            sinr = self._eesm(u, g.prb_start, g.n_prb, tb.mcs, True)
            eff = harq.combine(tb, sinr)
            ok = self._rand_ul() >= self.phy.bler.tb_bler(
                tb.mcs, tb.cbs_bits, tb.n_cb, 10.0 * math.log10(eff))
            self._account("ul", u, tb, ok, self._la_ul, ok)
            if ok:
                self._deliver(tb, True)
                harq.release(u)
            else:
                self._after_failure(tb, s + 1, harq, True)

    def _restore_ul_request(self, u: int, g: _Grant) -> None:
        """A grant that carried nothing: free its HARQ process and give the gNB back what it
        knew of the UE's request (a pending SR, or the bytes the grant was sized for)."""
        self._harq_ul.release(u)
        if g.from_sr:
            self._gnb_sr[u] = True
        else:
            self._gnb_ul_bytes[u] += g.payload_bytes
        self._ul_known.add(u)

    def _account(self, link: str, u: int, tb: TransportBlock, ok: bool, la: LinkAdaptation,
                 ack: bool) -> None:
        """A transmission's statistics: first transmissions feed the MCS histogram, the
        first-transmission BLER and link adaptation (with the ACK as the gNB read it); later ones
        count as retransmissions."""
        if tb.tx_count == 1:
            self._first_tx[link] += 1
            self._mcs_hist[link][tb.mcs] += 1
            if not ok:
                self._first_fail[link] += 1
            la.feedback(u, ack)
        else:
            self._retx[link] += 1

    def _after_failure(self, tb: TransportBlock, ready_slot: int, harq: HarqEntity,
                       ul: bool) -> None:
        """A transmission failed: queue a retransmission or, out of attempts, lose the TB."""
        if harq.exhausted(tb):
            self._residual["ul" if ul else "dl"] += 1
            self._lose(tb, ul)
            if ul:
                harq.release(tb.ue)
            else:
                self._dl_release.append((ready_slot, tb.ue))
        else:
            harq.queue_retx(tb, ready_slot)

    def _run_pucch(self, s: int) -> None:
        """SRs of UEs with a triggered BSR and no grant on its way."""
        period = self.config.sr_period_slots
        for u in sorted(self._sr_candidates):
            if self._ue_grants[u]:
                continue  # a grant is coming; its PUSCH carries the BSR
            buf = self._ul_buf[u]
            if not buf.bytes:
                self._sr_candidates.discard(u)
                continue
            if (s + u) % period:
                continue
            self._sr_candidates.discard(u)
            self._gnb_sr[u] = True
            self._ul_prio[u] = buf.best_priority()
            self._ul_known.add(u)

    def _drop_skipped_grants(self, s: int) -> None:
        """The caller skipped slots with grants pending (it should not, has_pending() was True):
        undo those grants as if the UEs had missed them."""
        harq = self._harq_ul
        for slot in sorted(k for k in self._ul_pipeline if k < s):
            for g in self._ul_pipeline.pop(slot):
                u = g.ue
                if g.tb is not None:
                    harq.queue_retx(g.tb, s)
                    continue
                self._ue_grants[u] -= 1
                self._ue_grant_bytes[u] -= g.payload_bytes
                self._restore_ul_request(u, g)

    # ------------------------------------------------------------------ downlink
    def _run_dl(self, s: int) -> None:
        """Assign, send and decode the PDSCH of slot ``s`` (K0 = 0)."""
        cfg = self.config
        n_prb = self._n_prb
        harq = self._harq_dl
        max_ues = cfg.max_dl_ues_per_slot
        pos = 0
        count = 0
        taken: set[int] = set()
        for tb, start in harq.take_due(s, max_ues, pos, n_prb, taken):
            self._dl_transmit(s, tb, start)
            pos = start + tb.n_prb
            count += 1
        if not self._dl_active or count >= max_ues or pos >= n_prb:
            return
        if self._wb_stale_dl:
            self._update_wideband(False)
        candidates = []
        for u in sorted(self._dl_active):
            if not self._dl_buf[u].bytes:
                self._dl_active.discard(u)
                self._dl_prio[u] = 1 << 30
            elif u not in taken and harq.has_free_process(u):
                candidates.append(u)
        la = self._la_dl
        for u in self._sched_dl.ranked(candidates, self._dl_prio, self._rate_dl, s, self._urgency):
            if count >= max_ues or pos >= n_prb:
                break
            buf = self._dl_buf[u]
            n = self._prbs_for(8 * buf.report_bytes(), self._mcs_wb_dl[u], self._dl_re,
                               n_prb - pos)
            est = self._eesm(u, pos, n, la.last_mcs[u], False)
            mcs = la.select(u, est, n, self._dl_re)
            la.last_mcs[u] = mcs
            fmt = self.phy.tb_format(n, mcs, self._dl_re)
            queued = buf.bytes
            segments = buf.fill(fmt.tbs_bits // 8)
            self._dl_prio[u] = buf.best_priority()
            if not buf.bytes:
                self._dl_active.discard(u)
            if not segments:
                continue
            tb = TransportBlock(u, segments, fmt.tbs_bits, mcs, n, fmt.cbs_bits, fmt.n_cb,
                                queued - buf.bytes)
            harq.occupy(u)
            self._sched_dl.served(u, fmt.tbs_bits, s)
            self._dl_transmit(s, tb, pos)
            pos += n
            count += 1

    def _dl_transmit(self, s: int, tb: TransportBlock, p0: int) -> None:
        """One PDSCH transmission of ``tb`` at PRB ``p0`` and the gNB's reading of its ACK."""
        cfg = self.config
        harq = self._harq_dl
        u = tb.ue
        self._dl_prb_used += tb.n_prb
        ready = s + self._k1 + 1
        if self._rand_ctrl() < cfg.pdcch_miss_prob:
            # The UE never saw the assignment: no soft bits, the gNB reads DTX as a NACK.
            self._pdcch_missed += 1
            tb.tx_count += 1
            if tb.tx_count > 1:
                self._retx["dl"] += 1
            if harq.exhausted(tb) and tb.decoded:
                self._dl_release.append((ready, u))
            else:
                self._after_failure(tb, ready, harq, False)
            return
        sinr = self._eesm(u, p0, tb.n_prb, tb.mcs, False)
        eff = harq.combine(tb, sinr)
        if tb.decoded:
            ok = True  # a retransmission caused by a lost ACK: the UE already has the TB
        else:
            ok = self._rand_dl() >= self.phy.bler.tb_bler(
                tb.mcs, tb.cbs_bits, tb.n_cb, 10.0 * math.log10(eff))
            if ok:
                tb.decoded = True
                self._deliver(tb, False)
        r = self._rand_ctrl()
        gnb_ack = r >= cfg.ack_miss_prob if ok else r < cfg.nack_to_ack_prob
        self._account("dl", u, tb, ok, self._la_dl, gnb_ack)
        if gnb_ack:
            if not tb.decoded:
                self._residual["dl"] += 1
                self._lose(tb, False)  # NACK read as ACK: the gNB drops data the UE lacks
            self._dl_release.append((ready, u))
        elif harq.exhausted(tb) and tb.decoded:
            self._dl_release.append((ready, u))
        else:
            self._after_failure(tb, ready, harq, False)

    # ------------------------------------------------------------------ outcomes
    def _deliver(self, tb: TransportBlock, ul: bool) -> None:
        """The receiver decoded ``tb``: packets whose last missing bytes it carries arrive."""
        end = self._slot_end_us
        out = self._out
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
        if ul:
            self._ul_bytes[tb.ue] += delivered
            self._delivered["ul"] += done
        else:
            self._dl_bytes[tb.ue] += delivered
            self._delivered["dl"] += done

    def _lose(self, tb: TransportBlock, ul: bool) -> None:
        """Residual HARQ failure: every packet with bytes in ``tb`` is lost (RLC UM does not
        recover it); its bytes still queued are dropped rather than sent for nothing."""
        buf = self._ul_buf[tb.ue] if ul else self._dl_buf[tb.ue]
        out = self._out
        for e, _ in tb.segments:
            if e.lost:
                continue
            e.lost = True
            buf.drop_unsent(e, e.packet.flow)
            self._lost[LOSS_CHANNEL] += 1
            out.append(PacketOutcome(e.packet, None, LOSS_CHANNEL))
