"""A hall split into partitions by gNB (netsim.nr.multicell ``own_gnbs``): each partition holds
its gNBs' cells, takes the others' transmissions of the slot before and decodes one slot late,
and together they decide every packet as the whole hall does, with the same transmissions; AGVs
hand over between partitions, the packets held for them passed on a slot later."""

from __future__ import annotations

import pytest

from netsim.nr.agv_traffic import AgvTraffic
from netsim.nr.handover import HandoverParams
from netsim.nr.layout import InfLayout
from netsim.nr.mobility import AgvRoute, Fleet
from netsim.nr.multicell import MultiCell, Tx
from netsim.radio_cell import Packet, PacketOutcome
from netsim.standalone import camera_layout
from scenario.nr import NrConfig

HALL = (120.0, 60.0, 10.0)
N_GNB = 4


def _traffic(ues: dict, s: int, pid: int) -> list[Packet]:
    """Frames of 23 packets per camera every 33 slots up, pose-sized packets every 10 down."""
    t = s * 1000
    out = []
    for i, ue in enumerate(ues):
        if (s + 7 * i) % 33 == 0:
            out += [Packet(pid + len(out) + k, f"{ue}/video", ue, "ul", 1500, t)
                    for k in range(23)]
        if (s + 3 * i) % 10 == 0:
            out.append(Packet(pid + len(out), f"{ue}/pose", ue, "dl", 120, t))
    return out


def _run(parts: list[MultiCell], ues: dict, slots: int, handovers: list[tuple] | None = None
         ) -> tuple[list[tuple[int, int | None, str | None]], list[tuple]]:
    """Drive the partitions ``parts`` in lockstep, each given the others' transmissions of the
    slot before and the packets held for an AGV handing over into one of its gNBs; every
    packet's fate and every transmission, sorted (the handovers into ``handovers``)."""
    fates: list[tuple[int, int | None, str | None]] = []
    sent: list[tuple] = []
    remote: list[dict[str, list[Tx]]] = [{"dl": [], "ul": []} for _ in parts]
    held: list[tuple[int, str, int, list[Packet], dict]] = []
    pid = 0
    for s in range(slots):
        for gnb, ue, start_us, packets, fading in held:  # sent a slot ago, in before this slot
            next(p for p in parts if gnb in p.own).take_held(ue, start_us, packets, fading)
        packets = _traffic(ues, s, pid)
        pid += len(packets)
        outcomes: list[PacketOutcome] = []
        for part in parts:
            mine = [p for p in packets if p.ue in part.serving_gnb_index
                    and part.serving_gnb_index[p.ue] in part.cell_gnb]
            outcomes += part.enqueue_many(mine)
        for part, theirs in zip(parts, remote, strict=True):
            outcomes += part.run_slot(s * 1000, theirs)
        planned = [part.slot_transmissions() for part in parts]
        remote = [{link: [tx for j, other in enumerate(planned) if j != i for tx in other[link]]
                   for link in ("dl", "ul")} for i in range(len(parts))]
        held = [h for part in parts for h in part.held_out()]
        fates += [(o.packet.packet_id, o.deliver_us, o.cause) for o in outcomes]
        for part in parts:
            rec = part.transmissions() or {}
            sent += list(zip(*rec.values(), strict=True)) if rec else []
            if handovers is not None:
                rows = part.handovers() or {}
                handovers += list(zip(*rows.values(), strict=True)) if rows else []
    return sorted(fates, key=lambda f: f[0]), sorted(sent)


@pytest.mark.parametrize("reuse", [1, 3])
def test_partitions_by_gnb_decide_every_packet_as_the_whole_hall(reuse: int) -> None:
    layout = InfLayout.lattice("SL", *HALL, N_GNB, reuse=reuse)
    _, ues = camera_layout(N_GNB * 5)
    # The channel drawn (maps, shadowing, fading), so interference and its fading matter.
    cfg = NrConfig()

    def hall(own: list[int] | None) -> MultiCell:
        return MultiCell(cfg, layout, ues, 11, record=True, own_gnbs=own)

    whole = _run([hall(None)], ues, 400)
    split = _run([hall([0, 1]), hall([2, 3])], ues, 400)
    three = _run([hall([0]), hall([1, 3]), hall([2])], ues, 400)
    fates, sent = whole
    assert len(fates) > 3000 and len(sent) > 1000
    assert sum(f[1] is None for f in fates) < len(fates)
    assert split == whole
    assert three == whole


def test_a_partition_refuses_what_it_cannot_hold() -> None:
    layout = InfLayout.lattice("SL", *HALL, N_GNB)
    _, ues = camera_layout(8)
    with pytest.raises(ValueError, match="own_gnbs"):
        MultiCell(NrConfig(), layout, ues, 1, own_gnbs=[0, 7])


@pytest.mark.parametrize("forward", [True, False])
def test_agvs_hand_over_between_partitions_as_in_the_whole_hall(forward: bool) -> None:
    # Four gNBs 30 m apart on a line, the split putting gNBs 1 and 2 in different partitions; an
    # AGV driving along the hall, another shuttling across their boundary (ping-pongs: no L3
    # filtering, a short time to trigger).
    layout = InfLayout.explicit("SL", *HALL, [(15.0 + 30 * g, 30.0, 1.5) for g in range(N_GNB)])
    _, ues = camera_layout(N_GNB * 3)
    cfg = NrConfig()
    params = HandoverParams(filter_k=0, hysteresis_db=0.5, time_to_trigger_ms=40, interruption_ms=20.0,
                            forward=forward)

    def hall(own: list[int] | None) -> MultiCell:
        fleet = Fleet([AgvRoute([(20.0, 30.0), (100.0, 30.0)], 10.0, 30.0, 1.5),
                       AgvRoute([(52.0, 30.0), (68.0, 30.0)], 10.0, 0.0, 1.5)])
        traffic = AgvTraffic(["agv-0", "agv-1"], 8.0, 1.0, 1500, 120)
        return MultiCell(cfg, layout, ues, 3, record=True, fleet=fleet, agv_traffic=traffic,
                         handover=params, own_gnbs=own)

    whole_handovers: list[tuple] = []
    split_handovers: list[tuple] = []
    whole_hall, parts = [hall(None)], [hall([0, 1]), hall([2, 3])]
    whole = _run(whole_hall, ues, 2500, whole_handovers)
    split = _run(parts, ues, 2500, split_handovers)
    crossing = [h for h in whole_handovers if {h[1], h[2]} == {1, 2}]
    assert len(crossing) >= 2, whole_handovers  # across the partitions' boundary
    assert sum(h[5 if forward else 6] for h in crossing) > 0  # with packets held
    assert sorted(split_handovers) == sorted(whole_handovers)
    assert split == whole
    # Each partition counts what it decided, the handovers into its gNBs: they add up.
    hall_agvs = whole_hall[0].stats()["agvs"]
    assert hall_agvs["ping_pongs"] > 0
    for key in ("handovers", "handovers_completed", "ping_pongs", "forwarded_packets",
                "lost_packets_handover"):
        assert sum(p.stats()["agvs"][key] for p in parts) == hall_agvs[key], key


def test_a_partition_with_agvs_needs_a_handover_interruption() -> None:
    layout = InfLayout.lattice("SL", *HALL, N_GNB)
    _, ues = camera_layout(8)
    fleet = Fleet([AgvRoute([(20.0, 30.0), (100.0, 30.0)], 2.0)])
    with pytest.raises(ValueError, match="needs a handover interruption"):
        MultiCell(NrConfig(), layout, ues, 1, fleet=fleet, agv_traffic=AgvTraffic(["agv-0"], 1.0, 1.0, 1500, 120),
                  handover=HandoverParams(interruption_ms=0.0), own_gnbs=[0, 1])

