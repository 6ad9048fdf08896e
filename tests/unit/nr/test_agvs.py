"""Moving radios in a hall of several gNBs (netsim.nr.multicell with agv_traffic, gnb_cell
detach/attach, handover): an AGV driving from one gNB to another hands over where the geometry
says, its packets are forwarded or lost, its streams load the cells, and the run is
deterministic."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from netsim.federate import make_cell
from netsim.nr.agv_traffic import AgvTraffic
from netsim.nr.handover import HandoverParams
from netsim.nr.layout import InfLayout
from netsim.nr.mobility import AgvRoute, Fleet
from netsim.nr.multicell import MultiCell
from netsim.radio_cell import LOSS_HANDOVER, Packet, PacketOutcome
from scenario.nr import NrConfig
from scenario.schema import ScenarioError, parse_scenario

HALL = (120.0, 60.0, 10.0)
SLOT_US = 1000


def _hall(forward: bool = True, interruption_ms: float = 50.0, rate_mbps: float = 2.0,
          seed: int = 5) -> MultiCell:
    """Two gNBs 40 m apart, a static UE near each, one AGV driving at 2 m/s between them
    (x 40 -> 60 -> 40 m), with LOS everywhere and no shadowing: the handover point is geometry."""
    cfg = NrConfig(los_mode="los", shadowing_enabled=False, fading="none", pdcch_miss_prob=0.0,
                   ack_miss_prob=0.0, nack_to_ack_prob=0.0)
    layout = InfLayout.explicit("SL", *HALL, [(30.0, 30.0, 1.5), (70.0, 30.0, 1.5)])
    ues = {"a": (28.0, 32.0, 1.5), "b": (72.0, 32.0, 1.5)}
    fleet = Fleet([AgvRoute([(40.0, 30.0), (60.0, 30.0)], 2.0, 0.0, 1.5)])
    traffic = AgvTraffic(["agv-0"], rate_mbps, rate_mbps / 4, 1500, 120)
    params = HandoverParams(interruption_ms=interruption_ms, forward=forward)
    return MultiCell(cfg, layout, ues, seed=seed, record=True, fleet=fleet, agv_traffic=traffic,
                     handover=params)


def _run(cell: MultiCell, seconds: float) -> list[PacketOutcome]:
    out: list[PacketOutcome] = []
    for s in range(int(seconds * 1e6 / SLOT_US)):
        out += cell.run_slot(s * SLOT_US)
    return out


def test_an_agv_hands_over_past_the_midpoint_and_back() -> None:
    cell = _hall()
    assert cell.serving_gnb_index["agv-0"] == 0 and len(cell.cells) == 2
    out = _run(cell, 20.0)  # out to x = 60 at 10 s and back to 40 at 20 s
    control = cell.handover
    assert control is not None
    done = [h for h in control.handovers if h.done]
    assert [(h.source, h.target) for h in done] == [(0, 1), (1, 0)]
    # Symmetric gNBs and no shadowing: the A3 event (3 dB hysteresis, then the 256 ms time to
    # trigger and the filter's lag) fires past the midpoint (x = 50 m) on the way out, before
    # it on the way back: a handover position between 50 m and 58 m out, 42 m and 50 m back.
    x_out = 40.0 + 2.0 * done[0].start_us / 1e6
    x_back = 60.0 - 2.0 * (done[1].start_us / 1e6 - 10.0)
    assert 50.0 < x_out < 58.0 and 42.0 < x_back < 50.0
    for h in done:
        assert h.end_us - h.start_us == 50_000
    # The AGV's packets: every one decided, a few at most lost (none to the handover, which
    # forwards), its UL through gNB 1 between the handovers.
    agv = [o for o in out if o.packet.ue == "agv-0"]
    assert agv and all(o.packet.packet_id < 0 for o in agv)
    # Each packet decided once, every one but the last few still queued or in the air.
    ids = [o.packet.packet_id for o in agv]
    traffic = cell.agv_traffic
    assert traffic is not None and len(ids) == len(set(ids))
    made = -traffic._next_id - 1
    assert set(ids) <= set(range(-made, 0)) and made - len(ids) < 20
    assert sum(o.cause == LOSS_HANDOVER for o in agv) == 0
    st = cell.stats()
    kpi = st["agvs"]
    assert kpi["handovers_completed"] == 2 and kpi["ping_pongs"] == 0
    assert kpi["interruption_s"] == pytest.approx(0.1)
    assert kpi["ul"]["delivered_packets"] > 0.95 * 20.0 * 2e6 / (1500 * 8)
    # Held packets waited out the interruption: the worst latencies span it.
    assert kpi["ul"]["latency_ms_p99"] is not None and kpi["ul"]["latency_ms_p50"] < 10
    assert st["ues"]["agv-0"]["handovers"] == 2
    rows = cell.handovers()
    assert rows is not None and rows["source"] == [0, 1] and rows["target"] == [1, 0]
    assert cell.handovers() == {k: [] for k in rows}


def test_without_forwarding_the_held_packets_are_lost() -> None:
    cell = _hall(forward=False, interruption_ms=200.0, rate_mbps=8.0)
    out = _run(cell, 9.0)
    control = cell.handover
    assert control is not None and [h.target for h in control.handovers if h.done] == [1]
    lost = [o for o in out if o.cause == LOSS_HANDOVER]
    # At 8 Mbit/s about 133 UL packets reach the AGV's modem during 200 ms, all lost.
    assert len(lost) >= 100 and all(o.packet.ue == "agv-0" for o in lost)
    assert cell.stats()["lost_packets"][LOSS_HANDOVER] == len(lost)


def test_detach_returns_every_undelivered_packet_once_and_attach_takes_them() -> None:
    cell = _hall()
    src = cell.cell_of_gnb[0]
    dst = cell.cell_of_gnb[1]
    assert src is not None and dst is not None
    _run(cell, 0.2)
    # Queue a burst for the AGV in its cell, let part of it go out, then take it away.
    burst = [Packet(10_000 + k, "agv-0/video", "agv-0", "ul", 1500, 200_000) for k in range(300)]
    cell.enqueue_many(burst)
    delivered: set[int] = set()
    for s in range(200, 210):
        delivered |= {o.packet.packet_id for o in cell.run_slot(s * SLOT_US) if o.delivered}
    # As the hall does it: the slot in the air decoded first, then the AGV detached.
    planned, cell._planned = cell._planned, None
    assert planned is not None
    decoded: list[PacketOutcome] = []
    cell._decode(planned, {}, decoded, 211_000)
    delivered |= {o.packet.packet_id for o in decoded if o.delivered}
    held = src.detach("agv-0", 210_000)
    ids = [p.packet_id for p in held]
    assert len(ids) == len(set(ids))
    assert [(p.enqueue_us, p.packet_id) for p in held] == sorted((p.enqueue_us, p.packet_id)
                                                                 for p in held)
    burst_ids = {p.packet_id for p in burst}
    assert 0 < len(burst_ids & delivered) < len(burst)  # part of the burst went out
    assert set(ids) >= burst_ids - delivered and not set(ids) & delivered
    u = src.ue_ids.index("agv-0")
    assert src._ul_buf[u].bytes == 0 and src._dl_buf[u].bytes == 0
    assert all(g.ue != u for grants in src._ul.pipeline.values() for g in grants)
    assert dst.attach("agv-0", 210_000, held) == []
    v = dst.ue_ids.index("agv-0")
    assert dst._ul_buf[v].bytes == sum(p.size_bytes for p in held if p.direction == "ul")


def test_same_seed_same_handovers_and_outcomes() -> None:
    def trace(seed: int) -> list[tuple[int, int | None]]:
        cell = _hall(seed=seed)
        return [(o.packet.packet_id, o.deliver_us) for o in _run(cell, 3.0)]

    assert trace(5) == trace(5)


def test_a_scenario_with_agvs_runs_them_in_netsim() -> None:
    sets = ["loops=8", "hall.work_cells_per_row=8", "hall.work_cell_pitch_m=[10.0, 8.0]",
            "hall.inf_layout.gnb_count=4", "agvs.count=3"]
    sc = parse_scenario({}, sets)
    cell = make_cell(SimpleNamespace(scenario=sc, name="netsim"))  # type: ignore[arg-type]
    assert isinstance(cell, MultiCell) and cell.agv_ids == ["agv-0", "agv-1", "agv-2"]
    assert cell.has_pending()  # the AGVs' streams start at once
    out = _run(cell, 0.3)
    assert {o.packet.ue for o in out} >= {"agv-0", "agv-1", "agv-2"}
    with pytest.raises(ScenarioError, match="agvs.count"):
        parse_scenario({}, ["agvs.count=2"])  # one gNB: nothing to hand over between


def test_agv_streams_are_constant_rate_and_staggered() -> None:
    traffic = AgvTraffic(["agv-0", "agv-1"], 1.2, 0.096, 1500, 120)
    first = traffic.due(SLOT_US)
    assert {p.ue for p in first} == {"agv-0"}  # agv-1 starts half an interval later
    total = first + [p for s in range(2, 1001) for p in traffic.due(s * SLOT_US)]
    ul = [p for p in total if p.direction == "ul"]
    # 1.2 Mbit/s of 1500-byte packets: 100 a second per AGV.
    assert len([p for p in ul if p.ue == "agv-0"]) == 100
    assert len({p.packet_id for p in total}) == len(total) and max(p.packet_id for p in total) < 0
    assert all(p.enqueue_us % SLOT_US == 0 for p in total)
    assert np.isclose(len([p for p in total if p.direction == "dl"]) / 2, 100, atol=1)


def test_agvs_served_elsewhere_take_no_configured_grant_occasions() -> None:
    """Configured grants, an occasion every slot for each UE over half the carrier: three AGVs
    served by gNB 0 leave gNB 1's static UE every occasion of its own, as with no AGV at all."""
    cfg = NrConfig(los_mode="los", shadowing_enabled=False, fading="none", ul_access="configured_grant",
                   cg_period_slots=1, cg_prb=NrConfig().n_prb // 2)
    layout = InfLayout.explicit("SL", *HALL, [(30.0, 30.0, 1.5), (70.0, 30.0, 1.5)])
    ues = {"a": (28.0, 32.0, 1.5), "b": (72.0, 32.0, 1.5)}

    def delivered_to_b(agvs: int) -> tuple[int, list[list[int]]]:
        ids = [f"agv-{i}" for i in range(agvs)]
        kw = ({"fleet": Fleet([AgvRoute([(20.0, 30.0), (25.0, 30.0)], 0.5, 0.0, 1.5) for _ in ids]),
               "agv_traffic": AgvTraffic(ids, 0.1, 0.01, 1500, 120), "handover": HandoverParams()}
              if agvs else {})
        hall = MultiCell(cfg, layout, ues, seed=5, **kw)
        assert all(hall.serving_gnb_index[i] == 0 for i in ids)
        delivered = 0
        for s in range(400):
            hall.enqueue_many([Packet(6 * s + k, "b/video", "b", "ul", 1500, s * SLOT_US) for k in range(6)])
            delivered += sum(o.packet.ue == "b" and o.deliver_us is not None for o in hall.run_slot(s * SLOT_US))
        cell = hall.cell_of_gnb[1]
        return delivered, [cell._ul._cg_occasions(s) for s in range(4)]

    alone = delivered_to_b(0)
    assert alone[1] == [[0]] * 4 and alone[0] > 2000
    assert delivered_to_b(3) == alone
