"""Soak and chaos (``make soak``, ``make chaos``): many runs in one coordinator, and runs with a
fault at a random moment, must each end in one state and leave nothing behind.

What each checks: docs/architecture.md sec. 10, "Soak and chaos". Each prints a table and writes
results/bench/{soak,chaos}.{md,json}; exit code 1 when a check fails.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).parents[1]
SMOKE = ROOT / "configs" / "scenarios" / "smoke.yaml"
OUT = ROOT / "results" / "bench"


def rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def processes_of(marker: str) -> list[tuple[int, str]]:
    """Processes (other than this one) whose command line mentions ``marker``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                cmd = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            if marker.encode() in cmd:
                out.append((int(entry.name), cmd.replace(b"\0", b" ").decode(errors="replace")[:120]))
    return out


def docker_leftovers(run_ids: list[str]) -> list[str]:
    """Containers, networks and volumes labelled with one of ``run_ids``."""
    try:
        from coordinator.docker_runs import LABEL_RUN
        from coordinator.runtime_docker import docker_client
        client = docker_client()
    except Exception:
        return []
    out = []
    wanted = set(run_ids)
    for c in client.containers.list(all=True, filters={"label": LABEL_RUN}):
        if c.labels.get(LABEL_RUN) in wanted:
            out.append(f"container {c.name}")
    for n in client.networks.list(filters={"label": LABEL_RUN}):
        if n.attrs["Labels"].get(LABEL_RUN) in wanted:
            out.append(f"network {n.name}")
    for v in client.volumes.list(filters={"label": LABEL_RUN}):
        if (v.attrs.get("Labels") or {}).get(LABEL_RUN) in wanted:
            out.append(f"volume {v.name}")
    client.close()
    return out


def wait_gone(run_ids: list[str], timeout_s: float) -> tuple[list[str], float]:
    """Leftovers of the runs once ``timeout_s`` passed (or none were left), and how long it took."""
    t0 = time.monotonic()
    while True:
        left = [f"process {pid}: {cmd}" for rid in run_ids for pid, cmd in processes_of(rid)]
        left += docker_leftovers(run_ids)
        if not left or time.monotonic() - t0 > timeout_s:
            return left, time.monotonic() - t0
        time.sleep(0.5)


def write(name: str, record: dict[str, Any], table: list[tuple[str, Any]]) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{name}.json").write_text(json.dumps(record, indent=2, sort_keys=True, default=str) + "\n")
    width = max(len(k) for k, _ in table)
    lines = [f"{k:<{width}}  {v}" for k, v in table]
    (OUT / f"{name}.md").write_text(f"# {name}\n\n```\n" + "\n".join(lines) + "\n```\n")
    print("\n".join(lines))


# ---- soak -------------------------------------------------------------------------------------

def soak(runs: int, docker_runs: int, duration_s: float, results: Path) -> int:
    from coordinator.process_memory import limit_malloc_arenas
    from coordinator.run import execute_run
    from scenario.schema import load_scenario

    limit_malloc_arenas()  # as `cosim5g serve` does: this process is the coordinator of every run

    statuses: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    run_ids: list[str] = []
    rss: list[int] = []
    fds: list[int] = []
    t0 = time.monotonic()
    # Warm-up runs first: what the coordinator loads once is not growth (its first two process
    # runs: +6 MiB, lazily imported modules and buffers; the first docker run: +8 MiB, the docker
    # SDK and its connection pool). RSS growth is measured from after them.
    warm = ["process"] * min(runs, 2) + ["docker"] * min(docker_runs, 1)
    plan = warm + ["process"] * (runs - min(runs, 2)) + ["docker"] * (docker_runs - min(docker_runs, 1))
    base = max(0, len(warm) - 1)
    for i, runtime in enumerate(plan):
        sc = load_scenario(SMOKE, [f"duration_s={duration_s}", f"runtime={runtime}", f"seed={i + 1}"])
        result = execute_run(sc, results)
        run_ids.append(result.run_id)
        statuses[f"{runtime}:{result.status}"] += 1
        if result.status != "completed":
            reasons[f"{runtime}: {result.reason}"] += 1
        rss.append(rss_kib())
        fds.append(open_fds())
        print(f"  {i + 1}/{len(plan)} {runtime} {result.status} rss {rss[-1] / 1024:.0f} MiB fds {fds[-1]}",
              file=sys.stderr)
    left, _ = wait_gone(run_ids, 15)
    growth = (rss[-1] - rss[base]) / rss[base] if rss else 0.0
    ok = not left and growth < 0.10 and fds[-1] <= fds[base] and not reasons
    record = {"runs": len(plan), "statuses": dict(statuses), "failures": dict(reasons), "leftovers": left,
              "rss_kib_after_first": rss[0] if rss else None, "rss_kib_after_warmup": rss[base] if rss else None,
              "rss_kib_after_last": rss[-1] if rss else None,
              "rss_growth": growth, "fds_after_warmup": fds[base] if fds else None,
              "fds_after_last": fds[-1] if fds else None, "duration_s": duration_s,
              "wall_s": time.monotonic() - t0, "ok": ok}
    write("soak", record, [
        ("runs", f"{len(plan)} ({runs} process, {docker_runs} docker), {duration_s} s simulated each"),
        ("end states", ", ".join(f"{k} {v}" for k, v in sorted(statuses.items()))),
        ("failures", "; ".join(f"{k} x{v}" for k, v in reasons.items()) or "none"),
        ("leftovers", "; ".join(left) or "none"),
        ("coordinator RSS", f"{rss[base] / 1024:.1f} MiB after the warm-up run(s) -> {rss[-1] / 1024:.1f} MiB "
                            f"({growth * 100:+.1f}%); after the first run {rss[0] / 1024:.1f} MiB" if rss else "-"),
        ("open fds", f"{fds[base]} -> {fds[-1]}" if fds else "-"),
        ("wall", f"{record['wall_s']:.0f} s"),
        ("verdict", "ok" if ok else "FAILED"),
    ])
    return 0 if ok else 1


# ---- chaos ------------------------------------------------------------------------------------

FAULTS = ("sigkill", "sigstop", "coordinator", "oom")


def _federate_pid(run_id: str, name: str) -> int | None:
    for pid, cmd in processes_of(run_id):
        if "services.main" in cmd and f"--name {name} " in cmd + " ":
            return pid
    return None


def _container(run_id: str, name: str) -> Any:
    from coordinator.docker_runs import LABEL_FEDERATE, LABEL_RUN
    from coordinator.runtime_docker import docker_client
    client = docker_client()
    found = client.containers.list(filters={"label": [f"{LABEL_RUN}={run_id}", f"{LABEL_FEDERATE}={name}"]})
    return found[0] if found else None


def chaos_run(i: int, fault: str, runtime: str, rng: random.Random, results: Path) -> dict[str, Any]:
    """One run with one fault; what it ended as and what it left."""
    run_id = f"chaos-{i:03d}-{fault}-{runtime}-{rng.randrange(16 ** 6):06x}"
    federates = ["physics", "netsim", "edge", "camera-0", "camera-1", "robot-0", "robot-1"]
    victim = "edge" if fault == "oom" else rng.choice(federates)
    sets = ["duration_s=30", f"runtime={runtime}", f"seed={i + 1}", "watchdog.window_timeout_s=5"]
    if fault == "oom":
        # The Edge's pose network and frames need far more than this: the node hits its limit.
        sets.append("nodes.edge.mem_mb=64")
    cmd = [sys.executable, "-m", "interfaces.cli", "run", str(SMOKE), "--quiet", "--results", str(results),
           "--run-id", run_id, *[a for s in sets for a in ("--set", s)]]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    at_s = rng.uniform(2.0, 8.0)  # wall seconds after the run's first window
    run_dir = results / run_id
    t0 = time.monotonic()
    while not (run_dir / "logs").exists() and time.monotonic() - t0 < 120 and proc.poll() is None:
        time.sleep(0.1)
    time.sleep(at_s)
    injected = None
    if fault == "coordinator":
        proc.send_signal(signal.SIGKILL)
        injected = "coordinator SIGKILL"
    elif fault in ("sigkill", "sigstop"):
        sig = signal.SIGKILL if fault == "sigkill" else signal.SIGSTOP
        if runtime == "process":
            pid = _federate_pid(run_id, victim)
            if pid is not None:
                os.kill(pid, sig)
                injected = f"{victim} {sig.name}"
        else:
            c = _container(run_id, victim)
            if c is not None:
                if fault == "sigstop":
                    # SIGSTOP to a container stops only its init (tini), not the federate under
                    # it: the container's cgroup is frozen instead, every process of the node.
                    c.pause()
                    injected = f"{victim} frozen (docker pause)"
                else:
                    c.kill(signal=sig.name)
                    injected = f"{victim} {sig.name}"
    else:
        injected = f"{victim} memory limit 64 MiB"
    try:
        code = proc.wait(timeout=600)  # a 30 s run on a loaded 2-core host, when the fault never bites
    except subprocess.TimeoutExpired:
        proc.kill()
        code = proc.wait()
    kpis_path = run_dir / "kpis.json"
    kpis = json.loads(kpis_path.read_text()) if kpis_path.is_file() else {}
    status, reason = kpis.get("status"), kpis.get("reason") or ""
    left, took = wait_gone([run_id], 20)
    if fault == "coordinator":
        # Nobody is left to write the end state: the federates must notice and leave on their own.
        ok = not left
        status = status or "coordinator killed (no end state: nobody left to write it)"
    elif injected is None:
        ok = not left  # the run ended before the fault could land
    elif fault == "oom":
        ok = status == "failed" and "edge" in reason and "memory" in reason.lower() and not left
    else:
        ok = status in ("failed", "timed_out") and victim in reason and not left
    return {"run_id": run_id, "fault": fault, "runtime": runtime, "injected": injected, "at_s": round(at_s, 1),
            "exit_code": code, "status": status, "reason": reason, "leftovers": left,
            "gone_after_s": round(took, 1), "ok": ok}


def chaos(runs: int, runtimes: list[str], seed: int, results: Path, faults: list[str]) -> int:
    rng = random.Random(seed)
    rows = []
    t0 = time.monotonic()
    for i in range(runs):
        runtime = runtimes[i % len(runtimes)]
        options = [f for f in faults if f != "oom" or runtime == "docker"]
        fault = options[i % len(options)]
        row = chaos_run(i, fault, runtime, rng, results)
        rows.append(row)
        print(f"  {i + 1}/{runs} {runtime} {row['injected'] or fault + ' (not injected)'}: {row['status']}: "
              f"{row['reason'][:90]} {'ok' if row['ok'] else 'FAILED'}", file=sys.stderr)
    by_reason = Counter(f"{r['fault']} -> {r['status']}" for r in rows)
    failed = [r for r in rows if not r["ok"]]
    left = [x for r in rows for x in r["leftovers"]]
    record = {"runs": rows, "seed": seed, "wall_s": time.monotonic() - t0, "ok": not failed}
    write("chaos", record, [
        ("runs", f"{len(rows)} ({', '.join(runtimes)}), seed {seed}"),
        ("fault -> end state", "; ".join(f"{k} x{v}" for k, v in sorted(by_reason.items()))),
        ("faults not injected", str(sum(1 for r in rows if r["injected"] is None))),
        ("runs failing a check", "; ".join(f"{r['run_id']}: {r['status']}: {r['reason'][:80]}" for r in failed) or "none"),
        ("leftovers", "; ".join(left) or "none"),
        ("slowest clean-up", f"{max((r['gone_after_s'] for r in rows), default=0)} s"),
        ("wall", f"{record['wall_s']:.0f} s"),
        ("verdict", "ok" if not failed else "FAILED"),
    ])
    return 0 if not failed else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("soak")
    s.add_argument("--runs", type=int, default=100, help="smoke runs in the process runtime")
    s.add_argument("--docker-runs", type=int, default=0, help="smoke runs in containers (needs `make images`)")
    s.add_argument("--duration-s", type=float, default=2.0, help="simulated seconds of each run")
    c = sub.add_parser("chaos")
    c.add_argument("--runs", type=int, default=30)
    c.add_argument("--runtime", choices=["process", "docker", "both"], default="process")
    c.add_argument("--faults", default=",".join(FAULTS), help=f"comma-separated, of {', '.join(FAULTS)}")
    c.add_argument("--seed", type=int, default=1)
    for p in (s, c):
        p.add_argument("--results", default=None, help="run directories (default: a temporary folder)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix=f"cosim5g-{args.what}-") as tmp:
        results = Path(args.results) if args.results else Path(tmp)
        if args.what == "soak":
            return soak(args.runs, args.docker_runs, args.duration_s, results)
        runtimes = ["process", "docker"] if args.runtime == "both" else [args.runtime]
        faults = [f.strip() for f in args.faults.split(",") if f.strip()]
        bad = [f for f in faults if f not in FAULTS]
        if bad:
            print(f"--faults: {bad} not among {', '.join(FAULTS)}", file=sys.stderr)
            return 2
        return chaos(args.runs, runtimes, args.seed, results, faults)


if __name__ == "__main__":
    sys.exit(main())
