"""The part of a sweep's report that compares gNB layouts (``hall.inf_layout``), rebuilt from the
saved runs: which grid field sweeps the layout, the gNBs of each of its values, the SINR of the
runs' transmissions per layout, Fig. 9 and 10 and the capacity-per-layout table.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from coordinator.run_state import RunState
from experiments.figures import save
from experiments.figures_layout import LINKS, layout_capacity, layout_capacity_figure, sinr_figure
from experiments.spec import VARIANT, SweepSpec
from netsim.nr.layout import layout_from_hall
from scenario.schema import load_scenario

LAYOUT_PREFIX = "hall.inf_layout"
TITLES = {"fig9_sinr_cdf": "Fig. 9: effective SINR of the transmissions per layout, UL and DL",
          "fig10_layout_capacity": "Fig. 10: capacity vs the number of gNBs, in the hall and per gNB"}


def layout_field(spec: SweepSpec) -> str | None:
    """The grid field that sweeps the gNB layout: a ``hall.inf_layout`` field with several
    values, or ``variant`` when the variants set one; None when the layout is the same in every
    point."""
    grid = spec.grid_values()
    for path, values in grid.items():
        if path.startswith(LAYOUT_PREFIX) and len(values) > 1:
            return path
    if VARIANT in grid and len(grid[VARIANT]) > 1:
        seen = {tuple(sorted((k, repr(v)) for k, v in spec.variants[name].items()
                             if k.startswith(LAYOUT_PREFIX))) for name in grid[VARIANT]}
        if len(seen) > 1:
            return VARIANT
    return None


def _gnb_count(run_dir: Path) -> int | None:
    config = run_dir / "config.yaml"
    if not config.is_file():
        return None
    layout = layout_from_hall(load_scenario(config).hall)
    return 1 if layout is None else layout.n_gnb


def _sinr_db(run_dir: Path) -> dict[str, np.ndarray]:
    path = run_dir / "transmissions.parquet"
    if not path.is_file():
        return {}
    t = pq.read_table(path, columns=["dir", "sinr_db"])
    link = t.column("dir").to_numpy(zero_copy_only=False)
    sinr = t.column("sinr_db").to_numpy(zero_copy_only=False).astype(float)
    return {k: sinr[link == k] for k in LINKS}


def layout_figures(spec: SweepSpec, sweep_dir: Path, records: list[dict[str, Any]],
                   summary: list[dict[str, Any]], series_fields: list[str], field: str
                   ) -> tuple[dict[str, list[str]], dict[str, Any]]:
    """Fig. 9 and 10 of a sweep whose ``field`` sweeps the layout, and the capacity per layout
    (``layout_capacity``'s record with each layout's gNB count)."""
    x = spec.capacity.x
    gnbs: dict[str, int] = {}
    sinr: dict[str, dict[str, list[np.ndarray]]] = {}
    for rec in records:
        if rec["status"] != RunState.COMPLETED or field not in rec["values"]:
            continue
        layout, run_dir = str(rec["values"][field]), sweep_dir / rec["run_dir"]
        if layout not in gnbs and (n := _gnb_count(run_dir)) is not None:
            gnbs[layout] = n
        for link, values in _sinr_db(run_dir).items():
            sinr.setdefault(layout, {}).setdefault(link, []).append(values)
    order = sorted(sinr, key=lambda lay: (gnbs.get(lay, 0), lay))
    pooled = {lay: {link: np.concatenate(parts) for link, parts in sinr[lay].items()} for lay in order}
    caps = layout_capacity(summary, x, series_fields, field, spec.capacity.thresholds, gnbs,
                           per_gnb_x=spec.scale.get(x, "").startswith(LAYOUT_PREFIX))
    figures = {"fig9_sinr_cdf": save(sinr_figure(pooled, field), sweep_dir / "fig9_sinr_cdf"),
               "fig10_layout_capacity": save(layout_capacity_figure(caps),
                                             sweep_dir / "fig10_layout_capacity")}
    return figures, {"field": field, "gnbs": gnbs, "series": caps}


def layout_lines(by_layout: dict[str, Any]) -> list[str]:
    """The report's table of capacity per layout: loops in the hall and per gNB."""
    lines = ["", f"## Per layout (`{by_layout['field']}`)", "",
             "Capacity of each layout in loops of the hall and per gNB (`>=`: no load swept failed).", "",
             "| series | threshold | " + " | ".join(
                 f"{lay} ({n} gNB{'s' if n > 1 else ''})" for lay, n in
                 sorted(by_layout["gnbs"].items(), key=lambda kv: kv[1])) + " |",
             "|---|---|" + "---|" * len(by_layout["gnbs"])]
    for name, by_label in by_layout["series"].items():
        for label, rows in by_label.items():
            cells = {r["layout"]: f"{'>= ' if r['lower_bound'] else ''}{r['loops']:g} ({r['per_gnb']:.3g}/gNB)"
                     for r in rows}
            lines.append(f"| {name} | {label} | " + " | ".join(
                cells.get(lay, "-") for lay, _ in sorted(by_layout["gnbs"].items(), key=lambda kv: kv[1]))
                + " |")
    return lines
