"""The study's figures, one function each: a table in, a matplotlib Figure out.

Fig. 4 success vs loops; 5 injected traffic and throughput vs loops, with the cell's capacity;
6 uplink latency CDF and tail at a few loads; 7 capacity gain over the reference per group
(reference-limited groups marked); 8 (``map_y``) success over two grid fields, a panel per group.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import FuncFormatter, MaxNLocator  # noqa: E402

from experiments.summary import series_name  # noqa: E402

MARKERS = "osD^vP*X"


def _load_axis(ax: Any, x: str, loads: list[Any]) -> None:
    ax.set_xlabel(f"{x} (control loops in the radio cell)" if x == "loops" else x)
    if all(isinstance(v, int) for v in loads):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _by_series(summary: list[dict[str, Any]], x: str, series_fields: list[str]) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for row in summary:
        out[series_name(row, series_fields)].append(row)
    return {k: sorted(v, key=lambda r: r[x]) for k, v in out.items()}


def success_figure(summary: list[dict[str, Any]], x: str, series_fields: list[str],
                   thresholds: list[float]) -> Figure:
    fig, ax = plt.subplots(figsize=(7, 4.2), layout="constrained")
    for i, (name, rows) in enumerate(_by_series(summary, x, series_fields).items()):
        rows = [r for r in rows if r["success_rate"] is not None]
        xs = [r[x] for r in rows]
        ys = np.array([r["success_rate"] * 100 for r in rows])
        lo = np.maximum(0.0, ys - np.array([r["success_ci_low"] * 100 for r in rows]))
        hi = np.maximum(0.0, np.array([r["success_ci_high"] * 100 for r in rows]) - ys)
        ax.errorbar(xs, ys, yerr=[lo, hi], marker=MARKERS[i % len(MARKERS)], capsize=3, label=name)
    for th in thresholds:
        ax.axhline(th * 100, color="grey", lw=0.8, ls=":")
    _load_axis(ax, x, [r[x] for r in summary])
    ax.set_ylabel("task success rate (%)")
    ax.set_title("Task success vs load (95% Wilson intervals)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    return fig


def traffic_figure(summary: list[dict[str, Any]], x: str, series_fields: list[str],
                   radio_cell_capacity_mbps: float | None) -> Figure:
    fig, ax = plt.subplots(figsize=(7, 4.2), layout="constrained")
    for i, (name, rows) in enumerate(_by_series(summary, x, series_fields).items()):
        colour = f"C{i}"
        xs = [r[x] for r in rows]
        for key, style, what in (("ul_injected_mbps", "--", "injected"), ("ul_throughput_mbps", "-", "throughput")):
            ys = [r[key] if r[key] is not None else np.nan for r in rows]
            err = [r[f"{key}_ci95"] or 0.0 for r in rows]
            ax.errorbar(xs, ys, yerr=err, ls=style, marker=MARKERS[i % len(MARKERS)], color=colour,
                        capsize=2, label=f"{name}: UL {what}")
    if radio_cell_capacity_mbps:
        ax.axhline(radio_cell_capacity_mbps, color="black", lw=1.0, ls="-.",
                   label=f"radio cell UL capacity (measured) {radio_cell_capacity_mbps:.1f} Mbit/s")
    _load_axis(ax, x, [r[x] for r in summary])
    ax.set_ylabel("Mbit/s")
    ax.set_title("Uplink traffic injected and delivered")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    return fig


def latency_figure(latencies_ms: dict[str, dict[Any, np.ndarray]], x: str) -> Figure:
    """``latencies_ms``: series -> load -> delivered uplink packet latencies (ms)."""
    fig, (ax, tail) = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
    styles = ["-", "--", ":", "-."]
    for i, (name, per_load) in enumerate(latencies_ms.items()):
        for j, (load, lat) in enumerate(sorted(per_load.items())):
            if lat.size == 0:
                continue
            v = np.sort(lat)
            cdf = np.arange(1, v.size + 1) / v.size
            # A run has up to millions of packets: keep a few thousand points, dense in the tail.
            idx = np.unique(np.concatenate([np.linspace(0, v.size - 1, 2000),
                                            v.size - np.logspace(0, np.log10(v.size), 500)]).astype(int))
            v, cdf = v[idx], cdf[idx]
            n = lat.size
            label = f"{name}, {x}={load}"
            ax.plot(v, cdf, color=f"C{i}", ls=styles[j % len(styles)], drawstyle="steps-post", label=label)
            # P(latency >= v): never zero, so the last packets stay on the log scale.
            tail.plot(v, 1 - cdf + 1 / n, color=f"C{i}", ls=styles[j % len(styles)],
                      drawstyle="steps-post", label=label)
    ax.set_xscale("log")
    ax.set_xlabel("uplink IP packet latency (ms)")
    ax.set_ylabel("CDF")
    ax.set_title("Latency CDF")
    ax.grid(alpha=0.3, which="both")
    tail.set_xscale("log")
    tail.set_yscale("log")
    tail.set_xlabel("uplink IP packet latency (ms)")
    tail.set_ylabel("P(latency >= x)")
    for a in (ax, tail):  # 3, 5, 10 ms rather than 3x10^0
        a.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        a.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:g}"[0] in "25" else ""))
    tail.set_title("Tail")
    tail.grid(alpha=0.3, which="both")
    if ax.lines:  # a sweep whose runs kept no packets draws empty axes
        ax.legend(fontsize=7, loc="lower right")
    return fig


def gain_figure(grouped: dict[str, Any], label: str) -> Figure:
    """Capacity gain over the reference per group and series at threshold ``label`` (a
    ``grouped_capacity`` record); a gain that is a lower bound (no load swept failed) is hatched,
    a group whose reference misses tasks at its smallest load is marked and has no bars."""
    groups = list(grouped["groups"])
    first = grouped["groups"][groups[0]] if groups else {"series": {}, "reference": None}
    ref = first["reference"]
    names = [n for n in first["series"] if n != ref and first.get("references", {}).get(n) != n]
    fig, ax = plt.subplots(figsize=(max(7.0, 0.6 * len(groups) * max(1, len(names)) / 2), 4.2), layout="constrained")
    width = 0.8 / max(1, len(names))
    for i, name in enumerate(names):
        labelled = False
        for j, g in enumerate(groups):
            cap = grouped["groups"][g]
            gain = cap["gain_over_reference"].get(name, {}).get(label, {}).get("ratio")
            if cap["reference_limited"] or gain is None:
                continue
            lower = cap["series"][name][label].get("lower_bound")
            ax.bar(j + (i - (len(names) - 1) / 2) * width, gain, width, color=f"C{i}",
                   hatch="//" if lower else None, label=None if labelled else name)
            labelled = True
    for j, g in enumerate(groups):
        if grouped["groups"][g]["reference_limited"]:
            ax.text(j, 0.05, "reference\nbelow 100%", ha="center", va="bottom", fontsize=7, rotation=90)
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xticks(range(len(groups)), groups, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("capacity gain over the reference")
    ax.set_title(f"Capacity gain per {grouped['group']} over {ref}\n({label}; hatched: at least, no load swept failed)",
                 fontsize=9)
    ax.grid(alpha=0.3, axis="y")
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncol=min(3, len(labels)), fontsize=8)
    return fig


def map_figure(summary: list[dict[str, Any]], x: str, y: str, group: str | None) -> Figure:
    """Fig. 8: the task success rate over grid fields ``x`` and ``y`` as a heat map, one panel per
    value of ``group`` (or one panel); each cell says placed / ended tasks."""
    groups = list(dict.fromkeys(r[group] for r in summary)) if group else [None]
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups) + 1, 3.8), layout="constrained",
                             squeeze=False)
    image = None
    for ax, g in zip(axes[0], groups, strict=True):
        rows = [r for r in summary if group is None or r[group] == g]
        xs = sorted({r[x] for r in rows})
        ys = sorted({r[y] for r in rows})
        grid = np.full((len(ys), len(xs)), np.nan)
        for r in rows:
            if r["success_rate"] is not None:
                i, j = ys.index(r[y]), xs.index(r[x])
                grid[i, j] = r["success_rate"] * 100
                ax.text(j, i, f"{r['tasks_placed']}/{r['tasks']}", ha="center", va="center", fontsize=7)
        image = ax.imshow(grid, origin="lower", aspect="auto", cmap="RdYlGn", vmin=0, vmax=100)
        ax.set_xticks(range(len(xs)), [f"{v:g}" for v in xs], rotation=45, fontsize=8)
        ax.set_yticks(range(len(ys)), [f"{v:g}" for v in ys], fontsize=8)
        ax.set_xlabel(x)
        ax.set_ylabel(y)
        ax.set_title(str(g) if g is not None else "task success", fontsize=9)
    if image is not None:
        fig.colorbar(image, ax=axes[0].tolist(), label="task success rate (%)")
    return fig


def save(fig: Figure, stem: Any) -> list[str]:
    """PNG and SVG beside each other; returns the file names."""
    names = []
    for ext in ("png", "svg"):
        path = stem.with_suffix(f".{ext}")
        fig.savefig(path, dpi=120)
        names.append(path.name)
    plt.close(fig)
    return names
