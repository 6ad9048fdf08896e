"""The results pages the API serves to a browser: plain server-side HTML, no JavaScript.

``/`` lists the sweeps (progress of the running ones) and the recent runs; ``/sweeps/{id}`` shows
one sweep: its progress while it runs (the page reloads itself), and once it is done the capacity
table and the study's figures (Fig. 4-6), then every point with its state and KPIs.
"""

from __future__ import annotations

from html import escape
from typing import Any

from coordinator.run_state import ACTIVE, RunState
from experiments.summary import capacity_text, gain_text

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
.bar { background: #eee; width: 300px; height: 1em; display: inline-block; vertical-align: middle; }
.bar span { background: #4a8; height: 100%; display: block; }
.state-completed { color: #272; } .state-failed, .state-timed_out { color: #b22; }
.state-running { color: #26b; } .state-cancelled { color: #777; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.5em 0; }
"""
FIGURES = (("fig4_success", "Fig. 4: task success rate vs loops"),
           ("fig5_traffic", "Fig. 5: uplink traffic injected and delivered vs loops"),
           ("fig6_latency_cdf", "Fig. 6: uplink IP packet latency CDF"))
# Drawn only when the spec asks: (stem, title, the spec's section and field that asks).
OPTIONAL_FIGURES = (("fig7_gain", "Fig. 7: capacity gain over the reference, per group", "capacity", "group"),
                    ("fig8_map", "Fig. 8: task success rate map", "figures", "map_y"))


def _page(title: str, body: str, refresh_s: int | None = None) -> str:
    refresh = f'<meta http-equiv="refresh" content="{refresh_s}">' if refresh_s else ""
    return (f"<!doctype html><html><head><meta charset='utf-8'>{refresh}<title>{escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>{body}</body></html>")


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return escape(str(v))


def _state(s: str) -> str:
    return f'<span class="state-{escape(s)}">{escape(s)}</span>'


def _bar(done: int, total: int) -> str:
    pct = 100 * done / total if total else 0
    return f'<span class="bar"><span style="width:{pct:.0f}%"></span></span> {done}/{total}'


def index_page(sweeps: list[dict[str, Any]], runs: list[dict[str, Any]]) -> str:
    rows = "".join(
        f'<tr><td class="l"><a href="/sweeps/{escape(s["sweep_id"])}">{escape(s["sweep_id"])}</a></td>'
        f'<td class="l">{escape(s["name"])}</td><td class="l">{_state(s["state"])}</td>'
        f'<td class="l">{_bar(s["progress"]["points_done"], s["progress"]["points_total"])}</td></tr>'
        for s in sweeps)
    run_rows = "".join(
        f'<tr><td class="l">{escape(r["run_id"])}</td><td class="l">{escape(r["scenario"])}</td>'
        f'<td class="l">{_state(r["status"])}</td><td>{_fmt(r.get("sim_time_s"))}</td>'
        f'<td>{_fmt(r.get("real_time_factor"))}</td></tr>' for r in runs)
    running = any(s["state"] in ACTIVE for s in sweeps)
    body = ("<h1>cosim5g</h1><h2>Sweeps</h2>"
            + (f'<table><tr><th class="l">sweep</th><th class="l">name</th><th class="l">state</th>'
               f'<th class="l">points</th></tr>{rows}</table>' if sweeps else "<p>No sweep yet.</p>")
            + "<h2>Runs</h2>"
            + (f'<table><tr><th class="l">run</th><th class="l">scenario</th><th class="l">state</th>'
               f'<th>sim s</th><th>speed</th></tr>{run_rows}</table>' if runs else "<p>No run yet.</p>"))
    return _page("cosim5g", body, refresh_s=10 if running else None)


def capacity_table(cap: dict[str, Any]) -> str:
    series = cap.get("series", {})
    if not series:
        return "<p>No capacity: no point completed.</p>"
    labels = list(next(iter(series.values())))
    head = "".join(f"<th>{escape(lab)}</th>" for lab in labels)
    rows = ""
    for name, entry in series.items():
        gains = cap.get("gain_over_reference", {}).get(name, {})
        cells = ""
        for lab in labels:
            cells += f"<td>{escape(capacity_text(entry[lab]))}</td>"
        gain = escape(" / ".join(gain_text(g, entry[lab]) for lab, g in gains.items()))
        rows += f'<tr><td class="l">{escape(name)}</td>{cells}<td>{gain}</td></tr>'
    ref = escape(str(cap.get("reference")))
    cell = cap.get("radio_cell_ul_capacity_mbps")
    note = f"<p>Radio cell uplink capacity (measured): {cell:.1f} Mbit/s.</p>" if cell else ""
    return (f'<table id="capacity"><tr><th class="l">series</th>{head}<th>gain over {ref}</th></tr>{rows}</table>'
            f"<p>Capacity: the largest {escape(str(cap.get('x')))} with every smaller one of the grid at or "
            f"above the task success threshold (success pooled over seeds).</p>{note}")


def sweep_page(s: dict[str, Any]) -> str:
    sid = escape(s["sweep_id"])
    prog = s["progress"]
    active = s["state"] in ACTIVE
    eta = f", ETA {prog['eta_s'] / 60:.1f} min" if prog.get("eta_s") is not None else ""
    failed = f", {prog['points_failed']} failed" if prog["points_failed"] else ""
    body = (f'<p><a href="/">all sweeps</a></p><h1>Sweep {sid}</h1>'
            f"<p>{_state(s['state'])}{': ' + escape(s['reason']) if s.get('reason') else ''} &nbsp; "
            f"{_bar(prog['points_done'], prog['points_total'])} points"
            f"{failed}{escape(eta)}</p>")
    if s.get("capacity"):
        body += "<h2>Capacity</h2>" + capacity_table(s["capacity"])
        spec = s["spec"]
        drawn = [(stem, title) for stem, title, section, field in OPTIONAL_FIGURES
                 if (spec.get(section) or {}).get(field)]
        for stem, title in (*FIGURES, *drawn):
            body += (f"<h2>{escape(title)}</h2><a href='/sweeps/{sid}/files/{stem}.svg'>"
                     f"<img alt='{escape(title)}' src='/sweeps/{sid}/files/{stem}.png'></a>")
        body += f"<p><a href='/sweeps/{sid}/report'>report.md</a></p>"
    fields = list(s["spec"]["grid"])
    head = "".join(f"<th>{escape(f)}</th>" for f in fields)
    rows = ""
    for p in s["points"]:
        k = p.get("kpis") or {}
        progress = f"sim {_fmt(p.get('sim_time_s'))} s" if p["state"] == RunState.RUNNING else escape(p.get("reason") or "")
        rows += ("<tr>" + "".join(f"<td>{_fmt(p['values'].get(f))}</td>" for f in fields)
                 + f"<td>{p['seed']}</td><td class='l'>{_state(p['state'])}</td><td>{_fmt(k.get('tasks'))}</td>"
                 f"<td>{_fmt(k.get('task_success_rate'))}</td><td>{_fmt(k.get('ul_injected_mbps'))}</td>"
                 f"<td>{_fmt(k.get('ul_ip_latency_ms.p99'))}</td><td class='l'>{progress}</td></tr>")
    body += (f"<h2>Points</h2><table><tr>{head}<th>seed</th><th class='l'>state</th><th>tasks</th>"
             f"<th>success</th><th>UL injected Mbit/s</th><th>UL p99 ms</th><th class='l'></th></tr>{rows}</table>")
    return _page(f"sweep {s['sweep_id']}", body, refresh_s=5 if active else None)
