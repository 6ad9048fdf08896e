"""What a runtime must do to host a run's federates: start them, report deaths, show logs, stop.

``FederateSpec`` describes one federate process, a federate or a group (``members``), which
stands for each of its federates in deaths and logs (``names``); docs/architecture.md sec. 8.
"""

from __future__ import annotations

import os
import signal
import subprocess
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class NodeLimits:
    """A compute node's capacity: fraction of one host core, memory (None: unlimited), and how its
    jobs are timed (``wall``, ``cpu`` or ``model``), which decides how the docker runtime limits it."""

    cpus: float | None = None
    mem_mb: int | None = None
    timing: str = "cpu"


@dataclass(frozen=True)
class FederateSpec:
    """One federate of a run."""

    name: str  # e.g. "camera-0"
    role: str  # physics, camera, edge, robot, netsim, loops; or group (of ``members``)
    limits: NodeLimits = field(default_factory=NodeLimits)
    # A group's federates (name, role), served together by its process (``fabric.group``).
    members: tuple[tuple[str, str], ...] = ()
    # CPUs a runtime that places processes on a cluster reserves for a process without a node
    # profile (``limits``), which nothing throttles: a netsim partition, busy every window.
    reserve_cpus: float | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """The participant and every federate its process serves."""
        return (self.name, *(name for name, _ in self.members))

    def argv(self, run_id: str, endpoint: str, scenario_path: str, results_dir: str) -> list[str]:
        """Arguments after ``python``."""
        return [
            "-m", "services.main", self.role,
            "--name", self.name,
            "--run-id", run_id,
            "--endpoint", endpoint,
            "--scenario", scenario_path,
            "--results", results_dir,
            *(a for name, role in self.members for a in ("--member", f"{name}:{role}")),
        ]


class Launcher(ABC):
    """Starts and supervises the federates of one run."""

    def router_listen_endpoint(self, router_port: int) -> str:
        """Where the coordinator's zenoh router listens (loopback unless a runtime needs more)."""
        return f"tcp/127.0.0.1:{router_port}"

    @abstractmethod
    def router_endpoint_for_federates(self, router_port: int) -> str:
        """The zenoh endpoint federates connect to, given the coordinator's router port."""

    @abstractmethod
    def start(self, specs: list[FederateSpec], run_id: str, endpoint: str, scenario_path: Path,
              run_dir: Path) -> None:
        """Start every federate; returns once they are launched (not necessarily ready)."""

    @abstractmethod
    def dead(self) -> dict[str, str]:
        """Federates that have exited, with a reason (exit code, OOM kill, ...)."""

    @abstractmethod
    def last_log_lines(self, name: str, n: int = 20) -> list[str]:
        """The last ``n`` lines a federate wrote to its log."""

    def resource_note(self, name: str) -> str | None:
        """What the runtime sees of a failed federate's resources that explains its failure
        (e.g. a node stuck at its memory limit), or None."""
        return None

    def placement(self) -> dict[str, dict[str, Any]]:
        """Where each federate ran, for ``kpis.json`` (e.g. the Ray node), or {} when on this host."""
        return {}

    def records_lost(self) -> list[str]:
        """Federates whose records, written where the run directory could not see them, did not
        come back when the run stopped (after ``stop``)."""
        return []

    def where(self, name: str) -> str:
        """Where federate ``name`` runs when that is not this host, for a failure's reason: the
        node and every federate it holds (a lost node takes them all), or ""."""
        return ""

    @abstractmethod
    def stop(self, grace_s: float = 5.0) -> None:
        """Stop every federate (terminate, then kill after ``grace_s``) and release resources.
        Safe to call twice and on every exit path."""


def terminate_session(proc: subprocess.Popen[bytes]) -> None:
    """Ask the session (process group) led by ``proc`` to end: SIGTERM, then SIGCONT, since a
    stopped (hung) process must wake to die."""
    for sig in (signal.SIGTERM, signal.SIGCONT):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass


def reap(proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    """Wait up to ``timeout_s`` for ``proc`` to end, then kill its session and wait for it."""
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
