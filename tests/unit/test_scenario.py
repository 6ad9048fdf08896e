"""Scenario validation: field-level errors, overrides, the time contract, the CLI's exit codes."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from interfaces.cli import main
from scenario.schema import ScenarioError, load_scenario, parse_scenario

SCENARIOS = sorted((Path(__file__).parents[2] / "configs" / "scenarios").glob("*.yaml"))


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_shipped_scenarios_validate(path: Path) -> None:
    sc = load_scenario(path)
    assert sc.name == path.stem


def test_required_scenarios_exist() -> None:
    assert {"smoke", "baseline", "co_design"} <= {p.stem for p in SCENARIOS}
    assert load_scenario(SCENARIOS[0].parent / "co_design.yaml").policy.name == "heuristic"


def test_unknown_field_is_named() -> None:
    with pytest.raises(ScenarioError) as err:
        parse_scenario({"camera": {"fsp": 30}})
    assert err.value.errors[0][0] == "camera.fsp"
    assert "unknown field" in err.value.errors[0][1]


def test_wrong_type_names_field_and_value() -> None:
    with pytest.raises(ScenarioError) as err:
        parse_scenario({"loops": "many"})
    field, msg = err.value.errors[0]
    assert field == "loops" and "'many'" in msg


def test_latency_below_window_is_rejected_with_the_latency_named() -> None:
    with pytest.raises(ScenarioError, match=r"robot\.actuation_latency_us = 500 us is below window_us"):
        parse_scenario({"robot": {"actuation_latency_us": 500}})


def test_overrides_apply_dotted_paths_with_yaml_values() -> None:
    sc = parse_scenario({}, ["loops=8", "seed=3", "policy.name=fixed", "policy.pdp=0.5"])
    assert (sc.loops, sc.seed, sc.policy.name, sc.policy.pdp) == (8, 3, "fixed", 0.5)


def test_cell_layout_gives_every_ue_a_position_in_the_hall() -> None:
    sc = parse_scenario({"loops": 20})
    pos = sc.ue_positions_m()
    assert len(pos) == 40
    assert all(0 <= x <= sc.hall.length_m and 0 <= y <= sc.hall.width_m for x, y, _ in pos.values())


def test_more_cells_than_the_hall_holds_are_refused_with_how_many_fit() -> None:
    assert parse_scenario({"loops": 64, "detailed_loops": 0}).loops == 64
    with pytest.raises(ScenarioError, match=r"loops = 72 work cells do not fit in the hall .* at most 64 fit"):
        parse_scenario({"loops": 72, "detailed_loops": 0})
    wide = {"length_m": 120, "width_m": 100, "gnb_position_m": [60, 50, 1.5], "work_cells_per_row": 12}
    assert parse_scenario({"loops": 128, "detailed_loops": 0, "hall": wide}).loops == 128
    # Far past the hall, how many fit is still found (bisected, not searched down from loops).
    with pytest.raises(ScenarioError, match=r"loops = 1024 work cells .* at most 64 fit"):
        parse_scenario({"loops": 1024, "detailed_loops": 0})


@pytest.mark.parametrize(("data", "field", "says"), [
    ({"seed": 2**32}, "seed", "less than 4294967296"),  # the streams take a seed's low 32 bits
    ({"name": "a" * 65}, "name", "at most 64 characters"),
    ({"camera": {"readout_latency_us": 10**25}}, "camera.readout_latency_us", "below 2**53"),
    ({"nodes": {"edge": {"cpus": 1, "model_us": {"compres": {"mean_us": 10}}}}}, "nodes",
     "'compres' is not a job kind; job kinds: compress, pose, policy, control"),
    # Values that passed the schema and then crashed a started run (an overflow, a NaN, a hang).
    ({"robot": {"max_estimate_age_ms": 1e308}}, "robot.max_estimate_age_ms", "less than or equal to 60000"),
    ({"policy": {"latency_budget_ms": 1e308}}, "policy.latency_budget_ms", "less than or equal to 10000"),
    ({"work_cell": {"object_period_s": 1e308}}, "work_cell.object_period_s", "less than or equal to 3600"),
    ({"work_cell": {"first_object_spread_s": 1e13}}, "work_cell.first_object_spread_s", "less than or equal to 86400"),
    ({"work_cell": {"belt_speed_m_s": 1e-5}}, "work_cell.belt_speed_m_s", "greater than or equal to 0.01"),
    ({"netsim": {"nr": {"ue_tx_power_dbm": 5000}}}, "netsim.nr.ue_tx_power_dbm", "less than or equal to 33"),
    ({"netsim": {"nr": {"noise_psd_dbm_per_hz": 1e308}}}, "netsim.nr.noise_psd_dbm_per_hz", "less than or equal to -150"),
    ({"netsim": {"nr": {"k2_slots": 10**24}}}, "netsim.nr.k2_slots", "less than or equal to 32"),
    ({"netsim": {"nr": {"ue_speed_kmh": 1e12}}}, "netsim.nr.ue_speed_kmh", "less than or equal to 500"),
    ({"netsim": {"model": "simple", "ul_rate_mbps": 1e308}}, "netsim.ul_rate_mbps", "less than or equal to 1000000"),
    ({"hall": {"length_m": 100_000}}, "hall.length_m", "less than or equal to 1000"),
    ({"hall": {"gnb_position_m": [60, 30, 1000]}}, "hall", "hall.gnb_position_m = (60, 30, 1000) is outside the hall"),
    ({"nodes": {"camera": {"cpus": 1e-300}}}, "nodes.camera.cpus", "greater than or equal to 0.001"),
    ({"nodes": {"edge": {"cpus": 1, "timing": "wall"}}}, "(scenario)", "only runtime docker gives"),
    ({"duration_s": 1e-7}, "(scenario)", "shorter than one window"),
    ({"watchdog": {"window_timeout_s": 1e-9}}, "watchdog.window_timeout_s", "greater than or equal to 0.1"),
    ({"policy": {"learned_model": ""}}, "policy.learned_model", "at least 1 character"),
    # One IP packet each, at most a jumbo frame; a depth noise no sensor has.
    ({"edge": {"pose_packet_bytes": 10**9}}, "edge.pose_packet_bytes", "less than or equal to 9000"),
    ({"edge": {"qos_packet_bytes": 10**9}}, "edge.qos_packet_bytes", "less than or equal to 9000"),
    ({"camera": {"depth_noise_mm": 1e308}}, "camera.depth_noise_mm", "less than or equal to 100"),
    ({"edge": {"pose_queue": "lifo"}}, "edge.pose_queue", "'fifo' or 'newest'"),
])
def test_values_no_run_could_carry_are_refused_naming_the_field(data: dict, field: str, says: str) -> None:
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(data)
    [(got, msg)] = exc.value.errors
    assert got == field and says in msg, exc.value.errors


def test_a_sections_own_check_is_not_followed_by_the_whole_section() -> None:
    with pytest.raises(ScenarioError) as exc:
        parse_scenario({"netsim": {"nr": {"olla_min_offset_db": 20}}})
    [(field, msg)] = exc.value.errors
    assert field == "netsim.nr" and "olla_min_offset_db (20) must be <= olla_max_offset_db (" in msg and "given" not in msg


def test_an_override_nested_too_deep_is_refused_naming_it() -> None:
    with pytest.raises(ScenarioError) as exc:
        load_scenario(SCENARIOS[0], ["loops=" + "[" * 2000 + "]" * 2000])
    assert exc.value.errors[0][0] == "loops" and "nested too deep" in exc.value.errors[0][1]


@pytest.mark.parametrize("pitch", [[0.0, 0.0], [-8.0, 8.0]])
def test_a_pitch_that_is_not_positive_is_refused(pitch: list[float]) -> None:
    with pytest.raises(ScenarioError, match=r"hall.work_cell_pitch_m: .* each must be positive"):
        parse_scenario({"loops": 4, "hall": {"work_cell_pitch_m": pitch}})


@pytest.mark.parametrize("hall", [{"work_cell_pitch_m": [1.9, 8.0]},
                                  {"work_cell_pitch_m": [8.0, 1.9], "work_cells_per_row": 2}])
def test_work_cells_closer_than_their_footprint_are_refused(hall: dict) -> None:
    with pytest.raises(ScenarioError, match=r"work cells 0 and [12] .* overlap: .* at least 2 m apart .* "
                                            r"hall.work_cell_pitch_m"):
        parse_scenario({"loops": 4, "hall": hall})
    # Along an axis no two work cells share, any pitch: one row of four.
    assert parse_scenario({"loops": 4, "hall": {"work_cell_pitch_m": [2.0, 1.0]}}).loops == 4


def test_work_cells_around_the_gnbs_need_several_gnbs_and_may_not_overlap() -> None:
    spread = {"work_cell_fill": "gnbs", "work_cells_per_row": 5, "work_cell_pitch_m": [4.0, 5.0],
              "inf_layout": {"gnb_count": 18}}
    # 20 m between gNBs: five 4-m work cells a row fill it, two rows a gNB stand in its 20 m of width.
    assert parse_scenario({"loops": 180, "detailed_loops": 0, "hall": spread}).loops == 180
    with pytest.raises(ScenarioError, match=r"hall: .*work_cell_fill = gnbs .* set hall.inf_layout"):
        parse_scenario({"loops": 4, "hall": {"work_cell_fill": "gnbs"}})
    # 11 m along x: a gNB's second work cell stands 9 m from the next gNB's first.
    wide = {**spread, "work_cell_pitch_m": [11.0, 5.0], "inf_layout": {"gnb_count": 4}}
    with pytest.raises(ScenarioError, match=r"loops = 8 work cells around 4 gNBs overlap .* work cell 1 "
                                            r"\(gNB 1\) .* closer than hall.work_cell_pitch_m"):
        parse_scenario({"loops": 8, "detailed_loops": 0, "hall": wide})


def test_cli_bad_input_exits_2_without_traceback(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("loops: 2\ncamera:\n  fsp: 30\n")
    assert main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "camera.fsp: unknown field; allowed here: " in err and "fps" in err and "Traceback" not in err
    assert main(["run", str(bad)]) == 2
    short = tmp_path / "short.yaml"
    short.write_text("robot:\n  actuation_latency_us: 10\n")
    assert main(["run", str(short)]) == 2
    assert "actuation_latency_us = 10 us is below window_us" in capsys.readouterr().err
    assert main(["validate", str(SCENARIOS[0]), "--set", "loops=zero"]) == 2
    assert main(["validate", str(tmp_path / "missing.yaml")]) == 2


def test_old_field_names_load_once_with_a_warning_naming_the_new_ones(tmp_path: Path) -> None:
    """The work cell was `cell`, and the hall's `cells_per_row` and `cell_pitch_m` named it too:
    scenario files, inline scenarios and overrides written then still load."""
    path = tmp_path / "old.yaml"
    path.write_text("loops: 4\ncell: {belt_speed_m_s: 0.3}\nhall: {cells_per_row: 2, cell_pitch_m: [6, 6]}\n")
    with pytest.warns(FutureWarning) as warned:
        sc = load_scenario(path, ["cell.object_period_s=3.0"])
    said = {str(w.message).split(":")[0] for w in warned}
    assert said == {f"scenario field {old!r} is now {new!r}" for old, new in
                    (("cell", "work_cell"), ("hall.cells_per_row", "hall.work_cells_per_row"),
                     ("hall.cell_pitch_m", "hall.work_cell_pitch_m"))}
    assert (sc.work_cell.belt_speed_m_s, sc.work_cell.object_period_s) == (0.3, 3.0)
    assert (sc.hall.work_cells_per_row, tuple(sc.hall.work_cell_pitch_m)) == (2, (6.0, 6.0))
    with pytest.raises(ScenarioError, match="given twice.*keep 'work_cell'"):
        parse_scenario({"cell": {}, "work_cell": {}})


def test_hall_has_no_inf_layout_unless_asked_and_takes_one_by_subset_or_positions() -> None:
    assert all((load_scenario(p).hall.inf_layout is None) == (p.stem not in ("factory_small", "factory"))
               for p in SCENARIOS)
    sc = parse_scenario({}, ["hall.inf_layout.gnb_count=6", "hall.inf_layout.reuse=3"])
    layout = sc.hall.inf_layout
    assert layout is not None
    assert (layout.sub_scenario, layout.gnb_count, layout.reuse) == ("SL", 6, 3)
    assert (layout.ul_p0_dbm, layout.ul_alpha) == (-90.0, 1.0)
    given = parse_scenario({"hall": {"inf_layout": {
        "sub_scenario": "DH", "gnb_positions_m": [[20, 30, 8], [100, 30, 8]], "ul_alpha": 0.7}}})
    assert given.hall.inf_layout is not None
    assert given.hall.inf_layout.gnb_positions_m == [(20.0, 30.0, 8.0), (100.0, 30.0, 8.0)]


@pytest.mark.parametrize(("inf_layout", "hall", "field", "message"), [
    ({"gnb_count": 5}, {}, "hall.inf_layout.gnb_count",
     r"gnb_count = 5 is not a subset of the 6 x 3 gNB lattice: allowed 1, 2, 4, 6, 9, 18"),
    ({"gnb_positions_m": [[10, 10, 1.5], [130, 10, 1.5]]}, {}, "hall",
     r"hall\.inf_layout\.gnb_positions_m\[1\] = \(130, 10, 1\.5\) m lies outside the hall "
     r"\(0\.\.120 x 0\.\.60 x 0\.\.10 m\)"),
    ({"gnb_positions_m": [[10, 10, 12]]}, {}, "hall", r"gnb_positions_m\[0\] .* outside the hall"),
    ({"sub_scenario": "SH"}, {"height_m": 6}, "hall",
     r"sub_scenario = SH puts the gNBs at 8 m, above hall\.height_m = 6"),
    ({"ul_alpha": 0.3}, {}, "hall.inf_layout.ul_alpha",
     r"ul_alpha = 0\.3 is not a TS 38\.213 alpha: allowed 0, 0\.4, 0\.5, 0\.6, 0\.7, 0\.8, 0\.9, 1"),
    ({"reuse": 2}, {}, "hall.inf_layout.reuse", r"1 or 3"),
    ({"sub_scenario": "HH"}, {}, "hall.inf_layout.sub_scenario", r"'SL', 'DL', 'SH' or 'DH'"),
])
def test_bad_inf_layout_is_refused_naming_the_field(inf_layout: dict, hall: dict, field: str,
                                                    message: str) -> None:
    with pytest.raises(ScenarioError) as err:
        parse_scenario({"hall": {**hall, "inf_layout": inf_layout}})
    (where, said), = err.value.errors
    assert where == field
    assert re.search(message, said), said


def test_no_agvs_unless_asked_and_handover_defaults() -> None:
    # Only the factory drives AGVs among the shipped scenarios.
    assert {p.stem: load_scenario(p).agvs.count for p in SCENARIOS if load_scenario(p).agvs.count} == {
        "factory": 4}
    sc = parse_scenario({})
    assert (sc.agvs.count, sc.agvs.speed_m_s, sc.agvs.waypoints_m) == (0, 1.0, None)
    ho = sc.netsim.handover
    assert (ho.filter_k, ho.a3_offset_db, ho.hysteresis_db, ho.time_to_trigger_ms,
            ho.interruption_ms, ho.forward, ho.measurement_period_ms) == (4, 0.0, 3.0, 256, 50.0,
                                                                         True, 20)
    given = parse_scenario({"hall": {"inf_layout": {"gnb_count": 4}}, "agvs": {
        "speed_m_s": 2, "waypoints_m": [[0, 0], [120, 60]], "ul_rate_mbps": 4}},
        ["netsim.handover.time_to_trigger_ms=640", "netsim.handover.hysteresis_db=1.5"])
    assert given.agvs.waypoints_m == [(0.0, 0.0), (120.0, 60.0)]
    assert (given.agvs.ul_rate_mbps, given.netsim.handover.time_to_trigger_ms) == (4.0, 640)


@pytest.mark.parametrize(("data", "field", "message"), [
    ({"agvs": {"count": 1}}, "(scenario)",
     r"agvs\.count = 1 needs several gNBs to hand over between: set hall\.inf_layout"),
    ({"hall": {"inf_layout": {}}, "agvs": {"count": 1, "waypoints_m": [[10, 10], [130, 10]]}},
     "(scenario)", r"agvs\.waypoints_m\[1\] = \(130, 10\) m lies outside the hall floor "
     r"\(0\.\.120 x 0\.\.60 m\)"),
    ({"hall": {"inf_layout": {}}, "agvs": {"count": 2}, "netsim": {"model": "simple"}},
     "(scenario)", r"hall\.inf_layout needs netsim\.model = nr"),
    ({"agvs": {"delay_budget_ms": 0}}, "agvs.delay_budget_ms", r"greater than or equal to 0.001"),
    ({"agvs": {"waypoints_m": [[10, -1], [20, 10]]}}, "(scenario)",
     r"agvs\.waypoints_m\[0\] = \(10, -1\) m lies outside"),
    ({"agvs": {"speed_m_s": 2.5}}, "agvs.speed_m_s",
     r"speed_m_s = 2\.5 m/s is outside the AGV speeds: allowed 0\.5 to 2 m/s"),
    ({"agvs": {"speed_m_s": 0.3}}, "agvs.speed_m_s", r"allowed 0\.5 to 2 m/s"),
    ({"agvs": {"waypoints_m": [[5, 5], [5, 5]]}}, "agvs.waypoints_m", r"two different points"),
    ({"netsim": {"handover": {"time_to_trigger_ms": 200}}}, "netsim.handover.time_to_trigger_ms",
     r"time_to_trigger_ms = 200 is not a TS 38\.331 TimeToTrigger: allowed 0, 40, 64, 80, 100, "
     r"128, 160, 256, 320, 480, 512, 640, 1024, 1280, 2560, 5120 ms"),
    ({"netsim": {"handover": {"filter_k": 10}}}, "netsim.handover.filter_k",
     r"filter_k = 10 is not a TS 38\.331 filterCoefficient: allowed 0, 1, 2, 3, 4, 5, 6, 7, 8, "
     r"9, 11, 13, 15, 17, 19"),
    ({"netsim": {"handover": {"hysteresis_db": 1.2}}}, "netsim.handover.hysteresis_db",
     r"hysteresis_db = 1\.2 dB is not a multiple of 0\.5 dB"),
    ({"netsim": {"handover": {"a3_offset_db": 20}}}, "netsim.handover.a3_offset_db",
     r"less than or equal to 15"),
])
def test_bad_agvs_and_handover_are_refused_naming_the_field(data: dict, field: str,
                                                            message: str) -> None:
    with pytest.raises(ScenarioError) as err:
        parse_scenario(data)
    (where, said), = err.value.errors
    assert where == field
    assert re.search(message, said), said


def test_a_run_id_in_use_exits_2_before_anything_runs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "taken").mkdir()
    smoke = Path(__file__).parents[2] / "configs" / "scenarios" / "smoke.yaml"
    assert main(["run", str(smoke), "--results", str(tmp_path), "--run-id", "taken", "--quiet"]) == 2
    assert "--run-id taken" in capsys.readouterr().err and not (tmp_path / "taken" / "status.json").exists()


@pytest.mark.parametrize("nr,match", [
    ({"n_prb": 2, "cg_prb": 1}, r"n_prb = 2 leaves no PRB per cell with hall.inf_layout.reuse = 3"),
    ({"n_prb": 20, "cg_prb": 8, "ul_access": "configured_grant"},
     r"cg_prb = 8 exceeds the 6 PRBs of a cell .*reuse = 3\): at most 6"),
])
def test_a_reuse_3_cell_must_hold_a_prb_and_a_configured_grant(nr: dict, match: str) -> None:
    hall = {"inf_layout": {"gnb_count": 4, "reuse": 3}}
    with pytest.raises(ScenarioError, match=match):
        parse_scenario({"loops": 2, "hall": hall, "netsim": {"model": "nr", "nr": nr}})
    fits = {**nr, "cg_prb": 6} if "ul_access" in nr else {**nr, "n_prb": 3}
    assert parse_scenario({"loops": 2, "hall": hall, "netsim": {"model": "nr", "nr": fits}}).loops == 2


def test_an_agv_delay_budget_under_a_microsecond_is_refused() -> None:
    hall = {"inf_layout": {"gnb_count": 2}}
    with pytest.raises(ScenarioError, match=r"agvs.delay_budget_ms: .* greater than or equal to 0.001"):
        parse_scenario({"loops": 2, "hall": hall, "netsim": {"model": "nr"},
                        "agvs": {"count": 1, "delay_budget_ms": 0.0004}})
