"""The ``cosim5g`` command line: validate scenarios, run them, run the standalone network simulator.

Exit codes: 0 success, 1 the run did not complete, 2 bad input (with a message naming the field).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from coordinator.conductor import Progress
from services.common.scenario import Scenario, ScenarioError, load_scenario

DEFAULT_RESULTS = Path("results") / "runs"


def _progress_printer(stream: Any) -> Any:
    def show(p: Progress) -> None:
        frac = p.t_us / p.end_us if p.end_us else 1.0
        bar = "#" * int(frac * 30)
        rtf = (p.t_us / 1e6) / p.wall_s if p.wall_s > 0 else 0.0
        stream.write(f"\r[{bar:<30}] sim {p.t_us / 1e6:7.2f}/{p.end_us / 1e6:.2f} s  "
                     f"rtf {rtf:5.2f}  windows {p.windows}")
        if p.t_us >= p.end_us:
            stream.write("\n")
        stream.flush()

    return show


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items()) or "-"
    return "-" if v is None else str(v)


def kpi_table(k: dict[str, Any]) -> str:
    rows = ["status", "reason", "loops", "tasks", "tasks_placed", "task_success_rate", "task_outcomes",
            "ul_injected_mbps", "ul_throughput_mbps", "camera_bitrate_mbps_mean", "ip_latency_ms",
            "lost_packets", "estimator", "sim_time_s", "wall_time_s", "real_time_factor", "windows",
            "trace_hash", "results_dir"]
    width = max(len(r) for r in rows)
    lines = [f"{r:<{width}}  {_fmt(k.get(r))}" for r in rows if r in k and (r != "reason" or k[r])]
    return "\n".join(lines)


def _load(path: str, overrides: list[str]) -> Scenario:
    return load_scenario(path, overrides)


def cmd_validate(args: argparse.Namespace) -> int:
    try:
        sc = _load(args.file, args.set or [])
    except ScenarioError as exc:
        print(f"{args.file}: invalid scenario\n{exc.format()}", file=sys.stderr)
        return 2
    print(f"{args.file}: ok ({sc.loops} loops, {sc.detailed_loops} detailed, policy {sc.policy.name}, "
          f"{sc.duration_s} s, runtime {sc.runtime})")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from coordinator.run import execute_run

    try:
        sc = _load(args.file, args.set or [])
    except ScenarioError as exc:
        print(f"{args.file}: invalid scenario\n{exc.format()}", file=sys.stderr)
        return 2
    cancel = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        cancel.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    progress = None if args.quiet else _progress_printer(sys.stderr)
    result = execute_run(sc, Path(args.results), on_progress=progress, cancel=cancel)
    k = result.kpis
    if k.get("status") != "completed":
        print(f"run {result.run_id} {k.get('status')}: {k.get('reason')}", file=sys.stderr)
        for line in k.get("log_tail") or []:
            print(f"  | {line}", file=sys.stderr)
    print(kpi_table(k))
    if args.json:
        print(json.dumps(k, sort_keys=True, default=str))
    return 0 if result.status == "completed" else 1


def cmd_netsim(args: argparse.Namespace) -> int:
    try:
        from netsim.standalone import main as netsim_main
    except ImportError:
        print("the standalone NR network simulator is not available in this build", file=sys.stderr)
        return 2
    return int(netsim_main(args.rest))


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from coordinator.api import create_app

    app = create_app(Path(args.results), Path(args.db), Path(args.scenarios))
    uvicorn.run(app, host=args.host, port=args.port, log_level="info")
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    from coordinator.client import ApiError, call, follow, wait_healthy

    try:
        wait_healthy(args.api, args.wait_s)
        body = {"scenario": args.scenario, "overrides": args.set or []}
        run_id = call(args.api, "POST", "/runs", body)["run_id"]
        print(f"run {run_id} submitted to {args.api}", file=sys.stderr)
        if not args.follow:
            print(run_id)
            return 0
        run = follow(args.api, run_id)
    except ApiError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    k = run.get("kpis") or {}
    if run["status"] != "completed":
        print(f"run {run_id} {run['status']}: {run.get('reason')}", file=sys.stderr)
        for line in k.get("log_tail") or []:
            print(f"  | {line}", file=sys.stderr)
    print(kpi_table({**k, "status": run["status"], "reason": run.get("reason")}))
    return 0 if run["status"] == "completed" else 1


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="cosim5g", description="5G factory co-simulator")
    sub = ap.add_subparsers(dest="command", required=True)
    v = sub.add_parser("validate", help="check a scenario file and print field-level errors")
    v.add_argument("file")
    v.add_argument("--set", action="append", metavar="FIELD=VALUE", help="override a field (repeatable)")
    v.set_defaults(fn=cmd_validate)
    r = sub.add_parser("run", help="run a scenario and print its KPIs")
    r.add_argument("file")
    r.add_argument("--set", action="append", metavar="FIELD=VALUE", help="override a field, e.g. loops=8")
    r.add_argument("--json", action="store_true", help="print the KPI JSON as the last stdout line")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--results", default=str(DEFAULT_RESULTS), help="folder for run directories")
    r.set_defaults(fn=cmd_run)
    s = sub.add_parser("serve", help="REST API: start runs, follow them, /metrics")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8080)
    s.add_argument("--results", default=str(DEFAULT_RESULTS))
    s.add_argument("--db", default="results/cosim5g.db")
    s.add_argument("--scenarios", default="configs/scenarios")
    s.set_defaults(fn=cmd_serve)
    c = sub.add_parser("submit", help="start a run through the coordinator's REST API")
    c.add_argument("scenario", help="name of a scenario in the coordinator's configs/scenarios/")
    c.add_argument("--api", default="http://127.0.0.1:8080")
    c.add_argument("--set", action="append", metavar="FIELD=VALUE")
    c.add_argument("--follow", action="store_true", help="wait for the end and print the KPIs")
    c.add_argument("--wait-s", type=float, default=120.0, help="how long to wait for the API")
    c.set_defaults(fn=cmd_submit)
    n = sub.add_parser("netsim", help="standalone 5G NR cell (calibration, benchmarks)", add_help=False)
    n.add_argument("rest", nargs=argparse.REMAINDER)
    n.set_defaults(fn=cmd_netsim)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["netsim"]:  # its own argument parser, options included
        return cmd_netsim(argparse.Namespace(rest=argv[1:]))
    args = build_parser().parse_args(argv)
    return int(args.fn(args))


if __name__ == "__main__":
    sys.exit(main())
