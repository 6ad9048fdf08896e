"""Several gNBs in one hall: InF layouts, per-link large scale, association, UL power control and
geometry SINR (netsim.nr.layout, large_scale, interference; InF additions of netsim.nr.channel)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from netsim.nr import interference as itf
from netsim.nr.channel import (
    INF_NLOS_SHADOWING_STD_DB,
    inf_los_probability,
    inf_pathloss_db,
    inf_sl_los_probability,
    inf_sl_pathloss_db,
)
from netsim.nr.large_scale import InfLinks
from netsim.nr.layout import (
    SUB_SCENARIOS,
    InfLayout,
    drop_ues,
    lattice_positions_m,
    layout_from_hall,
    reuse_groups,
)
from scenario.lattice import GNB_COUNTS, lattice_index, lattice_subset
from scenario.schema import INF_BS_HEIGHT_M, HallConfig, InfLayoutConfig

FC = 3.5e9


# --- layouts ---------------------------------------------------------------------------------

def test_sub_scenarios_are_table_7_8_7() -> None:
    for name, sub in SUB_SCENARIOS.items():
        assert sub.name == name
        # 18 BSs on a 6 x 3 lattice of spacing D, D/2 from the walls, fill the hall exactly.
        assert sub.hall_length_m == 6 * sub.bs_spacing_m
        assert sub.hall_width_m == 3 * sub.bs_spacing_m
        assert sub.bs_height_m == INF_BS_HEIGHT_M[name]  # the schema's copy stays equal
        assert sub.nlos_shadowing_std_db == INF_NLOS_SHADOWING_STD_DB[name]
    assert (SUB_SCENARIOS["SL"].hall_length_m, SUB_SCENARIOS["DL"].hall_length_m) == (120, 300)
    assert SUB_SCENARIOS["DH"].clutter_density == 0.6 and SUB_SCENARIOS["SH"].bs_height_m == 8


@pytest.mark.parametrize("name", ["SL", "DL"])
def test_lattice_is_d_spaced_half_a_spacing_from_the_walls(name: str) -> None:
    sub = SUB_SCENARIOS[name]
    d = sub.bs_spacing_m
    pos = lattice_positions_m(sub.hall_length_m, sub.hall_width_m, sub.bs_height_m)
    assert pos.shape == (18, 3)
    assert pos[0] == pytest.approx([d / 2, d / 2, sub.bs_height_m])
    assert pos[17] == pytest.approx([sub.hall_length_m - d / 2, sub.hall_width_m - d / 2,
                                     sub.bs_height_m])
    assert pos[lattice_index(4, 2)] == pytest.approx([4.5 * d, 2.5 * d, sub.bs_height_m])
    assert sorted(set(pos[:, 0])) == pytest.approx([d / 2 + i * d for i in range(6)])
    assert sorted(set(pos[:, 1])) == pytest.approx([d / 2 + i * d for i in range(3)])


def test_subsets_are_blocks_around_the_hall_centre() -> None:
    pos = lattice_positions_m(120, 60, 1.5)
    assert lattice_subset(18) == tuple(range(18))
    assert lattice_subset(1) == (8,)  # column 2, middle row: (50, 30)
    assert lattice_subset(2) == (8, 9)
    for n in GNB_COUNTS:
        subset = lattice_subset(n)
        assert len(subset) == len(set(subset)) == n
        centre = pos[list(subset), :2].mean(axis=0)
        # Symmetric about the centre (60, 30) for 2, 4, 6, 18; half a pitch towards x = 0 else.
        assert centre == pytest.approx([60.0 if n in (2, 4, 6, 18) else 50.0, 30.0])


@pytest.mark.parametrize("n", [0, 3, 5, 12, 19])
def test_other_subset_sizes_are_refused(n: int) -> None:
    with pytest.raises(ValueError, match=r"allowed 1, 2, 4, 6, 9, 18"):
        lattice_subset(n)


def test_explicit_positions_and_the_hall_setting() -> None:
    assert layout_from_hall(HallConfig()) is None  # today's single gNB
    six = layout_from_hall(HallConfig(inf_layout=InfLayoutConfig(gnb_count=6, sub_scenario="DH")))
    assert six is not None and six.n_gnb == 6
    assert six.gnb_ids == ("lattice-2", "lattice-3", "lattice-8", "lattice-9", "lattice-14",
                           "lattice-15")
    assert np.all(six.gnb_positions_m[:, 2] == 8.0)
    where = [(10.0, 20.0, 3.0), (100.0, 40.0, 3.0), (60.0, 5.0, 2.0)]
    explicit = layout_from_hall(HallConfig(inf_layout=InfLayoutConfig(
        gnb_positions_m=where, reuse=3, ul_p0_dbm=-80, ul_alpha=0.8)))
    assert explicit is not None
    assert explicit.gnb_positions_m.tolist() == [list(p) for p in where]
    assert explicit.gnb_ids == ("gnb-0", "gnb-1", "gnb-2")
    assert (explicit.reuse, explicit.ul_p0_dbm, explicit.ul_alpha) == (3, -80, 0.8)
    assert sorted(explicit.groups) == [0, 1, 2]


@pytest.mark.parametrize("count", GNB_COUNTS)
def test_the_halls_gnb_positions_are_the_layouts(count: int) -> None:
    hall = HallConfig(inf_layout=InfLayoutConfig(gnb_count=count, sub_scenario="SH"), length_m=300,
                      width_m=150)
    layout = layout_from_hall(hall)
    assert layout is not None and layout.gnb_positions_m.tolist() == [list(p) for p in hall.gnb_positions()]
    assert HallConfig().gnb_positions() == [HallConfig().gnb_position_m]


def test_work_cells_dealt_to_the_gnbs_stand_in_rows_around_each() -> None:
    hall = HallConfig(inf_layout=InfLayoutConfig(gnb_count=4), work_cells_per_row=3,
                      work_cell_pitch_m=(4.0, 5.0), work_cell_fill="gnbs")
    gnbs = [(x, y) for x, y, _ in hall.gnb_positions()]  # (30, 30), (50, 30), (70, 30), (90, 30)
    cells = hall.work_cell_origins(26)
    # Work cell i at gNB i mod 4, nearest first: the middle of the row above the gNB, then its
    # right and left, then the row below; the gNB stands in the aisle between the two rows.
    assert [cells[i] for i in (0, 4, 8, 12, 16, 20, 24)] == [
        (30.0, 32.5), (34.0, 32.5), (26.0, 32.5), (30.0, 27.5), (34.0, 27.5), (26.0, 27.5), (30.0, 37.5)]
    for i, (x, y) in enumerate(cells):
        gx, gy = gnbs[i % 4]
        assert abs(x - gx) <= 4.0 and 2.5 <= abs(y - gy) <= 7.5
    # The first loops take one work cell at each gNB, not the centre of the floor, and a work
    # cell stays where it is as loops are added.
    assert hall.work_cell_origins(4) == [(30.0, 32.5), (50.0, 32.5), (70.0, 32.5), (90.0, 32.5)]
    assert hall.work_cell_origins(10) == cells[:10]
    # `centre` (the default) keeps the one grid around gnb_position_m.
    assert HallConfig(work_cells_per_row=3).work_cell_origins(4) == [(52.0, 26.0), (60.0, 26.0),
                                                                      (68.0, 26.0), (52.0, 34.0)]


def test_drops_stay_in_the_hall_away_from_the_gnbs_and_repeat_with_the_seed() -> None:
    layout = InfLayout.calibration("SL")
    a = drop_ues(2000, 120, 60, np.random.default_rng(4), layout.gnb_positions_m)
    b = drop_ues(2000, 120, 60, np.random.default_rng(4), layout.gnb_positions_m)
    assert np.array_equal(a, b) and a.shape == (2000, 3)
    assert np.all((a[:, 0] >= 0) & (a[:, 0] <= 120) & (a[:, 1] >= 0) & (a[:, 1] <= 60))
    assert np.all(a[:, 2] == 1.5)
    d = np.hypot(a[:, None, 0] - layout.gnb_positions_m[None, :, 0],
                 a[:, None, 1] - layout.gnb_positions_m[None, :, 1])
    assert d.min() >= 1.0


# --- path loss and LOS probability (TR 38.901 Tables 7.4.1-1, 7.4.2-1) -----------------------

# By hand, f = 3.5 GHz (20 log10 f = 10.881, 19 log10 f = 10.337):
# LOS 31.84 + 21.5 log10 d + 10.337; NLOS SL 33 + 25.5 log10 d + 10.881, DL 18.6 + 35.7 log10 d
# + 10.881 (and at least SL), SH 32.4 + 23 log10 d + 10.881, DH 33.63 + 21.9 log10 d + 10.881.
@pytest.mark.parametrize(("d_m", "los", "sl", "dl", "sh", "dh"), [
    (1.0, 42.177, 43.881, 43.881, 43.281, 44.511),
    (10.0, 63.677, 69.381, 69.381, 66.281, 66.411),  # DL below SL here: the SL floor holds
    (30.0, 73.935, 81.548, 82.215, 77.255, 76.860),
    (100.0, 85.177, 94.881, 100.881, 89.281, 88.311)])
def test_pathloss_at_reference_distances(d_m: float, los: float, sl: float, dl: float, sh: float,
                                         dh: float) -> None:
    for name, nlos in (("SL", sl), ("DL", dl), ("SH", sh), ("DH", dh)):
        assert float(inf_pathloss_db(name, d_m, FC, True)) == pytest.approx(los, abs=1e-3)
        assert float(inf_pathloss_db(name, d_m, FC, False)) == pytest.approx(nlos, abs=1e-3)


def test_sl_pathloss_and_los_probability_equal_the_single_gnb_ones() -> None:
    d = np.array([0.5, 3.0, 17.0, 55.0, 130.0])
    for los in (True, False):
        assert np.array_equal(inf_pathloss_db("SL", d, FC, los), inf_sl_pathloss_db(d, FC, los))
    assert np.allclose(inf_los_probability("SL", d, 0.2, 10.0, 2.0, 1.5, 1.5),
                       inf_sl_los_probability(d, 0.2, 10.0))


def test_los_probability_of_every_sub_scenario() -> None:
    # P = (1 - r) ** (d / d_clutter x (h_c - h_UT) / (h_BS - h_UT)), the high-BS factor 1 if low.
    def p(name: str, d: float) -> float:
        s = SUB_SCENARIOS[name]
        return float(inf_los_probability(name, d, s.clutter_density, s.clutter_size_m,
                                         s.clutter_height_m, s.bs_height_m, 1.5))

    assert p("SL", 10) == pytest.approx(0.8)
    assert p("DL", 10) == pytest.approx(0.4**5)
    assert p("SH", 10) == pytest.approx(0.8 ** (1.0 * 0.5 / 6.5))
    assert p("DH", 10) == pytest.approx(0.4 ** (5 * 4.5 / 6.5))
    assert p("SH", 0) == 1.0
    with pytest.raises(ValueError, match="UT height < clutter height"):
        inf_los_probability("DH", 10.0, 0.6, 2.0, 6.0, 5.0, 1.5)  # BS below the clutter
    with pytest.raises(ValueError, match="not one of SL, DL, SH, DH"):
        inf_pathloss_db("HH", 10.0, FC, True)


# --- per-link large scale -------------------------------------------------------------------

def _ues(n: int, seed: int, layout: InfLayout) -> np.ndarray:
    return drop_ues(n, layout.hall_length_m, layout.hall_width_m, np.random.default_rng(seed),
                    layout.gnb_positions_m)


def test_links_are_arrays_per_pair_with_coupling_loss_from_their_parts() -> None:
    layout = InfLayout.calibration("SH")
    links = InfLinks(layout, _ues(50, 1, layout), FC, seed=3, gnb_antenna_gain_dbi=2.0,
                     ue_antenna_gain_dbi=1.0)
    for a in (links.d2d_m, links.los, links.pathloss_db, links.shadowing_db,
              links.coupling_loss_db):
        assert a.shape == (50, 18)
    assert np.allclose(links.coupling_loss_db,
                       links.pathloss_db + links.shadowing_db - 3.0)
    assert np.allclose(links.pathloss_db, inf_pathloss_db("SH", links.d3d_m, FC, links.los))
    assert np.all(links.d3d_m > 6.4)  # 8 m BS, 1.5 m UE


def test_forced_state_without_shadowing_is_the_path_loss() -> None:
    layout = InfLayout.calibration("DL")
    ue = _ues(20, 2, layout)
    for mode, los in (("los", True), ("nlos", False)):
        links = InfLinks(layout, ue, FC, seed=1, los_mode=mode, shadowing_enabled=False)
        assert np.all(links.los == los)
        assert np.array_equal(links.coupling_loss_db, inf_pathloss_db("DL", links.d3d_m, FC, los))


def test_same_seed_same_links_and_a_pair_does_not_depend_on_the_other_ues() -> None:
    layout = InfLayout.calibration("SL")
    ue = _ues(300, 5, layout)
    a = InfLinks(layout, ue, FC, seed=7)
    b = InfLinks(layout, ue, FC, seed=7)
    assert np.array_equal(a.coupling_loss_db, b.coupling_loss_db)
    assert np.array_equal(a.los, b.los)
    assert not np.array_equal(a.coupling_loss_db, InfLinks(layout, ue, FC, seed=8).coupling_loss_db)
    few = InfLinks(layout, ue[::7], FC, seed=7)
    assert np.array_equal(few.coupling_loss_db, a.coupling_loss_db[::7])
    # A lattice gNB keeps its maps in every subset: lattice point 8 is gNB 0 of the 1-gNB layout.
    one = InfLinks(InfLayout.lattice("SL", 120, 60, 10, count=1), ue, FC, seed=7)
    assert np.array_equal(one.coupling_loss_db[:, 0], a.coupling_loss_db[:, 8])


def test_los_share_follows_the_probability_and_one_map_cell_shares_its_state() -> None:
    layout = InfLayout.calibration("SL")
    links = InfLinks(layout, _ues(4000, 6, layout), FC, seed=2)
    assert links.los.mean() == pytest.approx(links.los_probability.mean(), abs=0.03)
    nlos = links.shadowing_db[~links.los]
    assert nlos.std() == pytest.approx(5.7, rel=0.15)
    # Two UEs in one 1 m cell of the maps share LOS states and shadowing.
    pair = InfLinks(layout, [[30.2, 20.1, 1.5], [30.4, 19.8, 1.5]], FC, seed=2)
    assert np.array_equal(pair.los[0], pair.los[1])
    assert np.array_equal(pair.shadowing_db[0], pair.shadowing_db[1])


def test_shadowing_is_correlated_over_10_m() -> None:
    layout = InfLayout.calibration("SL")
    ue = _ues(600, 9, layout)
    ue = ue[ue[:, 0] < 70]

    def shadowing(offset_m: float) -> np.ndarray:
        moved = ue + [offset_m, 0.0, 0.0]
        links = InfLinks(layout, np.vstack([ue, moved]), FC, seed=4, los_mode="nlos")
        return links.shadowing_db.reshape(2, len(ue), -1)

    near, far = shadowing(1.0), shadowing(40.0)
    corr = [np.corrcoef(s[0].ravel(), s[1].ravel())[0, 1] for s in (near, far)]
    assert corr[0] > 0.8  # exp(-1 / 10) = 0.90
    assert abs(corr[1]) < 0.2  # exp(-40 / 10) = 0.02


# --- association, power control, geometry SINR ---------------------------------------------

def test_association_picks_the_strongest_rsrp() -> None:
    cl = np.array([[70.0, 60.0, 80.0], [55.0, 65.0, 50.0], [60.0, 60.0, 90.0]])
    assert itf.serving_gnb(cl).tolist() == [1, 2, 0]  # the tie goes to the lower index
    # A gNB sending 15 dB more reference-signal power wins UE 0 despite 10 dB more loss.
    assert itf.serving_gnb(cl, np.array([15.0, 0.0, 0.0])).tolist() == [0, 0, 0]
    assert itf.serving_values(cl, np.array([1, 2, 0])).tolist() == [60.0, 50.0, 60.0]


def test_ul_power_control_follows_ts38213_and_caps_at_p_cmax() -> None:
    pl = np.array([40.0, 60.0, 80.0, 120.0])
    p = itf.ul_power_dbm(pl, n_prb=100, p0_dbm=-90.0, alpha=1.0)
    assert p[:3] == pytest.approx(-90 + 20 + pl[:3])  # 10 log10(100) = 20
    assert p[3] == 23.0  # -90 + 20 + 120 = 50 > P_CMAX
    assert np.all(itf.ul_power_dbm(pl, 100, -90.0, 1.0, p_cmax_dbm=10.0) <= 10.0)
    assert itf.ul_power_dbm(pl, 100, -60.0, 0.0) == pytest.approx([-40.0] * 4)  # no compensation
    assert itf.ul_power_dbm(60.0, 10, -100.0, 0.8, numerology=1) == pytest.approx(
        -100 + 10 * math.log10(20) + 48)


def _noise_mw(nf_db: float, bandwidth_hz: float) -> float:
    return 10 ** ((-174 + nf_db + 10 * math.log10(bandwidth_hz)) / 10)


def test_dl_sinr_counts_every_other_gnb_and_reuse_3_removes_the_other_groups() -> None:
    cl = np.array([[60.0, 70.0, 75.0, 80.0]])
    serving = np.array([0])
    mw = 10 ** ((30.0 - cl[0]) / 10)
    reuse1 = itf.dl_geometry_sinr_db(cl, serving, 30.0, np.zeros(4, int), 100e6, 9.0)
    assert reuse1[0] == pytest.approx(
        10 * math.log10(mw[0] / (mw[1:].sum() + _noise_mw(9.0, 100e6))))
    groups = np.array([0, 1, 2, 0])
    reuse3 = itf.dl_geometry_sinr_db(cl, serving, 30.0, groups, 100e6, 9.0, reuse=3)
    assert reuse3[0] == pytest.approx(10 * math.log10(mw[0] / (mw[3] + _noise_mw(9.0, 100e6 / 3))))
    alone = itf.dl_geometry_sinr_db(cl, serving, 30.0, np.array([0, 1, 2, 1]), 100e6, 9.0, 3)
    assert alone[0] == pytest.approx(10 * math.log10(mw[0] / _noise_mw(9.0, 100e6 / 3)))


def test_reuse_3_on_the_lattice() -> None:
    sub = SUB_SCENARIOS["SL"]
    pos = lattice_positions_m(120, 60, 1.5)
    groups = reuse_groups(pos, 3)
    for k, g in enumerate(groups):
        assert g == (k % 6 - k // 6) % 3  # (column - row) mod 3
    assert np.bincount(groups).tolist() == [6, 6, 6]
    co = [math.dist(pos[i, :2], pos[j, :2]) for i in range(18) for j in range(i)
          if groups[i] == groups[j]]
    assert min(co) == pytest.approx(math.sqrt(2) * sub.bs_spacing_m)
    assert reuse_groups(pos, 1).tolist() == [0] * 18
    with pytest.raises(ValueError, match="reuse 2"):
        reuse_groups(pos, 2)


def test_ul_sinr_one_co_scheduled_ue_per_other_cell_at_its_power() -> None:
    # UE 0 and 1 in cell 0, UE 2 in cell 1, UE 3 in cell 2 (another reuse-3 group).
    cl = np.array([[60.0, 80.0, 85.0], [65.0, 90.0, 70.0], [75.0, 62.0, 90.0], [90.0, 95.0, 58.0]])
    serving = itf.serving_gnb(cl)
    assert serving.tolist() == [0, 0, 1, 2]
    power = itf.ul_power_dbm(itf.serving_values(cl, serving), 50, -90.0, 1.0)
    co = itf.co_scheduled_ues(serving, 3, np.random.default_rng(1))
    assert co[2].tolist() in ([0, -1, 3], [1, -1, 3]) and co[3, 1] == 2 and co[0, 0] == -1
    noise = _noise_mw(5.0, 50 * 180e3)
    sinr = itf.ul_geometry_sinr_db(cl, serving, power, np.zeros(3, int), 50, 180e3, 5.0, co)
    rx = lambda u, b: 10 ** ((power[u] - cl[u, b]) / 10)  # noqa: E731
    assert sinr[2] == pytest.approx(
        10 * math.log10(rx(2, 1) / (rx(co[2, 0], 1) + rx(3, 1) + noise)))
    sinr3 = itf.ul_geometry_sinr_db(cl, serving, power, np.array([0, 0, 1]), 50, 180e3, 5.0, co)
    assert sinr3[2] == pytest.approx(10 * math.log10(rx(2, 1) / (rx(co[2, 0], 1) + noise)))
    assert sinr3[3] == pytest.approx(10 * math.log10(rx(3, 2) / noise))  # alone in its group


def test_geometry_is_deterministic_for_a_seed() -> None:
    def run(seed: int) -> np.ndarray:
        layout = InfLayout.calibration("DH", reuse=3)
        links = InfLinks(layout, _ues(400, seed, layout), FC, seed=seed)
        serving = itf.serving_gnb(links.coupling_loss_db)
        power = itf.ul_power_dbm(itf.serving_values(links.coupling_loss_db, serving), 156, -90, 1)
        co = itf.co_scheduled_ues(serving, 18, np.random.default_rng(seed))
        return np.concatenate([
            itf.dl_geometry_sinr_db(links.coupling_loss_db, serving, 30.0, layout.groups, 100e6,
                                    9.0, 3),
            itf.ul_geometry_sinr_db(links.coupling_loss_db, serving, power, layout.groups, 156,
                                    180e3, 5.0, co)])

    assert np.array_equal(run(11), run(11))
    assert not np.array_equal(run(11), run(12))
