"""``NrCell.earliest_delivery_us`` is a lower bound: no packet the cell holds when asked arrives
before the slot it names, whatever the channel, HARQ, control errors and delay budgets do; and
``MultiCell``'s, which decodes a slot one slot late, likewise."""

from __future__ import annotations

import numpy as np
import pytest

from netsim.nr.layout import InfLayout
from netsim.nr.multicell import MultiCell
from netsim.nr.radio_cell import NrCell
from netsim.radio_cell import FlowQos, Packet
from scenario.nr import NrConfig

GNB = (60.0, 30.0, 1.5)
UES = {f"ue{i}": (10.0 + 12.0 * i, 8.0 + 5.0 * i, 1.5) for i in range(8)}


class BoundWatch:
    """Drives a cell and checks every delivery against the bounds given while it held the packet."""

    def __init__(self, cell: NrCell | MultiCell) -> None:
        self.cell = cell
        self.bound: dict[int, int] = {}  # packet id -> the latest bound given while the cell held it
        self.held: dict[tuple[str, str], set[int]] = {}
        self.checked = self.late = self.beyond_next_slot = 0

    def enqueue(self, packets: list[Packet]) -> None:
        refused = {o.packet.packet_id for o in self.cell.enqueue_many(packets)}
        for p in packets:
            if p.packet_id not in refused:
                self.held.setdefault((p.ue, p.direction), set()).add(p.packet_id)

    def slot(self, t: int) -> None:
        """Ask the bound of every (UE, direction) holding packets, then run the slot at ``t``."""
        for (ue, direction), ids in self.held.items():
            if ids:
                b = self.cell.earliest_delivery_us(ue, direction)
                assert b is not None
                self.beyond_next_slot += b > t
                for pid in ids:
                    self.bound[pid] = max(self.bound.get(pid, b), b)
        for o in self.cell.run_slot(t):
            p = o.packet
            self.held[p.ue, p.direction].discard(p.packet_id)
            if o.deliver_us is not None:
                self.checked += 1
                self.late += o.deliver_us - self.cell.slot_us < self.bound[p.packet_id]


@pytest.mark.parametrize(("access", "gnbs"), [("grant_based", 1), ("configured_grant", 1),
                                              ("grant_based", 2)])
def test_no_packet_arrives_before_the_bound_given_while_it_was_held(access: str,
                                                                    gnbs: int) -> None:
    cfg = NrConfig(ul_access=access, pdcch_miss_prob=0.02)
    cell: NrCell | MultiCell = NrCell(cfg, GNB, UES, seed=3)
    if gnbs == 2:
        layout = InfLayout.explicit("SL", 120.0, 60.0, 10.0, [(30.0, 30.0, 8.0), (90.0, 30.0, 8.0)])
        cell = MultiCell(cfg, layout, UES, seed=3)
        assert set(cell.serving().values()) == {0, 1}
    slot = cell.slot_us
    cell.set_flow_qos("ue1-ul", FlowQos(delay_budget_us=12 * slot))
    rng = np.random.default_rng(7)
    watch = BoundWatch(cell)
    next_id = 0
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
                watch.enqueue(packets)
        watch.slot(t)
    assert watch.late == 0
    assert watch.checked > 5000
    if access == "grant_based":
        assert watch.beyond_next_slot > 1000  # the bound often says more than "the next slot"


def test_a_packet_lost_ahead_of_a_small_one_does_not_delay_the_bound() -> None:
    # One transmission per TB and grants two slots ahead: when the first grant's TB fails, the
    # big packet it started is lost at once and the small one behind it goes in the next grant.
    late = 0
    for seed in range(40):
        cell = NrCell(NrConfig(k2_slots=2, harq_max_transmissions=1, bler_target=0.5), GNB,
                      {"ue0": UES["ue0"]}, seed=seed)
        watch = BoundWatch(cell)
        for s in range(60):
            t = s * cell.slot_us
            if s % 20 == 0:
                watch.enqueue([Packet(2 * s, "f", "ue0", "ul", 300_000, t),
                               Packet(2 * s + 1, "f", "ue0", "ul", 100, t)])
            watch.slot(t)
        late += watch.late
    assert late == 0
