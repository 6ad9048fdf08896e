"""The ``cosim5g`` command line: validate scenarios, run them, run the standalone network simulator,
calibrate the compute emulation.

Exit codes: 0 success, 1 the run did not complete, 2 bad input (with a message naming the field).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from coordinator.conductor import Progress
from coordinator.run_state import RunState
from fabric.tables import write_json
from scenario.schema import Scenario, ScenarioError, load_scenario

DEFAULT_RESULTS = Path("results") / "runs"
DEFAULT_SWEEPS = Path("results") / "sweeps"


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


def _progress_writer(path: Path, every_s: float = 1.0) -> Any:
    """Writes the run's progress as JSON at most once per ``every_s`` (a sweep's progress bar
    reads it while the run goes)."""
    last = [-every_s]

    def write(p: Progress) -> None:
        if p.wall_s - last[0] >= every_s or p.t_us >= p.end_us:
            last[0] = p.wall_s
            write_json(path, {"sim_time_s": p.t_us / 1e6, "end_s": p.end_us / 1e6, "wall_s": p.wall_s,
                              "windows": p.windows})

    return write


def cancel_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: the run or sweep then ends cleanly as cancelled."""
    cancel = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        cancel.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return cancel


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


def _run_id(text: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,127}", text):
        raise argparse.ArgumentTypeError(f"{text!r}: a run id is letters, digits, '_', '.', '-' (at most 128)")
    return text


def _load(path: str, overrides: list[str]) -> Scenario:
    """The scenario at ``path`` with ``overrides``, its policy checked as its Edges will build it."""
    from domain.policy import policy_errors

    sc = load_scenario(path, overrides)
    if errors := policy_errors(sc.policy, sc.work_cell):
        raise ScenarioError(errors)
    return sc


def cmd_validate(args: argparse.Namespace) -> int:
    try:
        sc = _load(args.file, args.set or [])
    except ScenarioError as exc:
        print(f"{args.file}: invalid scenario\n{exc.format()}", file=sys.stderr)
        return 2
    print(f"{args.file}: ok ({sc.loops} loops, {sc.detailed_loops} detailed, policy {sc.policy.name}, "
          f"{sc.duration_s} s, runtime {sc.runtime})")
    return 0


def _ray_launcher(sc: Scenario, address: str | None) -> Any:
    """The run's Ray launcher, its cluster joined and its CPUs reserved, before the run starts;
    RuntimeError saying what is missing."""
    from coordinator.run import federate_specs
    from coordinator.runtime_ray import RayLauncher

    launcher = RayLauncher(address=address)
    try:
        launcher.reserve(federate_specs(sc))
    except BaseException:
        launcher.stop()
        raise
    return launcher


def cmd_run(args: argparse.Namespace) -> int:
    from coordinator.run import execute_run

    try:
        sc = _load(args.file, args.set or [])
    except ScenarioError as exc:
        print(f"{args.file}: invalid scenario\n{exc.format()}", file=sys.stderr)
        return 2
    if args.run_id and (Path(args.results) / args.run_id).exists():
        print(f"--run-id {args.run_id}: {Path(args.results) / args.run_id} exists already (a run directory "
              f"is never reused): give another run id, or leave it out for a new one", file=sys.stderr)
        return 2
    launcher = None
    if args.address and sc.runtime != "ray":
        print(f"--address is for runtime ray, and this run's runtime is {sc.runtime}: add --set runtime=ray",
              file=sys.stderr)
        return 2
    if sc.runtime == "ray":
        try:
            launcher = _ray_launcher(sc, args.address)
        except RuntimeError as exc:
            print(str(exc), file=sys.stderr)
            return 2
    cancel = cancel_on_signals()
    shows = [] if args.quiet else [_progress_printer(sys.stderr)]
    if args.progress_file:
        shows.append(_progress_writer(Path(args.progress_file)))

    def progress(p: Progress) -> None:
        for show in shows:
            show(p)

    result = execute_run(sc, Path(args.results), launcher=launcher, on_progress=progress, cancel=cancel,
                         run_id=args.run_id)
    k = result.kpis
    if k.get("status") != RunState.COMPLETED:
        print(f"run {result.run_id} {k.get('status')}: {k.get('reason')}", file=sys.stderr)
        for line in k.get("log_tail") or []:
            print(f"  | {line}", file=sys.stderr)
    print(kpi_table(k))
    if args.json:
        print(json.dumps(k, sort_keys=True, default=str))
    return 0 if result.status == RunState.COMPLETED else 1


def _sweep_progress(sweep: Any, jobs: int, stream: Any, stop: threading.Event) -> None:
    """One status line, redrawn every second: points done / total, the running points'
    simulated time, ETA."""
    while not stop.wait(1.0):
        s = sweep.progress.snapshot(jobs)
        frac = s["done"] / s["total"] if s["total"] else 0.0
        running = "; ".join(
            f"{c['point']} sim {c['sim_time_s']:.1f}/{c['end_s']:.0f} s" if c["sim_time_s"] is not None
            else f"{c['point']} starting" for c in s["running"])
        eta = f"{s['eta_s'] / 60:.1f} min" if s["eta_s"] is not None else "-"
        failed = f" ({s['failed']} failed)" if s["failed"] else ""
        stream.write(f"\r[{'#' * int(frac * 20):<20}] {s['done']}/{s['total']} points{failed}"
                     f" | {running or '-'} | ETA {eta}\x1b[K")
        stream.flush()


def cmd_sweep(args: argparse.Namespace) -> int:
    from experiments.executors import make_executor
    from experiments.records import SweepBusy
    from experiments.report import load_sweep_spec
    from experiments.spec import SweepError, dump_spec, load_spec
    from experiments.sweep import Sweep

    try:
        if args.resume:
            sweep_dir = Path(args.resume)
            spec = load_spec(args.file) if args.file else load_sweep_spec(sweep_dir)
            sweep = Sweep(spec, sweep_dir)
            sweep.dir.hold()  # refused at once, and never over the spec, if another runner has it
            if args.file:  # the report reads the spec it was resumed with (a grid extended, ...)
                sweep.dir.write_spec(dump_spec(spec))
        elif args.file:
            sweep = Sweep.create(load_spec(args.file), Path(args.results))
        else:
            print("give a sweep spec FILE, or --resume DIR", file=sys.stderr)
            return 2
        executor = make_executor(args.executor, args.jobs, args.address)
    except SweepError as exc:
        print(f"{args.file}: invalid sweep spec\n{exc.format()}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError, ImportError, SweepBusy) as exc:
        print(str(exc), file=sys.stderr)
        return 2
    cancel = cancel_on_signals()
    print(f"sweep {sweep.sweep_id}: {sweep.dir.path}", file=sys.stderr)

    def on_event(kind: str, data: dict[str, Any]) -> None:
        if kind == "point_done" and data["status"] != RunState.COMPLETED:
            print(f"\n  point {data['values']} seed {data['seed']}: {data['status']}: {data['reason']}",
                  file=sys.stderr)

    stop = threading.Event()
    bar = None
    if not args.quiet:
        bar = threading.Thread(target=_sweep_progress, args=(sweep, args.jobs or 1, sys.stderr, stop), daemon=True)
        bar.start()
    try:
        cap = sweep.run(executor, cancel, on_event)
    except RuntimeError as exc:  # the cluster cannot be joined or cannot hold a point, ...
        print(f"\nsweep {sweep.sweep_id} failed: {exc}", file=sys.stderr)
        return 1
    finally:
        stop.set()
        if bar is not None:
            bar.join()
            sys.stderr.write("\n")
    print(capacity_table(cap))
    print(f"report: {sweep.dir.path / 'report.md'}")
    meta = sweep.dir.meta()
    return 0 if meta.get("state") == RunState.COMPLETED else 1


def capacity_table(cap: dict[str, Any]) -> str:
    from experiments.summary import capacity_text

    labels = list(next(iter(cap["series"].values())).keys()) if cap.get("series") else []
    width = max([len(n) for n in cap.get("series", {})] + [6])
    lines = [f"{'series':<{width}}  " + "  ".join(f"{lab:>14}" for lab in labels)]
    for name, entry in cap.get("series", {}).items():
        lines.append(f"{name:<{width}}  " + "  ".join(f"{capacity_text(entry[lab]):>14}" for lab in labels))
    return "\n".join(lines)


def cmd_report(args: argparse.Namespace) -> int:
    from experiments.report import rebuild

    try:
        cap = rebuild(Path(args.dir))
    except FileNotFoundError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    print(capacity_table(cap))
    print(f"report: {Path(args.dir) / 'report.md'}")
    return 0


def cmd_salvage(args: argparse.Namespace) -> int:
    from coordinator.run import coordinator_alive, salvage_run

    code = 0
    for d in args.run_dirs:
        run_dir = Path(d)
        if not run_dir.is_dir():
            print(f"{run_dir}: no such run directory", file=sys.stderr)
            code = 2
            continue
        if (pid := coordinator_alive(run_dir)) is not None:
            print(f"{run_dir}: still running (its coordinator, pid {pid}, is alive); left as it is",
                  file=sys.stderr)
            code = 2
            continue
        kpis = salvage_run(run_dir, args.reason)
        if kpis is None:
            print(f"{run_dir}: has its kpis.json already; left as it is")
            continue
        rec = kpis["recorded"]
        print(f"{run_dir}: records merged up to {rec.get('sim_time_reached_s', 0.0):g} s simulated, rows "
              f"{rec.get('rows', {})}{'; ' + rec['error'] if 'error' in rec else ''}")
    return code


def cmd_netsim(args: argparse.Namespace) -> int:
    try:
        from netsim.standalone import main as netsim_main
    except ImportError:
        print("the standalone NR network simulator is not available in this build", file=sys.stderr)
        return 2
    return int(netsim_main(args.rest))


def cmd_calibrate(args: argparse.Namespace) -> int:
    from coordinator.calibrate import main as calibrate_main

    return int(calibrate_main(args.rest))


# Subcommands whose module has its own argument parser: it gets every argument after the name.
OWN_PARSER = {"netsim": cmd_netsim, "calibrate": cmd_calibrate}


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from fabric.settings import settings
    from interfaces.api import LIMITS, create_app
    from interfaces.auth import (
        TOKEN_ENV,
        TokenError,
        listen_sockets,
        server_token,
        token_file,
    )

    if args.sweep_jobs is not None:
        print("cosim5g serve: --sweep-jobs is now --slots (runs and sweep points share them)", file=sys.stderr)
        args.slots = args.slots or args.sweep_jobs
    try:
        limits = settings(**{name: getattr(args, name) for name in LIMITS})
    except ValueError as exc:
        print(f"cosim5g serve: {exc}", file=sys.stderr)
        return 2
    path = token_file(args.token_file).absolute()
    try:
        # A file named on purpose also gets a COSIM5G_TOKEN, for whoever reads it (Prometheus).
        token = server_token(path, keep_env_token=bool(args.token_file or limits.token_file))
        socks = listen_sockets(args.host or ["127.0.0.1"], args.port)
    except (TokenError, OSError) as exc:
        print(f"cosim5g serve: {exc}", file=sys.stderr)
        return 2
    hint = (f"the value of {TOKEN_ENV} where the coordinator runs" if limits.token
            else f"in {path} on the coordinator's host (readable by its owner only)")
    app = create_app(Path(args.results), Path(args.db), Path(args.scenarios), Path(args.sweeps),
                     Path(args.sweep_specs), token=token, limits=limits, token_hint=hint)
    where = ", ".join(f"http://{s.getsockname()[0]}:{s.getsockname()[1]}" for s in socks)
    print(f"cosim5g serve: API on {where}; token {hint}; limits {limits.model_dump(include=set(LIMITS))}",
          file=sys.stderr)
    uvicorn.Server(uvicorn.Config(app, log_level="info")).run(sockets=socks)
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    from interfaces.auth import TOKEN_FILE_ENV
    from interfaces.client import ApiError, call, follow, wait_healthy

    if args.token_file:  # every call of this process, the sweep path's too, reads the token there
        os.environ[TOKEN_FILE_ENV] = args.token_file
    if args.sweep:
        return _submit_sweep(args)
    if not args.scenario:
        print("give a SCENARIO name, or --sweep SPEC", file=sys.stderr)
        return 2
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
    if run["status"] != RunState.COMPLETED:
        print(f"run {run_id} {run['status']}: {run.get('reason')}", file=sys.stderr)
        for line in k.get("log_tail") or []:
            print(f"  | {line}", file=sys.stderr)
    print(kpi_table({**k, "status": run["status"], "reason": run.get("reason")}))
    return 0 if run["status"] == RunState.COMPLETED else 1


def _submit_sweep(args: argparse.Namespace) -> int:
    from interfaces.client import ApiError, call, follow_sweep, wait_healthy

    try:
        wait_healthy(args.api, args.wait_s)
        sweep_id = call(args.api, "POST", "/sweeps", {"spec": args.sweep})["sweep_id"]
        print(f"sweep {sweep_id} submitted to {args.api}", file=sys.stderr)
        if not args.follow:
            print(sweep_id)
            return 0
        s = follow_sweep(args.api, sweep_id)
    except ApiError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    if s["state"] != RunState.COMPLETED:
        print(f"sweep {sweep_id} {s['state']}: {s.get('reason')}", file=sys.stderr)
    if s.get("capacity"):
        print(capacity_table(s["capacity"]))
    print(f"report: {args.api}/sweeps/{sweep_id}")
    return 0 if s["state"] == RunState.COMPLETED else 1


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
    r.add_argument("--run-id", type=_run_id, help="name of the run directory (default: scenario-time-random)")
    r.add_argument("--progress-file", help="write the progress as JSON to this file while the run goes")
    r.add_argument("--address", help="runtime ray: the Ray cluster to join (auto or HOST:PORT); default "
                   "$COSIM5G_RAY_ADDRESS, else a local cluster started for the run")
    r.set_defaults(fn=cmd_run)
    s = sub.add_parser("serve", help="REST API: start runs, follow them, /metrics")
    s.add_argument("--host", action="append", help="address or name to listen on (repeatable; default "
                   "127.0.0.1); names are resolved once, at start")
    s.add_argument("--port", type=int, default=8080)
    s.add_argument("--token-file", help="the API token's file, created (mode 0600) if missing; default "
                   "$COSIM5G_TOKEN_FILE or results/auth/api-token. $COSIM5G_TOKEN overrides it (and is "
                   "written to it when the file is named by this flag or $COSIM5G_TOKEN_FILE)")
    s.add_argument("--max-duration-s", type=float, help="longest duration_s of a run or sweep point "
                   "(default $COSIM5G_MAX_DURATION_S or 3600)")
    s.add_argument("--max-run-timeout-s", type=float, help="largest watchdog.run_timeout_s "
                   "(default $COSIM5G_MAX_RUN_TIMEOUT_S or 21600)")
    s.add_argument("--max-sweep-points", type=int, help="most points in one sweep "
                   "(default $COSIM5G_MAX_SWEEP_POINTS or 1000)")
    s.add_argument("--max-queued", type=int, help="most runs and sweeps pending or running "
                   "(default $COSIM5G_MAX_QUEUED or 32)")
    s.add_argument("--results", default=str(DEFAULT_RESULTS))
    s.add_argument("--db", default="results/cosim5g.db")
    s.add_argument("--scenarios", default="configs/scenarios")
    s.add_argument("--sweeps", default=str(DEFAULT_SWEEPS), help="folder for sweep directories")
    s.add_argument("--sweep-specs", default="configs/sweeps", help="the shipped sweep specs")
    s.add_argument("--max-body-bytes", type=int, help="largest request body, answered 413 beyond it "
                   "(default $COSIM5G_MAX_BODY_BYTES or 1000000)")
    s.add_argument("--slots", type=int, help="runs and sweep points simulated at once, shared by runs and sweeps "
                   "(default $COSIM5G_SLOTS or half the host's cores, at least 1)")
    # Sweeps' points and runs now share --slots; the old flag still works, with a word.
    s.add_argument("--sweep-jobs", type=int, dest="sweep_jobs", help=argparse.SUPPRESS)
    s.set_defaults(fn=cmd_serve)
    c = sub.add_parser("submit", help="start a run (or a sweep) through the coordinator's REST API")
    c.add_argument("scenario", nargs="?", help="name of a scenario in the coordinator's configs/scenarios/")
    c.add_argument("--sweep", metavar="SPEC", help="start a sweep instead: a name in configs/sweeps/")
    c.add_argument("--api", default="http://127.0.0.1:8080")
    c.add_argument("--token-file", help="the coordinator's API token file (default $COSIM5G_TOKEN_FILE or "
                   "results/auth/api-token); $COSIM5G_TOKEN overrides it")
    c.add_argument("--set", action="append", metavar="FIELD=VALUE")
    c.add_argument("--follow", action="store_true", help="wait for the end and print the KPIs (or the capacity)")
    c.add_argument("--wait-s", type=float, default=120.0, help="how long to wait for the API")
    c.set_defaults(fn=cmd_submit)
    w = sub.add_parser("sweep", help="run a sweep spec: every grid point x seed, then summary, capacity, figures")
    w.add_argument("file", nargs="?", help="sweep spec (configs/sweeps/*.yaml); optional with --resume")
    w.add_argument("--jobs", type=int, help="points run side by side (default: 1 locally, the cluster's CPUs on Ray)")
    w.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local processes (default) or a Ray cluster")
    w.add_argument("--address", help="Ray cluster to join (auto or HOST:PORT); default: start a local one")
    w.add_argument("--resume", metavar="DIR", help="continue the sweep in DIR: completed points are skipped")
    w.add_argument("--results", default=str(DEFAULT_SWEEPS), help="folder for sweep directories")
    w.add_argument("--quiet", action="store_true", help="no progress line")
    w.set_defaults(fn=cmd_sweep)
    rp = sub.add_parser("report", help="rebuild a sweep's tables, capacity, figures and report.md")
    rp.add_argument("dir", help="a sweep directory (results/sweeps/<sweep_id>)")
    rp.set_defaults(fn=cmd_report)
    sv = sub.add_parser("salvage", help="close the records of runs whose coordinator died: merge what the "
                        "federates streamed, write kpis.json with how far each run got")
    sv.add_argument("run_dirs", nargs="+", help="run directories (results/runs/<run_id>)")
    sv.add_argument("--reason", default="coordinator stopped during the run", help="the runs' failure reason")
    sv.set_defaults(fn=cmd_salvage)
    n = sub.add_parser("netsim", help="standalone 5G NR cell (calibration, benchmarks)", add_help=False)
    n.add_argument("rest", nargs=argparse.REMAINDER)
    n.set_defaults(fn=cmd_netsim)
    cal = sub.add_parser("calibrate", help="how faithful compute emulation is: the real workloads under CPU "
                         "limits, process and docker runtimes (results/bench/calibrate.md)", add_help=False)
    cal.add_argument("rest", nargs=argparse.REMAINDER)
    cal.set_defaults(fn=cmd_calibrate)
    return ap


def main(argv: list[str] | None = None) -> int:
    from coordinator.process_memory import limit_malloc_arenas

    limit_malloc_arenas()  # a coordinator (run, sweep, serve) lives through many runs' threads
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] and argv[0] in OWN_PARSER:  # the module parses the rest, options included
        return OWN_PARSER[argv[0]](argparse.Namespace(rest=argv[1:]))
    args = build_parser().parse_args(argv)
    return int(args.fn(args))


if __name__ == "__main__":
    sys.exit(main())
