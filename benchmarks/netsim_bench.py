"""Speed of the NR cell: slots simulated per wall-clock second, and where the time goes.

36 and 16 cameras x 8.5 Mbps, best of ``--repeat`` runs (docs/netsim.md, "Speed"): ``slots/s``
the whole loop, ``cell slots/s`` packet creation and ``NrCell.enqueue``/``run_slot``,
``run_slot/s`` ``run_slot`` alone; ``--profile`` a cProfile of the 36-UE case. Several cells
(``MultiCell``): N gNBs x U saturated cameras each (8.5 Mbps, far above what an interfered cell
carries), ``--hall NxU[:reuse]`` (default 18x20 and 4x10 on one carrier). Writes
results/bench/netsim.md.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import platform
import pstats
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from a checkout without installing
    sys.path.insert(0, str(ROOT))
from fabric.settings import one_thread_pools  # noqa: E402

one_thread_pools(os.environ)  # as every federate runs netsim; before numpy loads

from fabric.heap import simulation_heap  # noqa: E402
from fabric.native import compiled_loaded  # noqa: E402
from netsim.standalone import run_hall_cameras, run_uplink_cameras  # noqa: E402
from scenario.lattice import GNB_COUNTS  # noqa: E402

CASES = [(36, 8.5), (16, 8.5)]
HALL_CASES = ["18x20:1", "4x10:1"]  # gNBs x cameras per gNB : reuse


def _profile(duration_s: float, top: int) -> str:
    prof = cProfile.Profile()
    prof.enable()
    run_uplink_cameras(36, 8.5, duration_s, seed=0)
    prof.disable()
    out = io.StringIO()
    stats = pstats.Stats(prof, stream=out)
    stats.sort_stats("tottime").print_stats(top)
    lines = [ln for ln in out.getvalue().splitlines() if ln.strip()]
    start = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("ncalls"))
    return "\n".join(ln.replace(str(ROOT) + "/", "") for ln in lines[start:])


def _hall_case(parser: argparse.ArgumentParser, text: str) -> tuple[int, int, int]:
    """``NxU[:REUSE]`` as (gNBs, cameras per gNB, reuse); a bad one exits naming it."""
    size, _, reuse = text.partition(":")
    gnbs, _, ues = size.partition("x")
    try:
        case = (int(gnbs), int(ues), int(reuse or 1))
    except ValueError:
        parser.error(f"--hall {text!r}: expected NxU or NxU:REUSE, e.g. 18x20:1")
    if case[0] not in GNB_COUNTS or case[1] < 1 or case[2] not in (1, 3):
        parser.error(f"--hall {text!r}: N one of {', '.join(map(str, GNB_COUNTS))}, U >= 1, "
                     "reuse 1 or 3")
    return case


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=2.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="runs per case (best kept)")
    parser.add_argument("--profile", action="store_true", help="add a cProfile summary")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "bench" / "netsim.md")
    parser.add_argument("--hall", action="append", metavar="NxU[:REUSE]",
                        help="a case of several cells: N gNBs (1, 2, 4, 6, 9 or 18) with U "
                        "cameras each, reuse 1 or 3 (repeatable; default "
                        f"{' and '.join(HALL_CASES)})")
    parser.add_argument("--only", choices=("single", "hall"), help="run one kind of case")
    args = parser.parse_args(argv)
    halls = [_hall_case(parser, text) for text in args.hall or HALL_CASES]

    def best_of(run: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        best = None
        for _ in range(args.repeat):
            cpu0 = time.process_time()
            with simulation_heap():  # as in the `cosim5g netsim` command and every federate
                r = run()
            r["cpu_slots_per_second"] = r["slots"] / (time.process_time() - cpu0)
            if best is None or r["slots_per_second"] > best["slots_per_second"]:
                best = r
        assert best is not None
        return best

    rows = [] if args.only == "hall" else [
        best_of(partial(run_uplink_cameras, n_ues, rate, args.duration_s, seed=0))
        for n_ues, rate in CASES]
    hall_rows = [] if args.only == "single" else [
        best_of(partial(run_hall_cameras, g, u, 8.5, args.duration_s, reuse=r, seed=0))
        for g, u, r in halls]

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# netsim NR speed",
        "",
        f"Host: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, load average {load:.1f} at the end of the runs. "
        f"{args.duration_s:g} s simulated per run, best of {args.repeat}. NR cell: "
        f"{'compiled (make native)' if compiled_loaded() else 'pure Python'}.",
        "",
    ]
    if rows:
        lines += [
            "| UEs | offered Mbps | delivered Mbps | slots/s (loop) | cell slots/s | run_slot/s "
            "| CPU slots/s | p50 / p99 latency ms |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
    for r in rows:
        lat = r["ip_latency_ms"]
        lines.append(
            f"| {r['ues']} | {r['offered_mbps']:.1f} | {r['ul_throughput_mbps']:.1f} | "
            f"{r['slots_per_second']:.0f} | {r['cell_slots_per_second']:.0f} | "
            f"{r['run_slot_per_second']:.0f} | {r['cpu_slots_per_second']:.0f} | "
            f"{lat['p50']:.1f} / {lat['p99']:.1f} |")
    if hall_rows:
        lines += [
            "",
            "Several cells (MultiCell), InF-SL lattice, cameras at 8.5 Mbps:",
            "",
            "| gNBs x UEs | reuse | offered Mbps | delivered Mbps | UL SINR p5 / p50 / p95 dB "
            "| slots/s (loop) | run_slot/s | CPU slots/s |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
    for r in hall_rows:
        sinr = r["ul_sinr_db"]
        lines.append(
            f"| {r['gnbs']} x {r['ues'] // r['gnbs']} | {r['reuse']} | {r['offered_mbps']:.0f} | "
            f"{r['ul_throughput_mbps']:.1f} | {sinr['p5']:.1f} / {sinr['p50']:.1f} / "
            f"{sinr['p95']:.1f} | {r['slots_per_second']:.0f} | {r['run_slot_per_second']:.0f} "
            f"| {r['cpu_slots_per_second']:.0f} |")
    text = "\n".join(lines) + "\n"
    if args.profile:
        text += ("\n## Profile, 36 UEs (cProfile, sorted by own time)\n\n```\n"
                 + _profile(min(args.duration_s, 2.0), 20) + "\n```\n")
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
