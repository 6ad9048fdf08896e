"""``make bench-cluster``: the ``factory`` scenario (360 loops, 18 gNBs, 4 AGVs) split into 1, 2
and 4 netsim partitions, in the process runtime and on 1, 2 and 4 Ray nodes of a local cluster,
where the machine has the cores for them (a core per partition). Per case: speed (simulated s / wall s), scaling efficiency (speed over the
partitions times the 1-partition process speed), the Ray / process ratio for the same
partitions and the upper bound of the share of wall time in the window protocol; every case
must give the same ``results_hash``. Written to results/bench/cluster.md and .json.

    python -m benchmarks.cluster [--factory-s 5] [--partitions 1,2,4]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.local_cluster import local_ray_cluster
from benchmarks.speed import FACTORY_SETS, ROOT, run_case
from coordinator.run import free_port


def cases(partitions: list[int], cores: int) -> list[tuple[int, str, int]]:
    """(partitions, runtime, Ray nodes) of every case this host has the cores for."""
    out = []
    for p in partitions:
        if p > cores:  # a core per partition; the core group shares them
            continue
        out.append((p, "process", 0))
        if p > 1:
            out += [(p, "ray", n) for n in sorted({1, p}) if n <= cores]
    return out


def run_on_ray(partitions: int, nodes: int, factory_s: float, results: Path) -> dict[str, Any]:
    """The factory in ``partitions`` on a local cluster of ``nodes`` nodes, spread over them."""
    from coordinator.runtime_ray import RayLauncher

    # Each node: its partitions' cores and one for the Edge (the only node profile the run has).
    per_node = -(-(partitions + 1) // nodes) + 1
    with local_ray_cluster(free_port(), per_node, nodes) as address:
        launcher = RayLauncher(address=address, strategy="SPREAD" if nodes > 1 else "PACK")
        return run_case(360, 0, factory_s, "ray", results, scenario="factory",
                        sets=[*FACTORY_SETS, f"partitions={partitions}"], launcher=launcher)


def render(meta: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    lines = ["# Factory on partitions and Ray nodes", "",
             f"{meta['date']}, {meta['cores']} cores, load average {meta['load_start']:.1f} at the start and "
             f"{meta['load_end']:.1f} at the end; `factory` (360 abstract loops, 18 gNBs, 4 AGVs), "
             f"{meta['factory_s']:g} simulated s, model timing. Speed = simulated s / wall s; scaling "
             "efficiency = speed / (partitions x the 1-partition process speed).", "",
             "| partitions | runtime | Ray nodes | speed | scaling efficiency | ray / process | windows/s "
             "| window protocol share (upper bound) | results_hash |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    base = next((r for r in rows if r["partitions"] == 1 and r["runtime"] == "process"
                 and r.get("speed")), None)
    for r in rows:
        if r["status"] != "completed":
            lines.append(f"| {r['partitions']} | {r['runtime']} | {r['nodes'] or ''} | {r['status']}: "
                         f"{r['reason']} | | | | | |")
            continue
        eff = f"{r['speed'] / (r['partitions'] * base['speed']):.0%}" if base else ""
        same = next((p for p in rows if p["runtime"] == "process" and p["partitions"] == r["partitions"]
                     and p.get("speed")), None)
        ratio = f"{r['speed'] / same['speed']:.2f}" if same and r["runtime"] == "ray" else ""
        lines.append(f"| {r['partitions']} | {r['runtime']} | {r['nodes'] or ''} | {r['speed']:.3g} | {eff} | "
                     f"{ratio} | {r['windows_per_s']:.3g} | {r['protocol_share_max']:.0%} | "
                     f"{(r['results_hash'] or '')[:12]} |")
    hashes = {r["results_hash"] for r in rows if r["status"] == "completed"}
    lines += ["", "Every case the same results: " + ("yes" if len(hashes) == 1 else f"NO ({len(hashes)} hashes)")]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--factory-s", type=float, default=5.0, help="simulated seconds per case")
    ap.add_argument("--partitions", default="1,2,4", help="comma-separated partition counts")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    args = ap.parse_args(argv)
    cores = os.cpu_count() or 1
    meta = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cores": cores,
            "load_start": os.getloadavg()[0], "factory_s": args.factory_s}
    rows = []
    todo = cases([int(x) for x in args.partitions.split(",")], cores)
    if importlib.util.find_spec("ray") is None:
        print("Ray is not installed (pip install -e '.[ray]'): the process cases only", file=sys.stderr)
        todo = [c for c in todo if c[1] != "ray"]
    with tempfile.TemporaryDirectory(prefix="cosim5g-cluster-") as tmp:
        for p, runtime, nodes in todo:
            print(f"factory, {p} partitions, {runtime}{f' on {nodes} nodes' if nodes else ''}", file=sys.stderr)
            if runtime == "ray":
                r = run_on_ray(p, nodes, args.factory_s, Path(tmp))
            else:
                r = run_case(360, 0, args.factory_s, "process", Path(tmp), scenario="factory",
                             sets=[*FACTORY_SETS, f"partitions={p}"])
            rows.append({**r, "partitions": p, "nodes": nodes})
    meta["load_end"] = os.getloadavg()[0]
    text = render(meta, rows)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cluster.md").write_text(text)
    (args.out / "cluster.json").write_text(json.dumps({"meta": meta, "runs": rows}, indent=1) + "\n")
    print(f"written to {args.out / 'cluster.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
