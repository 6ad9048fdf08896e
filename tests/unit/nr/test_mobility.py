"""AGVs as moving radios: routes as a pure function of time, the vectorised fleet, aisle loops,
the scenario's routes, and the large scale read at moving positions (netsim.nr.mobility,
netsim.nr.large_scale.InfMaps)."""

from __future__ import annotations

import numpy as np
import pytest

from netsim.nr.large_scale import InfLinks, InfMaps
from netsim.nr.layout import InfLayout
from netsim.nr.mobility import AgvRoute, Fleet, agv_ids, agv_routes, aisle_loops
from scenario.schema import HallConfig, Scenario, parse_scenario

SQUARE = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]  # 40 m a lap
S = 1_000_000  # us


# --- one route -------------------------------------------------------------------------------

@pytest.mark.parametrize(("t_s", "xy"), [
    (0.0, (0, 0)), (2.5, (5, 0)), (5.0, (10, 0)), (7.5, (10, 5)), (10.0, (10, 10)),
    (12.5, (5, 10)), (17.5, (0, 5)), (19.999999, (0, 0.000002)),
])
def test_position_follows_the_waypoints_at_known_times(t_s: float, xy: tuple[float, float]
                                                       ) -> None:
    route = AgvRoute(SQUARE, 2.0)
    assert route.length_m == 40.0 and route.lap_us == 20 * S
    assert route.position_m(round(t_s * S)) == pytest.approx([*xy, 1.5], abs=1e-9)


def test_the_route_loops_and_the_start_offset_shifts_it_along() -> None:
    route = AgvRoute(SQUARE, 2.0)
    for t in (0, 1_234_567, 13 * S):
        for laps in (1, 2, 7, 1000):
            assert route.position_m(t + laps * 20 * S) == pytest.approx(route.position_m(t))
    ahead = AgvRoute(SQUARE, 2.0, start_offset_m=5.0)
    for t in (0, 3 * S, 19 * S):
        assert ahead.position_m(t) == pytest.approx(route.position_m(t + 2_500_000))
    # Two points: back and forth between them.
    shuttle = AgvRoute([(20, 30), (80, 30)], 1.0, height_m=2.0)
    assert shuttle.position_m(30 * S) == pytest.approx([50, 30, 2.0])
    assert shuttle.position_m(90 * S) == pytest.approx([50, 30, 2.0])
    assert shuttle.position_m(70 * S) == pytest.approx([70, 30, 2.0])


def test_the_position_is_a_pure_function_of_time() -> None:
    route = AgvRoute(SQUARE, 1.5, 3.0)
    late = route.position_m(77 * S)
    route.position_m(3 * S)
    assert route.position_m(77 * S) == pytest.approx(late)
    assert np.array_equal(route.position_m(77 * S), AgvRoute(SQUARE, 1.5, 3.0).position_m(77 * S))


def test_repeated_points_are_dropped_and_a_route_needs_two_points_and_a_speed() -> None:
    route = AgvRoute([(0, 0), (0, 0), (10, 0), (10, 0), (0, 0)], 1.0)
    assert route.waypoints_m.tolist() == [[0, 0], [10, 0]] and route.length_m == 20
    with pytest.raises(ValueError, match="two different waypoints"):
        AgvRoute([(5, 5), (5, 5)], 1.0)
    with pytest.raises(ValueError, match="positive"):
        AgvRoute(SQUARE, 0.0)


# --- many routes -----------------------------------------------------------------------------

def test_the_fleet_gives_every_route_its_own_position() -> None:
    gen = np.random.default_rng(3)
    routes = [AgvRoute(gen.uniform(0, 100, size=(int(gen.integers(2, 9)), 2)),
                       float(gen.uniform(0.5, 2.0)), float(gen.uniform(0, 50)),
                       float(gen.uniform(1, 2)))
              for _ in range(12)]
    fleet = Fleet(routes)
    assert len(fleet) == 12
    for t in [0, 1, 999_999, 17 * S, 3_600 * S + 123, 86_400 * S, *gen.integers(0, 10**10, 20)]:
        got = fleet.positions_m(int(t))
        assert got.shape == (12, 3)
        want = np.array([r.position_m(int(t)) for r in routes])
        assert got == pytest.approx(want, abs=1e-9)
    assert Fleet([]).positions_m(5 * S).shape == (0, 3)


# --- aisles and the scenario's routes --------------------------------------------------------

def test_aisle_loops_drive_around_each_row_of_work_cells() -> None:
    hall = HallConfig()  # work cells centred on (60, 30), 8 per row, 8 m pitch
    loops = aisle_loops(hall, 16)
    assert len(loops) == 2  # two rows, y = 26 and 34
    assert loops[0].tolist() == [[28, 22], [92, 22], [92, 30], [28, 30]]
    assert loops[1].tolist() == [[28, 30], [92, 30], [92, 38], [28, 38]]
    cells = np.array(hall.work_cell_origins(16))
    for loop in loops:  # every work cell of the loop's row lies inside it, half a pitch in
        row = cells[np.isclose(cells[:, 1], loop[:, 1].mean())]
        assert len(row) == 8
        assert np.all((row[:, 0] - loop[0, 0] >= 4) & (loop[1, 0] - row[:, 0] >= 4))


def test_aisle_loops_are_clipped_to_the_floor() -> None:
    hall = HallConfig(length_m=30, width_m=10, gnb_position_m=(15, 5, 1.5),
                      work_cell_pitch_m=(8, 12), work_cells_per_row=4)
    (loop,) = aisle_loops(hall, 3)
    assert loop.min() >= 0 and loop[:, 0].max() <= 30 and loop[:, 1].max() <= 10
    assert loop.tolist() == [[3, 0], [27, 0], [27, 10], [3, 10]]


def with_agvs(sc: Scenario, count: int) -> Scenario:
    """``sc`` with ``count`` AGVs, past the check that refuses them while no run drives them."""
    return sc.model_copy(update={"agvs": sc.agvs.model_copy(update={"count": count})})


def test_scenario_routes_share_the_aisle_loops_or_the_given_route() -> None:
    layout = {"inf_layout": {"gnb_count": 6}}
    sc = with_agvs(parse_scenario({"loops": 16, "hall": layout, "agvs": {"speed_m_s": 1.5}}), 3)
    routes = agv_routes(sc)
    assert len(routes) == 3 and agv_ids(3) == ["agv-0", "agv-1", "agv-2"]
    assert all(r.speed_m_s == 1.5 and r.height_m == sc.hall.ue_height_m for r in routes)
    loops = aisle_loops(sc.hall, 16)
    assert np.array_equal(routes[0].waypoints_m, loops[0])
    assert np.array_equal(routes[1].waypoints_m, loops[1])
    assert np.array_equal(routes[2].waypoints_m, loops[0])
    # The two AGVs of loop 0 start half a lap apart; the one of loop 1 at its start.
    assert (routes[0].start_offset_m, routes[1].start_offset_m) == (0.0, 0.0)
    assert routes[2].start_offset_m == pytest.approx(routes[0].length_m / 2)

    given = with_agvs(parse_scenario({"hall": layout, "agvs": {
        "waypoints_m": [[10, 10], [110, 10], [110, 50], [10, 50]]}}), 4)
    routes = agv_routes(given)
    assert [r.start_offset_m for r in routes] == [0.0, 70.0, 140.0, 210.0]
    assert all(r.waypoints_m.tolist() == [[10, 10], [110, 10], [110, 50], [10, 50]]
               for r in routes)
    assert agv_routes(parse_scenario({})) == []


# --- large scale at moving positions ---------------------------------------------------------

@pytest.mark.parametrize(("los_mode", "shadowing"), [
    ("stochastic", True), ("los", True), ("nlos", True), ("stochastic", False)])
def test_maps_read_at_any_positions_equal_the_static_links(los_mode: str, shadowing: bool
                                                           ) -> None:
    layout = InfLayout.lattice("SL", 120, 60, 10, 6)
    maps = InfMaps(layout, 3.5e9, seed=11, los_mode=los_mode, shadowing_enabled=shadowing)
    pos = np.array([[0.2, 0.3, 1.5], [50.4, 29.6, 1.5], [71.0, 10.2, 2.0], [119.8, 59.9, 1.5]])
    static = InfLinks(layout, pos, 3.5e9, seed=11, los_mode=los_mode,
                      shadowing_enabled=shadowing)
    moving = maps.links(pos)
    for name in ("d2d_m", "d3d_m", "los_probability", "los", "pathloss_db", "shadowing_db",
                 "coupling_loss_db"):
        assert np.array_equal(getattr(moving, name), getattr(static, name)), name
    assert maps.coupling_loss_db(np.empty((0, 3))).shape == (0, 6)


def test_an_agv_sees_at_each_position_what_a_static_ue_there_sees() -> None:
    """Spatially consistent: the AGV's links at time t are those of a UE standing where the
    AGV is, whatever other UEs exist; links change little over a short drive."""
    layout = InfLayout.lattice("DH", 120, 60, 10, 18)
    maps = InfMaps(layout, 3.5e9, seed=5)
    fleet = Fleet([AgvRoute(SQUARE, 1.0, 0.0), AgvRoute([(20, 20), (100, 40)], 2.0, 7.0)])
    for t in (0, 4 * S, 31_415_926):
        pos = fleet.positions_m(t)
        got = maps.coupling_loss_db(pos)
        for i in range(len(pos)):
            alone = InfLinks(layout, pos[i:i + 1], 3.5e9, seed=5).coupling_loss_db[0]
            assert np.array_equal(got[i], alone)
    # 20 cm further the AGV is on the same map cell or the next: the path loss barely moves.
    a, b = maps.links(fleet.positions_m(0)), maps.links(fleet.positions_m(200_000))
    assert np.all(np.abs(a.pathloss_db - b.pathloss_db)[~(a.los ^ b.los)] < 0.5)
