"""The shared-capacity cell: capacity per slot, loss draws, delay budget, buffer limit."""

from __future__ import annotations

from collections import Counter

import numpy as np

from fabric.tables import PACKETS
from netsim.radio_cell import LOSS_BUFFER, LOSS_DELAY_BUDGET, FlowQos, Packet
from netsim.records import OutcomeColumns
from netsim.simple import SimpleCell


def cell(**kw: float) -> SimpleCell:
    args = dict(slot_us=1000, ul_rate_mbps=12.0, dl_rate_mbps=12.0, loss_probability=0.0,
                buffer_bytes=1_000_000)
    args.update(kw)
    return SimpleCell(rng=np.random.default_rng(0), **args)  # type: ignore[arg-type]


def run(c: SimpleCell, slots: int) -> list:
    out = []
    for s in range(slots):
        out += c.run_slot(s * 1000)
    return out


def test_delivers_at_slot_ends_at_capacity() -> None:
    c = cell()  # 12 Mbit/s = 1500 bytes per 1 ms slot
    for i in range(10):
        c.enqueue(Packet(i, "f", "ue0", "ul", 1500, 0))
    out = run(c, 12)
    assert [o.deliver_us for o in out] == [1000 * (i + 1) for i in range(10)]
    assert not c.has_pending()


def test_partial_packets_span_slots() -> None:
    c = cell()
    c.enqueue(Packet(0, "f", "ue0", "ul", 4000, 0))
    out = run(c, 4)
    assert [o.deliver_us for o in out] == [3000]


def test_loss_probability_is_drawn_per_packet() -> None:
    c = cell(ul_rate_mbps=1200.0, loss_probability=0.3)
    for i in range(2000):
        c.enqueue(Packet(i, "f", "ue0", "ul", 100, 0))
    out = run(c, 5)
    lost = sum(1 for o in out if not o.delivered)
    assert len(out) == 2000 and 500 < lost < 700


def test_delay_budget_and_buffer_overflow() -> None:
    c = cell(buffer_bytes=6000)
    c.set_flow_qos("f", FlowQos(delay_budget_us=2000))
    refused = [c.enqueue(Packet(i, "f", "ue0", "ul", 1500, 0)) for i in range(5)]
    assert [r.cause for r in refused if r] == [LOSS_BUFFER]
    out = run(c, 6)
    causes = [o.cause for o in out]
    assert causes.count(None) == 3 and causes.count(LOSS_DELAY_BUDGET) == 1


def test_outcomes_become_the_packets_tables_columns_and_counts() -> None:
    c = cell(buffer_bytes=3000)
    refused = [o for i in range(3) if (o := c.enqueue(Packet(i, "cam/video", "ue0", "ul", 1500, 0)))]
    assert len(refused) == 1  # the third does not fit the buffer
    outcomes = run(c, 3)
    columns = OutcomeColumns(outcomes + refused)
    table = columns.as_dict()
    assert list(table) == PACKETS.names
    assert table["packet_id"] == [o.packet.packet_id for o in outcomes + refused]
    assert table["latency_us"] == [1000, 2000, None]
    assert table["lost_cause"] == [None, None, LOSS_BUFFER]
    fates: Counter[tuple[str, str]] = Counter()
    bits = {"ul": 0, "dl": 0}
    latencies: dict[str, dict[int, int]] = {"ul": {}, "dl": {}}
    columns.tally(fates, bits, latencies)
    assert fates[("ul", "delivered")] == 2 and bits == {"ul": 2 * 8 * 1500, "dl": 0}
    assert latencies == {"ul": {1000: 1, 2000: 1}, "dl": {}}
    assert fates[("ul", LOSS_BUFFER)] == 1


def test_a_packet_that_overtakes_a_begun_one_is_sent_whole_and_the_begun_one_finishes() -> None:
    c = cell(ul_rate_mbps=1.0)  # 125 bytes a slot
    c.set_flow_qos("urgent", FlowQos(priority=1))
    c.enqueue(Packet(1, "bulk", "ue", "ul", 130, 0))
    assert c.run_slot(0) == []  # 5 bytes of the bulk packet left
    c.enqueue(Packet(2, "urgent", "ue", "ul", 250, 1000))
    sent = {o.packet.packet_id: o.deliver_us for o in run_from(c, 1, 4)}
    # The urgent packet takes its own two slots (not the 5 bytes the bulk one had left), then
    # the bulk packet its last 5 bytes.
    assert sent == {2: 3000, 1: 4000}


def run_from(c: SimpleCell, first: int, slots: int) -> list:
    out = []
    for s in range(first, first + slots):
        out += c.run_slot(s * 1000)
    return out
