"""MAC behaviour of NrCell: access timing, schedulers, HARQ, link adaptation, QoS, interface."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pytest

from netsim.nr.csi import EESM_CACHE_MAX
from netsim.nr.harq import HarqEntity, TransportBlock
from netsim.nr.radio_cell import NrCell
from netsim.nr.scheduler import MaxRate, ProportionalFair, RoundRobin, make_scheduler
from netsim.radio_cell import LOSS_BUFFER, LOSS_CHANNEL, LOSS_DELAY_BUDGET, FlowQos, Packet
from netsim.standalone import camera_layout
from scenario.nr import NrConfig

GNB = (60.0, 30.0, 1.5)


def ring(n: int, radius_m: float = 20.0) -> dict[str, tuple[float, float, float]]:
    """n UEs at the same distance from the gNB (identical channels when forced LOS, flat)."""
    import math

    return {f"ue{i}": (60.0 + radius_m * math.cos(2 * math.pi * i / n),
                       30.0 + radius_m * math.sin(2 * math.pi * i / n), 1.5) for i in range(n)}


class Driver:
    """Feeds packets to a cell slot by slot and collects every outcome."""

    def __init__(self, cell: NrCell) -> None:
        self.cell = cell
        self.next_id = 0
        self.outcomes: list = []
        self.slot = 0

    def send(self, ue: str, size: int, direction: str = "ul", flow: str | None = None,
             count: int = 1) -> list[Packet]:
        t = self.slot * self.cell.slot_us
        packets = []
        for _ in range(count):
            self.next_id += 1
            p = Packet(self.next_id, flow or f"{ue}-{direction}", ue, direction, size, t)
            refused = self.cell.enqueue(p)
            if refused is not None:
                self.outcomes.append(refused)
            packets.append(p)
        return packets

    def run(self, n_slots: int) -> None:
        for _ in range(n_slots):
            self.outcomes.extend(self.cell.run_slot(self.slot * self.cell.slot_us))
            self.slot += 1

    def delivered(self, ues: Iterable[str] | None = None) -> dict[str, int]:
        out: dict[str, int] = {}
        for o in self.outcomes:
            if o.delivered and (ues is None or o.packet.ue in ues):
                out[o.packet.ue] = out.get(o.packet.ue, 0) + o.packet.size_bytes
        return out

    def causes(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for o in self.outcomes:
            if not o.delivered:
                out[o.cause] = out.get(o.cause, 0) + 1
        return out


# ---------------------------------------------------------------- access timing
def test_grant_based_uplink_first_packet_takes_sr_grant_pusch(flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(1), seed=1))
    (p,) = d.send("ue0", 1500)
    d.run(5)
    (o,) = d.outcomes
    # SR in the PUCCH of slot 0, grant at the PDCCH of slot 1 (K2 = 1), PUSCH in slot 2.
    assert o.packet is p and o.deliver_us == 3000


def test_configured_grant_skips_the_sr(flat_config: NrConfig) -> None:
    cfg = flat_config.model_copy(update={"ul_access": "configured_grant", "cg_prb": 40})
    d = Driver(NrCell(cfg, GNB, ring(1), seed=1))
    d.send("ue0", 1500)
    d.run(3)
    assert [o.deliver_us for o in d.outcomes] == [1000]  # the occasion of slot 0 carries it
    # A burst larger than an occasion: the occasion's BSR brings dynamic grants K2 + 1 later.
    d.send("ue0", 1500, count=20)
    d.run(8)
    assert len(d.outcomes) == 21 and max(o.deliver_us for o in d.outcomes) <= 8000


def test_configured_grant_occasions_take_turns_when_more_ues_share_them_than_fit(
        flat_config: NrConfig) -> None:
    # 468 PRBs hold 11 occasions of 40 PRBs a slot; 30 UEs share every slot's occasions (period 1).
    cfg = flat_config.model_copy(update={"ul_access": "configured_grant", "cg_prb": 40})
    d = Driver(NrCell(cfg, GNB, ring(30), seed=1))
    for u in range(30):
        d.send(f"ue{u}", 100)
    d.run(6)
    assert sorted(o.packet.ue for o in d.outcomes) == sorted(f"ue{u}" for u in range(30))


def test_downlink_is_delivered_at_the_end_of_its_slot(flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(2), seed=1))
    d.send("ue1", 200, "dl")
    d.run(2)
    assert [(o.packet.ue, o.deliver_us) for o in d.outcomes] == [("ue1", 1000)]
    assert d.cell.stats()["dl"]["delivered_packets"] == 1


def test_a_burst_is_segmented_and_every_packet_delivered_at_a_slot_end(
        flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(2), seed=3))
    sent = d.send("ue0", 1500, count=40) + d.send("ue1", 777, count=3)
    d.run(20)
    assert sorted(o.packet.packet_id for o in d.outcomes) == [p.packet_id for p in sent]
    assert all(o.delivered and o.deliver_us % 1000 == 0 for o in d.outcomes)
    # The BSR of the first PUSCH sizes the bulk grants: everything is through within ~6 slots.
    assert max(o.deliver_us for o in d.outcomes) <= 7000
    assert not d.cell.has_pending()


def test_has_pending_tracks_buffers_and_grants(flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(1), seed=1))
    assert not d.cell.has_pending()
    d.send("ue0", 100)
    assert d.cell.has_pending()
    d.run(1)
    assert d.cell.has_pending()  # SR sent, grant on its way
    d.run(3)
    assert not d.cell.has_pending()


def test_packets_enqueued_for_a_later_boundary_wait_for_it(flat_config: NrConfig) -> None:
    cell = NrCell(flat_config, GNB, ring(1), seed=1)
    cell.run_slot(0)
    cell.enqueue(Packet(1, "f", "ue0", "dl", 100, 5000))  # enters at 5 ms
    outs = [o for s in range(1, 8) for o in cell.run_slot(s * 1000)]
    assert [o.deliver_us for o in outs] == [6000]


def test_idle_jumps_are_allowed_and_pending_grants_survive_a_skip(
        flat_config: NrConfig) -> None:
    cell = NrCell(flat_config, GNB, ring(1), seed=1)
    cell.run_slot(0)
    cell.run_slot(7000)  # idle jump: nothing pending, nothing happens
    cell.enqueue(Packet(1, "f", "ue0", "ul", 1500, 8000))
    assert cell.run_slot(8000) == [] and cell.run_slot(9000) == []  # SR, then grant for 10 ms
    assert cell.has_pending()
    # A caller that wrongly skips the granted slot: the grant is undone and the gNB re-grants
    # at the PDCCH of slot 20 for the PUSCH of slot 21.
    outs = [o for s in range(20, 26) for o in cell.run_slot(s * 1000)]
    assert [o.deliver_us for o in outs] == [22000]
    assert not cell.has_pending()


# ---------------------------------------------------------------- schedulers
def test_pf_is_fair_on_a_symmetric_case(flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(4), seed=2))
    for ue in ring(4):
        d.send(ue, 1500, count=600)  # 900 kB each: backlogged for the whole run
    d.run(300)
    got = d.delivered()
    assert len(got) == 4
    assert max(got.values()) - min(got.values()) <= 0.03 * max(got.values())


def test_pf_ranking_alternates_between_equal_ues() -> None:
    pf = ProportionalFair(3, 0.9)
    served = []
    for slot in range(30):
        first = pf.order([0, 1, 2], [10, 10, 10], [100.0, 100.0, 100.0], slot)[0]
        pf.served(first, 10_000, slot)
        served.append(first)
    assert served.count(0) == served.count(1) == served.count(2) == 10


def test_pf_gives_a_weak_ue_a_share_max_rate_does_not() -> None:
    rate = [400.0, 100.0]
    shares = {}
    for kind in ("pf", "rr", "max_rate"):
        sched = make_scheduler(kind, 2, 0.95)
        counts = [0, 0]
        for slot in range(200):
            u = sched.order([0, 1], [10, 10], rate, slot)[0]
            sched.served(u, int(rate[u] * 100), slot)
            counts[u] += 1
        shares[kind] = counts[1] / 200
    assert shares["max_rate"] == 0.0
    assert shares["rr"] == 0.5
    assert 0.4 < shares["pf"] <= 0.85  # PF equalises r/T: the weak UE gets the larger time share
    assert isinstance(make_scheduler("rr", 1, 0.9), RoundRobin)
    assert isinstance(make_scheduler("max_rate", 1, 0.9), MaxRate)


def test_strict_priority_beats_the_policy() -> None:
    pf = ProportionalFair(2, 0.95)
    assert pf.order([0, 1], [5, 1], [1000.0, 1.0], 0) == [1, 0]


def test_priority_flow_is_served_first_within_a_ue(flat_config: NrConfig) -> None:
    cell = NrCell(flat_config, GNB, ring(1), seed=1)
    cell.set_flow_qos("urgent", FlowQos(priority=1))
    d = Driver(cell)
    d.send("ue0", 1500, "dl", flow="bulk", count=200)
    urgent = d.send("ue0", 100, "dl", flow="urgent")
    d.run(1)
    assert urgent[0].packet_id in {o.packet.packet_id for o in d.outcomes}


# ---------------------------------------------------------------- HARQ and link adaptation
def _residual_losses(combining: str) -> tuple[int, int]:
    # LA aims at 50 % first-transmission BLER (OLLA off), 2 transmissions allowed: the second
    # transmission saves the TB only if it is combined with the first.
    cfg = NrConfig(los_mode="los", shadowing_enabled=False, fading="none", ue_tx_power_dbm=-15.0,
                   bler_target=0.5, olla_nack_step_db=0.0, harq_max_transmissions=2,
                   harq_combining=combining, pdcch_miss_prob=0.0)
    d = Driver(NrCell(cfg, GNB, ring(4, 25.0), seed=5))
    for _ in range(60):
        for ue in ring(4, 25.0):
            d.send(ue, 1500, count=2)
        d.run(10)
    d.run(20)
    return d.causes().get(LOSS_CHANNEL, 0), len(d.outcomes)


def test_chase_combining_lowers_residual_loss() -> None:
    lost_chase, n = _residual_losses("chase")
    lost_none, n2 = _residual_losses("none")
    assert n == n2 == 480
    assert lost_none >= 10  # TBs failing twice without combining
    assert lost_chase <= lost_none / 4


def test_harq_processes_come_back_when_the_sender_reads_the_ack() -> None:
    harq = HarqEntity(1, 1, 2, chase=True)
    harq.occupy(0)
    harq.release_later(0, 5)  # a DL TB ACKed in slot 3, read at the PDCCH of slot 5
    harq.release_due(4)
    assert not harq.has_free_process(0)
    harq.release_due(5)
    assert harq.has_free_process(0)
    tb = TransportBlock(0, [], 1000, 10, 4, 1000, 1, 100)
    harq.missed(tb)  # a missed DCI uses an attempt and adds no soft bits
    assert harq.combine(tb, 2.0) == 2.0 and harq.exhausted(tb)


def test_olla_holds_first_transmission_bler_at_target() -> None:
    # NLOS with fading at ~10 dB SNR: the MCS is SINR-limited, OLLA steers the BLER.
    cfg = NrConfig(los_mode="nlos", ue_tx_power_dbm=-12.0, pdcch_miss_prob=0.0)
    d = Driver(NrCell(cfg, GNB, ring(6, 30.0), seed=4))
    for ue in ring(6, 30.0):
        d.send(ue, 1500, count=660)
    d.run(1500)
    ul = d.cell.stats()["ul"]
    assert ul["first_transmissions"] > 1000
    assert ul["bler_first_transmission"] == pytest.approx(0.10, abs=0.03)
    assert 0 < sum(m * c for m, c in enumerate(ul["mcs_histogram"])) / sum(
        ul["mcs_histogram"]) < 28


# ---------------------------------------------------------------- QoS: budget and buffer
def test_delay_budget_discards_waiting_packets(flat_config: NrConfig) -> None:
    cell = NrCell(flat_config.model_copy(update={"n_prb": 20}), GNB, ring(1), seed=1)
    cell.set_flow_qos("cam", FlowQos(delay_budget_us=10_000))
    d = Driver(cell)
    d.send("ue0", 1500, flow="cam", count=100)
    d.run(40)
    causes = d.causes()
    assert causes.get(LOSS_DELAY_BUDGET, 0) > 50
    late = [o.deliver_us - o.packet.enqueue_us for o in d.outcomes if o.delivered]
    assert late and max(late) <= 10_000 + 1000  # at most the packet under way when it expired
    assert cell.stats()["lost_packets"][LOSS_DELAY_BUDGET] == causes[LOSS_DELAY_BUDGET]
    assert not cell.has_pending()


def test_budget_change_applies_to_queued_packets(flat_config: NrConfig) -> None:
    cell = NrCell(flat_config.model_copy(update={"n_prb": 10}), GNB, ring(1), seed=1)
    d = Driver(cell)
    d.send("ue0", 1500, "dl", flow="pose", count=50)
    cell.set_flow_qos("pose", FlowQos(delay_budget_us=3000))
    d.run(6)
    assert d.causes().get(LOSS_DELAY_BUDGET, 0) > 30
    with pytest.raises(ValueError, match="delay_budget_us"):
        cell.set_flow_qos("pose", FlowQos(delay_budget_us=0))


def test_buffer_limit_refuses_with_buffer_overflow(flat_config: NrConfig) -> None:
    cfg = flat_config.model_copy(update={"ul_buffer_limit_bytes": 4000})
    d = Driver(NrCell(cfg, GNB, ring(1), seed=1))
    d.send("ue0", 1500, count=4)
    assert d.causes() == {LOSS_BUFFER: 2}
    d.run(6)
    assert len(d.delivered()) == 1 and d.cell.stats()["lost_packets"][LOSS_BUFFER] == 2


# ---------------------------------------------------------------- interface and stats
def test_interface_errors_name_what_is_wrong(flat_config: NrConfig) -> None:
    cell = NrCell(flat_config, GNB, ring(1), seed=1)
    with pytest.raises(ValueError, match="unknown UE"):
        cell.enqueue(Packet(1, "f", "nobody", "ul", 10, 0))
    with pytest.raises(ValueError, match="direction"):
        cell.enqueue(Packet(1, "f", "ue0", "up", 10, 0))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="multiple of the slot"):
        cell.run_slot(500)
    cell.run_slot(1000)
    with pytest.raises(ValueError, match="does not advance"):
        cell.run_slot(1000)
    with pytest.raises(ValueError, match="outside the hall"):
        NrCell(flat_config, GNB, {"x": (130.0, 10.0, 1.5)}, seed=1)
    with pytest.raises(ValueError, match="at least one UE"):
        NrCell(flat_config, GNB, {}, seed=1)


def test_stats_expose_counters(flat_config: NrConfig) -> None:
    d = Driver(NrCell(flat_config, GNB, ring(3), seed=1))
    for ue in ring(3):
        d.send(ue, 1500, count=10)
        d.send(ue, 100, "dl")
    d.run(15)
    st = d.cell.stats()
    assert st["slots"] == 15 and st["n_prb"] == flat_config.n_prb
    assert st["ul"]["delivered_bytes"] == 3 * 15_000 and st["dl"]["delivered_bytes"] == 300
    assert 0 < st["ul"]["prb_utilisation"] <= 1 and sum(st["ul"]["mcs_histogram"]) > 0
    assert st["ues"]["ue1"]["ul_delivered_bytes"] == 15_000
    assert st["ues"]["ue1"]["ul_buffer_peak_bytes"] == 15_000
    assert st["ul"]["buffer_bytes"] == 0 and st["lost_packets"][LOSS_CHANNEL] == 0


def test_pf_weighs_equal_ues_by_the_urgency_of_their_budgets() -> None:
    pf = ProportionalFair(2, 0.9)
    for slot in range(10):  # equal service so far
        for u in (0, 1):
            pf.served(u, 10_000, slot)
    assert pf.order([0, 1], [10, 10], [100.0, 100.0], 10, [1.0, 4.0]) == [1, 0]
    assert pf.order([0, 1], [10, 10], [100.0, 100.0], 10, [1.0, 1.0]) == [0, 1]  # tie: UE index
    # Strict priority still comes first: urgency ranks within a priority class.
    assert pf.order([0, 1], [5, 10], [100.0, 100.0], 10, [1.0, 4.0]) == [0, 1]


def test_lower_layer_qos_serves_the_urgent_flow_first_in_the_same_slot(flat_config: NrConfig) -> None:
    """Two cameras with identical channels each queue a frame in the same slot, and the gNB may
    grant one UE per slot. Told (lower-layer signalling) that ue1's flow has a 25 ms budget and
    ue0's 200 ms, the scheduler grants ue1 first in the slot where both wait; without it, the UE
    index breaks the tie and ue0 goes first."""
    cfg = flat_config.model_copy(update={"max_ul_ues_per_slot": 1})

    def first_grant(urgent: bool) -> tuple[str, dict[str, int]]:
        cell = NrCell(cfg, GNB, ring(2), seed=1)
        if urgent:
            cell.set_flow_qos("ue0/video", FlowQos(delay_budget_us=200_000, urgency=0.5), ue="ue0")
            cell.set_flow_qos("ue1/video", FlowQos(delay_budget_us=25_000, urgency=4.0), ue="ue1")
        d = Driver(cell)
        for ue in ("ue0", "ue1"):
            d.send(ue, 1500, flow=f"{ue}/video", count=20)
        first: dict[str, int] = {}
        while len(first) < 2 and d.slot < 200:
            d.run(1)
            for o in d.outcomes:
                if o.delivered:
                    first.setdefault(o.packet.ue, o.deliver_us)
        return min(first, key=lambda ue: (first[ue], ue)), first

    winner, first = first_grant(urgent=True)
    assert winner == "ue1" and first["ue1"] < first["ue0"], first
    winner, first = first_grant(urgent=False)
    assert winner == "ue0" and first["ue0"] < first["ue1"], first


def test_pf_ranks_a_ue_starved_for_thousands_of_slots_first() -> None:
    """A UE unserved long enough has its average decay past the smallest float to 0.0: it ranks
    as one never served (first), with no division by zero."""
    pf = ProportionalFair(3, 0.95)
    pf.served(0, 10_000, 0)
    starved = 40_000  # 0.95**40_000 * 10_000 underflows to 0.0
    pf.served(1, 10_000, starved - 1)
    assert pf.average(0, starved) == 0.0
    assert pf.order([0, 1], [10, 10], [100.0, 100.0], starved)[0] == 0
    assert next(pf.ranked([1, 0], [10, 10], [100.0, 100.0], starved)) == 0
    # Urgency still orders two starved UEs, as it orders UEs never served.
    pf.served(2, 10_000, 0)
    assert pf.order([0, 2], [10, 10, 10], [100.0, 100.0, 100.0], starved, [1.0, 1.0, 4.0]) == [2, 0]


def test_the_eesm_cache_stays_bounded_when_no_fading_ever_empties_it() -> None:
    cfg = NrConfig(fading="none")
    gnb, ues = camera_layout(40, cfg)
    cell, ids, rng = NrCell(cfg, gnb, ues, seed=0), list(ues), np.random.default_rng(0)
    largest, pid = 0, 0
    for s in range(8000):  # random sizes: new allocations, so new entries, every slot
        for u in rng.choice(len(ids), 6, replace=False):
            pid += 2
            cell.enqueue(Packet(pid, "f", ids[u], "ul", int(rng.integers(40, 9000)), s * 1000))
            cell.enqueue(Packet(pid + 1, "g", ids[u], "dl", int(rng.integers(40, 3000)), s * 1000))
        cell.run_slot(s * 1000)
        largest = max(largest, len(cell._csi.eesm_cache))
    assert EESM_CACHE_MAX // 2 < largest <= EESM_CACHE_MAX + len(ids)
