"""Speed of whole runs (``make bench``): the cases the platform is held to, in one table.

What the cases are and how the windows' wall time is split: docs/architecture.md sec. 3, "Speed".
Writes results/bench/speed.{md,json}; compare ratios within one run of this script.

    python -m benchmarks.speed [--duration-s 30] [--loops 32] [--docker] [--only k0,k1] [--profile]
                               [--factory-s 5]

The factory case is the 360-loop, 18-gNB hall of configs/scenarios/factory.yaml, short
(``--factory-s``): 15 to 60 wall seconds per simulated second, and 20 s to a minute to set up.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from coordinator.launcher import Launcher
from coordinator.run import execute_run, federate_specs
from fabric.heap import simulation_heap
from fabric.native import compiled_loaded, library
from netsim.standalone import run_uplink_cameras
from scenario.schema import load_scenario
from services.main import PROFILE_DIR_ENV
from services.physics import stepper

ROOT = Path(__file__).parents[1]
CASES = ("k0", "k1", "factory", "netsim")
# The factory's windows are long (360 loops, 18 cells): a window may take minutes of wall time.
FACTORY_SETS = ["nodes.camera.timing=model", "nodes.edge.timing=model", "nodes.robot.timing=model",
                "watchdog.window_timeout_s=600"]


def run_case(loops: int, detailed: int, duration_s: float, runtime: str, results: Path,
             profile_dir: Path | None = None, cohost: str = "core", scenario: str = "baseline",
             sets: list[str] | None = None, launcher: Launcher | None = None) -> dict[str, Any]:
    """One run of ``scenario`` (the baseline, policy none) at ``loops`` / ``detailed``; its
    speed, where the wall time went and its processes' peak memory. With ``profile_dir`` its
    federates write their cProfile there; ``launcher``: the runtime's, made by the caller."""
    sc = load_scenario(ROOT / "configs" / "scenarios" / f"{scenario}.yaml",
                       [f"loops={loops}", f"detailed_loops={detailed}", f"duration_s={duration_s}",
                        f"runtime={runtime}", f"cohost={cohost}", *(sets or [])])
    t0 = time.perf_counter()
    if profile_dir is not None:
        os.environ[PROFILE_DIR_ENV] = str(profile_dir)  # federate processes inherit it
    try:
        r = execute_run(sc, results, launcher=launcher)
    finally:
        os.environ.pop(PROFILE_DIR_ENV, None)
    wall = time.perf_counter() - t0
    k = r.kpis
    feds = k.get("federates") or {}
    busy = {name: float(s.get("busy_wall_s", 0.0)) for name, s in feds.items()}
    cpu = {name: float(s.get("cpu_s", 0.0)) for name, s in feds.items()}
    run_wall = float(k.get("wall_time_s") or wall)
    # Shares of the windows' wall time: starting and stopping federates is not the protocol.
    windows_wall = float(k.get("windows_wall_s") or run_wall)
    # A group's members share one thread: the group's processing time is theirs added up.
    process_busy = dict(busy)
    for spec in federate_specs(sc):
        members = [n for n, _ in spec.members if n in busy]
        if members:
            for n in members:
                del process_busy[n]
            process_busy[f"{spec.name} ({', '.join(sorted(members))})"] = sum(busy[n] for n in members)
    busiest = max(process_busy.values(), default=0.0)
    # Peak RSS of the federate processes added up: a group's members report their one process's.
    rss = {name: float(s.get("peak_rss_mb") or 0.0) for name, s in feds.items()}
    peak_mb = sum(max(rss.get(n, 0.0) for n, _ in spec.members) if spec.members else rss.get(spec.name, 0.0)
                  for spec in federate_specs(sc))
    return {
        "status": r.status, "reason": r.reason, "loops": loops, "detailed_loops": detailed,
        "runtime": runtime, "sim_s": k.get("sim_time_s"), "wall_s": run_wall, "windows_wall_s": windows_wall,
        "speed": k.get("real_time_factor"), "windows": k.get("windows"),
        "windows_per_s": (k.get("windows") or 0) / windows_wall if windows_wall else None,
        "cohost": cohost,
        "busy_share": {n: b / windows_wall for n, b in sorted(process_busy.items())},
        "cpu_s": cpu,
        "protocol_share_max": max(0.0, 1.0 - busiest / windows_wall) if windows_wall else None,
        "tasks": k.get("tasks"), "task_success_rate": k.get("task_success_rate"),
        "tasks_placed": k.get("tasks_placed"), "ul_packets": k.get("ul_packets"),
        "peak_rss_mb": round(peak_mb, 1), "peak_rss_mb_per_federate": rss,
        "results_hash": k.get("results_hash"),
    }


def netsim_case(duration_s: float) -> dict[str, Any]:
    best: dict[str, Any] | None = None
    for _ in range(2):
        with simulation_heap():  # as in the `cosim5g netsim` command and every federate
            r = run_uplink_cameras(36, 8.5, duration_s, seed=0)
        if best is None or r["slots_per_second"] > best["slots_per_second"]:
            best = r
    assert best is not None
    return {"slots_per_second": best["slots_per_second"], "ues": 36, "offered_mbps": best["offered_mbps"]}


# Time spent waiting for the next control or data message: not work.
_IDLE = ("method 'get' of '_queue.SimpleQueue' objects",)


def profile_text(profile_dir: Path, top: int = 12) -> str:
    """Per federate, the ``top`` functions by own time (waiting for messages left out), as shares
    of the federate's profiled time."""
    out = []
    for path in sorted(profile_dir.glob("*.pstats")):
        stats = pstats.Stats(str(path), stream=io.StringIO())
        rows = [(tt, f"{Path(fn).name}:{line}({name})" if line else name, nc)
                for (fn, line, name), (_, nc, tt, _, _) in stats.stats.items()  # type: ignore[attr-defined]
                if not any(i in name for i in _IDLE)]
        total = sum(tt for tt, _, _ in rows)
        out += [f"- {path.stem}: {total:.1f} s of own time besides waiting; most:"]
        for tt, where, calls in sorted(rows, reverse=True)[:top]:
            out.append(f"  - {tt / total:5.1%} {where} ({calls} calls)")
    return "\n".join(out)


def render(meta: dict[str, Any], runs: dict[str, dict[str, Any]], netsim: dict[str, Any] | None) -> str:
    lines = ["# Speed", "",
             f"{meta['date']}, {meta['cores']} cores, load average {meta['load_start']:.1f} at the start "
             f"and {meta['load_end']:.1f} at the end. Speed = simulated s / wall s. NR cell: "
             f"{meta['netsim_build']}; physics stepper: {meta['stepper']}.", "",
             "| case | speed | windows/s | window protocol share (upper bound) | busiest federate | tasks, success "
             "| peak RSS, federate processes |",
             "|---|---:|---:|---:|---|---|---:|"]
    for name, r in runs.items():
        if r["status"] != "completed":
            lines.append(f"| {name} | {r['status']}: {r['reason']} | | | | | |")
            continue
        busiest = max(r["busy_share"].items(), key=lambda kv: kv[1], default=("-", 0.0))
        success = "-" if r["task_success_rate"] is None else f"{r['task_success_rate']:.0%}"
        lines.append(f"| {name} | {r['speed']:.3g} | {r['windows_per_s']:.3g} | {r['protocol_share_max']:.0%} | "
                     f"{busiest[0]} {busiest[1]:.0%} | {r['tasks']}, {success} | {r['peak_rss_mb']:.0f} MiB |")
    for case in ("k0", "k1"):
        grouped, alone = runs.get(f"{case} process"), runs.get(f"{case} process, cohost none")
        if grouped and alone and grouped.get("speed") and alone.get("speed"):
            lines.append(f"| {case}: cohost core / none | {grouped['speed'] / alone['speed']:.3f} (ratio) | | | | | |")
    one, two = runs.get("factory process"), runs.get("factory process, 2 partitions")
    if one and two and one.get("speed") and two.get("speed"):
        same = "same results" if one.get("results_hash") == two.get("results_hash") else "RESULTS DIFFER"
        lines.append(f"| factory: 2 partitions / 1 | {two['speed'] / one['speed']:.3f} (ratio, {same}) | | | | | |")
    if "k1 docker" in runs and "k1 process" in runs:
        d, p = runs["k1 docker"], runs["k1 process"]
        if d.get("speed") and p.get("speed"):
            lines.append(f"| docker / process, K=1 | {d['speed'] / p['speed']:.3f} (ratio) | | | | | |")
    if netsim is not None:
        lines.append(f"| netsim standalone, 36 UEs x 8.5 Mbit/s | {netsim['slots_per_second']:.0f} slots/s | "
                     "| | | | |")
    lines += ["", "Busy share per federate (processing windows / wall):", ""]
    for name, r in runs.items():
        shares = ", ".join(f"{n} {s:.0%}" for n, s in r["busy_share"].items())
        lines.append(f"- {name}: {shares}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration-s", type=float, default=30.0, help="simulated seconds per run")
    ap.add_argument("--loops", type=int, default=32)
    ap.add_argument("--docker", action="store_true", help="also the K=1 case in the docker runtime")
    ap.add_argument("--factory-s", type=float, default=5.0,
                    help="simulated seconds of the factory case (360 loops, 18 gNBs)")
    ap.add_argument("--only", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    ap.add_argument("--profile", action="store_true",
                    help="run the process-runtime federates under cProfile and list where their time went")
    args = ap.parse_args(argv)
    only = [c.strip() for c in args.only.split(",") if c.strip()]
    bad = [c for c in only if c not in CASES]
    if bad:
        ap.error(f"--only: {bad} not among {', '.join(CASES)}")
    meta = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cores": os.cpu_count(),
            "load_start": os.getloadavg()[0], "duration_s": args.duration_s, "loops": args.loops,
            # The federates inherit this interpreter and environment, so its view is theirs.
            "netsim_build": "compiled" if compiled_loaded() else "pure Python",
            "stepper": "C thread" if library(stepper.LIBRARY) is not None else "Python thread"}
    runs: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="cosim5g-speed-") as tmp:
        results = Path(tmp)
        def profile(case: str) -> Path | None:
            return args.out / "profile" / case if args.profile else None

        # Each case beside the same run with every federate in a process of its own (cohost none).
        if "k0" in only:
            runs["k0 process"] = run_case(args.loops, 0, args.duration_s, "process", results, profile("k0"))
            runs["k0 process, cohost none"] = run_case(args.loops, 0, args.duration_s, "process", results,
                                                       cohost="none")
        if "k1" in only:
            runs["k1 process"] = run_case(args.loops, 1, args.duration_s, "process", results, profile("k1"))
            runs["k1 process, cohost none"] = run_case(args.loops, 1, args.duration_s, "process", results,
                                                       cohost="none")
            if args.docker:
                runs["k1 docker"] = run_case(args.loops, 1, args.duration_s, "docker", results)
        if "factory" in only:
            runs["factory process"] = run_case(360, 0, args.factory_s, "process", results, profile("factory"),
                                               scenario="factory", sets=FACTORY_SETS)
            # netsim in 2 partitions, against the one netsim of the case above (profiled alike).
            runs["factory process, 2 partitions"] = run_case(
                360, 0, args.factory_s, "process", results, profile("factory-2"), scenario="factory",
                sets=[*FACTORY_SETS, "partitions=2"])
    netsim = netsim_case(2.0) if "netsim" in only else None
    meta["load_end"] = os.getloadavg()[0]
    text = render(meta, runs, netsim)
    if args.profile:
        for case in ("k0", "k1", "factory", "factory-2"):
            if (args.out / "profile" / case).is_dir():
                text += (f"\n## Profile, {case} process (cProfile: speeds above are slowed by it)\n\n"
                         + profile_text(args.out / "profile" / case) + "\n")
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "speed.md").write_text(text)
    (args.out / "speed.json").write_text(json.dumps({"meta": meta, "runs": runs, "netsim": netsim}, indent=1) + "\n")
    print(f"written to {args.out / 'speed.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
