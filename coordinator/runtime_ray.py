"""The ``ray`` runtime: each federate process a subprocess supervised by a Ray actor on a Ray cluster.

``RayLauncher`` implements ``coordinator.launcher.Launcher``: it joins a cluster (``auto``,
``HOST:PORT``) or starts a local one, reserves the CPUs the federates' node profiles ask for in
one placement group (refused before any federate starts when the cluster cannot hold it), and
starts one ``FederateActor`` per federate process, which runs ``python -m services.main ...`` as
its child. Why a supervised subprocess, what the cluster's nodes need: docs/architecture.md sec. 8.
"""

from __future__ import annotations

import io
import logging
import math
import os
import shutil
import socket
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from coordinator.conductor import RunFailed
from coordinator.launcher import FederateSpec, Launcher, reap, terminate_session
from fabric.metrics import PORT_ENV as METRICS_PORT_ENV
from fabric.settings import THREAD_POOL_VARS, env_name, settings
from services.main import PARENT_PID_ENV
from services.roles import ROLES

log = logging.getLogger(__name__)

RAY_EXTRA = "ray"  # pyproject.toml's optional dependency group that brings Ray
# Ray counts fractional resources in steps of 1e-4; a request is rounded up to the next step.
RAY_CPU_STEP = 1e-4
STRATEGIES = ("PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD")
# The coordinator's settings a federate acts on; the API token, the coordinator's pid and a metrics
# port (which every federate of a node would try to bind) stay home.
_NOT_FORWARDED = {env_name("token"), env_name("token_file"), PARENT_PID_ENV, METRICS_PORT_ENV}
ACTOR_START_TIMEOUT_S = 120.0  # a Ray worker process started and the federate's child spawned
# A folder of a node where an actor's federate writes when the node does not see the run
# directory: ``<tmp>/cosim5g-run-<actor pid>-<random>``.
LOCAL_PREFIX = "cosim5g-run-"
# Longest wait for the actors that write on a node of their own to ship their records back.
SHIP_WAIT_S = 120.0


class RayRuntimeError(RuntimeError):
    """The ray runtime cannot host the run; the message says what is missing and how to fix it."""


def import_ray() -> Any:
    """The ``ray`` module, or RayRuntimeError naming the extra to install."""
    try:
        import ray
    except ImportError:
        raise RayRuntimeError(
            f"runtime ray needs Ray, which is not installed here: pip install -e '.[{RAY_EXTRA}]' "
            f"(the `{RAY_EXTRA}` extra), on the coordinator's host and every node of the cluster") from None
    return ray


def bundle_cpus(cpus: float | None) -> float | None:
    """A node profile's ``cpus`` rounded up to what Ray accepts; None for a process without a
    node profile (the core group, physics, netsim, the abstract loops), which reserves none
    unless it is a netsim partition (``FederateSpec.reserve_cpus``)."""
    if cpus is None:
        return None
    return math.ceil(round(cpus / RAY_CPU_STEP, 6)) * RAY_CPU_STEP


def _what(spec: FederateSpec) -> str:
    node = ROLES[spec.role].node if spec.role in ROLES else None
    if node:
        return f"{spec.name} (nodes.{node}.cpus = {spec.limits.cpus:g})"
    if spec.reserve_cpus is not None:
        return f"{spec.name} (a netsim partition, {spec.reserve_cpus:g} CPU)"
    return spec.name


def reserved_cpus(spec: FederateSpec) -> float | None:
    """What ``spec``'s process reserves: its node profile's CPUs, a partition's core, or None."""
    if spec.limits.cpus is not None:
        return bundle_cpus(spec.limits.cpus)
    return bundle_cpus(spec.reserve_cpus)


def check_placement(asked: dict[str, float], node_cpus: dict[str, float], available_cpus: float,
                    strategy: str = "PACK") -> None:
    """Refuse a placement the cluster cannot hold: ``asked`` CPUs per federate process (its
    description as key), ``node_cpus`` the CPUs of each live node, ``available_cpus`` those free
    in the whole cluster. RayRuntimeError naming what is missing."""
    if strategy not in STRATEGIES:
        raise RayRuntimeError(f"ray placement strategy {strategy!r}: expected one of {', '.join(STRATEGIES)}")
    if not asked:
        return
    nodes = ", ".join(f"{node[:12]} {cpus:g}" for node, cpus in sorted(node_cpus.items())) or "none"
    biggest = max(node_cpus.values(), default=0.0)
    total = sum(asked.values())
    eps = RAY_CPU_STEP / 2
    too_big = [f"{what} asks {cpus:g} CPUs" for what, cpus in asked.items() if cpus > biggest + eps]
    if too_big:
        raise RayRuntimeError(
            f"runtime ray: {'; '.join(too_big)}, but the largest Ray node has {biggest:g} CPUs "
            f"(nodes: {nodes}): add a node with more CPUs or lower the node profile's cpus")
    if total > available_cpus + eps:
        listing = ", ".join(f"{what} {cpus:g}" for what, cpus in asked.items())
        raise RayRuntimeError(
            f"runtime ray: the run's federates ask {total:g} CPUs ({listing}), but the Ray cluster "
            f"has {available_cpus:g} free (nodes: {nodes}): {total - available_cpus:g} CPUs missing; "
            "add nodes, free the cluster, or lower the node profiles' cpus")
    if strategy == "STRICT_PACK" and total > biggest + eps:
        raise RayRuntimeError(
            f"runtime ray: STRICT_PACK puts the run's {total:g} CPUs on one node, but the largest has "
            f"{biggest:g} (nodes: {nodes}): use PACK or a larger node")
    if strategy == "STRICT_SPREAD" and len(asked) > len(node_cpus):
        raise RayRuntimeError(
            f"runtime ray: STRICT_SPREAD puts each of {len(asked)} federate processes on a node of its "
            f"own, but the cluster has {len(node_cpus)} nodes: use SPREAD or add nodes")


class FederateActor:
    """Runs on a Ray node: starts one federate process as its child and supervises it.

    The child is told this actor's pid as its parent's (``COSIM5G_PARENT_PID``) and asks the
    kernel for a signal when its parent dies, so it never outlives its actor. Ray runs a
    synchronous actor's methods on the worker's main thread, the thread that forks the child
    (the parent-death signal follows the forking thread)."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path: Path | None = None
        self.local_dir: Path | None = None  # where it writes when the run directory is not shared
        self.inputs: set[str] = set()

    def start(self, argv: list[str], env: dict[str, str], cwd: str, run_dir: str, log_path: str,
              inputs: bytes, stream: bool) -> dict[str, Any]:
        """Start the federate. Where the node sees ``run_dir`` (shared) and ``stream`` is off, it
        writes there. Else it streams its table parts to the coordinator as it writes them
        (``fabric.records``), and writes the rest (its log, files written at its end) into a
        folder of this node holding the run directory's ``inputs`` (a tar of what the
        coordinator wrote there before the start), which ``stop`` ships back."""
        import ray

        node_id = ray.get_runtime_context().get_node_id()
        if stream or not Path(run_dir).is_dir():
            remove_orphans()
            self.local_dir = Path(tempfile.mkdtemp(prefix=f"{LOCAL_PREFIX}{os.getpid()}-"))
            with tarfile.open(fileobj=io.BytesIO(inputs), mode="r") as tar:
                tar.extractall(self.local_dir, filter="data")
            self.inputs = set(_files(self.local_dir))
            argv = [str(self.local_dir) if a == run_dir else
                    str(self.local_dir / Path(a).relative_to(run_dir)) if a.startswith(run_dir + "/") else a
                    for a in argv] + ["--records", "stream"]
            log_path = str(self.local_dir / Path(log_path).relative_to(run_dir))
            run_dir = str(self.local_dir)
        full = dict(os.environ)
        full.update(env)
        full.setdefault("MUJOCO_GL", "egl")
        full[PARENT_PID_ENV] = str(os.getpid())
        self.log_path = Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, *argv], stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=full, cwd=cwd if Path(cwd).is_dir() else run_dir, start_new_session=True)
        return {"node_id": node_id, "node_ip": ray.util.get_node_ip_address(), "hostname": socket.gethostname(),
                "actor_pid": os.getpid(), "pid": self.proc.pid, "records": "streamed" if self.local_dir else "shared"}

    def poll(self) -> int | None:
        """The child's exit code (negative: killed by that signal), None while it runs."""
        return None if self.proc is None else self.proc.poll()

    def tail(self, n: int) -> list[str]:
        if self.log_path is None or not self.log_path.exists():
            return []
        with open(self.log_path, errors="replace") as f:
            return [line.rstrip("\n") for line in deque(f, maxlen=n)]

    def stop(self, grace_s: float) -> tuple[int | None, bytes | None]:
        """Terminate the child's session (a stopped child is woken to die), kill it after
        ``grace_s``; its exit code and, where it wrote into a folder of this node, a tar of what
        it wrote there (the folder is removed)."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            terminate_session(proc)
            reap(proc, grace_s)
        code = None if proc is None else proc.returncode
        if self.local_dir is None:
            return code, None
        buf = io.BytesIO()
        # Not compressed again: the table parts are compressed already.
        with tarfile.open(fileobj=buf, mode="w") as tar:
            for rel in sorted(set(_files(self.local_dir)) - self.inputs):
                tar.add(self.local_dir / rel, arcname=rel)
        shutil.rmtree(self.local_dir, ignore_errors=True)
        self.local_dir = None
        return code, buf.getvalue()


def remove_orphans() -> None:
    """Remove the node-local folders of actors on this host that died without being stopped
    (their raylet lost): each folder's name holds its actor's pid."""
    for folder in Path(tempfile.gettempdir()).glob(f"{LOCAL_PREFIX}*-*"):
        pid = folder.name[len(LOCAL_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _files(root: Path) -> list[str]:
    """Every file under ``root``, as paths relative to it."""
    return [str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()]


def pack_inputs(run_dir: Path) -> bytes:
    """What the coordinator wrote into ``run_dir`` before the federates start (scenario, plans,
    frame model): the inputs of a federate writing into a folder of its own node."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for rel in sorted(_files(run_dir)):
            if not rel.startswith(("logs/", "tables/")):
                tar.add(run_dir / rel, arcname=rel)
    return buf.getvalue()


class _Session:
    """This process's Ray session, shared by its runs (the API runs several at once): the first
    run joins or starts the cluster, the last one to finish leaves it (if it was not joined
    before the first run)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.users = 0
        self.owned = False  # ray.init called here (not by the code around the runs)
        self.local = False  # a local cluster started by this process

    def acquire(self, ray: Any, address: str | None) -> bool:
        """Join ``address`` or start a local cluster unless this process is in one already;
        whether the session is a local cluster started here."""
        with self.lock:
            if not ray.is_initialized():
                kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                          "logging_level": logging.WARNING}
                if address:
                    check_reachable(address)
                else:
                    no_usage_stats()
                try:
                    ray.init(address=address, **kwargs) if address else ray.init(**kwargs)
                except Exception as exc:
                    where = f"join the Ray cluster at {address}" if address else "start a local Ray cluster"
                    raise RayRuntimeError(f"runtime ray: cannot {where}: {short_error(exc)}") from None
                self.owned, self.local = True, not address
            self.users += 1
            return self.owned and self.local

    def release(self, ray: Any) -> None:
        with self.lock:
            self.users = max(0, self.users - 1)
            if self.users == 0 and self.owned:
                self.owned = self.local = False
                ray.shutdown()


_SESSION = _Session()


class RayLauncher(Launcher):
    """Hosts one run's federates as Ray actors (one launcher per run). Joins the cluster when made."""

    def __init__(self, address: str | None = None, router_host: str | None = None,
                 strategy: str | None = None, placement_timeout_s: float | None = None,
                 poll_interval_s: float = 0.2) -> None:
        """``address``: ``auto`` or ``HOST:PORT`` of a running cluster, else
        ``COSIM5G_RAY_ADDRESS``, else a local cluster started for the run. ``router_host``: the
        address nodes reach the coordinator's zenoh router at (``COSIM5G_RAY_ROUTER_HOST``; default
        127.0.0.1 on a local cluster, the coordinator's node address on a joined one).
        ``strategy``: the placement group's (``COSIM5G_RAY_PLACEMENT``, PACK).
        ``poll_interval_s``: how stale ``dead()`` may be."""
        self.ray = import_ray()
        given = settings()
        self.address = address or given.ray_address
        self.strategy = strategy or given.ray_placement
        if self.strategy not in STRATEGIES:
            raise RayRuntimeError(f"ray placement strategy {self.strategy!r}: expected one of {', '.join(STRATEGIES)}")
        self.placement_timeout_s = placement_timeout_s or given.ray_placement_timeout_s
        self.stream = given.ray_records == "stream"
        self._run_dir: Path | None = None
        self._records_lost: list[str] = []
        self.poll_interval_s = poll_interval_s
        self.local = _SESSION.acquire(self.ray, self.address)
        self._session = True
        self.node_id = str(self.ray.get_runtime_context().get_node_id())
        self.router_host = router_host or given.ray_router_host or (
            "127.0.0.1" if self.local else self._node_ip(self.node_id))
        self._pg: Any = None
        self._bundle: dict[str, int] = {}  # federate process -> its bundle in the placement group
        self._cpus: dict[str, float] = {}
        self._reserved_for: tuple[str, ...] | None = None
        self._actors: dict[str, Any] = {}  # federate process -> actor handle
        self._where: dict[str, dict[str, Any]] = {}
        self._hosted: dict[str, str] = {}  # federate -> the process serving it
        self._logs: dict[str, Path] = {}
        self._dead: dict[str, str] = {}  # federate process -> reason
        self._lost: set[str] = set()  # federate processes whose actor is gone (killed, node lost)
        self._pending: dict[Any, str] = {}
        self._polled = -math.inf
        self._stopped = False

    def _node_ip(self, node_id: str) -> str:
        for node in self.ray.nodes():
            if node.get("NodeID") == node_id:
                return str(node["NodeManagerAddress"])
        return str(self.ray.util.get_node_ip_address())

    # -- endpoints ----------------------------------------------------------------------------

    def router_listen_endpoint(self, router_port: int) -> str:
        return f"tcp/{self.router_host}:{router_port}"

    def router_endpoint_for_federates(self, router_port: int) -> str:
        return f"tcp/{self.router_host}:{router_port}"

    # -- placement ----------------------------------------------------------------------------

    def reserve(self, specs: list[FederateSpec]) -> None:
        """Reserve the CPUs of the federates' node profiles in one placement group, all or
        nothing; RayRuntimeError naming what is missing when the cluster cannot hold them."""
        names = tuple(s.name for s in specs)
        if self._reserved_for == names:
            return
        if self._pg is not None:
            raise RayRuntimeError(f"this launcher already reserved for {', '.join(self._reserved_for or ())}")
        from ray.util.placement_group import placement_group, remove_placement_group

        asked = {s.name: c for s in specs if (c := reserved_cpus(s)) is not None}
        node_cpus = {str(n["NodeID"]): float(n["Resources"].get("CPU", 0.0))
                     for n in self.ray.nodes() if n.get("Alive")}
        available = float(self.ray.available_resources().get("CPU", 0.0))
        check_placement({_what(s): asked[s.name] for s in specs if s.name in asked}, node_cpus, available,
                        self.strategy)
        if asked:
            order = list(asked)
            pg = placement_group([{"CPU": asked[n]} for n in order], strategy=self.strategy)
            try:
                self.ray.get(pg.ready(), timeout=self.placement_timeout_s)
            except Exception as exc:
                remove_placement_group(pg)
                raise RayRuntimeError(
                    f"runtime ray: the cluster did not place the run's federates ({sum(asked.values()):g} "
                    f"CPUs, strategy {self.strategy}) within {self.placement_timeout_s:g} s "
                    f"({type(exc).__name__}); free CPUs now: "
                    f"{self.ray.available_resources().get('CPU', 0.0):g}") from None
            self._pg = pg
            self._bundle = {n: i for i, n in enumerate(order)}
        self._cpus = asked
        self._reserved_for = names

    # -- start --------------------------------------------------------------------------------

    def _env(self) -> dict[str, str]:
        """What the coordinator passes on to every federate process, on any node."""
        env = {k: v for k, v in os.environ.items() if k.startswith("COSIM5G_") and k not in _NOT_FORWARDED}
        env["PYTHONUNBUFFERED"] = "1"
        # One thread per process, as the process runtime: Ray sets these to the actor's CPUs.
        for var in THREAD_POOL_VARS:
            env[var] = os.environ.get(var, "1")
        if "MUJOCO_GL" in os.environ:
            env["MUJOCO_GL"] = os.environ["MUJOCO_GL"]
        return env

    def start(self, specs: list[FederateSpec], run_id: str, endpoint: str, scenario_path: Path,
              run_dir: Path) -> None:
        from ray.util.scheduling_strategies import (
            NodeAffinitySchedulingStrategy,
            PlacementGroupSchedulingStrategy,
        )

        try:
            self.reserve(specs)
        except RayRuntimeError as exc:
            raise RunFailed(str(exc)) from None
        run_dir = Path(run_dir).absolute()
        (run_dir / "logs").mkdir(parents=True, exist_ok=True)
        env = self._env()
        self._run_dir = run_dir
        inputs = pack_inputs(run_dir)  # for the nodes that do not see the run directory
        remote = self.ray.remote(FederateActor)
        starts: dict[str, Any] = {}
        for spec in specs:
            log_path = run_dir / "logs" / f"{spec.name}.log"
            for name in spec.names:
                self._hosted[name] = spec.name
                self._logs[name] = log_path
            if spec.name in self._bundle:
                cpus = self._cpus[spec.name]
                strategy: Any = PlacementGroupSchedulingStrategy(
                    placement_group=self._pg, placement_group_bundle_index=self._bundle[spec.name])
            else:
                # No node profile, nothing reserved: next to the coordinator's router, which every
                # message of the run crosses.
                cpus = 0.0
                strategy = NodeAffinitySchedulingStrategy(node_id=self.node_id, soft=True)
            actor = remote.options(num_cpus=cpus, scheduling_strategy=strategy, max_restarts=0,
                                   name=f"cosim5g/{run_id}/{spec.name}").remote()
            self._actors[spec.name] = actor
            argv = spec.argv(run_id, endpoint, str(Path(scenario_path).absolute()), str(run_dir))
            starts[spec.name] = actor.start.remote(argv, env, os.getcwd(), str(run_dir), str(log_path),
                                                   inputs, self.stream)
        addresses = {str(n["NodeID"]): str(n["NodeManagerAddress"]) for n in self.ray.nodes()}
        deadline = time.monotonic() + ACTOR_START_TIMEOUT_S
        for name, ref in starts.items():
            try:
                where = self.ray.get(ref, timeout=max(0.1, deadline - time.monotonic()))
            except Exception as exc:
                raise RunFailed(f"federate {name} could not start as a Ray actor: {short_error(exc)}",
                                federate=name) from None
            # The address the node has in the cluster (what the actor's host would guess may differ).
            where["node_ip"] = addresses.get(where["node_id"], where["node_ip"])
            where["cpus_reserved"] = self._cpus.get(name, 0.0)
            self._where[name] = where

    # -- supervision --------------------------------------------------------------------------

    def _collect(self, timeout_s: float) -> None:
        """Take in the answers of the polls in flight that came within ``timeout_s``."""
        if not self._pending:
            return
        ready, _ = self.ray.wait(list(self._pending), num_returns=len(self._pending), timeout=timeout_s)
        for ref in ready:
            name = self._pending.pop(ref)
            try:
                code = self.ray.get(ref)
            except Exception as exc:
                self._lost.add(name)
                self._dead.setdefault(name, f"lost its Ray actor{self.where(name)} (the actor's process was "
                                      f"killed, or its node lost): {short_error(exc)}")
                continue
            if code is not None:
                how = f"killed by signal {-code}" if code < 0 else f"exited with code {code}"
                self._dead.setdefault(name, f"{how}{self._on(name)}")

    def _on(self, name: str) -> str:
        where = self._where.get(name)
        return f" on Ray node {where['node_ip']} ({where['node_id'][:12]})" if where else ""

    def records_lost(self) -> list[str]:
        return [name for name, host in sorted(self._hosted.items()) if host in self._records_lost]

    def where(self, name: str) -> str:
        host = self._hosted.get(name, name)
        at = self._where.get(host)
        if at is None:
            return ""
        held = sorted(n for n, h in self._hosted.items() if self._where.get(h, {}).get("node_id") == at["node_id"])
        return f"{self._on(host)}, which held {', '.join(held)}"

    def _poll(self) -> None:
        """Ask every live actor how its child is, at most every ``poll_interval_s``, never waiting."""
        now = time.monotonic()
        if not self._pending and now - self._polled >= self.poll_interval_s:
            self._polled = now
            self._pending = {actor.poll.remote(): name for name, actor in self._actors.items()
                             if name not in self._dead}
        self._collect(0)

    def _poll_now(self, timeout_s: float) -> None:
        """Ask every live actor at once, whatever polls are in flight, and take in the answers
        that come within ``timeout_s``."""
        self._pending.clear()
        self._polled = -math.inf
        self._poll()
        self._collect(timeout_s)

    def dead(self) -> dict[str, str]:
        self._poll()
        out = {}
        for name, host in self._hosted.items():
            if host in self._dead:
                out[name] = self._dead[host] if host == name else f"{self._dead[host]} (process of {host})"
        return out

    def last_log_lines(self, name: str, n: int = 20) -> list[str]:
        path = self._logs.get(name)
        if path is not None and path.exists():  # one host, or a shared run directory
            with open(path, errors="replace") as f:
                return [line.rstrip("\n") for line in deque(f, maxlen=n)]
        actor = self._actors.get(self._hosted.get(name, name))
        if actor is None:
            return []
        try:
            return list(self.ray.get(actor.tail.remote(n), timeout=5))
        except Exception:
            return []

    def placement(self) -> dict[str, dict[str, Any]]:
        return {name: {**self._where[host], "process": host} for name, host in sorted(self._hosted.items())
                if host in self._where}

    def stop(self, grace_s: float = 5.0) -> None:
        if self._stopped:
            return
        self._stopped = True
        try:
            self._stop_actors(grace_s)
        except Exception:  # the cluster may be gone: nothing more to stop there
            log.exception("stopping the run's Ray actors")
        finally:
            self._release()

    def _stop_actors(self, grace_s: float) -> None:
        ray = self.ray
        # Federates told to stop leave on their own; give them a moment before signalling.
        deadline = time.monotonic() + min(grace_s, 2.0)
        while time.monotonic() < deadline and len(self._dead) < len(self._actors):
            self._poll_now(max(0.0, deadline - time.monotonic()))
            time.sleep(0.02)
        # An actor found gone gets no stop call: on a lost node, it would only time out.
        stops = {actor.stop.remote(grace_s): name for name, actor in self._actors.items()
                 if name not in self._lost}
        shipping = {n for n, w in self._where.items() if w.get("records") == "streamed"}
        back: set[str] = set()
        if stops:
            ready, left = ray.wait(list(stops), num_returns=len(stops), timeout=grace_s + 5.0)
            if left and shipping:
                # Shipping a node's files back takes as long as they are large: wait longer for
                # those whose actor still answers (one on a lost node would only time out).
                self._poll_now(2.0)
                left = [ref for ref in left if stops[ref] not in self._lost]
                if left:
                    ready += ray.wait(left, num_returns=len(left), timeout=SHIP_WAIT_S)[0]
            for ref in ready:
                name = stops[ref]
                try:
                    _, records = ray.get(ref)
                    if records and self._run_dir is not None:  # written on a node of its own
                        with tarfile.open(fileobj=io.BytesIO(records), mode="r") as tar:
                            tar.extractall(self._run_dir, filter="data")
                        back.add(name)
                except Exception as exc:  # a dead actor: what its node wrote is lost with it
                    log.error("the records of %s did not come back: %s", name, short_error(exc))
        self._records_lost = sorted(shipping - back)
        for actor in self._actors.values():
            ray.kill(actor, no_restart=True)
        if self._pg is not None:
            from ray.util.placement_group import remove_placement_group

            remove_placement_group(self._pg)
            self._pg = None

    def _release(self) -> None:
        if self._session:
            self._session = False
            _SESSION.release(self.ray)


# How long a cluster address given as host:port may take to answer before joining it is given up
# (Ray itself retries for minutes, printing warnings, with nothing at the address).
CONNECT_TIMEOUT_S = 5.0


def no_usage_stats() -> None:
    """A local cluster about to start here reports nothing to Ray's usage statistics: the user's
    runs are theirs, and the host may reach no such service anyway (unless the user set it)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


def check_reachable(address: str) -> None:
    """RayRuntimeError unless the head at ``address`` (``host:port``; other forms, such as
    ``auto`` or ``ray://``, are left to Ray) accepts a connection within CONNECT_TIMEOUT_S."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise RayRuntimeError(f"cannot reach the Ray cluster at {address} ({short_error(exc)}): start "
                              f"its head (ray start --head) or give the address it prints") from None


def short_error(exc: BaseException, limit: int = 300) -> str:
    """An exception as one line of at most ``limit`` characters of its text, with its type."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:limit]}{'...' if len(text) > limit else ''}"
