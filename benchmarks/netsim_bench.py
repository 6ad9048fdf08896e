"""Speed of the NR cell: slots simulated per wall-clock second, and where the time goes.

36 and 16 cameras x 8.5 Mbps, best of ``--repeat`` runs (docs/netsim.md, "Speed"): ``slots/s``
the whole loop, ``cell slots/s`` packet creation and ``NrCell.enqueue``/``run_slot``,
``run_slot/s`` ``run_slot`` alone; ``--profile`` a cProfile of the 36-UE case. Writes
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
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from a checkout without installing
    sys.path.insert(0, str(ROOT))

from fabric.heap import simulation_heap  # noqa: E402
from fabric.native import compiled_loaded  # noqa: E402
from netsim.standalone import run_uplink_cameras  # noqa: E402

CASES = [(36, 8.5), (16, 8.5)]


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=2.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="runs per case (best kept)")
    parser.add_argument("--profile", action="store_true", help="add a cProfile summary")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "bench" / "netsim.md")
    args = parser.parse_args(argv)

    rows = []
    for n_ues, rate in CASES:
        best = None
        for _ in range(args.repeat):
            cpu0 = time.process_time()
            with simulation_heap():  # as in the `cosim5g netsim` command and every federate
                r = run_uplink_cameras(n_ues, rate, args.duration_s, seed=0)
            r["cpu_slots_per_second"] = r["slots"] / (time.process_time() - cpu0)
            if best is None or r["slots_per_second"] > best["slots_per_second"]:
                best = r
        assert best is not None
        rows.append(best)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# netsim NR speed",
        "",
        f"Host: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, load average {load:.1f} at the end of the runs. "
        f"{args.duration_s:g} s simulated per run, best of {args.repeat}. NR cell: "
        f"{'compiled (make native)' if compiled_loaded() else 'pure Python'}.",
        "",
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
