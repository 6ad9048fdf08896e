"""Handover of moving UEs (netsim.nr.handover): the layer-3 filter, event A3 and its time to
trigger, hysteresis against ping-pong, an AGV driving from one gNB to another, and the packets
held during the interruption, forwarded or lost. The cells are stand-ins with the interface the
NR cell provides (``CellQueues``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from netsim.nr.handover import (
    L1_MEASUREMENT_PERIOD_MS,
    HandoverControl,
    HandoverParams,
    L3Filter,
    filter_weight,
    ping_pongs,
)
from netsim.nr.large_scale import InfMaps
from netsim.nr.layout import InfLayout
from netsim.nr.mobility import AgvRoute, Fleet
from scenario.schema import TIME_TO_TRIGGER_MS, parse_scenario

MS = 1000  # us
S = 1_000_000  # us
TX_DBM = 23.0


class StandInCell:
    """A radio cell reduced to what the handover control uses: per-UE queues of packets."""

    def __init__(self) -> None:
        self.queues: dict[str, list[Any]] = {}
        self.log: list[tuple[str, str, int]] = []

    def detach(self, ue: str, t_us: int) -> list[Any]:
        self.log.append(("detach", ue, t_us))
        return self.queues.pop(ue, [])

    def attach(self, ue: str, t_us: int, packets: list[Any]) -> None:
        self.log.append(("attach", ue, t_us))
        self.queues.setdefault(ue, []).extend(packets)


def run(ctl: HandoverControl, rsrp: Callable[[int], np.ndarray], cells: list[StandInCell],
        until_us: int, step_us: int = MS) -> None:
    for t in range(0, until_us + 1, step_us):
        ctl.tick(t, rsrp, cells)


# --- layer-3 filter --------------------------------------------------------------------------

def test_filter_weight_is_ts_38331_at_the_l1_period_and_keeps_its_time_constant_elsewhere(
        ) -> None:
    assert L1_MEASUREMENT_PERIOD_MS == 200
    for k in (0, 1, 4, 8, 19):
        assert filter_weight(k, 200) == pytest.approx(1 / 2 ** (k / 4))
        # Ten 20 ms steps forget as much as one 200 ms step.
        assert (1 - filter_weight(k, 20)) ** 10 == pytest.approx(1 - 1 / 2 ** (k / 4))
    assert filter_weight(0, 20) == 1.0  # k = 0: no filtering
    with pytest.raises(ValueError, match=r"allowed 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 13, 15, 17"):
        filter_weight(10, 200)


def test_l3_filter_step_response_follows_the_formula() -> None:
    a = filter_weight(4, 200)  # 0.5
    filt = L3Filter(a)
    assert filt.update(np.array([-100.0, -80.0]))[0] == -100.0  # F_1 = M_1
    for n in range(1, 12):
        f = filt.update(np.array([-90.0, -80.0]))
        # A 10 dB step: F_n = -90 - 10 (1 - a)^n; a constant input stays.
        assert f == pytest.approx([-90 - 10 * (1 - a) ** n, -80.0])
    # Against the recursion itself, for an arbitrary input and a slow filter.
    gen = np.random.default_rng(0)
    m = gen.normal(-90, 6, size=50)
    a = filter_weight(13, 20)
    filt, ref = L3Filter(a), m[0]
    for x in m:
        ref = ref if x is m[0] else (1 - a) * ref + a * x
        assert filt.update(np.array([x]))[0] == pytest.approx(ref)


# --- event A3 and its time to trigger --------------------------------------------------------

def step_rsrp(neighbour_dbm: Callable[[int], float]) -> Callable[[int], np.ndarray]:
    """One UE served by gNB 0 at -80 dBm; gNB 1 at ``neighbour_dbm(t)``."""
    return lambda t: np.array([[-80.0, neighbour_dbm(t)]])


def test_a3_fires_only_after_the_condition_held_for_the_time_to_trigger() -> None:
    params = HandoverParams(filter_k=0, hysteresis_db=3, time_to_trigger_ms=160,
                            interruption_ms=0, measurement_period_ms=20)
    ctl = HandoverControl(params, ["ue"], [0], 2)
    cells = [StandInCell(), StandInCell()]
    rsrp = step_rsrp(lambda t: -70.0 if t >= 100 * MS else -90.0)
    run(ctl, rsrp, cells, 240 * MS)
    assert ctl.handovers == [] and ctl.serving_of("ue") == 0
    # Entering at the 100 ms measurement; 160 ms later, at 260 ms, it fires.
    out = ctl.tick(260 * MS, rsrp, cells)
    (h,) = out.started
    assert (h.source, h.target, h.start_us) == (0, 1, 260 * MS)


def test_a_break_in_the_condition_restarts_the_time_to_trigger() -> None:
    params = HandoverParams(filter_k=0, time_to_trigger_ms=100, interruption_ms=0)
    ctl = HandoverControl(params, ["ue"], [0], 2)
    cells = [StandInCell(), StandInCell()]
    # Better by 10 dB except one measurement at 60 ms, where only 2 dB (inside the hysteresis).
    rsrp = step_rsrp(lambda t: -78.0 if t == 60 * MS else -70.0)
    run(ctl, rsrp, cells, 400 * MS)
    assert [h.start_us for h in ctl.handovers] == [180 * MS]  # 80 ms + 100 ms


def test_a3_uses_the_offset_and_hysteresis_and_picks_the_best_neighbour() -> None:
    params = HandoverParams(filter_k=0, a3_offset_db=2, hysteresis_db=1, time_to_trigger_ms=0,
                            interruption_ms=0)
    cells = [StandInCell() for _ in range(3)]
    # Neighbours 2.5 dB better: below Off + Hys = 3 dB, nothing happens.
    ctl = HandoverControl(params, ["ue"], [0], 3)
    run(ctl, lambda t: np.array([[-80.0, -77.5, -77.5]]), cells, 200 * MS)
    assert ctl.handovers == []
    # 3.5 and 5 dB better: the stronger one is taken, at the first measurement.
    ctl = HandoverControl(params, ["ue"], [0], 3)
    run(ctl, lambda t: np.array([[-80.0, -76.5, -75.0]]), cells, 0)
    assert [(h.source, h.target, h.start_us) for h in ctl.handovers] == [(0, 2, 0)]


def test_time_to_trigger_values_are_the_ts_38331_ones() -> None:
    assert TIME_TO_TRIGGER_MS == (0, 40, 64, 80, 100, 128, 160, 256, 320, 480, 512, 640, 1024,
                                  1280, 2560, 5120)
    with pytest.raises(ValueError, match=r"time_to_trigger_ms = 200 is not a TS 38\.331 "
                                         r"TimeToTrigger: allowed 0, 40, 64, .*, 5120 ms"):
        HandoverParams(time_to_trigger_ms=200)
    with pytest.raises(ValueError, match="filterCoefficient"):
        HandoverParams(filter_k=12)
    sc = parse_scenario({"netsim": {"handover": {"time_to_trigger_ms": 640, "forward": False}}})
    params = HandoverParams.from_config(sc.netsim.handover)
    assert (params.time_to_trigger_us, params.forward, params.interruption_us) == (
        640 * MS, False, 50 * MS)


# --- hysteresis against ping-pong ------------------------------------------------------------

LINE = InfLayout.explicit("SL", 120, 60, 10, [(40, 30, 1.5), (80, 30, 1.5)])


def boundary_run(params: HandoverParams, seed: int = 4) -> HandoverControl:
    """An AGV driving 30 s along the flat border x = 60 between two gNBs (LOS, no shadowing:
    both links equal at every point), its measurements with errors."""
    maps = InfMaps(LINE, 3.5e9, seed, los_mode="los", shadowing_enabled=False)
    fleet = Fleet([AgvRoute([(60, 10), (60, 50)], 1.0)])
    ctl = HandoverControl(params, ["agv-0"], [0], 2, seed=seed)
    cells = [StandInCell(), StandInCell()]
    run(ctl, lambda t: TX_DBM - maps.coupling_loss_db(fleet.positions_m(t)), cells, 30 * S,
        step_us=20 * MS)
    return ctl


def test_hysteresis_and_filtering_prevent_ping_pong_on_a_flat_boundary() -> None:
    bare = boundary_run(HandoverParams(filter_k=0, hysteresis_db=0, time_to_trigger_ms=0,
                                       interruption_ms=0, measurement_noise_db=2.0))
    assert len(bare.handovers) > 100 and ping_pongs(bare.handovers) > 100
    # The defaults: k = 4, Hys 3 dB, TTT 256 ms.
    guarded = boundary_run(HandoverParams(interruption_ms=0, measurement_noise_db=2.0))
    assert guarded.handovers == []


def test_measurement_errors_are_per_ue_streams() -> None:
    params = HandoverParams(filter_k=0, hysteresis_db=0, time_to_trigger_ms=0,
                            interruption_ms=0, measurement_noise_db=2.0)
    flat = lambda n: (lambda t: np.full((n, 2), -80.0))  # noqa: E731
    cells = [StandInCell(), StandInCell()]
    alone = HandoverControl(params, ["a"], [0], 2, seed=9)
    pair = HandoverControl(params, ["b", "a"], [1, 0], 2, seed=9)
    run(alone, flat(1), cells, 2 * S, step_us=20 * MS)
    run(pair, flat(2), cells, 2 * S, step_us=20 * MS)
    def of(ctl: HandoverControl, ue: str) -> list[tuple[int, int, int]]:
        return [(h.source, h.target, h.start_us) for h in ctl.handovers if h.ue == ue]
    assert of(alone, "a") == of(pair, "a") and len(of(alone, "a")) > 5
    other = HandoverControl(params, ["a"], [0], 2, seed=10)
    run(other, flat(1), cells, 2 * S, step_us=20 * MS)
    assert of(other, "a") != of(alone, "a")


# --- an AGV from gNB A to gNB B --------------------------------------------------------------

def shuttle(params: HandoverParams, cells: list[StandInCell]
            ) -> tuple[HandoverControl, Fleet, Callable[[int], np.ndarray]]:
    """An AGV shuttling at 1 m/s between x = 30 and 90 along y = 30, gNB A at x = 40 and gNB B
    at x = 80 (LOS, no shadowing): it passes the midpoint x = 60 at 30 s, reaches B's end at
    60 s and comes back."""
    maps = InfMaps(LINE, 3.5e9, 1, los_mode="los", shadowing_enabled=False)
    fleet = Fleet([AgvRoute([(30, 30), (90, 30)], 1.0)])
    ctl = HandoverControl(params, ["agv-0"], [0], 2)
    return ctl, fleet, lambda t: TX_DBM - maps.coupling_loss_db(fleet.positions_m(t))


def test_an_agv_driving_from_a_to_b_hands_over_once_near_the_expected_place() -> None:
    cells = [StandInCell(), StandInCell()]
    params = HandoverParams()  # k = 4, Off 0, Hys 3 dB, TTT 256 ms, 50 ms interruption
    ctl, fleet, rsrp = shuttle(params, cells)
    served: list[int | None] = []
    for t in range(0, 60 * S, MS):
        ctl.tick(t, rsrp, cells)
        served.append(ctl.serving_of("agv-0"))
    (h,) = ctl.handovers
    assert (h.source, h.target, h.done) == (0, 1, True)
    # B is Hys = 3 dB stronger where d_A / d_B = 10^(3 / 21.5) (LOS path loss slope): x = 63.2;
    # the time to trigger and the filter's lag carry the AGV on by well under a metre.
    ratio = 10 ** (3 / 21.5)
    x_expected = (40 + ratio * 80) / (1 + ratio)
    x_start = fleet.positions_m(h.start_us)[0, 0]
    assert x_expected < x_start < x_expected + 1.0
    # No cell during the 50 ms interruption, then B.
    assert h.end_us - h.start_us == 50 * MS
    start_ms, end_ms = h.start_us // MS, h.end_us // MS
    assert set(served[:start_ms]) == {0}
    assert set(served[start_ms:end_ms]) == {None}
    assert set(served[end_ms:]) == {1}
    assert cells[0].log == [("detach", "agv-0", h.start_us)]
    assert cells[1].log == [("attach", "agv-0", h.end_us)]
    # Driving back, it returns to A once, past the midpoint the other way: no ping-pong.
    run(ctl, rsrp, cells, 120 * S)
    assert [(h.source, h.target) for h in ctl.handovers] == [(0, 1), (1, 0)]
    x_back = fleet.positions_m(ctl.handovers[1].start_us)[0, 0]
    assert 120 - x_expected - 1.0 < x_back < 120 - x_expected
    assert ping_pongs(ctl.handovers) == 0


def test_late_ticks_do_every_measurement_they_skipped() -> None:
    """A federate jumping over idle stretches ticks rarely: the outcome is the same, at the
    same times."""
    every_ms = shuttle(HandoverParams(), [StandInCell(), StandInCell()])
    run(every_ms[0], every_ms[2], [StandInCell(), StandInCell()], 120 * S)
    ctl, _, rsrp = shuttle(HandoverParams(), [StandInCell(), StandInCell()])
    cells = [StandInCell(), StandInCell()]
    t = 0
    while t <= 120 * S:
        ctl.tick(t, rsrp, cells)
        assert ctl.next_event_us() > t
        t += 7_777_777
    ctl.tick(120 * S, rsrp, cells)
    assert ([(h.source, h.target, h.start_us, h.end_us) for h in ctl.handovers]
            == [(h.source, h.target, h.start_us, h.end_us) for h in every_ms[0].handovers])


# --- packets held during the interruption ----------------------------------------------------

@pytest.mark.parametrize("forward", [True, False])
def test_held_packets_are_forwarded_to_the_target_or_lost(forward: bool) -> None:
    cells = [StandInCell(), StandInCell()]
    ctl, _, rsrp = shuttle(HandoverParams(forward=forward), cells)
    cells[0].queues["agv-0"] = ["dl-1", "dl-2", "ul-1"]
    started: list[Any] = []
    t = 0
    while not started:
        started = ctl.tick(t, rsrp, cells).started
        t += MS
    (h,) = started
    assert ctl.in_handover("agv-0") and "agv-0" not in cells[0].queues
    ctl.hold("agv-0", ["dl-3"])  # arrives during the interruption
    ctl.hold("agv-0", ["ul-2"])
    out = ctl.tick(h.end_us - 1, rsrp, cells)
    assert out.completed == [] and ctl.in_handover("agv-0")
    (done,) = ctl.tick(h.end_us, rsrp, cells).completed
    assert done is h and not ctl.in_handover("agv-0") and ctl.serving_of("agv-0") == 1
    held = ["dl-1", "dl-2", "ul-1", "dl-3", "ul-2"]
    if forward:
        assert cells[1].queues["agv-0"] == held and (h.forwarded, h.lost) == (5, [])
    else:
        assert cells[1].queues["agv-0"] == [] and (h.forwarded, h.lost) == (0, held)
    with pytest.raises(ValueError, match="not in a handover"):
        ctl.hold("agv-0", ["late"])


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="serving gNBs must lie in 0..1"):
        HandoverControl(HandoverParams(), ["a"], [2], 2)
    with pytest.raises(ValueError, match="unique"):
        HandoverControl(HandoverParams(), ["a", "a"], [0, 0], 2)
    ctl = HandoverControl(HandoverParams(), ["a"], [0], 2)
    with pytest.raises(ValueError, match="RSRP of shape"):
        ctl.tick(0, lambda t: np.zeros((1, 3)), [StandInCell(), StandInCell()])
