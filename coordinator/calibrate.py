"""``make calibrate``: the real workloads under node profiles of 1.0, 0.5 and 0.25 cpus.

For each workload and profile it reports the CPU time of a job without any limit (same image,
same interpreter, no CPU quota), the wall time of the job inside a container with that CFS quota
(what ``wall`` timing measures), the ``cpu``-mode estimate (CPU time in the container / cpus),
the ideal (unlimited CPU time / cpus) and the ratios of both to the ideal. Medians over
repetitions. The profiles are measured in interleaved rounds, because a shared virtual machine's
speed drifts over minutes. Written to results/bench/calibrate.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path
from typing import Any

from coordinator.launcher import NodeLimits
from coordinator.runtime_docker import RUNTIME_IMAGE, cgroup_limits, docker_client

PROFILES = (1.0, 0.5, 0.25)
ROOT = Path(__file__).parents[1]


def in_container(client: Any, cpus: float | None, reps: int) -> dict[str, Any]:
    """Run the workloads in the runtime image; ``cpus`` None: no CPU quota (the baseline, with the
    image's own interpreter -- the host's may be a different build and speed)."""
    raw = client.containers.run(
        RUNTIME_IMAGE, ["python", "-m", "services.workloads", "--reps", str(reps)],
        environment={"MUJOCO_GL": "egl", "HOME": "/tmp"}, remove=True, read_only=True,
        tmpfs={"/tmp": "size=64m"}, cap_drop=["ALL"], network_mode="none",
        **cgroup_limits(NodeLimits(cpus=cpus, mem_mb=1024)),
    )
    return dict(json.loads(raw.decode().strip().splitlines()[-1]))


def table(host: dict[str, Any], limited: dict[float, dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for name, h in host.items():
        host_cpu = statistics.median(h["cpu_ms"])
        for cpus in PROFILES:
            c = limited[cpus][name]
            wall = statistics.median(c["wall_ms"])
            cpu_mode = statistics.median(c["cpu_ms"]) / cpus
            ideal = host_cpu / cpus
            rows.append({"workload": name, "cpus": cpus, "host_cpu_ms": host_cpu, "wall_ms": wall,
                         "cpu_mode_ms": cpu_mode, "ideal_ms": ideal,
                         "wall_over_ideal": wall / ideal, "cpu_mode_over_ideal": cpu_mode / ideal})
    return rows


def render(rows: list[dict[str, Any]]) -> str:
    head = ("| workload | cpus | unlimited CPU ms | wall ms (limited) | cpu-mode ms | ideal ms | "
            "wall / ideal | cpu-mode / ideal |")
    lines = [head, "|" + "---|" * 8]
    for r in rows:
        lines.append(f"| {r['workload']} | {r['cpus']:.2f} | {r['host_cpu_ms']:.2f} | {r['wall_ms']:.2f} | "
                     f"{r['cpu_mode_ms']:.2f} | {r['ideal_ms']:.2f} | {r['wall_over_ideal']:.2f} | "
                     f"{r['cpu_mode_over_ideal']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--reps", type=int, default=5, help="repetitions per container")
    ap.add_argument("--rounds", type=int, default=4, help="interleaved rounds over the profiles")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    args = ap.parse_args(argv)
    client = docker_client()
    load = os.getloadavg()[0]
    samples: dict[float | None, dict[str, Any]] = {}
    for _ in range(args.rounds):
        for cpus in (None, *PROFILES):
            for name, m in in_container(client, cpus, args.reps).items():
                acc = samples.setdefault(cpus, {}).setdefault(name, {"cpu_ms": [], "wall_ms": []})
                acc["cpu_ms"] += m["cpu_ms"]
                acc["wall_ms"] += m["wall_ms"]
    host = samples.pop(None)
    limited = {cpus: samples[cpus] for cpus in PROFILES}
    rows = table(host, limited)
    text = render(rows) + (f"\n\nHost load average (1 min) at the start: {load:.2f} on {os.cpu_count()} cores; "
                           "ratios are meaningful on an otherwise idle host only.")
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "calibrate.md").write_text(text + "\n")
    (args.out / "calibrate.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"written to {args.out / 'calibrate.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
