"""Platform benchmark (``make bench``): conductor windows per second with idle federates, in
memory and over zenoh with real processes, and the smoke scenario's real-time factor.

Prints a table and writes ``results/bench/platform.md`` and ``platform.json``. Figures are
ratios and rates on a shared machine: compare them within one run, not across machines.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from benchmarks.ticker import Ticker, context
from coordinator.conductor import Conductor
from coordinator.run import execute_run, free_port
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.driver import WindowDriver
from fabric.zenoh_bus import ZenohBus
from scenario.schema import load_scenario

ROOT = Path(__file__).parents[1]
W = 1000


def windows_in_memory(federates: int, windows: int) -> float:
    hub = InMemoryHub()
    end = windows * W
    names = [f"f{i}" for i in range(federates)]
    feds = [Ticker(context(n, "bench", W, end), InMemoryBus(hub), W) for n in names]
    conductor = Conductor(InMemoryBus(hub), "bench", names, W, end)
    threads = [threading.Thread(target=WindowDriver(f).serve, daemon=True) for f in feds]
    for t in threads:
        t.start()
    conductor.wait_ready(10)
    t0 = time.perf_counter()
    result = conductor.run()
    rate = result.windows / (time.perf_counter() - t0)
    conductor.stop("completed", 5)
    return rate


def windows_over_zenoh(federates: int, windows: int) -> float:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = ZenohBus(endpoint, mode="router")
    end = windows * W
    names = [f"f{i}" for i in range(federates)]
    conductor = Conductor(router, "bench", names, W, end)
    procs = [subprocess.Popen([sys.executable, "-m", "benchmarks.ticker", n, "bench", endpoint, str(W), str(end)],
                              cwd=ROOT) for n in names]
    try:
        conductor.wait_ready(60)
        t0 = time.perf_counter()
        result = conductor.run()
        rate = result.windows / (time.perf_counter() - t0)
        conductor.stop("completed", 10)
    finally:
        for p in procs:
            p.wait(10)
        router.close()
    return rate


def smoke_rtf(results: Path, runtime: str = "process") -> dict:
    sc = load_scenario(ROOT / "configs" / "scenarios" / "smoke.yaml", [f"runtime={runtime}"])
    r = execute_run(sc, results)
    return {"status": r.status, "rtf": r.kpis["real_time_factor"], "windows": r.kpis["windows"],
            "sim_s": r.kpis["sim_time_s"], "wall_s": r.kpis["wall_time_s"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--windows", type=int, default=3000)
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    ap.add_argument("--skip-smoke", action="store_true")
    ap.add_argument("--docker", action="store_true", help="also run the smoke scenario in containers")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [
        ("conductor, in-memory bus, 6 idle federates (threads)", "windows/s",
         windows_in_memory(6, args.windows)),
        ("conductor, zenoh router, 6 idle federate processes", "windows/s",
         windows_over_zenoh(6, args.windows)),
    ]
    smoke: dict[str, dict] = {}
    if not args.skip_smoke:
        smoke["process"] = smoke_rtf(args.out / "runs")
        rows.append(("smoke scenario (2 detailed loops), process runtime", "real-time factor",
                     smoke["process"]["rtf"]))
        if args.docker:
            smoke["docker"] = smoke_rtf(args.out / "runs", "docker")
            rows.append(("smoke scenario, docker runtime", "real-time factor", smoke["docker"]["rtf"]))
            rows.append(("smoke scenario, docker RTF / process RTF", "ratio",
                         smoke["docker"]["rtf"] / smoke["process"]["rtf"]))
    width = max(len(r[0]) for r in rows)
    lines = [f"| {'benchmark':<{width}} | {'unit':<16} | {'value':>10} |",
             f"|{'-' * (width + 2)}|{'-' * 18}|{'-' * 12}|"]
    lines += [f"| {name:<{width}} | {unit:<16} | {value:>10.3f} |" for name, unit, value in rows]
    table = "\n".join(lines)
    print(table)
    (args.out / "platform.md").write_text(table + "\n")
    (args.out / "platform.json").write_text(json.dumps({"rows": rows, "smoke": smoke}, indent=2) + "\n")
    print(f"written to {args.out / 'platform.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
