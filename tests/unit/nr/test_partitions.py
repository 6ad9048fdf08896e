"""A hall split into partitions by gNB (netsim.nr.multicell ``own_gnbs``): each partition holds
its gNBs' cells, takes the others' transmissions of the slot before and decodes one slot late,
and together they decide every packet as the whole hall does, with the same transmissions."""

from __future__ import annotations

import pytest

from netsim.nr.layout import InfLayout
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


def _run(parts: list[MultiCell], ues: dict, slots: int
         ) -> tuple[list[tuple[int, int | None, str | None]], list[tuple]]:
    """Drive the partitions ``parts`` in lockstep, each given the others' transmissions of the
    slot before; every packet's fate and every transmission, sorted."""
    fates: list[tuple[int, int | None, str | None]] = []
    sent: list[tuple] = []
    remote: list[dict[str, list[Tx]]] = [{"dl": [], "ul": []} for _ in parts]
    pid = 0
    for s in range(slots):
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
        fates += [(o.packet.packet_id, o.deliver_us, o.cause) for o in outcomes]
        for part in parts:
            rec = part.transmissions() or {}
            sent += list(zip(*rec.values(), strict=True)) if rec else []
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
