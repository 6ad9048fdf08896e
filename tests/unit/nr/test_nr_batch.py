"""Batched paths: ``enqueue_many`` decides every packet as ``enqueue`` one by one would, and the
federate's bulk histogram update counts as many ``observe`` calls."""

from __future__ import annotations

from netsim.nr.radio_cell import NrCell
from netsim.radio_cell import FlowQos, Packet, PacketOutcome
from netsim.standalone import camera_layout
from scenario.nr import NrConfig


def _run(batched: bool) -> list[tuple[int, int | None, str | None]]:
    """A loaded cell with small buffers (refusals), a delay budget, DL packets and packets that
    enter at a later slot (staged); every outcome in order."""
    cfg = NrConfig(ul_buffer_limit_bytes=40_000)
    gnb, ues = camera_layout(12, cfg)
    cell = NrCell(cfg, gnb, ues, seed=3)
    cell.set_flow_qos("camera-1", FlowQos(delay_budget_us=4000))
    ids = list(ues)
    out: list[PacketOutcome] = []
    pid = 0
    for s in range(400):
        t = s * cell.slot_us
        for i, ue in enumerate(ids):
            if (s + 7 * i) % 11:
                continue
            frame = []
            for size in [1500] * 20 + [321]:
                pid += 1
                frame.append(Packet(pid, ue, ue, "ul", size, t))
            pid += 1
            frame.append(Packet(pid, f"{ue}-dl", ue, "dl", 200, t))
            pid += 1
            frame.append(Packet(pid, ue, ue, "ul", 800, t + 2 * cell.slot_us))
            if batched:
                out += cell.enqueue_many(frame)
            else:
                out += [o for o in map(cell.enqueue, frame) if o is not None]
        out += cell.run_slot(t)
    return [(o.packet.packet_id, o.deliver_us, o.cause) for o in out]


def test_enqueue_many_matches_enqueue() -> None:
    one_by_one = _run(False)
    assert any(cause == "buffer_overflow" for _, _, cause in one_by_one)
    assert any(cause == "delay_budget" for _, _, cause in one_by_one)
    assert _run(True) == one_by_one
