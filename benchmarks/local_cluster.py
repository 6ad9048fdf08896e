"""A Ray cluster of several nodes on this machine, started with Ray's own `ray start` and ended
by its session folder, so that only its processes end (the tests of the ray runtime and
sweeps, and `make bench-cluster`)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def processes_with(text: str | Path) -> list[int]:
    """Processes (other than this one) whose command line contains ``text``."""
    needle = str(text).encode()
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if needle in (entry / "cmdline").read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


def cluster_processes(temp: Path) -> set[int]:
    """A local Ray cluster's processes: those naming its session folder ``temp`` (GCS, raylets,
    monitors) and their descendants (agents, workers)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    found: set[int] = set()
    todo = list(processes_with(temp))
    while todo:
        pid = todo.pop()
        if pid not in found:
            found.add(pid)
            todo.extend(children.get(pid, []))
    return found


def stop_cluster(temp: Path, grace_s: float = 5.0) -> None:
    """End the processes of the cluster with session folder ``temp``, and only them (not
    `ray stop`, which ends every Ray on the host)."""
    pids = cluster_processes(temp)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline and any(Path(f"/proc/{pid}").exists() for pid in pids):
            time.sleep(0.2)


@contextmanager
def local_ray_cluster(port: int, cpus_per_node: int, nodes: int = 2) -> Iterator[str]:
    """A Ray head and ``nodes`` - 1 worker nodes on this machine, ``cpus_per_node`` CPUs each,
    the head on ``port``; yields its address and ends its processes afterwards."""
    ray = str(Path(sys.executable).parent / "ray")
    # Ray's session folder holds unix sockets, whose paths must stay short (pytest's tmp_path is long).
    temp = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))
    # Without token authentication: a head finding a token in ~/.ray (left by any local ray.init)
    # would require it, and nodes joining do not send it unless told to.
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}
    common = ["--node-ip-address=127.0.0.1", f"--num-cpus={cpus_per_node}", "--disable-usage-stats"]
    try:
        subprocess.run([ray, "start", "--head", f"--port={port}", "--include-dashboard=false",
                        f"--temp-dir={temp}", *common], check=True, env=env, capture_output=True,
                       timeout=180)
        for _ in range(nodes - 1):
            subprocess.run([ray, "start", f"--address=127.0.0.1:{port}", *common], check=True, env=env,
                           capture_output=True, timeout=180)
        yield f"127.0.0.1:{port}"
    finally:
        stop_cluster(temp)
        shutil.rmtree(temp, ignore_errors=True)
