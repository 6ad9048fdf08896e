"""Aggregation over seeds and the capacity rule (docs/architecture.md sec. 9, "Sweeps").

Per grid point: task success pooled over seeds with a Wilson 95% interval, every continuous KPI's
mean with a Student-t 95% interval. Capacity, per series and threshold: the largest load such
that every load up to it in the grid reaches the threshold.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from typing import Any

from coordinator.run_state import RunState

# Continuous KPIs summarised per grid point (keys of points' flattened KPIs).
METRICS = (
    "ul_injected_mbps", "ul_throughput_mbps", "dl_throughput_mbps", "camera_bitrate_mbps_mean",
    "ip_latency_ms.p50", "ip_latency_ms.p99", "ul_ip_latency_ms.p50", "ul_ip_latency_ms.p99",
    "real_time_factor", "wall_time_s",
)
# Two-sided 95% Student-t quantiles by degrees of freedom (1..30); 1.96 beyond.
_T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042)


def t95(df: int) -> float:
    return _T95[df - 1] if 1 <= df <= len(_T95) else 1.96


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float | None, float | None]:
    """Wilson score interval of a proportion."""
    if n == 0:
        return None, None
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At 0 or n successes the bound meets p exactly; rounding must not put it on the wrong side.
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def mean_ci(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and the half-width of its 95% interval (None from fewer than two values)."""
    if not values:
        return None, None
    m = sum(values) / len(values)
    if len(values) < 2:
        return m, None
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1))
    return m, t95(len(values) - 1) * sd / math.sqrt(len(values))


def summarise(points: list[dict[str, Any]], grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """One row per grid combination from the points table's rows (``kpi.*`` columns), in grid
    order (``grid``: field -> values as the spec lists them). Points of values the grid no longer
    lists (a resumed sweep whose grid was narrowed) are left out."""
    grid_fields = list(grid)
    points = [p for p in points if all(p.get(f) in grid[f] for f in grid_fields)]

    def order(p: dict[str, Any]) -> list[int]:
        return [grid[f].index(p.get(f)) for f in grid_fields]

    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for p in sorted(points, key=order):
        groups[json.dumps([p.get(f) for f in grid_fields])].append(p)
    rows = []
    for members in groups.values():
        done = [p for p in members if p["status"] == RunState.COMPLETED]
        tasks = sum(int(p.get("kpi.tasks") or 0) for p in done)
        placed = sum(int(p.get("kpi.tasks_placed") or 0) for p in done)
        low, high = wilson(placed, tasks)
        row: dict[str, Any] = {f: members[0].get(f) for f in grid_fields}
        row.update(runs=len(members), runs_completed=len(done),
                   seeds=",".join(str(p["seed"]) for p in sorted(members, key=lambda p: p["seed"])),
                   tasks=tasks, tasks_placed=placed, success_rate=placed / tasks if tasks else None,
                   success_ci_low=low, success_ci_high=high)
        for m in METRICS:
            vals = [float(v) for p in done if (v := p.get(f"kpi.{m}")) is not None]
            row[m], row[f"{m}_ci95"] = mean_ci(vals)
        rows.append(row)
    return rows


def series_name(row: dict[str, Any], series_fields: list[str]) -> str:
    return ", ".join(f"{f}={row.get(f)}" for f in series_fields) or "all"


def capacity(summary: list[dict[str, Any]], x: str, series_fields: list[str],
             thresholds: list[float], reference: str | None = None,
             loads: list[Any] | None = None) -> dict[str, Any]:
    """Capacity per series and threshold, and each series' gain over its reference series.

    ``loads``: the grid's values of ``x``; a series with no result at one of them knows nothing
    past it. ``reference`` names a series, or part of one: each series is then compared with the
    series that agrees with it on every other field (``references``); a series with none has
    no gain. Without a reference, the first series is every series' reference."""
    by_series: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for row in summary:
        by_series[series_name(row, series_fields)].append(row)
    out: dict[str, Any] = {"x": x, "thresholds": thresholds, "series": {}}
    for name, rows in by_series.items():
        curve = {r[x]: r["success_rate"] for r in rows}
        for load in loads or []:
            curve.setdefault(load, None)
        points = sorted(curve.items())
        out["series"][name] = {threshold_label(th): capacity_of_curve(points, th) for th in thresholds}
    names = list(out["series"])
    refs = references(names, reference)
    out["reference"] = reference if reference is not None else (names[0] if names else None)
    out["references"] = refs
    gains: dict[str, Any] = {}
    for name in names:
        ref = refs.get(name)
        if ref is None:
            continue
        g = {}
        for th in thresholds:
            label = threshold_label(th)
            mine, theirs = out["series"][name][label], out["series"][ref][label]
            a, b = mine["capacity"], theirs["capacity"]
            # Two capacities that are both only bounds have no known ratio.
            known = not (mine["lower_bound"] and theirs["lower_bound"]) or name == ref
            g[label] = {"ratio": a / b if a is not None and b and known else None,
                        "difference": a - b if a is not None and b is not None and known else None,
                        "reference_lower_bound": bool(theirs["lower_bound"]) and name != ref}
        gains[name] = g
    out["gain_over_reference"] = gains
    return out


def references(names: list[str], reference: str | None) -> dict[str, str | None]:
    """Each series' reference series (see ``capacity``), None where the spec's reference has no
    series that matches it."""
    if reference is None:
        return {n: names[0] for n in names}
    wanted = dict(part.split("=", 1) for part in reference.split(", ") if "=" in part)
    out: dict[str, str | None] = {}
    for name in names:
        parts = dict(part.split("=", 1) for part in name.split(", ") if "=" in part)
        twin = ", ".join(f"{f}={wanted.get(f, v)}" for f, v in parts.items())
        out[name] = twin if wanted and set(wanted) <= set(parts) and twin in names else None
    return out


def grouped_capacity(summary: list[dict[str, Any]], x: str, series_fields: list[str], thresholds: list[float],
                     reference: str | None, group: str, loads: list[Any] | None = None) -> dict[str, Any]:
    """``capacity`` within each value of the grid field ``group`` (e.g. each work cell), with
    each series' invariant against the group's reference series (``invariant``) and whether the
    reference itself misses tasks at the group's smallest load (``reference_limited``: the work
    cell cannot keep up whatever the network does; left out of ``gain_shares``).

    ``gain_shares``: per series and threshold, the gains over the reference of the groups that
    are not reference-limited, sorted, to read "at least G on a share S of the cells"."""
    inner = [f for f in series_fields if f != group]
    groups: dict[Any, list[dict[str, Any]]] = defaultdict(list)
    for row in summary:
        groups[row[group]].append(row)
    out: dict[str, Any] = {"group": group, "groups": {}}
    shares: dict[str, dict[str, list[float | None]]] = defaultdict(lambda: defaultdict(list))
    for value, rows in groups.items():
        cap = capacity(rows, x, inner, thresholds, reference, loads)
        by_series: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for row in rows:
            by_series[series_name(row, inner)].append(row)
        group_loads = sorted(set(loads or []) | {r[x] for r in rows})
        refs = cap["references"]
        ordered = {name: sorted(series, key=lambda r: r[x]) for name, series in by_series.items()}
        ref_of = {name: ordered.get(refs.get(name) or "", []) for name in ordered}
        cap["invariant"] = {name: invariant(series, ref_of[name], x, group_loads)
                            for name, series in ordered.items()}
        # Limited: a reference series that misses tasks at the group's smallest load.
        cap["reference_limited"] = any(rr and rr[0]["success_rate"] is not None and rr[0]["success_rate"] < 1.0
                                       for rr in ref_of.values())
        if not cap["reference_limited"]:
            for name, gains in cap["gain_over_reference"].items():
                if name == refs.get(name):
                    continue
                for label, g in gains.items():
                    shares[name][label].append(g["ratio"])
        out["groups"][str(value)] = cap
    out["gain_shares"] = {name: {label: sorted(v, key=lambda r: (r is None, r)) for label, v in by_label.items()}
                          for name, by_label in shares.items()}
    return out


def invariant(rows: list[dict[str, Any]], ref_rows: list[dict[str, Any]], x: str,
              loads: list[Any] | None = None) -> dict[str, Any]:
    """Where the reference series places every task (success 1 at a load), the series must too.
    ``holds_upto``: the largest load up to which it holds at every such load; ``breaks_at``: the
    first such load where the series places fewer (None: never); ``loads``: how many loads were
    checked. The check ends at the first load (of ``loads``, by default the reference's) where
    the reference or the series has no result: nothing is known there."""
    mine = {r[x]: r["success_rate"] for r in rows}
    theirs = {r[x]: r["success_rate"] for r in ref_rows}
    holds_upto, breaks_at, checked = None, None, 0
    for load in sorted(set(loads or []) | set(theirs)):
        ref_rate, rate = theirs.get(load), mine.get(load)
        if ref_rate is not None and ref_rate < 1.0:
            continue  # the reference misses tasks here: no constraint
        if ref_rate is None or rate is None:
            break
        checked += 1
        if rate < 1.0:
            breaks_at = load
            break
        holds_upto = load
    return {"holds_upto": holds_upto, "breaks_at": breaks_at, "loads": checked}


def capacity_text(entry: dict[str, Any]) -> str:
    """A capacity as a table shows it: ``>= 64`` when no load swept failed, with where a
    non-monotone curve passes again."""
    note = "" if entry["monotone"] else f" (passes again up to {entry['max_passing']})"
    return f"{'>= ' if entry.get('lower_bound') else ''}{entry['capacity']}{note}"


def gain_text(gain: dict[str, Any], entry: dict[str, Any]) -> str:
    """A gain over the reference series (``entry``: this series' capacity at that threshold):
    at least it where this capacity is a bound, at most it where the reference's is."""
    if gain["ratio"] is None:
        return "-"
    bound = ">= " if entry.get("lower_bound") else "<= " if gain.get("reference_lower_bound") else ""
    return f"{bound}{gain['ratio']:.3g}x"


def threshold_label(threshold: float) -> str:
    return f"success>={threshold * 100:g}%"


def capacity_of_curve(curve: list[tuple[Any, float | None]], threshold: float) -> dict[str, Any]:
    """``curve``: (load, success rate or None when the point has no result), sorted by load.

    capacity: the largest load with every load up to it at or above the threshold (0 when the
    smallest fails; a load without a result stops the scan, since nothing is known past it).
    lower_bound: no load of the curve fails, so the capacity lies at or beyond the largest load
    swept (extend the grid to find it), or the scan stopped at a load without a result.
    """
    eps = 1e-12
    cap: Any = 0
    first_fail = None
    unknown = False  # the scan stopped at a load without a result
    missing = []
    for load, rate in curve:
        if rate is None:
            missing.append(load)
            if first_fail is None:
                first_fail, unknown = load, True
            continue
        if rate + eps < threshold:
            if first_fail is None:
                first_fail = load
        elif first_fail is None:
            cap = load
    passing = [load for load, rate in curve if rate is not None and rate + eps >= threshold]
    max_passing = max(passing) if passing else 0
    return {"capacity": cap, "first_failing": first_fail, "max_passing": max_passing,
            "monotone": max_passing == cap, "missing": missing,
            "lower_bound": bool(curve) and (first_fail is None or unknown)}
