"""The ``process`` runtime: every federate an OS process on this host, logs in the run directory.

Each federate process has a session of its own and learns of the coordinator's death itself; no
cgroup is made, so ``cpus`` acts through ``cpu`` or ``model`` timing (docs/architecture.md sec. 8).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections import deque
from pathlib import Path

from coordinator.launcher import FederateSpec, Launcher, reap, terminate_session
from fabric.metrics import PORT_ENV as METRICS_PORT_ENV
from fabric.settings import one_thread_pools
from services.main import PARENT_PID_ENV


class ProcessLauncher(Launcher):
    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.logs: dict[str, Path] = {}
        self.hosted: dict[str, str] = {}  # federate -> the federate whose process serves it
        self._stopping = False

    def router_endpoint_for_federates(self, router_port: int) -> str:
        return f"tcp/127.0.0.1:{router_port}"

    def start(self, specs: list[FederateSpec], run_id: str, endpoint: str, scenario_path: Path,
              run_dir: Path) -> None:
        log_dir = run_dir / "logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        # Every federate of a run shares this host: one metrics port for all would fail all but
        # the first (metrics on a port are the docker runtime's, a port per container).
        env = {k: v for k, v in os.environ.items() if k != METRICS_PORT_ENV}
        env.setdefault("MUJOCO_GL", "egl")
        env["PYTHONUNBUFFERED"] = "1"
        env[PARENT_PID_ENV] = str(os.getpid())
        one_thread_pools(env)
        for spec in specs:
            log_path = log_dir / f"{spec.name}.log"
            for name in spec.names:
                self.logs[name] = log_path
                self.hosted[name] = spec.name
            with open(log_path, "ab") as log:
                self.procs[spec.name] = subprocess.Popen(
                    [sys.executable, *spec.argv(run_id, endpoint, str(scenario_path), str(run_dir))],
                    stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                    start_new_session=True,
                )

    def dead(self) -> dict[str, str]:
        out = {}
        for name, host in self.hosted.items():
            code = self.procs[host].poll()
            if code is not None:
                how = f"killed by signal {-code}" if code < 0 else f"exited with code {code}"
                out[name] = how if host == name else f"{how} (process of {host})"
        return out

    def last_log_lines(self, name: str, n: int = 20) -> list[str]:
        path = self.logs.get(name)
        if path is None or not path.exists():
            return []
        with open(path, errors="replace") as f:
            return [line.rstrip("\n") for line in deque(f, maxlen=n)]

    def stop(self, grace_s: float = 5.0) -> None:
        # Federates told to stop leave on their own; give them a moment before signalling.
        deadline = time.monotonic() + min(grace_s, 2.0)
        while time.monotonic() < deadline and any(p.poll() is None for p in self.procs.values()):
            time.sleep(0.02)
        for proc in self.procs.values():
            if proc.poll() is None:
                terminate_session(proc)
        deadline = time.monotonic() + grace_s
        for proc in self.procs.values():
            reap(proc, max(0.0, deadline - time.monotonic()))
