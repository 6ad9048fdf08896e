"""Sweep specs, points, the summary statistics and the capacity rule (no run is started)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from experiments.points import expand
from experiments.records import SweepDir, flatten_kpis, write_rows
from experiments.spec import SweepError, load_spec, parse_spec
from experiments.summary import (
    capacity,
    capacity_of_curve,
    grouped_capacity,
    mean_ci,
    summarise,
    wilson,
)
from interfaces.cli import main
from scenario.schema import load_scenario

ROOT = Path(__file__).parents[2]
SCENARIOS = ROOT / "configs" / "scenarios"


def spec(**fields: Any) -> dict[str, Any]:
    base: dict[str, Any] = {"name": "t", "base": "baseline", "grid": {"loops": [2, 4]}, "seeds": 1}
    base.update(fields)
    return base


def errors_of(data: dict[str, Any]) -> list[tuple[str, str]]:
    with pytest.raises(SweepError) as exc:
        parse_spec(data, SCENARIOS)
    return exc.value.errors


def test_shipped_specs_load_and_expand() -> None:
    quick = load_spec(ROOT / "configs" / "sweeps" / "quick.yaml", SCENARIOS)
    assert quick.grid_values()["loops"] == [4, 8, 12, 16, 20, 24, 28, 32, 36]
    assert len(expand(quick, SCENARIOS)) == 18
    full = load_spec(ROOT / "configs" / "sweeps" / "reproduce.yaml", SCENARIOS)
    points = expand(full, SCENARIOS)
    assert full.grid_values()["loops"] == list(range(2, 37, 2))
    assert len(points) == 18 * 2 * 3
    assert {p.scenario.policy.name for p in points} == {"none", "heuristic"}
    assert all(p.scenario.detailed_loops == 0 and p.scenario.duration_s == 60.0 for p in points)
    fast = expand(load_spec(ROOT / "configs" / "sweeps" / "fast_cells.yaml", SCENARIOS), SCENARIOS)
    assert len(fast) == 4 * 3 * 9 * 3
    assert {p.scenario.camera.frame_keep for p in fast} == {"bernoulli", "spaced"}
    assert {p.scenario.work_cell.first_object_spread_s for p in fast} == {0.0, 4.0, 6.0}
    shared = expand(load_spec(ROOT / "configs" / "sweeps" / "shared_edge.yaml", SCENARIOS), SCENARIOS)
    assert len(shared) == 2 * 3 * 16 * 3
    assert {p.scenario.edge.abstract_compute for p in shared} == {"shared"}
    assert {p.scenario.edge.pose_queue for p in shared} == {"fifo", "newest"}
    # The other shipped specs expand in the test below, but for this one.
    assert expand(load_spec(ROOT / "configs" / "sweeps" / "factory_gnbs.yaml", SCENARIOS), SCENARIOS)


def test_co_design_keeps_frames_spaced_where_its_results_were_not_measured_otherwise() -> None:
    """co_design ships the spaced keep; the specs measured with each frame drawn alone (and the
    sensitivity sweeps, whose loss rate is each frame lost alone) keep that."""
    for name in ("co_design", "co_design_learned"):
        assert load_scenario(SCENARIOS / f"{name}.yaml").camera.frame_keep == "spaced"
    keeps = {name: {p.scenario.camera.frame_keep
                    for p in expand(load_spec(ROOT / "configs" / "sweeps" / f"{name}.yaml", SCENARIOS), SCENARIOS)}
             for name in ("family", "overload", "codesign", "codesign_family", "sensitivity", "sensitivity_detailed")}
    assert keeps == {"family": {"spaced"}, "overload": {"spaced"}, "codesign": {"bernoulli"},
                     "codesign_family": {"bernoulli"}, "sensitivity": {"bernoulli"},
                     "sensitivity_detailed": {"bernoulli"}}


def test_unknown_field_is_named_with_the_allowed_ones() -> None:
    [(field, msg)] = errors_of(spec(grids={"loops": [2]}))
    assert field == "grids" and "allowed here" in msg and "grid" in msg


def test_unknown_dotted_path_names_the_part_and_the_section() -> None:
    errs = dict(errors_of(spec(grid={"policy.nme": ["none"], "loops": [2]})))
    assert "no field 'nme' in policy" in errs["grid.policy.nme"]
    assert "allowed there" in errs["grid.policy.nme"] and "name" in errs["grid.policy.nme"]


def test_empty_grid_and_empty_values_are_refused() -> None:
    assert errors_of(spec(grid={}))[0][0] == "grid"
    assert ("grid.loops", "no values: give at least one") in errors_of(spec(grid={"loops": []}))


def test_a_bad_grid_value_is_named_by_its_index() -> None:
    errs = dict(errors_of(spec(grid={"loops": [2, 500]})))
    assert "grid.loops[1]" in errs and "500" in errs["grid.loops[1]"]
    errs = dict(errors_of(spec(grid={"policy.name": ["none", "clever"], "loops": [2]})))
    assert "clever" in errs["grid.policy.name[1]"]


def test_a_combination_that_breaks_a_scenario_rule_is_refused() -> None:
    errs = errors_of(spec(grid={"loops": [1, 4], "detailed_loops": [2]}))
    assert errs and "detailed_loops" in errs[0][1] and "loops" in errs[0][0]


def test_unknown_base_and_capacity_axis_are_named() -> None:
    assert errors_of(spec(base="nonesuch"))[0][0] == "base"
    assert "capacity.x" in errors_of(spec(capacity={"x": "seed"}))[0][1]


def test_cli_exits_2_naming_the_field(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: t\nbase: baseline\ngrid: {loops: [2], policy.nme: [none]}\n")
    assert main(["sweep", str(bad), "--results", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "grid.policy.nme" in err and "Traceback" not in err
    assert not any(tmp_path.glob("t-*")), "no sweep directory for a spec that cannot run"


def test_points_are_keyed_by_resolved_config_and_seed() -> None:
    s = parse_spec(spec(seeds=[1, 2]), SCENARIOS)
    a, b = expand(s, SCENARIOS), expand(s, SCENARIOS)
    assert [p.key for p in a] == [p.key for p in b]
    assert len({p.key for p in a}) == 4
    # The same point reached through a range or a list, or another base default, is the same run.
    r = parse_spec(spec(grid={"loops": {"start": 2, "stop": 4, "step": 2}}, seeds=[1, 2]), SCENARIOS)
    assert [p.key for p in expand(r, SCENARIOS)] == [p.key for p in a]


def test_range_values() -> None:
    s = parse_spec(spec(grid={"loops": {"start": 2, "stop": 36, "step": 2}}), SCENARIOS)
    assert s.grid_values()["loops"] == list(range(2, 37, 2))
    s = parse_spec(spec(grid={"loops": [2], "policy.pdp": {"start": 0.2, "stop": 0.6, "step": 0.2}}), SCENARIOS)
    assert s.grid_values()["policy.pdp"] == [0.2, 0.4, 0.6]


def test_wilson_interval_and_mean_ci() -> None:
    low, high = wilson(10, 10)
    assert high == 1.0 and 0.69 < low < 0.73  # 10/10 does not prove 100%
    low, high = wilson(0, 0)
    assert low is None and high is None
    for n in range(1, 400):  # the bounds never cross the estimate, whatever the rounding
        for k in (0, n):
            low, high = wilson(k, n)
            assert low is not None and high is not None and low <= k / n <= high
    m, half = mean_ci([1.0, 2.0, 3.0])
    assert m == 2.0 and half == pytest.approx(4.303 * 1.0 / 3 ** 0.5, rel=1e-3)
    assert mean_ci([5.0]) == (5.0, None)


def test_capacity_of_a_monotone_curve() -> None:
    curve = [(4, 1.0), (8, 1.0), (12, 0.99), (16, 0.9)]
    assert capacity_of_curve(curve, 1.0)["capacity"] == 8
    assert capacity_of_curve(curve, 0.98)["capacity"] == 12
    c = capacity_of_curve(curve, 0.98)
    assert c["first_failing"] == 16 and c["monotone"]


def test_capacity_of_a_non_monotone_curve_stops_at_the_first_failure() -> None:
    curve = [(4, 1.0), (8, 0.97), (12, 1.0), (16, 1.0), (20, 0.5)]
    c = capacity_of_curve(curve, 1.0)
    assert c["capacity"] == 4 and c["first_failing"] == 8
    assert c["max_passing"] == 16 and not c["monotone"]
    assert capacity_of_curve(curve, 0.95)["capacity"] == 16


def test_capacity_edge_cases() -> None:
    assert capacity_of_curve([(4, 0.5), (8, 1.0)], 1.0)["capacity"] == 0
    c = capacity_of_curve([(4, 1.0), (8, None), (12, 1.0)], 1.0)
    assert c["capacity"] == 4 and c["missing"] == [8]  # nothing is known past a missing point
    assert capacity_of_curve([(4, 1.0), (8, 1.0)], 1.0)["first_failing"] is None


def point(loops: int, policy: str, seed: int, tasks: int, placed: int, status: str = "completed",
          **kpis: float) -> dict[str, Any]:
    return {"key": f"{loops}{policy}{seed}", "loops": loops, "policy.name": policy, "seed": seed,
            "status": status, "kpi.tasks": tasks, "kpi.tasks_placed": placed, **{f"kpi.{k}": v for k, v in kpis.items()}}


def test_summary_pools_tasks_over_seeds_and_capacity_gain() -> None:
    points = [
        point(4, "heuristic", 1, 50, 50, ul_injected_mbps=10.0), point(4, "heuristic", 2, 50, 50, ul_injected_mbps=12.0),
        point(4, "none", 1, 50, 50), point(4, "none", 2, 50, 50),
        point(8, "none", 1, 100, 99), point(8, "none", 2, 100, 96),
        point(8, "heuristic", 1, 100, 100), point(8, "heuristic", 2, 100, 100, status="failed"),
        point(12, "none", 1, 150, 100), point(12, "heuristic", 1, 150, 149),
    ]
    grid = {"loops": [4, 8, 12], "policy.name": ["none", "heuristic"]}
    rows = summarise(points, grid)
    assert [(r["loops"], r["policy.name"]) for r in rows] == [
        (4, "none"), (4, "heuristic"), (8, "none"), (8, "heuristic"), (12, "none"), (12, "heuristic")]
    r8 = rows[2]
    assert r8["tasks"] == 200 and r8["success_rate"] == pytest.approx(195 / 200)
    assert r8["success_ci_low"] < 0.975 < r8["success_ci_high"]
    h8 = rows[3]
    assert (h8["runs"], h8["runs_completed"], h8["tasks"]) == (2, 1, 100)  # a failed run adds no tasks
    assert rows[1]["ul_injected_mbps"] == pytest.approx(11.0) and rows[1]["ul_injected_mbps_ci95"] > 0
    cap = capacity(rows, "loops", ["policy.name"], [1.0, 0.98], reference="policy.name=none")
    assert cap["series"]["policy.name=none"]["success>=100%"]["capacity"] == 4
    assert cap["series"]["policy.name=heuristic"]["success>=100%"]["capacity"] == 8
    assert cap["series"]["policy.name=heuristic"]["success>=98%"]["capacity"] == 12
    assert cap["gain_over_reference"]["policy.name=heuristic"]["success>=100%"]["ratio"] == 2.0


def test_records_keep_the_latest_line_of_a_point_and_survive_a_torn_line(tmp_path: Path) -> None:
    sd = SweepDir(tmp_path)
    sd.create({"sweep_id": "x"}, "name: x\n")
    sd.append({"key": "a", "values": {"loops": 2}, "seed": 1, "status": "failed", "run_id": "a-1",
               "run_dir": "runs/a-1", "kpis": {}})
    sd.append({"key": "a", "values": {"loops": 2}, "seed": 1, "status": "completed", "run_id": "a-2",
               "run_dir": "runs/a-2", "kpis": {"tasks": 3}})
    with open(sd.log_path, "a") as f:
        f.write('{"key": "b", "valu')  # a crash in the middle of a line
    rows = sd.write_points_table()
    assert [(r["key"], r["status"], r["run_id"], r["kpi.tasks"]) for r in rows] == [("a", "completed", "a-2", 3)]
    assert sd.completed_keys() == {"a"}


def test_flatten_and_typed_columns(tmp_path: Path) -> None:
    flat = flatten_kpis({"tasks": 3, "ip_latency_ms": {"p50": 5.0}, "lost_packets": {}, "federates": {"x": 1},
                         "log_tail": ["a"], "reason": None})
    assert flat == {"tasks": 3, "ip_latency_ms.p50": 5.0, "reason": None}
    import pyarrow.parquet as pq
    write_rows(tmp_path / "t.parquet", [{"a": 1, "b": "x"}, {"a": 2.5, "c": True}])
    t = pq.read_table(tmp_path / "t.parquet")
    assert str(t.schema.field("a").type) == "double" and t.column("c").to_pylist() == [None, True]


def test_repeat_until_adds_seeds_only_where_tasks_are_short(tmp_path: Path) -> None:
    from experiments.sweep import Sweep

    s = parse_spec(spec(grid={"loops": [2, 8]}, seeds=2, repeat_until={"min_tasks": 30, "max_seeds": 5}),
                   SCENARIOS)
    sweep = Sweep.create(s, tmp_path, scenarios_dir=SCENARIOS)
    points = expand(s, SCENARIOS)
    tasks = {2: 4, 8: 16}  # per run: 2 loops give 4 tasks, 8 loops 16
    for p in points:
        sweep.dir.append({"key": p.key, "values": p.values, "seed": p.seed, "status": "completed",
                          "run_id": p.key[:12], "run_dir": "runs/x", "kpis": {"tasks": tasks[p.values["loops"]]}})
    extra = sweep._more_seeds(points)
    # loops=2 has 8 tasks over 2 seeds and needs 30: 6 more seeds would do, 3 fit under max_seeds;
    # loops=8 has 32 >= 30: nothing.
    assert [(p.values["loops"], p.seed) for p in extra] == [(2, 3), (2, 4), (2, 5)]
    for p in extra:
        sweep.dir.append({"key": p.key, "values": p.values, "seed": p.seed, "status": "completed",
                          "run_id": p.key[:12], "run_dir": "runs/x", "kpis": {"tasks": 4}})
    assert sweep._more_seeds(points) == [], "max_seeds reached (seeds added earlier count, also on resume)"


def test_variants_sweep_named_sets_of_fields() -> None:
    s = parse_spec(spec(variants={"pdp1": {"policy.name": "none"},
                                  "lower": {"policy.name": "learned", "policy.signalling": "lower"}}),
                   SCENARIOS)
    assert list(s.grid) == ["variant", "loops"], "every variant is swept when the grid leaves it out"
    points = expand(s, SCENARIOS)
    assert [(p.values["variant"], p.scenario.policy.name, p.scenario.policy.signalling) for p in points] == [
        ("pdp1", "none", "app"), ("pdp1", "none", "app"), ("lower", "learned", "lower"), ("lower", "learned", "lower")]
    codesign = load_spec(ROOT / "configs" / "sweeps" / "codesign.yaml", SCENARIOS)
    controls = {p.values["variant"]: p.scenario.policy.controls for p in expand(codesign, SCENARIOS)}
    assert controls["learned_lower_pdp_only"] == "pdp" and controls["learned_lower"] == "both"
    family = load_spec(ROOT / "configs" / "sweeps" / "codesign_family.yaml", SCENARIOS)
    speeds = {p.values["variant"]: p.scenario.work_cell.belt_speed_m_s for p in expand(family, SCENARIOS)}
    assert speeds["cell2_none"] == speeds["cell2_learned_lower"] == 0.2869


def test_bad_variants_are_named() -> None:
    [(field, msg)] = errors_of(spec(variants={"a": {"policy.nam": "none"}}))
    assert field == "variants.a.policy.nam" and "allowed there" in msg
    [(field, msg)] = errors_of(spec(grid={"loops": [2], "variant": ["a", "b"]}, variants={"a": {"policy.name": "none"}}))
    assert field == "(sweep)" and "'b' not in variants (a)" in msg
    [(field, msg)] = errors_of(spec(grid={"loops": [2], "variant": ["a"]}))
    assert "needs a `variants` section" in msg
    [(field, msg)] = errors_of(spec(set={"policy.name": "none"}, variants={"a": {"policy.name": "fixed"}}))
    assert field == "variants.a.policy.name" and "neither fixed nor swept" in msg
    [(field, msg)] = errors_of(spec(variants={"a": {"policy.pdp": 2}}))
    assert field.startswith("grid.variant[0]") and "policy.pdp" in msg


def test_a_series_stops_after_its_loads_fail_and_larger_loads_are_not_run(tmp_path: Path) -> None:
    from experiments.point_runs import PointOutcome, PointTask
    from experiments.sweep import Sweep

    # Success by (policy, loops): `none` fails from 6 loops, `heuristic` never in this grid.
    success = {"none": {2: 1.0, 4: 1.0, 6: 0.5, 8: 0.4, 10: 0.9, 12: 0.1}, "heuristic": dict.fromkeys(range(2, 13, 2), 1.0)}
    ran: list[tuple[str, int]] = []

    class TableExecutor:
        name = "table"

        def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: Any) -> None:
            for t in tasks:
                on_start(t)
                policy, loops = t.point.values["policy.name"], t.point.values["loops"]
                ran.append((policy, loops))
                on_done(t, PointOutcome(t.point.key, t.run_id, "completed", None, t.runs_dir / t.run_id, 0.1,
                                        {"tasks": 10, "tasks_placed": round(10 * success[policy][loops])}))

    s = parse_spec(spec(grid={"policy.name": ["none", "heuristic"], "loops": [2, 4, 6, 8, 10, 12]},
                        capacity={"thresholds": [1.0, 0.98], "stop_after": 2}), SCENARIOS)
    sweep = Sweep.create(s, tmp_path, scenarios_dir=SCENARIOS)
    cap = sweep.run(TableExecutor())  # type: ignore[arg-type]
    assert [loops for policy, loops in ran if policy == "none"] == [2, 4, 6, 8], "stopped after 6 and 8 failed"
    assert [loops for policy, loops in ran if policy == "heuristic"] == [2, 4, 6, 8, 10, 12]
    assert ran[:4] == [("none", 2), ("heuristic", 2), ("none", 4), ("heuristic", 4)], "one load at a time"
    assert cap["series"]["policy.name=none"]["success>=100%"]["capacity"] == 4
    assert sweep.dir.meta()["passed_over"] == 2 and sweep.progress.snapshot()["total"] == 10
    assert "Not run: 2 points" in (tmp_path / sweep.sweep_id / "report.md").read_text()


def test_seeds_added_on_resume_join_a_stopped_series_up_to_its_stop(tmp_path: Path) -> None:
    from experiments.point_runs import PointOutcome, PointTask
    from experiments.sweep import Sweep

    ran: list[tuple[int, int]] = []  # (seed, loops) of `none`, which fails from 6 loops

    class TableExecutor:
        name = "table"

        def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: Any) -> None:
            for t in tasks:
                on_start(t)
                loops = t.point.values["loops"]
                ran.append((t.point.seed, loops))
                on_done(t, PointOutcome(t.point.key, t.run_id, "completed", None, t.runs_dir / t.run_id, 0.1,
                                        {"tasks": 10, "tasks_placed": 10 if loops < 6 else 5}))

    grid = {"policy.name": ["none"], "loops": [2, 4, 6, 8, 10, 12]}
    capacity = {"thresholds": [1.0, 0.98], "stop_after": 2}
    sweep = Sweep.create(parse_spec(spec(grid=grid, capacity=capacity), SCENARIOS), tmp_path,
                         scenarios_dir=SCENARIOS)
    sweep.run(TableExecutor())  # type: ignore[arg-type]
    assert ran == [(1, 2), (1, 4), (1, 6), (1, 8)]
    ran.clear()
    resumed = Sweep(parse_spec(spec(grid=grid, capacity=capacity, seeds=2), SCENARIOS), sweep.dir.path,
                    scenarios_dir=SCENARIOS)
    resumed.run(TableExecutor())  # type: ignore[arg-type]
    assert ran == [(2, 2), (2, 4), (2, 6), (2, 8)], "the new seed runs where the series ran, and stops with it"


def test_a_capacity_no_load_failed_is_a_lower_bound() -> None:
    from experiments.summary import capacity_text, gain_text

    c = capacity_of_curve([(4, 1.0), (8, 1.0)], 1.0)
    assert c["lower_bound"] and capacity_text(c) == ">= 8"
    assert gain_text({"ratio": 2.0}, c) == ">= 2x"
    c = capacity_of_curve([(4, 1.0), (8, 0.5), (12, 1.0)], 1.0)
    assert not c["lower_bound"] and capacity_text(c) == "4 (passes again up to 12)"


def cell_point(cell: str, loops: int, policy: str, tasks: int, placed: int) -> dict[str, Any]:
    return {**point(loops, policy, 1, tasks, placed), "key": f"{cell}{loops}{policy}", "variant": cell}


def test_grouped_capacity_reads_gains_and_the_invariant_within_each_cell() -> None:
    curves = {  # cell -> policy -> placed of 10 tasks at loads 4, 8, 12, 16
        "fast": {"none": [10, 10, 4, 1], "heuristic": [10, 9, 10, 10]},
        "slow": {"none": [10, 10, 10, 2], "heuristic": [10, 10, 10, 10]},
        "dense": {"none": [8, 8, 2, 1], "heuristic": [9, 9, 9, 9]},  # the arm cannot keep up
    }
    points = [cell_point(c, load, pol, 10, placed) for c, by in curves.items() for pol, ys in by.items()
              for load, placed in zip((4, 8, 12, 16), ys, strict=True)]
    grid = {"variant": list(curves), "policy.name": ["none", "heuristic"], "loops": [4, 8, 12, 16]}
    rows = summarise(points, grid)
    g = grouped_capacity(rows, "loops", ["variant", "policy.name"], [1.0], "policy.name=none", "variant")
    fast, slow, dense = (g["groups"][c] for c in ("fast", "slow", "dense"))
    assert fast["invariant"]["policy.name=heuristic"] == {"holds_upto": 4, "breaks_at": 8, "loads": 2}
    assert slow["invariant"]["policy.name=heuristic"] == {"holds_upto": 12, "breaks_at": None, "loads": 3}
    assert slow["gain_over_reference"]["policy.name=heuristic"]["success>=100%"]["ratio"] == pytest.approx(16 / 12)
    assert slow["series"]["policy.name=heuristic"]["success>=100%"]["lower_bound"]
    assert dense["reference_limited"] and not fast["reference_limited"]
    # The arm-limited cell is left out of the shares; the fast cell's gain is 4 / 8.
    assert g["gain_shares"]["policy.name=heuristic"]["success>=100%"] == [pytest.approx(0.5), pytest.approx(16 / 12)]


def test_the_capacity_group_must_be_a_grid_field_other_than_the_load() -> None:
    assert "capacity.group" in errors_of(spec(capacity={"group": "seed"}))[0][1]
    assert "load axis" in errors_of(spec(capacity={"group": "loops"}))[0][1]


def test_excluded_combinations_are_not_run_and_the_family_runs_pdp_1_once() -> None:
    s = parse_spec(spec(grid={"policy.name": ["none", "heuristic"], "policy.floor": [True, False],
                              "loops": [2, 4]}, seeds=2,
                        exclude=[{"policy.name": "none", "policy.floor": False}]), SCENARIOS)
    assert s.points() == 3 * 2 * 2
    points = expand(s, SCENARIOS)
    assert len(points) == s.points()
    assert {(p.scenario.policy.name, p.scenario.policy.floor) for p in points} == {
        ("none", True), ("heuristic", True), ("heuristic", False)}
    family = load_spec(ROOT / "configs" / "sweeps" / "family.yaml", SCENARIOS)
    assert family.points() == 13 * 5 * 15 * 3, "13 cells x 5 series x 15 loads x 3 seeds"
    assert "policy.name=none, policy.floor=False" not in family.series_names()


def test_bad_exclusions_are_named_with_what_is_allowed() -> None:
    grid = {"policy.name": ["none", "heuristic"], "loops": [2, 4]}
    [(field, msg)] = errors_of(spec(grid=grid, exclude=[{"policy.nam": "none"}]))
    assert field == "(sweep)" and "exclude[0].policy.nam: not a grid field" in msg and "policy.name" in msg
    [(field, msg)] = errors_of(spec(grid=grid, exclude=[{"policy.name": "learned"}]))
    assert "exclude[0].policy.name = 'learned' is not one of its grid values ('none', 'heuristic')" in msg
    [(field, msg)] = errors_of(spec(grid=grid, exclude=[{}]))
    assert "exclude[0] names no field" in msg


def test_the_capacity_reference_must_name_a_series_that_runs() -> None:
    grid = {"policy.name": ["none", "heuristic"], "loops": [2, 4]}
    [(field, msg)] = errors_of(spec(grid=grid, capacity={"reference": "policy.name=nne"}))
    assert "capacity.reference = 'policy.name=nne' names no series" in msg
    assert "'policy.name=none', 'policy.name=heuristic'" in msg
    [(field, msg)] = errors_of(spec(grid=grid, capacity={"reference": "policy.name=none"},
                                    exclude=[{"policy.name": "none"}]))
    assert "names no series" in msg, "an excluded series is no reference"
    partial = parse_spec(spec(grid={"variant": ["a", "b"], **grid}, variants={"a": {"duration_s": 2.0},
                                                                              "b": {"duration_s": 3.0}},
                              capacity={"reference": "policy.name=none"}), SCENARIOS)
    assert partial.capacity.reference == "policy.name=none", "part of a series: read within each variant"


def test_the_map_field_must_be_a_grid_field() -> None:
    assert "figures.map_y" in errors_of(spec(figures={"map_y": "seed"}))[0][1]


def test_a_spec_written_with_old_field_names_loads_under_the_new_ones() -> None:
    data = {"name": "old", "base": "baseline", "grid": {"loops": [2], "cell.belt_speed_m_s": [0.2, 0.3]},
            "set": {"cell.object_period_s": 3.0}, "variants": {"v": {"hall.cells_per_row": 4}}}
    with pytest.warns(FutureWarning):
        spec = parse_spec(data)
    assert set(spec.grid) == {"variant", "loops", "work_cell.belt_speed_m_s"}
    assert spec.set == {"work_cell.object_period_s": 3.0} and spec.variants == {"v": {"hall.work_cells_per_row": 4}}


def test_values_that_would_break_the_engine_are_refused_naming_their_field() -> None:
    # A grid value that gives the points another one gives would share its run directory.
    [(field, msg)] = errors_of(spec(grid={"loops": [2, 2.0]}))
    assert field == "grid.loops[1]" and "give each value once" in msg
    # A variant named by a list, a range too wide to count, a long name, seeds past 32 bits.
    assert "not in variants" in errors_of(spec(variants={"a": {"loops": 2}}, grid={"variant": [["a"]]}))[0][1]
    assert "at most 1000" in errors_of(spec(grid={"loops": {"start": 0, "stop": 1e300, "step": 1e-300}}))[0][1]
    assert errors_of(spec(name="a" * 65))[0][0] == "name"
    assert "0..4294967295" in errors_of(spec(seeds=[1, 2**32 + 1]))[0][1]
    # Both sides of a scale are numbers before anything is multiplied.
    errs = errors_of(spec(grid={"duration_s": [1.5], "loops": [2]}, scale={"duration_s": "hall.gnb_position_m"},
                          set={"hall.gnb_position_m": [60, 30, 1.5]}))
    assert errs[0][0] == "scale.duration_s" and "not a finite number" in errs[0][1]


def test_a_grid_excluded_whole_or_too_large_before_exclusion_is_refused() -> None:
    grid = {"policy.name": ["none", "heuristic"], "loops": [2, 4]}
    [(_, msg)] = errors_of(spec(grid=grid, exclude=[{"policy.name": "none"}, {"policy.name": "heuristic"}]))
    assert "every grid combination is excluded" in msg
    big = {"loops": {"start": 1, "stop": 1000, "step": 1}, "duration_s": {"start": 1, "stop": 1000, "step": 1},
           "policy.name": ["none", "heuristic"]}
    errs = errors_of(spec(grid=big, exclude=[{"policy.name": "none"}]))
    assert "points" in errs[0][1] and "at most 100000" in errs[0][1]


def test_a_caller_check_holds_every_resolved_point_and_errors_stop_at_a_cap() -> None:
    def short(sc: Any) -> list[tuple[str, str]]:
        return [("duration_s", f"{sc.duration_s:g} s is too long")] if sc.duration_s > 30 else []

    def refused(data: dict[str, Any]) -> list[tuple[str, str]]:
        with pytest.raises(SweepError) as exc:
            parse_spec(data, SCENARIOS, check=short)
        return exc.value.errors

    assert refused(spec(set={"duration_s": 40})) == [("set.duration_s", "40 s is too long")]
    assert refused(spec(grid={"loops": [2], "duration_s": [10, 40]}))[0][0] == "grid.duration_s[1]"
    assert refused(spec(variants={"v": {"duration_s": 45}}))[0][0] == "variants.v.duration_s"
    errs = refused(spec(grid={"duration_s": [20], "loops": [2]}, scale={"duration_s": "loops"}))
    assert errs and all("40 s" in msg for _, msg in errs)
    many = refused(spec(grid={"loops": {"start": 1, "stop": 200, "step": 1}, "duration_s": [5]},
                        set={"watchdog.run_timeout_s": 10.0, "detailed_loops": 0, "hall.work_cells_per_row": 1}))
    assert 1 < len(many) <= 21 and many[-1][0] == "(sweep)"


def test_a_grid_load_without_a_result_leaves_the_capacity_a_bound_and_ends_the_invariant() -> None:
    from experiments.summary import invariant

    grid = {"policy.name": ["none", "heuristic"], "loops": [4, 8, 12]}
    rows = summarise([point(4, "none", 1, 50, 50), point(12, "none", 1, 50, 50),  # 8 never ran
                      point(4, "heuristic", 1, 50, 50), point(8, "heuristic", 1, 50, 50),
                      point(12, "heuristic", 1, 50, 50)], grid)
    cap = capacity(rows, "loops", ["policy.name"], [1.0], "policy.name=none", loads=grid["loops"])
    entry = cap["series"]["policy.name=none"]["success>=100%"]
    assert (entry["capacity"], entry["lower_bound"], entry["missing"]) == (4, True, [8])
    # Nothing is known of the reference at 8: the invariant is checked up to 4 only.
    none = [r for r in rows if r["policy.name"] == "none"]
    mine = [r for r in rows if r["policy.name"] == "heuristic"]
    assert invariant(mine, none, "loops", grid["loops"]) == {"holds_upto": 4, "breaks_at": None, "loads": 1}


def test_a_reference_naming_part_of_a_series_compares_each_series_with_its_twin() -> None:
    grid = {"policy.signalling": ["app", "lower"], "policy.name": ["heuristic", "none"], "loops": [4, 8, 12]}
    fails = {("app", "none"): 8, ("lower", "none"): 12, ("app", "heuristic"): 12, ("lower", "heuristic"): 99}
    pts = [{**point(load, pol, 1, 50, 50 if load < fails[sig, pol] else 40), "policy.signalling": sig,
            "key": f"{sig}{pol}{load}"} for sig in grid["policy.signalling"] for pol in grid["policy.name"]
           for load in grid["loops"]]
    cap = capacity(summarise(pts, grid), "loops", ["policy.signalling", "policy.name"], [1.0],
                   "policy.name=none", loads=grid["loops"])
    assert cap["references"]["policy.signalling=lower, policy.name=heuristic"] == \
        "policy.signalling=lower, policy.name=none"
    gains = cap["gain_over_reference"]
    assert gains["policy.signalling=app, policy.name=heuristic"]["success>=100%"]["ratio"] == 2.0  # 8 / 4
    # Over a reference of 8 that is exact, a series that never failed gains at least 12 / 8.
    lower = gains["policy.signalling=lower, policy.name=heuristic"]["success>=100%"]
    assert lower["ratio"] == 1.5 and not lower["reference_lower_bound"]


def test_a_group_without_its_reference_has_no_gains_and_bounds_on_both_sides_no_ratio() -> None:
    from experiments.summary import gain_text

    pts = [cell_point("a", 4, "none", 10, 10), cell_point("a", 8, "none", 10, 9),
           cell_point("a", 4, "learned", 10, 10), cell_point("a", 8, "learned", 10, 10),
           cell_point("b", 4, "learned", 10, 10), cell_point("b", 8, "learned", 10, 10)]
    grid = {"variant": ["a", "b"], "policy.name": ["none", "learned"], "loops": [4, 8]}
    g = grouped_capacity(summarise(pts, grid), "loops", ["variant", "policy.name"], [1.0],
                         "policy.name=none", "variant", grid["loops"])
    assert g["groups"]["b"]["gain_over_reference"] == {}
    assert g["gain_shares"]["policy.name=learned"]["success>=100%"] == [2.0]  # cell a alone
    # Both capacities only bounds: no ratio; only the reference's: at most.
    rows = summarise([point(load, pol, 1, 10, 10) for pol in ("none", "learned") for load in (4, 8)]
                     + [point(4, "heuristic", 1, 10, 10), point(8, "heuristic", 1, 10, 9)],
                     {"policy.name": ["none", "learned", "heuristic"], "loops": [4, 8]})
    cap = capacity(rows, "loops", ["policy.name"], [1.0], "policy.name=none", loads=[4, 8])
    gains = cap["gain_over_reference"]
    assert gains["policy.name=learned"]["success>=100%"]["ratio"] is None
    heuristic = gains["policy.name=heuristic"]["success>=100%"]
    assert gain_text(heuristic, cap["series"]["policy.name=heuristic"]["success>=100%"]) == "<= 0.5x"


def test_seeds_added_until_enough_tasks_let_a_series_run_the_loads_it_had_passed_over(tmp_path: Path) -> None:
    from experiments.point_runs import PointOutcome, PointTask
    from experiments.sweep import Sweep

    ran: list[tuple[int, int]] = []  # (seed, loops); seed 1 misses a part at loads 4 and 6

    class TableExecutor:
        name = "table"

        def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: Any) -> None:
            for t in tasks:
                on_start(t)
                loops, seed = t.point.values["loops"], t.point.seed
                ran.append((seed, loops))
                on_done(t, PointOutcome(t.point.key, t.run_id, "completed", None, t.runs_dir / t.run_id, 0.1,
                                        {"tasks": 10, "tasks_placed": 9 if seed == 1 and loops in (4, 6) else 10}))

    data = spec(grid={"policy.name": ["none"], "loops": [2, 4, 6, 8]}, repeat_until={"min_tasks": 100, "max_seeds": 10},
                capacity={"thresholds": [0.98], "stop_after": 2})
    sweep = Sweep.create(parse_spec(data, SCENARIOS), tmp_path, scenarios_dir=SCENARIOS)
    cap = sweep.run(TableExecutor())  # type: ignore[arg-type]
    # Seed 1 stopped the series at 4 and 6 (90 %); pooled over 10 seeds they pass (99 %), so 8 runs.
    assert ran.index((1, 8)) > ran.index((10, 6)) and {s for s, loops in ran if loops == 8} == set(range(1, 11))
    assert cap["series"]["policy.name=none"]["success>=98%"]["capacity"] == 8
    assert sweep.dir.meta()["passed_over"] == 0


def test_a_line_cut_short_by_a_crash_does_not_swallow_the_next_record(tmp_path: Path) -> None:
    sweep = SweepDir(tmp_path)
    sweep.append({"key": "a", "status": "completed"})
    sweep.log_path.write_bytes(sweep.log_path.read_bytes() + b'{"key": "b", "sta')  # died mid-write
    sweep.append({"key": "c", "status": "completed"})
    assert [r["key"] for r in sweep.records()] == ["a", "c"]
    assert sweep.completed_keys() == {"a", "c"}


@pytest.mark.parametrize("where", [{"set": {"seed": 42}}, {"grid": {"loops": [1], "seed": [7, 8]}},
                                   {"variants": {"a": {"seed": 3}}}])
def test_a_seed_outside_seeds_is_refused(where: dict[str, Any]) -> None:
    spec = {"name": "s", "base": "baseline", "grid": {"loops": [1]}, **where}
    with pytest.raises(SweepError, match=r"seed in .*: a sweep's seeds are its `seeds`"):
        parse_spec(spec)


def test_a_sweep_directory_another_process_runs_is_refused_and_left_as_it_is(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import subprocess
    import sys

    from experiments.records import SweepBusy
    from experiments.sweep import Sweep

    class NoRun:
        name = "none"

        def run(self, tasks: Any, on_start: Any, on_done: Any, cancel: Any) -> None:
            raise AssertionError("a busy sweep must run no point")

    sweep = Sweep.create(parse_spec(spec(grid={"loops": [2]}), SCENARIOS), tmp_path, scenarios_dir=SCENARIOS)
    meta, spec_text = sweep.dir.meta(), (sweep.dir.path / "sweep.yaml").read_text()
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, pathlib; from experiments.records import SweepDir; "
         f"d = SweepDir(pathlib.Path({str(sweep.dir.path)!r})); d.hold(); print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2])
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with pytest.raises(SweepBusy, match=rf"being run by another runner \(pid {holder.pid}\)"):
            sweep.run(NoRun())  # type: ignore[arg-type]
        assert sweep.dir.meta() == meta, "the holder's sweep.json is not touched"
        other = tmp_path / "other.yaml"
        other.write_text(spec_text.replace("loops:\n  - 2", "loops:\n  - 2\n  - 4"))
        assert main(["sweep", "--resume", str(sweep.dir.path), str(other)]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
        assert (sweep.dir.path / "sweep.yaml").read_text() == spec_text, "nor is its spec"
    finally:
        holder.communicate("")  # the holder ends; the kernel drops its lock
    ran: list[str] = []

    class OneRun:
        name = "one"

        def run(self, tasks: Any, on_start: Any, on_done: Any, cancel: Any) -> None:
            from experiments.point_runs import PointOutcome
            for t in tasks:
                ran.append(t.run_id)
                on_done(t, PointOutcome(t.point.key, t.run_id, "completed", None, t.runs_dir / t.run_id, 0.1,
                                        {"tasks": 1, "tasks_placed": 1}))

    sweep.run(OneRun())  # type: ignore[arg-type]
    assert len(ran) == 1 and sweep.dir.meta()["state"] == "completed"
    first_end = sweep.dir.meta()["finished"]
    sweep.dir.hold()  # the runner's own hold is taken again by its run, and dropped at its end
    sweep.run(OneRun())  # type: ignore[arg-type]
    SweepDir(sweep.dir.path).hold()  # released: a new runner takes it
    assert sweep.dir.meta()["finished"] >= first_end


def test_a_resumed_sweep_does_not_show_its_previous_end_while_it_runs(tmp_path: Path) -> None:
    from experiments.sweep import Sweep

    seen: list[dict[str, Any]] = []
    sweep = Sweep.create(parse_spec(spec(grid={"loops": [2]}), SCENARIOS), tmp_path, scenarios_dir=SCENARIOS)
    sweep.dir.write_meta({**sweep.dir.meta(), "state": "cancelled", "finished": "2026-01-01T00:00:00+00:00",
                          "reason": "cancelled by the user", "wall_s": 5.0})

    class Watch:
        name = "watch"

        def run(self, tasks: Any, on_start: Any, on_done: Any, cancel: Any) -> None:
            seen.append(sweep.dir.meta())

    sweep.run(Watch())  # type: ignore[arg-type]
    assert seen[0]["state"] == "running" and not {"finished", "reason", "wall_s"} & set(seen[0])
