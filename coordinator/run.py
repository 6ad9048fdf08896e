"""One run's life cycle: prepare the run directory, start the router and the federates, conduct
simulated time, stop everything on every exit path, write results and KPIs.

A run ends in exactly one state (``STATES``); ``salvage_run`` closes one whose coordinator died
(docs/architecture.md sec. 10).
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from coordinator.conductor import Conductor, Progress, RunFailed
from coordinator.edges import provide_edge_plan
from coordinator.launcher import FederateSpec, Launcher, NodeLimits
from coordinator.provision import FrameModelError, provide_frame_model
from coordinator.results import (
    compute_kpis,
    loop_kpis,
    merge_tables,
    recorded_summary,
    results_hash,
    versions,
)
from coordinator.run_state import RunState
from fabric import keys
from fabric.messages import Stopped
from fabric.records import RecordSink
from fabric.tables import write_json
from fabric.zenoh_bus import ZenohBus
from scenario.schema import Scenario, dump_scenario
from services.roles import ROLES, federates

log = logging.getLogger(__name__)

def new_run_id(scenario: Scenario) -> str:
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return f"{scenario.name}-{stamp}-{secrets.token_hex(3)}"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ``cohost: core`` serves the core roles' federates (``services.roles``) as one group
# (``fabric.group``) in one process.
CORE_GROUP = "core"
# What a runtime placing processes on a cluster (``ray``) reserves for a netsim partition: a
# process busy every window, one core.
PARTITION_CPUS = 1.0
# The longest window given to a participant alone with something to do (the core group, while
# the detailed loops' federates wait): it meets the conductor at least this often.
LONG_WINDOW_US = 100_000


def federate_specs(scenario: Scenario) -> list[FederateSpec]:
    """One spec per process (participant of the window protocol); with ``cohost: core`` the core
    federates are the members of the group ``core``."""
    specs = []
    every = federates(scenario)
    core = tuple((name, r) for name, r in every if ROLES[r].in_core(scenario))
    if scenario.cohost == "core":
        specs.append(FederateSpec(name=CORE_GROUP, role="group", members=core))
    for name, r in every:
        if scenario.cohost == "core" and ROLES[r].in_core(scenario):
            continue
        node = ROLES[r].node
        p = getattr(scenario.nodes, node) if node else None
        limits = NodeLimits(cpus=p.cpus, mem_mb=p.mem_mb, timing=p.timing) if p else NodeLimits()
        apart = ROLES[r].apart
        reserve = PARTITION_CPUS if apart is not None and apart(scenario) else None
        specs.append(FederateSpec(name=name, role=r, limits=limits, reserve_cpus=reserve))
    return specs


@dataclass
class RunResult:
    run_id: str
    status: str
    run_dir: Path
    kpis: dict[str, Any] = field(default_factory=dict)
    reason: str | None = None


# Longest wait, once the federates reported, for the rest of their streamed table parts.
STREAM_SETTLE_S = 30.0
# How long a federate's lost liveliness waits for its runtime to report how it died.
DEATH_REPORT_GRACE_S = 3.0


def _death_report(launcher: Launcher, name: str) -> dict[str, str]:
    """The runtime's dead federates once it reports ``name`` among them, or {} after
    ``DEATH_REPORT_GRACE_S``."""
    grace = time.monotonic() + DEATH_REPORT_GRACE_S
    while time.monotonic() < grace:
        dead = launcher.dead()
        if name in dead:
            return dead
        time.sleep(0.1)
    return {}


class LivenessWatch:
    """Records federates whose liveliness token vanished while the run was going."""

    def __init__(self, bus: Any, run_id: str) -> None:
        self.seen: set[str] = set()
        self.lost: list[str] = []
        self.armed = True
        bus.watch_liveliness(keys.alive_all(run_id), self._on_change)

    def _on_change(self, key: str, alive: bool) -> None:
        name = keys.last_segment(key)
        if name == keys.COORDINATOR:  # our own token (the conductor's), not a federate's
            return
        if alive:
            self.seen.add(name)
        elif self.armed and name in self.seen:
            self.lost.append(name)


ROUTER_ATTEMPTS = 3


def _open_router(launcher: Launcher) -> tuple[int, ZenohBus]:
    """The run's zenoh router on a free port: a port is free when chosen, and another process
    (a run beside this one) may take it before the router binds, so a few are tried."""
    for attempt in range(ROUTER_ATTEMPTS):
        port = free_port()
        try:
            return port, ZenohBus(launcher.router_listen_endpoint(port), mode="router")
        except Exception:
            if attempt == ROUTER_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")


def execute_run(
    scenario: Scenario,
    results_root: Path,
    launcher: Launcher | None = None,
    on_progress: Callable[[Progress], None] | None = None,
    cancel: threading.Event | None = None,
    run_id: str | None = None,
) -> RunResult:
    """Run ``scenario`` to its end; never raises for a failing run (see ``RunResult.status``)."""
    if launcher is None:
        if scenario.runtime == "docker":
            from coordinator.docker_runs import reap_dead_runs
            from coordinator.runtime_docker import DockerLauncher, docker_client
            client = docker_client()
            reap_dead_runs(client)  # leftovers of runs whose coordinator died
            launcher = DockerLauncher(client)
        elif scenario.runtime == "ray":
            from coordinator.runtime_ray import RayLauncher
            launcher = RayLauncher()  # joins the cluster; RayRuntimeError before the run starts
        else:
            from coordinator.runtime_process import ProcessLauncher
            launcher = ProcessLauncher()
    created: Path | None = None  # this run's directory, once made
    try:  # what the launcher holds already (a Ray session) is released if the run cannot start
        run_id = run_id or new_run_id(scenario)
        run_dir = (results_root / run_id).resolve()
        run_dir.mkdir(parents=True, exist_ok=False)
        created = run_dir
        scenario_path = run_dir / "config.yaml"
        scenario_path.write_text(dump_scenario(scenario))
        write_json(run_dir / "versions.json", versions())
        write_json(run_dir / "status.json", {"run_id": run_id, "status": RunState.RUNNING, "seed": scenario.seed,
                                             "coordinator": coordinator_identity()})
        wall0 = time.monotonic()
        port, router = _open_router(launcher)
        try:  # parts streamed by federates on nodes that do not see run_dir
            sink = RecordSink(router, run_id, run_dir, [name for name, _ in federates(scenario)])
        except BaseException:
            router.close()
            raise
    except BaseException as exc:
        launcher.stop()
        if created is not None:  # its status is not left running
            write_json(created / "status.json", {"run_id": created.name, "status": RunState.FAILED,
                                                 "seed": scenario.seed,
                                                 "reason": f"the run could not start: {type(exc).__name__}: {exc}"})
        raise
    conducted_s: float | None = None  # wall time of the windows, once they all ran
    status, reason, failed_federate = RunState.COMPLETED, None, None
    log_tail: list[str] = []
    conductor = None
    stopped: dict[str, Any] = {}
    unsettled: dict[str, str] = {}
    result_trace = ""
    windows = 0
    sim_us = 0
    try:
        try:
            provide_frame_model(scenario, scenario_path, run_dir)
        except (FrameModelError, OSError) as exc:
            raise RunFailed(f"abstract loops' frame model: {exc}", federate="loops") from None
        try:  # each work cell's gNB, for the Edge sides (domain/edges.py)
            provide_edge_plan(scenario, run_dir)
        except (ValueError, OSError) as exc:
            raise RunFailed(f"Edge plan: {exc}") from None
        liveness = LivenessWatch(router, run_id)
        specs = federate_specs(scenario)
        groups = {s.name: [name for name, _ in s.members] for s in specs if s.role == "group"}
        deadline = wall0 + scenario.watchdog.run_timeout_s

        def health() -> None:
            if cancel is not None and cancel.is_set():
                raise RunFailed("cancelled by the user", status=RunState.CANCELLED)
            dead = launcher.dead()
            if not dead and liveness.lost:
                # A dead process closes its connection at once; its runtime may take a moment
                # to report how it died (exit code, OOM kill): the reason that names the cause.
                name = liveness.lost[0]
                dead = _death_report(launcher, name)
                if not dead:
                    raise RunFailed(f"federate {name} lost its liveliness token (died or disconnected)"
                                    f"{launcher.where(name)}", federate=name)
            if dead:
                name = sorted(dead)[0]  # a group sorts before its members, who died with it
                what = f"{name} (the process of {', '.join(groups[name])})" if name in groups else name
                raise RunFailed(f"federate {what} {dead[name]}", federate=name)
            if time.monotonic() > deadline:
                raise RunFailed(f"run exceeded watchdog.run_timeout_s = {scenario.watchdog.run_timeout_s} s",
                                status=RunState.TIMED_OUT)

        conductor = Conductor(router, run_id, [s.name for s in specs], scenario.window_us, scenario.duration_us,
                              scenario.watchdog.window_timeout_s, health, on_progress, groups=groups,
                              long_window_us=LONG_WINDOW_US)
        launcher.start(specs, run_id, launcher.router_endpoint_for_federates(port), scenario_path, run_dir)
        conductor.wait_ready(scenario.watchdog.ready_timeout_s)
        conducted0 = time.monotonic()
        outcome = conductor.run()
        conducted_s = time.monotonic() - conducted0
        windows, sim_us, result_trace = outcome.windows, outcome.t_end_us, outcome.trace_hash
    except RunFailed as exc:
        status, reason, failed_federate = exc.status, exc.reason, exc.federate
        if failed_federate:
            log_tail = launcher.last_log_lines(failed_federate, 20)
            note = launcher.resource_note(failed_federate)
            if note and note not in reason:
                reason = f"{reason}; {failed_federate} {note}"
        windows = conductor.windows if conductor else 0
        sim_us = conductor.t_us if conductor else 0
    except Exception as exc:  # a coordinator bug must still end the run cleanly
        log.exception("run %s crashed", run_id)
        status, reason = RunState.FAILED, f"coordinator error: {type(exc).__name__}: {exc}"
    finally:
        try:
            if conductor is not None:
                liveness.armed = False
                # Healthy federates write their tables before leaving, also when the run failed.
                gone = {*liveness.lost, *launcher.dead()} if status != RunState.COMPLETED else set()
                stopped = conductor.stop(status, timeout_s=30.0 if status == RunState.COMPLETED else 3.0,
                                         gone=gone, dead=launcher.dead)
                # A federate closes its tables before it reports: their last streamed bytes are
                # on their way, behind the report.
                unsettled = sink.settle({n: s.summary.get("records", {}) for n, s in stopped.items()
                                         if s.summary.get("records_streamed")},
                                        timeout_s=STREAM_SETTLE_S if status == RunState.COMPLETED else 3.0)
        finally:
            launcher.stop(grace_s=3.0)
            router.close()
            sink.close()

    wall_s = time.monotonic() - wall0
    sim_s = min(sim_us, scenario.duration_us) / 1e6
    if status == RunState.COMPLETED and len(stopped) < len(federates(scenario)):
        missing = sorted({n for n, _ in federates(scenario)} - set(stopped))
        dead = launcher.dead()
        how = "; ".join(f"{n} {dead[n]}" for n in missing if n in dead)
        status, reason = RunState.FAILED, f"no final report from {', '.join(missing)}" + (f": {how}" if how else "")
        failed_federate = missing[0]
        log_tail = launcher.last_log_lines(failed_federate, 20)
    lost = launcher.records_lost()
    if status == RunState.COMPLETED and lost:
        status, reason = RunState.FAILED, f"the records of {', '.join(lost)} did not come back from their nodes"
    if status == RunState.COMPLETED and unsettled:
        status, reason = RunState.FAILED, ("streamed table parts did not come in whole: "
                                           + ", ".join(f"{name} ({why})" for name, why in unsettled.items()))
    kpis: dict[str, Any] = {}
    # What the federates streamed, merged for completed and failed runs alike; with how far it
    # got: a run that did not complete, as far as every federate's records reach (a federate
    # that died stopped recording at its last flush, the others went on to the failure). Its
    # KPIs stay rates over the conductor's time, which the healthy federates' rows reach.
    recorded = close_records(run_dir, sim_s if status == RunState.COMPLETED else None)
    if status == RunState.COMPLETED and (short := records_short(recorded, stopped)):
        status, reason = RunState.FAILED, f"records lost: {short}"
    try:
        kpis = compute_kpis(run_dir, sim_s, scenario.loops)
    except Exception as exc:  # tables of a failed run may be missing or partial
        kpis = {"kpi_error": f"{type(exc).__name__}: {exc}"}
    try:
        loop_kpis(run_dir, scenario.loops, scenario.detailed_loops, sim_s)
    except Exception as exc:
        kpis["loop_kpi_error"] = f"{type(exc).__name__}: {exc}"
    summaries = {name: s.summary for name, s in sorted(stopped.items())}
    edge = summaries.get("edge", {})
    trace = conductor.trace_hash(stopped) if conductor is not None and status == RunState.COMPLETED else None
    outcomes = None
    if status == RunState.COMPLETED:
        try:
            outcomes = results_hash(run_dir)
        except Exception as exc:
            kpis["results_hash_error"] = f"{type(exc).__name__}: {exc}"
    kpis.update({
        "run_id": run_id,
        "scenario": scenario.name,
        "status": status,
        "reason": reason,
        "failed_federate": failed_federate,
        "log_tail": log_tail,
        "seed": scenario.seed,
        "policy": scenario.policy.name,
        "detailed_loops": scenario.detailed_loops,
        "estimator": edge.get("estimator", scenario.edge.estimator),
        "sim_time_s": sim_s,
        "wall_time_s": wall_s,
        "real_time_factor": sim_s / wall_s if wall_s > 0 else None,
        # The windows alone, without starting and stopping the federates: where speed is won.
        "windows_wall_s": conducted_s,
        "windows": windows,
        "windows_trace": result_trace,
        "recorded": recorded,
        "trace_hash": trace,
        # The same whatever the partitions (``trace_hash`` also covers processes and windows).
        "results_hash": outcomes,
        "results_dir": str(run_dir),
        "federates": summaries,
        # Per node: host score, scale to the reference core, speed during the run, drift flag.
        "compute_speed": {n: s["compute_speed"] for n, s in summaries.items() if "compute_speed" in s},
    })
    placement = launcher.placement()
    if placement:  # which node ran which federate (runtime ray)
        kpis["placement"] = placement
    write_json(run_dir / "kpis.json", kpis)
    write_json(run_dir / "status.json", {"run_id": run_id, "status": status, "reason": reason,
                                         "seed": scenario.seed})
    return RunResult(run_id, status, run_dir, kpis, reason)


def close_records(run_dir: Path, sim_time_reached_s: float | None = None) -> dict[str, Any]:
    """Merge what the federates streamed into the run tables; ``kpis.json``'s ``recorded``: rows
    per table and part, and how far the run got (given, or where every federate's records reach).
    A merge that fails is logged and said, so that the rest of the run's results are still written."""
    try:
        merged = merge_tables(run_dir)
    except Exception as exc:  # partial or unreadable parts
        log.exception("%s: merging the tables failed", run_dir)
        return {"sim_time_reached_s": sim_time_reached_s or 0.0, "error": f"{type(exc).__name__}: {exc}"}
    recorded = recorded_summary(merged)
    if sim_time_reached_s is None:
        # A part closed cleanly ends its federate's records; the run got as far as the parts
        # left open reach (every part's, when all were closed).
        parts = [info for m in merged.values() for info in m["parts"].values() if info.get("upto_s") is not None]
        open_parts = [info for info in parts if not info.get("complete")]
        reached = [info["upto_s"] for info in (open_parts or parts)]
        sim_time_reached_s = min(reached) if reached else 0.0
    return {"sim_time_reached_s": sim_time_reached_s, **recorded}


def records_short(recorded: dict[str, Any], stopped: dict[str, Stopped]) -> str:
    """Where the merged tables hold fewer rows of a federate than it reports having written
    (``records`` of its final summary), as ``name/table merged of written``; empty if none."""
    merged: dict[tuple[str, str], int] = {}
    for part in recorded.get("parts", []):
        key = (part["federate"], part["table"])
        merged[key] = merged.get(key, 0) + int(part["rows"])
    short = [f"{name}/{table} {merged.get((name, table), 0)} of {n}"
             for name, s in sorted(stopped.items())
             for table, n in sorted((s.summary.get("records") or {}).items())
             if isinstance(n, int) and merged.get((name, table), 0) < n]
    return ", ".join(short)


def coordinator_identity() -> dict[str, Any]:
    """This process as a run's status names its coordinator: host, pid and the pid's start time
    (a pid is reused, after a restart or in a new container, where the start time is not)."""
    return {"host": socket.gethostname(), "pid": os.getpid(), "started": _started(os.getpid())}


def _started(pid: int) -> str | None:
    try:  # field 22 of /proc/<pid>/stat, after the command name in parentheses
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def coordinator_alive(run_dir: Path) -> int | None:
    """The pid of the coordinator still running ``run_dir``'s run on this host, else None."""
    try:
        who = json.loads((run_dir / "status.json").read_text()).get("coordinator") or {}
    except (OSError, ValueError):
        return None
    pid = who.get("pid")
    if who.get("host") != socket.gethostname() or not isinstance(pid, int) or pid == os.getpid():
        return None
    started = _started(pid)
    return pid if started is not None and started == who.get("started") else None


def salvage_run(run_dir: Path, reason: str) -> dict[str, Any] | None:
    """Close the records of a run whose coordinator died before it ended: merge what every
    federate streamed (``tables/`` parts) into the run tables and write ``kpis.json`` with status
    ``failed``, ``reason`` and how far the records go (``recorded``), so that nothing written is
    lost and the run says where it stopped. A run that has its ``kpis.json``, or whose coordinator
    is still running it (its parts are being written), is left as it is (None); otherwise the
    KPIs written."""
    if (run_dir / "kpis.json").exists() or not run_dir.is_dir() or coordinator_alive(run_dir):
        return None
    status = {}
    try:
        status = json.loads((run_dir / "status.json").read_text())
    except (OSError, ValueError):
        pass
    recorded = close_records(run_dir)
    kpis = {"run_id": status.get("run_id", run_dir.name), "status": RunState.FAILED, "reason": reason,
            "seed": status.get("seed"), "recorded": recorded, "results_dir": str(run_dir)}
    write_json(run_dir / "kpis.json", kpis)
    write_json(run_dir / "status.json", {**status, "run_id": kpis["run_id"], "status": RunState.FAILED, "reason": reason})
    return kpis

