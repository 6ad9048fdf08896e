"""``NrCell.earliest_delivery_us`` is a lower bound: no packet the cell holds when asked arrives
before the slot it names, whatever the channel, HARQ, control errors and delay budgets do."""

from __future__ import annotations

import numpy as np
import pytest

from netsim.cell import FlowQos, Packet
from netsim.nr.cell import NrCell
from scenario.nr import NrConfig

GNB = (60.0, 30.0, 1.5)
UES = {f"ue{i}": (10.0 + 12.0 * i, 8.0 + 5.0 * i, 1.5) for i in range(8)}


@pytest.mark.parametrize("access", ["grant_based", "configured_grant"])
def test_no_packet_arrives_before_the_bound_given_while_it_was_held(access: str) -> None:
    cell = NrCell(NrConfig(ul_access=access, pdcch_miss_prob=0.02), GNB, UES, seed=3)
    slot = cell.slot_us
    cell.set_flow_qos("ue1-ul", FlowQos(delay_budget_us=12 * slot))
    rng = np.random.default_rng(7)
    bound: dict[int, int] = {}  # packet id -> the latest bound given while the cell held it
    held: dict[tuple[str, str], set[int]] = {}
    next_id = 0
    later_than_next_slot = checked = 0
    for s in range(1500):
        t = s * slot
        # Saturating uplink (frames of 1500-byte packets, some entering a few slots later) and
        # a lighter downlink.
        for ue in UES:
            for direction, rate in (("ul", 0.25), ("dl", 0.1)):
                if rng.random() >= rate:
                    continue
                enter = t + slot * int(rng.integers(0, 3) if direction == "ul" else 0)
                sizes = [1500] * int(rng.integers(1, 12)) + [int(rng.integers(40, 1500))]
                packets = []
                for size in sizes:
                    next_id += 1
                    packets.append(Packet(next_id, f"{ue}-{direction}", ue, direction, size, enter))
                refused = {o.packet.packet_id for o in cell.enqueue_many(packets)}
                held.setdefault((ue, direction), set()).update(
                    p.packet_id for p in packets if p.packet_id not in refused)
        for (ue, direction), ids in held.items():
            if ids:
                b = cell.earliest_delivery_us(ue, direction)
                assert b is not None
                later_than_next_slot += b > t
                for pid in ids:
                    bound[pid] = max(bound.get(pid, b), b)
        for o in cell.run_slot(t):
            p = o.packet
            held[p.ue, p.direction].discard(p.packet_id)
            if o.deliver_us is not None:
                checked += 1
                assert o.deliver_us - slot >= bound[p.packet_id], (p, bound[p.packet_id])
    assert checked > 5000
    if access == "grant_based":
        assert later_than_next_slot > 1000  # the bound often says more than "the next slot"


def test_a_packet_lost_ahead_of_a_small_one_does_not_delay_the_bound() -> None:
    # One transmission per TB and grants two slots ahead: when the first grant's TB fails, the
    # big packet it started is lost at once and the small one behind it goes in the next grant.
    late = 0
    for seed in range(40):
        cell = NrCell(NrConfig(k2_slots=2, harq_max_transmissions=1, bler_target=0.5), GNB,
                      {"ue0": UES["ue0"]}, seed=seed)
        slot = cell.slot_us
        held: set[int] = set()
        bound: dict[int, int] = {}
        for s in range(60):
            t = s * slot
            if s % 20 == 0:
                cell.enqueue_many([Packet(2 * s, "f", "ue0", "ul", 300_000, t),
                                   Packet(2 * s + 1, "f", "ue0", "ul", 100, t)])
                held |= {2 * s, 2 * s + 1}
            if held:
                b = cell.earliest_delivery_us("ue0", "ul")
                assert b is not None
                for pid in held:
                    bound[pid] = max(bound.get(pid, b), b)
            for o in cell.run_slot(t):
                held.discard(o.packet.packet_id)
                late += o.deliver_us is not None and o.deliver_us - slot < bound[o.packet.packet_id]
    assert late == 0
