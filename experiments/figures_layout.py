"""Figures of a sweep over the gNB layout of a hall (``hall.inf_layout``), one function each.

Fig. 9 the transmissions' effective SINR CDF, UL and DL, a curve per layout; Fig. 10 capacity
against the number of gNBs, a line per series, in loops of the hall and per gNB. The curves are
computed by ``sinr_cdf`` and ``layout_capacity`` (tested on their own); the figures draw them.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from experiments.figures import MARKERS  # noqa: E402
from experiments.summary import capacity, threshold_label  # noqa: E402

LINKS = ("ul", "dl")
CDF_POINTS = 2000  # points kept of a CDF: a run has up to millions of transmissions


def sinr_cdf(sinr_db: np.ndarray, points: int = CDF_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Empirical CDF of ``sinr_db`` (dB, NaN left out): sorted values and P(SINR <= value), at
    most ``points`` of them, evenly spaced in rank, the first and the last always kept."""
    v = np.sort(np.asarray(sinr_db, dtype=float))
    v = v[~np.isnan(v)]
    if v.size == 0:
        return v, v
    cdf = np.arange(1, v.size + 1) / v.size
    if v.size > points:
        idx = np.unique(np.linspace(0, v.size - 1, points).astype(int))
        v, cdf = v[idx], cdf[idx]
    return v, cdf


def sinr_figure(sinr_db: dict[str, dict[str, np.ndarray]], layout_field: str) -> Figure:
    """``sinr_db``: layout value (as text) -> link (``ul``, ``dl``) -> the effective SINR of
    every transmission of its runs, dB. A panel per link, a curve per layout."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained", sharey=True)
    for ax, link in zip(axes, LINKS, strict=True):
        for i, (layout, per_link) in enumerate(sinr_db.items()):
            values = per_link.get(link, np.empty(0))
            v, cdf = sinr_cdf(values)
            if v.size:
                ax.plot(v, cdf, color=f"C{i}", drawstyle="steps-post",
                        label=f"{layout_field}={layout} ({values.size} TBs)")
        ax.set_xlabel(f"{link.upper()} effective SINR of a transmission (dB)")
        ax.set_title(f"{link.upper()} SINR CDF")
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7, loc="lower right")
    axes[0].set_ylabel("CDF")
    return fig


def layout_capacity(summary: list[dict[str, Any]], x: str, series_fields: list[str],
                    layout_field: str, thresholds: list[float], gnbs: dict[str, int],
                    per_gnb_x: bool) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Capacity per layout, series (the grid fields besides ``x`` and ``layout_field``) and
    threshold: series -> threshold label -> rows sorted by gNB count, each with ``layout``,
    ``gnbs``, ``loops`` (the hall's), ``per_gnb`` and ``lower_bound`` (no load swept failed).

    ``gnbs``: layout value (as text) -> its number of gNBs; ``per_gnb_x``: the load ``x`` counts
    loops per gNB (the sweep scales it by the gNB count), else loops of the hall."""
    inner = [f for f in series_fields if f != layout_field]
    by_layout: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for row in summary:
        by_layout[str(row[layout_field])].append(row)
    out: dict[str, dict[str, list[dict[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for layout, rows in by_layout.items():
        n = gnbs.get(layout)
        if not n:
            continue
        cap = capacity(rows, x, inner, thresholds)
        for name, entry in cap["series"].items():
            for th in thresholds:
                label = threshold_label(th)
                load = entry[label]["capacity"]
                loops, per = (load * n, load) if per_gnb_x else (load, load / n)
                out[name][label].append({"layout": layout, "gnbs": n, "loops": loops, "per_gnb": per,
                                         "lower_bound": entry[label]["lower_bound"]})
    return {name: {lab: sorted(rows, key=lambda r: r["gnbs"]) for lab, rows in by_label.items()}
            for name, by_label in out.items()}


def layout_capacity_figure(caps: dict[str, dict[str, list[dict[str, Any]]]]) -> Figure:
    """Fig. 10 from ``layout_capacity``: loops of the hall (left) and per gNB (right) against the
    number of gNBs; a colour per series, a line style per threshold, hollow markers where the
    capacity is a lower bound (no load swept failed)."""
    fig, (ax, per) = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
    styles = ["-", "--", ":", "-."]
    labels = list(next(iter(caps.values()), {}))  # the thresholds in the spec's order
    for i, (name, by_label) in enumerate(caps.items()):
        for label, rows in by_label.items():
            ls = styles[labels.index(label) % len(styles)]
            n = [r["gnbs"] for r in rows]
            for a, key in ((ax, "loops"), (per, "per_gnb")):
                a.plot(n, [r[key] for r in rows], color=f"C{i}", ls=ls, label=f"{name}, {label}")
                for r in rows:
                    a.plot(r["gnbs"], r[key], MARKERS[i % len(MARKERS)], color=f"C{i}",
                           mfc="none" if r["lower_bound"] else f"C{i}")
    for a, what in ((ax, "capacity (loops in the hall)"), (per, "capacity per gNB (loops)")):
        a.set_xlabel("gNBs in the hall")
        a.set_ylabel(what)
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.set_ylim(bottom=0)
        a.grid(alpha=0.3)
    ax.set_title("Capacity vs gNBs (hollow: at least, no load swept failed)", fontsize=9)
    per.set_title("Capacity per gNB", fontsize=9)
    if ax.lines:
        ax.legend(fontsize=7, loc="upper left")
    return fig
