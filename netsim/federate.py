"""The netsim federate: turns every IP packet handed to a modem into a delivery at a slot end (or a
loss with its cause) using a cell model, and records every packet's fate.

Packets arrive as ``packet`` messages (``wire.bodies.Packet``) naming the UE, direction, flow,
size, the destination federate and the application body to deliver; the destination receives
that body, as a message of its own kind, with the packet's id and the payload bytes. Packet records stream to
the ``packets`` table as packets are decided: nothing per packet is kept past its fate.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any, cast

import msgspec
from msgspec.structs import replace

from domain.partitions import NETSIM, PartitionPlan, load_plan, netsim_name
from fabric import metrics, native
from fabric.federate import NEVER_US, Federate, Handlers
from fabric.messages import Message
from netsim.nr.agv_traffic import AgvTraffic
from netsim.nr.handover import HandoverParams
from netsim.nr.layout import layout_from_hall
from netsim.nr.mobility import Fleet, agv_ids, agv_routes
from netsim.nr.multicell import MultiCell
from netsim.nr.radio_cell import NrCell
from netsim.radio_cell import (
    LOSS_BUFFER,
    LOSS_CHANNEL,
    LOSS_DELAY_BUDGET,
    LOSS_HANDOVER,
    Direction,
    FlowQos,
    Packet,
    PacketOutcome,
    RadioCell,
)
from netsim.records import OutcomeColumns
from netsim.simple import SimpleCell
from wire import bodies
from wire.bodies import FadingProcesses, HeldPackets, QosCtl, SlotTransmissions

log = logging.getLogger(__name__)

# Bounds of a UE's urgency weight in the PF ranking (budgets 8x shorter or longer than the usual).
MAX_URGENCY = 8.0
# Packet ids count per gNB, the gNB's index above these bits: a packet gets the same id whatever
# partition holds its gNB (one gNB: the ids count from 0 as ever).
GNB_ID_SHIFT = 40


def make_cell(federate: Federate, own_gnbs: list[int] | None = None) -> RadioCell:
    """The cell model the scenario names, with the UEs of every loop at their hall positions: the
    NR cells of every gNB of ``hall.inf_layout`` when it is set (or of ``own_gnbs`` only, a
    partition's), else the one gNB's. Its streams are netsim's whatever federate holds it."""
    sc = federate.scenario
    prefix = f"{NETSIM}/nr"
    cfg = sc.netsim
    if cfg.model == "simple":
        return SimpleCell(cfg.slot_us, cfg.ul_rate_mbps, cfg.dl_rate_mbps, cfg.loss_probability,
                          cfg.buffer_bytes, federate.rng("cell"))
    layout = layout_from_hall(sc.hall)
    if layout is not None:
        agvs = sc.agvs
        if not agvs.count:
            return MultiCell(cfg.nr, layout, sc.ue_positions_m(), sc.seed,
                             stream_prefix=prefix, record=True, own_gnbs=own_gnbs)
        traffic = AgvTraffic(agv_ids(agvs.count), agvs.ul_rate_mbps, agvs.dl_rate_mbps,
                             agvs.ul_packet_bytes, agvs.dl_packet_bytes,
                             None if agvs.delay_budget_ms is None
                             else round(agvs.delay_budget_ms * 1000))
        return MultiCell(cfg.nr, layout, sc.ue_positions_m(), sc.seed,
                         stream_prefix=prefix, record=True,
                         fleet=Fleet(agv_routes(sc)), agv_traffic=traffic,
                         handover=HandoverParams.from_config(cfg.handover), own_gnbs=own_gnbs)
    return NrCell(cfg.nr, gnb_position_m=sc.hall.gnb_position_m,
                  ue_positions_m=sc.ue_positions_m(), seed=sc.seed, stream_prefix=prefix)


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flatten nested cell statistics into ``a.b`` keys (numbers only) for the run summary."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if k == "ues":
            continue  # per-UE detail stays out of the run summary
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        elif isinstance(v, int | float):
            out[f"{prefix}{k}"] = v
    return out


class NetsimFederate(Federate):
    role = "netsim"

    def setup(self) -> None:
        sc = self.scenario
        # A partition's cells, and the partitions it exchanges each slot's transmissions with.
        own: list[int] | None = None
        self.peers: list[str] = []
        self.plan: PartitionPlan | None = None
        if sc.partitions > 1:
            self.plan = plan = load_plan(sc, self.results_dir)
            mine = [p for p in range(plan.count) if netsim_name(p) == self.name]
            if not mine:
                raise ValueError(f"{self.name} is no netsim partition of {plan.count}")
            own = plan.own_gnbs(mine[0])
            self.peers = [netsim_name(p) for p in range(plan.count) if p != mine[0]]
        self.cell = make_cell(self, own)
        self.gnb_of = getattr(self.cell, "serving_gnb_index", {})  # UE -> gNB with several
        self.remote: dict[int, dict[str, list[Any]]] = {}  # slot -> the peers' transmissions
        compiled = native.compiled_loaded()
        log.info("cell model %s: %s", type(self.cell).__name__,
                 f"compiled ({', '.join(compiled)})" if compiled else "pure Python")
        self.slot_us = self.scenario.netsim.slot_us
        self.next_packet_id: Counter[int] = Counter()  # per gNB
        self.slot_scheduled: int | None = None
        self.packets = self.table("packets")
        # Every run has the table, empty with one gNB (the model keeps no transmissions then).
        self.transmissions = self.table("transmissions")
        self.handovers = self.table("handovers")
        self.serving = self.cell.serving()
        self.flow_pdb: dict[str, int | None] = {}
        # Simulated-time rates for the dashboards, refreshed every simulated second.
        self.delivered_bits = {"ul": 0, "dl": 0}
        self.rates_at: tuple[int, dict[str, int], dict[str, float]] = (0, dict(self.delivered_bits), self._prb_slots())
        # The metric series of each direction and fate, looked up once: a label lookup per packet
        # costs more than the update. Every loss cause has its series from the start, at zero.
        self.packet_series = {(d, fate): metrics.PACKETS.labels(d, fate) for d in ("ul", "dl")
                              for fate in ("delivered", "lost", LOSS_BUFFER, LOSS_CHANNEL, LOSS_DELAY_BUDGET,
                                           LOSS_HANDOVER)}
        self.byte_series = {d: metrics.PACKET_BYTES.labels(d) for d in ("ul", "dl")}
        self.latency_series = {d: metrics.PACKET_LATENCY.labels(d) for d in ("ul", "dl")}
        # Counts go to their series once a slot, not once a packet (tens of thousands a second).
        self.fates: Counter[tuple[str, str]] = Counter()
        self.bits_published = dict(self.delivered_bits)
        # Packets in the cell for a federate outside this one's group, per (UE, direction)
        # (``external_horizon_us``).
        self.outside_in_cell: Counter[tuple[str, str]] = Counter()
        if self.cell.has_pending():  # moving radios' streams run from the start
            self._ensure_slot(0)

    def next_send_us(self, plane: str, now_us: int) -> int:
        return now_us if plane == "net" else NEVER_US  # deliveries are its only messages

    def external_horizon_us(self) -> int | None:
        if self.peers and self.cell.has_pending():
            return self.now  # its next slot sends its transmissions to the other partitions
        # Deliveries are its only messages: while the cell holds none for a federate outside the
        # group (the abstract loops' packets go back to their group), it sends nothing out. Else
        # the earliest slot that may deliver one of those, sent at that slot's start.
        horizon = NEVER_US
        for (ue, direction), n in self.outside_in_cell.items():
            if n:
                at = self.cell.earliest_delivery_us(ue, direction)
                if at is None:
                    return self.now
                horizon = min(horizon, at)
        return horizon

    def handlers(self) -> Handlers:
        return {bodies.Packet: self._on_packet, bodies.Packets: self._on_packets, QosCtl: self._lower_layer_qos,
                SlotTransmissions: self._on_transmissions, HeldPackets: self._on_held}

    def _on_held(self, b: HeldPackets, msg: Message) -> None:
        assert isinstance(self.cell, MultiCell)
        self.cell.take_held(b.ue, b.start_us, [Packet(i, flow, b.ue, cast(Direction, d), size, t)
                                               for i, flow, d, size, t in b.packets],
                            msgspec.structs.asdict(b.fading))

    def _on_transmissions(self, b: SlotTransmissions, msg: Message) -> None:
        # From the partitions in name order, which is gNB order: the whole hall's order.
        into = self.remote.setdefault(b.slot, {"dl": [], "ul": []})
        into["dl"] += b.dl
        into["ul"] += b.ul

    def _on_packet(self, p: bodies.Packet, msg: Message) -> None:
        # A packet's ref: (destination, application body, payload bytes, index in its message
        # or None); the delivered message's body is built from it at delivery.
        pid = self._check_entry(p, msg)
        self._enqueue_packets([Packet(pid, p.flow, p.ue, p.direction, p.size, msg.t_us, (p.dst, p.app, msg.blob, None))], p, msg.t_us)

    def _on_packets(self, p: bodies.Packets, msg: Message) -> None:
        # The packets of one application message (an abstract loop's frame): the same flow,
        # entry slot and destination; each delivered with its index in ``app.idx``.
        if msg.blob is not None:
            raise ValueError("netsim: a packets message carries no payload bytes (send packet)")
        pid = self._check_entry(p, msg)
        self._enqueue_packets([Packet(pid + idx, p.flow, p.ue, p.direction, size, msg.t_us, (p.dst, p.app, None, idx))
                       for idx, size in enumerate(p.sizes)], p, msg.t_us)

    def _check_entry(self, p: bodies.Packet | bodies.Packets, msg: Message) -> int:
        """Check a packet message's entry time, apply its flow's budget; the first packet id."""
        if msg.t_us % self.slot_us:
            raise ValueError(f"netsim: {msg.kind} from {msg.src} enters at {msg.t_us} us, not a slot boundary")
        pdb = p.pdb_us
        if self.flow_pdb.get(p.flow, "unset") != pdb:
            self.flow_pdb[p.flow] = pdb
            self.cell.set_flow_qos(p.flow, FlowQos(priority=5 if p.direction == "dl" else 10,
                                                   delay_budget_us=None if pdb is None else int(pdb)))
        g = self.gnb_of.get(p.ue, 0)
        return (g << GNB_ID_SHIFT) + self.next_packet_id[g]

    def _enqueue_packets(self, packets: list[Packet], p: bodies.Packet | bodies.Packets, t_us: int) -> None:
        self.next_packet_id[self.gnb_of.get(p.ue, 0)] += len(packets)
        refused = self.cell.enqueue_many(packets)
        if refused:
            self._record(refused)
        if p.dst not in self.cohosted:
            self.outside_in_cell[p.ue, p.direction] += len(packets) - len(refused)
        self._ensure_slot(t_us)

    def _lower_layer_qos(self, b: QosCtl, msg: Message) -> None:
        """A loop's QoS signalled to the gNB (``policy.signalling: lower``): the flow's delay budget,
        and its UE weighed in the scheduler by the budget's urgency, the scenario's default budget
        over this one (a loop given half the usual budget counts twice in the PF ranking)."""
        pdb = None if b.pdb_us is None else int(b.pdb_us)  # FlowQos takes whole microseconds
        reference_us = self.scenario.policy.latency_budget_ms * 1000
        urgency = 1.0 if pdb is None else min(MAX_URGENCY, max(1.0 / MAX_URGENCY, reference_us / pdb))
        self.flow_pdb[b.flow] = pdb
        self.cell.set_flow_qos(b.flow, FlowQos(priority=10, delay_budget_us=pdb, urgency=urgency), ue=b.ue)

    def _ensure_slot(self, t_us: int) -> None:
        if self.slot_scheduled is None:
            self.slot_scheduled = t_us
            self.schedule(t_us, self._slot, after_inputs=True)

    def _prb_slots(self) -> dict[str, float]:
        """PRB-slots used so far per link, in units of whole-cell slots."""
        st = self.cell.stats()
        if "ul" in st and isinstance(st["ul"], dict):  # NR cell: utilisation over all slots so far
            return {d: st[d]["prb_utilisation"] * st["slots"] for d in ("ul", "dl")}
        return {d: float(st.get(f"{d}_busy_slots", 0)) for d in ("ul", "dl")}

    def _publish_rates(self) -> None:
        t0, bits0, prb0 = self.rates_at
        span_s = (self.now - t0) / 1e6
        prb = self._prb_slots()
        slots = max(1.0, (self.now - t0) / self.slot_us)
        for d in ("ul", "dl"):
            metrics.THROUGHPUT.labels(d).set((self.delivered_bits[d] - bits0[d]) / span_s)
            metrics.PRB_UTILISATION.labels(d).set(min(1.0, (prb[d] - prb0[d]) / slots))
        self.rates_at = (self.now, dict(self.delivered_bits), prb)

    def _slot(self) -> None:
        self.slot_scheduled = None
        if self.now - self.rates_at[0] >= 1_000_000:
            self._publish_rates()
        # Deliveries without payload bytes go to each destination as one bundle per delivery
        # time, in the cell's order; one with bytes (a detailed camera's) goes on its own and
        # first sends what was bundled before it for that destination, which keeps the order.
        # The packets of one ``packets`` message delivered together are one item, at the place
        # of the last of them: the receiver acts when a frame's last packet is in, so it acts in
        # the same order as with an item a packet.
        bundles: dict[tuple[str, int], list[bodies.Payload | None]] = {}
        places: dict[tuple[str, int], dict[int, int]] = {}  # per bundle: id(app) -> its item's index
        if self.peers:
            # Decode the last slot against every partition's transmissions of it, then tell the
            # others this slot's (they decode theirs at the next slot's start).
            slot = self.now // self.slot_us
            remote = self.remote.pop(slot - 1, None)
            for old in [s for s in self.remote if s < slot]:
                del self.remote[old]
            assert isinstance(self.cell, MultiCell)
            outcomes = self.cell.run_slot(self.now, remote)
            sent_tx = self.cell.slot_transmissions()
            if sent_tx["dl"] or sent_tx["ul"]:
                for peer in self.peers:
                    self.send(peer, self.now + self.slot_us,
                              SlotTransmissions(slot=slot, dl=sent_tx["dl"], ul=sent_tx["ul"]))
            assert self.plan is not None
            for gnb, ue, start_us, held, fading in self.cell.held_out():
                # A handover into another partition's gNB: what the source cell held goes there.
                self.send(netsim_name(self.plan.gnb_partition[gnb]), self.now + self.slot_us,
                          HeldPackets(ue=ue, start_us=start_us,
                                      packets=[(p.packet_id, p.flow, p.direction, p.size_bytes, p.enqueue_us)
                                               for p in held], fading=FadingProcesses(**fading)))
        else:
            outcomes = self.cell.run_slot(self.now)
        self._record(outcomes)
        sent = self.cell.transmissions()
        if sent:
            self.transmissions.extend_columns(sent)
        handed = self.cell.handovers()
        if handed and handed["ue"]:
            self.handovers.extend_columns(handed)
        if self.outside_in_cell.total():
            for o in outcomes:
                p = o.packet
                if p.ref is not None and p.ref[0] not in self.cohosted:
                    self.outside_in_cell[p.ue, p.direction] -= 1
        for outcome in outcomes:
            # An AGV's packets (no ref) go to no federate: their records are all there is.
            if outcome.deliver_us is None or outcome.packet.ref is None:
                continue
            dst, app, blob, idx = outcome.packet.ref
            key = (dst, outcome.deliver_us)
            if idx is not None:
                items = bundles.setdefault(key, [])
                place = places.setdefault(key, {})
                at = place.get(id(app))
                item: bodies.Payload | None
                if at is None:
                    item = replace(app, idx=[idx], packet_ids=[outcome.packet.packet_id])
                else:
                    item, items[at] = items[at], None
                    assert isinstance(item, bodies.Aframe) and item.idx is not None and item.packet_ids is not None
                    item.idx.append(idx)
                    item.packet_ids.append(outcome.packet.packet_id)
                place[id(app)] = len(items)
                items.append(item)
                continue
            body = replace(app, packet_id=outcome.packet.packet_id)
            if blob is None:
                bundles.setdefault(key, []).append(body)
                continue
            for k in [k for k in bundles if k[0] == dst]:
                self._send_items(dst, k[1], bundles.pop(k))
                places.pop(k, None)
            self.send(dst, outcome.deliver_us, body, blob)
        for (dst, deliver_us), pending in bundles.items():
            self._send_items(dst, deliver_us, pending)
        self._publish_counts()
        if self.cell.has_pending():
            self._ensure_slot(self.now + self.slot_us)

    def _send_items(self, dst: str, deliver_us: int, items: list[bodies.Payload | None]) -> None:
        """Send a bundle's items, leaving out the places merged items moved from."""
        self.send_bundle(dst, deliver_us, [i for i in items if i is not None])

    def _record(self, outcomes: list[PacketOutcome]) -> None:
        """Count and record the fates of ``outcomes``. Latencies are slot multiples, so the
        histogram gets each distinct value once with its count rather than once a packet."""
        # A column at a time: the same rows and batches as a row a packet, without a dict per
        # packet (netsim.records, compiled).
        columns = OutcomeColumns(outcomes, self.serving)
        self.packets.extend_columns(columns.as_dict())
        latencies: dict[str, dict[int, int]] = {"ul": {}, "dl": {}}
        columns.tally(self.fates, self.delivered_bits, latencies)
        for link, counts in latencies.items():
            for latency, n in counts.items():
                metrics.observe_many(self.latency_series[link], latency / 1e6, n)

    def _publish_counts(self) -> None:
        """Move the packet and byte counts since the last call into the metric series."""
        for key, n in self.fates.items():
            if n:
                self.packet_series[key].inc(n)
        self.fates.clear()
        for d, bits in self.delivered_bits.items():
            if bits > self.bits_published[d]:
                self.byte_series[d].inc((bits - self.bits_published[d]) // 8)
                self.bits_published[d] = bits

    def finish(self, reason: str) -> dict[str, Any]:
        self._publish_counts()
        return {"packets": self.packets.rows_written + self.packets.buffered,
                "model": self.scenario.netsim.model,
                **_flat(self.cell.stats())}
