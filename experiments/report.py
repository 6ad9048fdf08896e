"""Everything a sweep concludes, rebuilt from its saved records only (``cosim5g report DIR``):
points and per-loop tables, the summary over seeds, capacity, the figures and ``report.md``.
Nothing is rerun, so a report can be remade after a change to the figures or the capacity rule.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import yaml

from coordinator.run_state import RunState
from experiments.figures import (
    gain_figure,
    latency_figure,
    map_figure,
    save,
    success_figure,
    traffic_figure,
)
from experiments.radio_capacity import measure_ul_capacity
from experiments.records import SweepDir, write_rows
from experiments.report_layout import TITLES as LAYOUT_TITLES
from experiments.report_layout import layout_field, layout_figures, layout_lines
from experiments.spec import SweepSpec
from experiments.summary import (
    capacity,
    capacity_text,
    gain_text,
    grouped_capacity,
    series_name,
    summarise,
    threshold_label,
)
from fabric.tables import write_json
from scenario.schema import load_scenario


def load_sweep_spec(sweep_dir: Path) -> SweepSpec:
    path = sweep_dir / "sweep.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"{sweep_dir} is not a sweep directory (no sweep.yaml)")
    return SweepSpec.model_validate(yaml.safe_load(path.read_text()))


def _radio_cell_capacity(sd: SweepDir, records: list[dict[str, Any]]) -> dict[str, Any] | None:
    cached = sd.path / "radio_cell_capacity.json"
    if cached.is_file():
        return dict(json.loads(cached.read_text()))
    for rec in records:
        config = sd.path / rec["run_dir"] / "config.yaml"
        if config.is_file():
            out = measure_ul_capacity(load_scenario(config))
            write_json(cached, out)
            return out
    return None


def _latency_loads(spec: SweepSpec, loads: list[Any]) -> list[Any]:
    if spec.figures.latency_loads:
        return [v for v in spec.figures.latency_loads if v in loads]
    loads = sorted(set(loads))
    return sorted({loads[0], loads[len(loads) // 2], loads[-1]}) if loads else []


def _ul_latencies_ms(run_dir: Path) -> np.ndarray:
    path = run_dir / "packets.parquet"
    if not path.is_file():
        return np.empty(0)
    t = pq.read_table(path, columns=["dir", "latency_us"])
    ul = t.column("dir").to_numpy(zero_copy_only=False) == "ul"
    lat = t.column("latency_us").to_numpy(zero_copy_only=False).astype(float)[ul]
    return lat[~np.isnan(lat)] / 1000


def rebuild(sweep_dir: Path) -> dict[str, Any]:
    """Write every derived file of ``sweep_dir``; returns the capacity record."""
    sd = SweepDir(sweep_dir)
    spec = load_sweep_spec(sweep_dir)
    grid_fields = list(spec.grid)
    x = spec.capacity.x
    series_fields = [f for f in grid_fields if f != x]
    records = sd.records()
    points = sd.write_points_table()
    sd.write_loops_table()
    summary = summarise(points, spec.grid_values())
    write_rows(sweep_dir / "summary.parquet", summary)
    loads = spec.grid_values()[x]
    cap = capacity(summary, x, series_fields, spec.capacity.thresholds, spec.capacity.reference, loads)
    if spec.capacity.group:
        cap["grouped"] = grouped_capacity(summary, x, series_fields, spec.capacity.thresholds,
                                          spec.capacity.reference, spec.capacity.group, loads)
    cell = _radio_cell_capacity(sd, records)
    cap["radio_cell_ul_capacity_mbps"] = cell["ul_capacity_mbps"] if cell else None
    write_json(sweep_dir / "capacity.json", cap)

    figures: dict[str, list[str]] = {}
    if summary:
        figures["fig4_success"] = save(success_figure(summary, x, series_fields, spec.capacity.thresholds),
                                       sweep_dir / "fig4_success")
        figures["fig5_traffic"] = save(traffic_figure(summary, x, series_fields,
                                                      cap["radio_cell_ul_capacity_mbps"]), sweep_dir / "fig5_traffic")
        loads = _latency_loads(spec, [r[x] for r in summary])
        lat: dict[str, dict[Any, np.ndarray]] = {}
        for rec in records:
            if rec["status"] != RunState.COMPLETED or rec["values"].get(x) not in loads:
                continue
            name = series_name(rec["values"], series_fields)
            per_load = lat.setdefault(name, {})
            load = rec["values"][x]
            per_load[load] = np.concatenate([per_load.get(load, np.empty(0)),
                                             _ul_latencies_ms(sweep_dir / rec["run_dir"])])
        figures["fig6_latency_cdf"] = save(latency_figure(lat, x), sweep_dir / "fig6_latency_cdf")
        if spec.figures.map_y:
            figures["fig8_map"] = save(map_figure(summary, x, spec.figures.map_y, spec.capacity.group),
                                       sweep_dir / "fig8_map")
        if (layout := layout_field(spec)) is not None:
            layout_figs, cap["by_layout"] = layout_figures(spec, sweep_dir, records, summary,
                                                           series_fields, layout)
            figures.update(layout_figs)
            write_json(sweep_dir / "capacity.json", cap)
        if "grouped" in cap:
            figures["fig7_gain"] = save(gain_figure(cap["grouped"], threshold_label(max(spec.capacity.thresholds))),
                                        sweep_dir / "fig7_gain")
    (sweep_dir / "report.md").write_text(render_report(spec, sd.meta(), summary, cap, cell, points, figures))
    return cap


def grouped_lines(grouped: dict[str, Any], labels: list[str], x: str) -> list[str]:
    """The report's section of a sweep grouped by condition: per group and series, the capacity
    at each threshold, the gain over the group's reference and where the invariant holds; then
    the share of groups each gain reaches."""
    group = grouped["group"]
    lines = ["", f"## Per `{group}`", "",
             f"Capacity within each `{group}`; the invariant: at every `{x}` where the reference places "
             "every task, the series does too (held up to / first broken at). A group whose reference "
             "misses tasks at its smallest load cannot keep up whatever the network does: reported, "
             "and left out of the gains.", "",
             f"| {group} | series | " + " | ".join(labels) + " | gain | invariant held up to | broken at |",
             "|---" * (len(labels) + 5) + "|"]
    for value, cap in grouped["groups"].items():
        for name, entry in cap["series"].items():
            gains = cap["gain_over_reference"].get(name, {})
            gain = ("reference below 100% at the smallest load" if cap["reference_limited"]
                    else " / ".join(gain_text(g, entry[lab]) for lab, g in gains.items()))
            inv = cap["invariant"].get(name, {})
            lines.append(f"| {value} | {name} | " + " | ".join(capacity_text(entry[lab]) for lab in labels)
                         + f" | {gain} | {_f(inv.get('holds_upto'))} | {_f(inv.get('breaks_at'))} |")
    lines += ["", "Gains over the reference, groups that keep up at the smallest load: "]
    for name, by_label in grouped["gain_shares"].items():
        for lab, ratios in by_label.items():
            known = [r for r in ratios if r is not None]
            if known:
                lines.append(f"- {name}, {lab}: smallest {min(known):.3g}x, median "
                             f"{float(np.median(known)):.3g}x over {len(known)} groups")
    return lines


def _f(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _pct(v: Any) -> str:
    return "-" if v is None else f"{v * 100:.1f}%"


def render_report(spec: SweepSpec, meta: dict[str, Any], summary: list[dict[str, Any]], cap: dict[str, Any],
                  cell: dict[str, Any] | None, points: list[dict[str, Any]], figures: dict[str, list[str]]) -> str:
    x = cap["x"]
    grid_fields = list(spec.grid)
    labels = list(next(iter(cap["series"].values())).keys()) if cap["series"] else []
    lines = [f"# Sweep `{meta.get('sweep_id', spec.name)}`", ""]
    lines += [f"Base scenario `{spec.base}`, fixed fields {json.dumps(spec.set) if spec.set else 'none'}; grid "
              + "; ".join(f"`{k}` in {v}" for k, v in spec.grid_values().items())
              + f"; seeds {spec.seed_list()}"
              + (f", more seeds (up to {spec.repeat_until.max_seeds}) until a grid point has "
                 f"{spec.repeat_until.min_tasks} tasks" if spec.repeat_until else "") + ".", ""]
    done = sum(1 for p in points if p["status"] == RunState.COMPLETED)
    lines += [f"Runs: {len(points)} ({done} completed). State: {meta.get('state', '-')}. "
              f"Wall time: {_f(meta.get('wall_s'))} s.", ""]
    if spec.variants:
        lines += ["Variants: " + "; ".join(f"`{name}` = " + ", ".join(f"{k}={v}" for k, v in fields.items())
                                           for name, fields in spec.variants.items()) + ".", ""]
    if meta.get("passed_over"):
        lines += [f"Not run: {meta['passed_over']} points past {spec.capacity.stop_after} consecutive "
                  f"loads of their series below {min(spec.capacity.thresholds) * 100:g}% success "
                  "(`capacity.stop_after`).", ""]
    lines += ["## Capacity", "",
              f"The largest `{x}` whose task success rate (pooled over seeds), and that of every smaller "
              f"`{x}` of the grid, reaches the threshold; `>=` where no load swept failed (the "
              f"capacity lies at or beyond the grid's end) or a load has no result yet. A gain is "
              f"over the reference series that agrees with the series on every other field; `<=` "
              f"where only the reference's capacity is a bound.", ""]
    lines += ["| series | " + " | ".join(labels) + " | gain over " + f"`{cap['reference']}` |",
              "|---" * (len(labels) + 2) + "|"]
    for name, entry in cap["series"].items():
        gains = cap["gain_over_reference"].get(name, {})
        cells = []
        for lab in labels:
            cells.append(capacity_text(entry[lab]))
        gain = " / ".join(gain_text(g, entry[lab]) for lab, g in gains.items())
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {gain} |")
    if "grouped" in cap:
        lines += grouped_lines(cap["grouped"], labels, x)
    if "by_layout" in cap:
        lines += layout_lines(cap["by_layout"])
    if cell:
        lines += ["", f"Radio cell uplink capacity: {cell['ul_capacity_mbps']:.1f} Mbit/s ({cell['method']})."]
    lines += ["", "## Figures", ""]
    titles = {"fig7_gain": "Fig. 7: capacity gain over the reference, per group",
              "fig8_map": "Fig. 8: task success rate map",
              "fig4_success": "Fig. 4: task success rate vs loops",
              "fig5_traffic": "Fig. 5: injected uplink traffic and throughput vs loops",
              "fig6_latency_cdf": "Fig. 6: uplink IP packet latency CDF", **LAYOUT_TITLES}
    for stem, files in figures.items():
        png = next(f for f in files if f.endswith(".png"))
        lines += [f"### {titles.get(stem, stem)}", "", f"![{titles.get(stem, stem)}]({png})", ""]
    lines += ["## Per grid point", "",
              "| " + " | ".join(grid_fields) + " | runs | tasks | success (95% CI) | UL injected Mbit/s | "
              "UL throughput Mbit/s | UL latency p50 / p99 ms | speed |",
              "|---" * (len(grid_fields) + 7) + "|"]
    for r in summary:
        ci = (f"{_pct(r['success_rate'])} ({_pct(r['success_ci_low'])}-{_pct(r['success_ci_high'])})"
              if r["success_rate"] is not None else "-")
        lines.append("| " + " | ".join(str(r[f]) for f in grid_fields)
                     + f" | {r['runs_completed']}/{r['runs']} | {r['tasks']} | {ci} | {_f(r['ul_injected_mbps'])} | "
                     f"{_f(r['ul_throughput_mbps'])} | {_f(r['ul_ip_latency_ms.p50'])} / "
                     f"{_f(r['ul_ip_latency_ms.p99'])} | {_f(r['real_time_factor'])}x |")
    failed = [p for p in points if p["status"] != RunState.COMPLETED]
    if failed:
        lines += ["", "## Runs that did not complete", ""]
        lines += [f"- {' '.join(f'{f}={p.get(f)}' for f in grid_fields)} seed={p['seed']}: {p['status']}: "
                  f"{p.get('reason')}" for p in failed]
    lines += ["", "Per-run rows: `points.parquet`; per-loop rows (tasks, failure causes, mean PDP, uplink "
              "latency and losses of every loop of every run): `loops.parquet`; over seeds: `summary.parquet`.", ""]
    return "\n".join(lines)
