"""Several NR cells in one hall (netsim.nr.multicell, gnb_cell, sinr, link_fading): interference
only between co-channel transmissions on shared PRBs in the same slot, reuse 3, geometry, UL power
control, determinism and the one-gNB case against the single cell."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from netsim.federate import make_cell
from netsim.nr import interference as itf
from netsim.nr.layout import InfLayout
from netsim.nr.link_fading import LinkFading
from netsim.nr.multicell import MultiCell
from netsim.nr.phy import eesm
from netsim.nr.radio_cell import NrCell
from netsim.nr.sinr import slot_sinr
from netsim.radio_cell import Packet, PacketOutcome
from netsim.standalone import camera_layout
from scenario.nr import NrConfig
from scenario.schema import parse_scenario

HALL = (120.0, 60.0, 10.0)


def _flat_fading(n_links: int) -> LinkFading:
    return LinkFading([f"u{i}" for i in range(n_links)], ["g"], np.ones((n_links, 1), bool), 24,
                      NrConfig(fading="none"), 0, "t", np.ones((n_links, 1), bool))


def _sinr(p0: list[int], n: list[int], cross: list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    t = len(p0)
    return slot_sinr(np.array(p0), np.array(n), np.full(t, 100.0), np.full(t, 5.0),
                     np.arange(t), np.array(cross), np.zeros((t, t), dtype=np.int64),
                     _flat_fading(t), 0, 20)


def test_interference_counts_only_the_prbs_both_transmissions_use() -> None:
    # A on PRBs 0-99, B on 50-149: half of A's PRBs and half of B's meet the other.
    eff, inr = _sinr([0, 50], [100, 100], [[0.0, 4.0], [9.0, 0.0]])
    assert inr == pytest.approx([4.0 * 50 / 100, 9.0 * 50 / 100])
    # EESM of SINR 100 on 50 PRBs and 100 / 5 on the other 50 (beta 5).
    expect = 20.0 - 5.0 * math.log((50 * math.exp(-(100.0 - 20.0) / 5.0) + 50) / 100)
    assert eff[0] == pytest.approx(expect)
    # Side by side (B from PRB 100): no interference at all, the SINR is the SNR.
    eff, inr = _sinr([0, 100], [100, 100], [[0.0, 4.0], [9.0, 0.0]])
    assert inr.tolist() == [0.0, 0.0] and eff.tolist() == [100.0, 100.0]
    # Zero coupling (the same cell, another frequency group): none either.
    eff, inr = _sinr([0, 0], [100, 100], [[0.0, 0.0], [0.0, 0.0]])
    assert eff.tolist() == [100.0, 100.0]


class _SubbandGains:
    """What ``slot_sinr`` reads of the fading: a gain per link and subband, brought up to date."""

    def __init__(self, gain: np.ndarray) -> None:
        self.gain = gain

    def refresh(self, links: np.ndarray, update: int) -> None:
        pass


def test_each_prb_takes_its_own_subbands_gain_when_the_first_subbands_are_unused() -> None:
    # 156 PRBs in subbands of 20 (8 subbands), two transmissions on PRBs 20-89 and 90-155: the
    # segments are as many as the subbands, but start at the second one.
    gain = np.array([[10.0 ** (k - 4) for k in range(8)], [10.0 ** (4 - k) for k in range(8)]], np.float32)
    p0, n = np.array([20, 90]), np.array([70, 66])
    eff, _ = slot_sinr(p0, n, np.ones(2), np.full(2, 1.5), np.arange(2), np.zeros((2, 2)),
                       np.zeros((2, 2), dtype=np.int64), _SubbandGains(gain), 0, 20)  # type: ignore[arg-type]
    for i in range(2):
        prbs = np.arange(p0[i], p0[i] + n[i])
        assert eff[i] == pytest.approx(eesm(gain[i, prbs // 20].astype(float), 1.5), rel=1e-12)


def _flat(**kw: object) -> NrConfig:
    return NrConfig(los_mode="los", shadowing_enabled=False, fading="none", pdcch_miss_prob=0.0,
                    ack_miss_prob=0.0, nack_to_ack_prob=0.0, **kw)  # type: ignore[arg-type]


def _two_cells(reuse: int = 1, ue_b_x: float = 85.0) -> MultiCell:
    layout = InfLayout.explicit("SL", *HALL, [(30.0, 30.0, 1.5), (60.0, 30.0, 1.5),
                                              (90.0, 30.0, 1.5)], reuse=reuse)
    ues = {"a": (35.0, 30.0, 1.5), "c": (60.0, 35.0, 1.5), "b": (ue_b_x, 30.0, 1.5)}
    return MultiCell(_flat(), layout, ues, seed=3, record=True)


def _send(cell: MultiCell, ue: str, t_us: int, pid: int, direction: str = "ul") -> None:
    cell.enqueue_many([Packet(pid + k, ue, ue, direction, 1500, t_us) for k in range(4)])  # type: ignore[arg-type]


def _run(cell: MultiCell, slots: range, sends: dict[int, list[str]] | None = None,
         direction: str = "ul") -> dict[str, list]:
    """Run ``slots`` and the one after (the hall decodes a slot one slot late), the UEs of
    ``sends[slot]`` each handing 4 packets to its modem then; the transmissions of ``slots``."""
    rec: dict[str, list] = {}
    pid = 0
    for s in [*slots, slots[-1] + 1]:
        for ue in (sends or {}).get(s, []):
            _send(cell, ue, s * 1000, pid, direction)
            pid += 10
        cell.run_slot(s * 1000)
        for k, v in (cell.transmissions() or {}).items():
            rec.setdefault(k, []).extend(v)
    return rec


def _ul_snr_db(cell: MultiCell, ue: str, n_prb: int) -> float:
    gnb = cell.serving_gnb_index[ue]
    k = cell.cell_gnb.index(gnb)
    local = cell.cells[k].ue_ids.index(ue)
    return 10 * math.log10(cell.cells[k].csi.ul_scale(local, n_prb))


def test_two_co_channel_cells_interfere_only_in_the_slots_they_share() -> None:
    cell = _two_cells()
    assert [cell.serving_gnb_index[u] for u in ("a", "c", "b")] == [0, 1, 2]
    # a alone, then a and b in the same slots (from PRB 0 both).
    rec = _run(cell, range(40), {0: ["a"], 20: ["a", "b"]})
    rows = list(zip(rec["t_us"], rec["ue"], rec["n_prb"], rec["sinr_db"], strict=True))
    alone = [r for r in rows if r[1] == "a" and r[0] < 20_000]
    shared = [r for r in rows if r[1] == "a" and r[0] >= 20_000]
    assert alone and shared
    for _, ue, n, sinr in alone:
        assert sinr == pytest.approx(_ul_snr_db(cell, ue, n), abs=1e-9)
    b_slots = {t for t, ue, _, _ in rows if ue == "b"}
    for t, ue, n, sinr in shared:
        if t in b_slots:
            assert sinr < _ul_snr_db(cell, ue, n) - 0.01
        else:
            assert sinr == pytest.approx(_ul_snr_db(cell, ue, n), abs=1e-9)
    assert any(t in b_slots for t, *_ in shared)


def test_reuse_3_cells_do_not_interfere() -> None:
    cell = _two_cells(reuse=3)
    assert len(set(cell.layout.groups.tolist())) == 3
    rec = _run(cell, range(20), {0: ["a", "b", "c"]})
    assert len(set(rec["gnb"])) == 3 and set(rec["cell_prb"]) == {468 // 3}
    for ue, n, sinr in zip(rec["ue"], rec["n_prb"], rec["sinr_db"], strict=True):
        assert sinr == pytest.approx(_ul_snr_db(cell, ue, n), abs=1e-9)


def test_a_ue_far_from_the_interferer_sees_a_higher_sinr() -> None:
    # b 5 m from its gNB (x = 90) either way, while gNB 0 and 1 (x = 30, 60) send to a and c in
    # the same slot: at x = 95 it is 10 m farther from gNB 1 than at x = 85.
    sinr = {}
    for x in (85.0, 95.0):
        cell = _two_cells(ue_b_x=x)
        rec = _run(cell, range(1), {0: ["a", "c", "b"]}, "dl")
        assert rec["ue"] == ["a", "c", "b"]  # one PDSCH each, in slot 0, all from PRB 0
        sinr[x] = rec["sinr_db"][2]
    # Interference-limited: about 21.5 log10(35 / 25) = 3.1 dB apart (LOS path loss slope).
    assert sinr[95.0] > sinr[85.0] + 2.0


def test_ul_power_control_follows_ts38213_and_caps_at_p_cmax() -> None:
    cfg = _flat()
    for p0, alpha in ((-90.0, 1.0), (-60.0, 0.8), (10.0, 1.0)):
        layout = InfLayout.explicit("SL", *HALL, [(30.0, 30.0, 1.5)], ul_p0_dbm=p0, ul_alpha=alpha)
        cell = MultiCell(cfg, layout, {"near": (32.0, 30.0, 1.5), "far": (110.0, 55.0, 1.5)}, 1)
        noise_dbm = -174 + 10 * math.log10(180e3) + cfg.gnb_noise_figure_db
        for ue in ("near", "far"):
            cl = float(cell.links.coupling_loss_db[cell.ue_ids.index(ue), 0])
            for n in (1, 20, 468):
                power = float(itf.ul_power_dbm(cl, n, p0, alpha, p_cmax_dbm=cfg.ue_tx_power_dbm))
                assert power <= cfg.ue_tx_power_dbm
                expect = power - 10 * math.log10(n) - cl - noise_dbm
                assert _ul_snr_db(cell, ue, n) == pytest.approx(expect, abs=1e-9)
    # P0 10 dBm per PRB: every allocation at P_CMAX, the single cell's full power.
    assert _ul_snr_db(cell, "far", 468) == pytest.approx(
        cfg.ue_tx_power_dbm - 10 * math.log10(468) - float(cell.links.coupling_loss_db[1, 0])
        - noise_dbm, abs=1e-9)


def _drive(cell: NrCell | MultiCell, ues: dict, slots: int) -> list[tuple[int, int | None, str | None]]:
    """Frames of 23 packets per UE every 33 slots up, 120-byte packets every 10 slots down."""
    out: list[tuple[int, int | None, str | None]] = []

    def keep(outcomes: list[PacketOutcome]) -> None:
        out.extend((o.packet.packet_id, o.deliver_us, o.cause) for o in outcomes)

    pid = 0
    for s in range(slots):
        t = s * 1000
        pk = []
        for i, ue in enumerate(ues):
            if (s + 7 * i) % 33 == 0:
                pk += [Packet(pid + k, ue, ue, "ul", 1500, t) for k in range(23)]
                pid += 23
            if (s + 3 * i) % 10 == 0:
                pk.append(Packet(pid, "d" + ue, ue, "dl", 120, t))
                pid += 1
        keep(cell.enqueue_many(pk))
        keep(cell.run_slot(t))
    return out


def _hall(n_gnb: int, seed: int, per_gnb: int = 4) -> tuple[MultiCell, dict]:
    layout = InfLayout.lattice("SL", *HALL, n_gnb)
    _, ues = camera_layout(n_gnb * per_gnb)
    return MultiCell(NrConfig(), layout, ues, seed, record=True), ues


def test_same_seed_same_outcomes_and_another_seed_others() -> None:
    runs = []
    for seed in (7, 7, 8):
        cell, ues = _hall(4, seed)
        runs.append((_drive(cell, ues, 300), cell.transmissions()))
    assert runs[0] == runs[1]
    assert runs[0][0] != runs[2][0]
    sent = runs[0][1]
    assert sent is not None and len(sent["t_us"]) > 100 and set(sent["gnb"]) == {0, 1, 2, 3}


def test_one_gnb_is_the_single_cell_when_the_radio_is_the_same() -> None:
    """The same gNB, a deterministic radio (forced LOS, no shadowing, no fading, no control
    errors) and P0 at P_CMAX (the single cell's full power): the multi-cell path, its streams
    named under the gNB's id, decides every packet as NrCell does, in the same order, and
    delivers it one slot later (it decodes a slot one slot late)."""
    cfg = _flat()
    gnb, ues = camera_layout(12, cfg)
    single = NrCell(cfg, gnb, ues, 5, stream_prefix="netsim/nr/gnb-0")
    layout = InfLayout.explicit("SL", *HALL, [gnb], ul_p0_dbm=24.0)
    multi = MultiCell(cfg, layout, ues, 5)
    alone = _drive(single, ues, 600)
    late = _drive(multi, ues, 601)
    decided = [(p, t, cause) for p, t, cause in alone if t is None or t < 600_000]
    assert late[:len(decided)] == [(p, None if t is None else t + 1000, cause)
                                   for p, t, cause in decided]
    assert len(decided) > 5000
    assert single.stats()["ul"]["delivered_bytes"] == multi.stats()["ul"]["delivered_bytes"]


def test_one_gnb_with_fading_and_power_control_stays_close_to_the_single_cell() -> None:
    """With the InF-SL channel drawn (its own maps and fading streams) and P0 -90 dBm, alpha 1,
    one gNB delivers what the single cell delivers below capacity, and over capacity (24
    cameras, 200 Mbit/s) a few percent less: power control lowers the SNR, so the MCS."""
    cfg = NrConfig()
    # 0.2 %: below capacity the hall's last slot is still to be decoded (one slot late).
    for n, rel in ((12, 0.002), (24, 0.08)):
        gnb, ues = camera_layout(n, cfg)
        layout = InfLayout.explicit("SL", *HALL, [gnb])
        single, multi = NrCell(cfg, gnb, ues, 2), MultiCell(cfg, layout, ues, 2)
        delivered = {}
        for name, cell in (("single", single), ("multi", multi)):
            _drive(cell, ues, 1500)
            delivered[name] = cell.stats()["ul"]["delivered_bytes"]
        assert delivered["multi"] == pytest.approx(delivered["single"], rel=rel)
        assert delivered["multi"] <= delivered["single"]


def test_association_stats_and_records_per_gnb() -> None:
    cell, ues = _hall(4, 1)
    expect = itf.serving_gnb(cell.links.coupling_loss_db)
    assert [cell.serving_gnb_index[u] for u in ues] == expect.tolist()
    _drive(cell, ues, 200)
    st = cell.stats()
    assert st["gnbs"] == len(cell.cells) == len(set(expect.tolist()))
    for g in set(expect.tolist()):
        assert 0 < st[f"gnb{g}"]["ul"]["prb_utilisation"] <= 1
    assert st["ul"]["sinr_db_p5"] <= st["ul"]["sinr_db_p50"] <= st["ul"]["sinr_db_p95"]
    rec = cell.transmissions()
    assert rec is not None and set(rec) == {"t_us", "gnb", "dir", "ue", "n_prb", "cell_prb", "mcs",
                                            "tx", "sinr_db", "ok"}
    with pytest.raises(ValueError, match="unknown UE"):
        cell.enqueue(Packet(0, "x", "nobody", "ul", 100, 0))


def test_a_scenario_with_an_inf_layout_runs_the_cells_of_its_gnbs() -> None:
    sets = ["loops=8", "hall.work_cells_per_row=8", "hall.work_cell_pitch_m=[10.0, 8.0]"]
    single = make_cell(SimpleNamespace(scenario=parse_scenario({}, sets), name="netsim"))  # type: ignore[arg-type]
    assert isinstance(single, NrCell) and single.serving() is None
    sc = parse_scenario({}, [*sets, "hall.inf_layout.gnb_count=4"])
    multi = make_cell(SimpleNamespace(scenario=sc, name="netsim"))  # type: ignore[arg-type]
    assert isinstance(multi, MultiCell) and multi.record
    served = multi.serving()
    assert served is not None and set(served) == set(sc.ue_positions_m())
    assert set(served.values()) <= {0, 1, 2, 3} and len(set(served.values())) > 1
