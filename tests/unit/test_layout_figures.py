"""Figures and capacity of sweeps over the gNB layout, on synthetic records (no run is started)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from experiments.figures_layout import (
    layout_capacity,
    layout_capacity_figure,
    sinr_cdf,
    sinr_figure,
)
from experiments.report_layout import layout_field, layout_figures, layout_lines
from experiments.spec import SweepError, SweepSpec, parse_spec
from scenario.schema import dump_scenario, load_scenario

ROOT = Path(__file__).parents[2]
SCENARIOS = ROOT / "configs" / "scenarios"
LAYOUTS = {"gnb1": {"hall.inf_layout.gnb_count": 1}, "gnb4": {"hall.inf_layout.gnb_count": 4}}


def layout_spec(**fields: Any) -> dict[str, Any]:
    data: dict[str, Any] = {"name": "t", "base": "factory_small", "variants": LAYOUTS,
                            "grid": {"variant": ["gnb1", "gnb4"], "policy.name": ["none", "heuristic"],
                                     "loops": [2, 4]},
                            "scale": {"loops": "hall.inf_layout.gnb_count"}, "seeds": 1,
                            "capacity": {"reference": "policy.name=none"}}
    data.update(fields)
    if "policy.name" not in data["grid"]:  # no policy series, so no reference among them
        data["capacity"] = {k: v for k, v in data["capacity"].items() if k != "reference"}
    return data


def row(layout: str, policy: str, loops: int, rate: float | None) -> dict[str, Any]:
    return {"variant": layout, "policy.name": policy, "loops": loops, "success_rate": rate}


def test_sinr_cdf_sorts_drops_nan_and_keeps_both_ends() -> None:
    v, cdf = sinr_cdf(np.array([3.0, np.nan, -1.0, 7.0, 3.0]))
    assert v.tolist() == [-1.0, 3.0, 3.0, 7.0]
    assert cdf.tolist() == [0.25, 0.5, 0.75, 1.0]
    big = np.arange(10_001, dtype=float)[::-1]
    v, cdf = sinr_cdf(big, points=101)
    assert v.size == 101 and v[0] == 0.0 and v[-1] == 10_000.0 and cdf[-1] == 1.0
    assert np.all(np.diff(v) > 0) and np.all(np.diff(cdf) > 0)
    assert np.allclose(cdf, (v + 1) / big.size)  # P(SINR <= v) at every kept point
    assert sinr_cdf(np.array([np.nan]))[0].size == 0


def test_sinr_figure_draws_a_curve_per_layout_and_link() -> None:
    data = {"1": {"ul": np.array([0.0, 10.0]), "dl": np.array([20.0])},
            "4": {"ul": np.array([-5.0, 0.0, 5.0, 10.0])}}
    fig = sinr_figure(data, "hall.inf_layout.gnb_count")
    ul, dl = fig.axes
    assert [line.get_xdata().tolist() for line in ul.lines] == [[0.0, 10.0], [-5.0, 0.0, 5.0, 10.0]]
    assert ul.lines[1].get_ydata().tolist() == [0.25, 0.5, 0.75, 1.0]
    assert [line.get_xdata().tolist() for line in dl.lines] == [[20.0]]  # the 4-gNB runs had no DL TB
    assert "hall.inf_layout.gnb_count=4 (4 TBs)" in [t.get_text() for t in ul.get_legend().get_texts()]


def summary_rows() -> list[dict[str, Any]]:
    # 1 gNB: none carries 10 per gNB at 100% (15 at 98%); heuristic passes every load (20+).
    # 4 gNBs: none 5 per gNB at both; heuristic 10 at 100%, 15 at 98%.
    curves = {("gnb1", "none"): [1.0, 1.0, 0.99, 0.9], ("gnb1", "heuristic"): [1.0, 1.0, 1.0, 1.0],
              ("gnb4", "none"): [1.0, 0.95, 0.9, 0.5], ("gnb4", "heuristic"): [1.0, 1.0, 0.985, 0.9]}
    return [row(lay, pol, load, rate) for (lay, pol), rates in curves.items()
            for load, rate in zip([5, 10, 15, 20], rates, strict=True)]


def test_layout_capacity_per_layout_and_series_in_hall_loops_and_per_gnb() -> None:
    caps = layout_capacity(summary_rows(), "loops", ["variant", "policy.name"], "variant", [1.0, 0.98],
                           {"gnb1": 1, "gnb4": 4}, per_gnb_x=True)
    assert set(caps) == {"policy.name=none", "policy.name=heuristic"}
    none = caps["policy.name=none"]
    assert [(r["gnbs"], r["loops"], r["per_gnb"]) for r in none["success>=100%"]] == [(1, 10, 10), (4, 20, 5)]
    assert [(r["gnbs"], r["loops"], r["per_gnb"]) for r in none["success>=98%"]] == [(1, 15, 15), (4, 20, 5)]
    heur = caps["policy.name=heuristic"]
    assert [(r["loops"], r["lower_bound"]) for r in heur["success>=100%"]] == [(20, True), (40, False)]
    assert [r["loops"] for r in heur["success>=98%"]] == [20, 60]
    # A load axis counting the hall's loops: capacity stays, per gNB divides.
    hall = layout_capacity(summary_rows(), "loops", ["variant", "policy.name"], "variant", [1.0],
                           {"gnb1": 1, "gnb4": 4}, per_gnb_x=False)
    assert [(r["loops"], r["per_gnb"]) for r in hall["policy.name=none"]["success>=100%"]] == [(10, 10.0), (5, 1.25)]
    # A layout whose gNB count is unknown (no completed run) is left out.
    partial = layout_capacity(summary_rows(), "loops", ["variant", "policy.name"], "variant", [1.0],
                              {"gnb4": 4}, per_gnb_x=True)
    assert [r["layout"] for r in partial["policy.name=none"]["success>=100%"]] == ["gnb4"]


def test_layout_capacity_figure_plots_the_curves() -> None:
    caps = layout_capacity(summary_rows(), "loops", ["variant", "policy.name"], "variant", [1.0, 0.98],
                           {"gnb1": 1, "gnb4": 4}, per_gnb_x=True)
    fig = layout_capacity_figure(caps)
    hall, per = fig.axes
    lines = {line.get_label(): line for line in hall.lines if not line.get_label().startswith("_")}
    heur = lines["policy.name=heuristic, success>=98%"]
    assert heur.get_xdata().tolist() == [1, 4] and heur.get_ydata().tolist() == [20, 60]
    per_lines = {line.get_label(): line for line in per.lines if not line.get_label().startswith("_")}
    assert per_lines["policy.name=none, success>=100%"].get_ydata().tolist() == [10, 5]


def test_the_layout_field_is_the_grid_field_or_variant_that_changes_the_layout() -> None:
    spec = SweepSpec.model_validate(layout_spec())
    assert layout_field(spec) == "variant"
    direct = SweepSpec.model_validate({"name": "t", "base": "factory_small",
                                       "grid": {"hall.inf_layout.gnb_count": [1, 4], "loops": [4]}})
    assert layout_field(direct) == "hall.inf_layout.gnb_count"
    same = SweepSpec.model_validate({"name": "t", "base": "factory_small",
                                     "variants": {"a": {"policy.name": "none"}, "b": {"policy.name": "heuristic"}},
                                     "grid": {"loops": [4]}})
    assert layout_field(same) is None


def test_scale_multiplies_a_grid_field_by_the_points_gnb_count() -> None:
    spec = parse_spec(layout_spec(), SCENARIOS)
    assert spec.fields({"variant": "gnb4", "policy.name": "none", "loops": 4})["loops"] == 16
    assert spec.fields({"variant": "gnb1", "policy.name": "none", "loops": 4})["loops"] == 4
    with pytest.raises(SweepError, match=r"scale\.loops.*neither in `set`, the grid"):
        parse_spec(layout_spec(variants={"a": {"policy.name": "none"}, "b": {"policy.name": "heuristic"}},
                               grid={"variant": ["a", "b"], "loops": [2]}), SCENARIOS)
    with pytest.raises(SweepError, match=r"scale\.duration_s: not a grid field"):
        parse_spec(layout_spec(scale={"duration_s": "hall.inf_layout.gnb_count"}), SCENARIOS)


def test_layout_figures_read_gnbs_and_sinr_from_the_runs(tmp_path: Path) -> None:
    spec = parse_spec(layout_spec(grid={"variant": ["gnb1", "gnb4"], "loops": [2]}), SCENARIOS)
    records, summary = [], []
    for layout, sinr in (("gnb1", [10.0, 12.0]), ("gnb4", [1.0, 3.0, 5.0])):
        run = tmp_path / "runs" / layout
        run.mkdir(parents=True)
        sc = load_scenario(SCENARIOS / "factory_small.yaml", [f"loops={2 * (4 if layout == 'gnb4' else 1)}",
                                                             f"hall.inf_layout.gnb_count={layout[3:]}"])
        (run / "config.yaml").write_text(dump_scenario(sc))
        pq.write_table(pa.table({"dir": ["ul"] * len(sinr) + ["dl"], "sinr_db": [*sinr, 30.0]}),
                       run / "transmissions.parquet")
        records.append({"status": "completed", "values": {"variant": layout, "loops": 2},
                        "run_dir": f"runs/{layout}"})
        summary.append(row(layout, "heuristic", 2, 1.0))
    figures, by_layout = layout_figures(spec, tmp_path, records, summary, ["variant"], "variant")
    assert by_layout["gnbs"] == {"gnb1": 1, "gnb4": 4}
    assert [(r["gnbs"], r["loops"], r["per_gnb"]) for r in by_layout["series"]["all"]["success>=100%"]] \
        == [(1, 2, 2), (4, 8, 2)]
    assert set(figures) == {"fig9_sinr_cdf", "fig10_layout_capacity"}
    assert (tmp_path / "fig9_sinr_cdf.png").stat().st_size > 0
    assert "| all | success>=100% | >= 2 (2/gNB) | >= 8 (2/gNB) |" in layout_lines(by_layout)
