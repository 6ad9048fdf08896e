"""The docker runtime: one cgroup-limited, unprivileged container per federate on a per-run network.

``DockerLauncher`` implements ``coordinator.launcher.Launcher`` with the docker SDK; labels and the
reaper are ``coordinator.docker_runs``, cgroup limits ``coordinator.docker_limits``. Containers,
limits, hardening and how federates reach the router: docs/docker.md, "Running a run's federates".
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import signal
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import docker
from docker.errors import APIError, DockerException, ImageNotFound, NotFound

from coordinator.docker_limits import cgroup_limits
from coordinator.docker_runs import (
    ATTACH_RUN_NETWORKS,
    LABEL_ALIAS,
    LABEL_ATTACH,
    LABEL_FEDERATE,
    LABEL_METRICS_PORT,
    LABEL_OWNER,
    LABEL_ROLE,
    LABEL_RUN,
    owner_id,
    remove_run_objects,
)
from coordinator.launcher import FederateSpec, Launcher, NodeLimits
from fabric.settings import env_name, settings

log = logging.getLogger(__name__)

RUNTIME_IMAGE = "cosim5g/runtime:latest"

# A node using this share of its memory limit when it fails is taken to have run out of memory.
MEMORY_FULL = 0.95
# The image's unprivileged user (images/runtime.Dockerfile).
IMAGE_UID = 10001
IMAGE_GID = 10001
HOST_ALIAS = "host.docker.internal"
TMPFS_TMP = "rw,nosuid,nodev,noexec,size=256m"
PIDS_LIMIT = 512
_SIOCGIFADDR = 0x8915  # ioctl: an interface's IPv4 address
# Docker object names: [a-zA-Z0-9][a-zA-Z0-9_.-]*; run ids and federate names become part of them.
_NAME_RE = re.compile(r"^[a-zA-Z0-9][a-zA-Z0-9_.-]*$")


class DockerRuntimeError(RuntimeError):
    """The docker runtime could not do what was asked; the message says what and how to fix it."""


def docker_client(timeout_s: int = 30) -> Any:
    """A docker SDK client for the daemon of the environment (DOCKER_HOST or the local socket)."""
    try:
        client = docker.from_env(timeout=timeout_s)
        client.ping()
    except DockerException as e:
        where = os.environ.get("DOCKER_HOST", "unix:///var/run/docker.sock")
        raise DockerRuntimeError(
            f"Docker daemon not reachable at {where}: {e}. Start it, or use the `process` runtime."
        ) from e
    return client


# ---------------------------------------------------------------------------------------------
# The launcher
# ---------------------------------------------------------------------------------------------

def _default_bridge_address(client: Any) -> str | None:
    """The IPv4 address of the default bridge on this host: what ``host-gateway`` maps to."""
    try:
        bridge = client.networks.get("bridge").attrs
    except NotFound:
        return None
    for cfg in (bridge.get("IPAM") or {}).get("Config") or []:
        gw = cfg.get("Gateway", "")
        if gw and ":" not in gw:
            return str(gw)
    # Docker 20.10 often leaves the gateway out of the default bridge's IPAM config: ask the
    # kernel for the bridge interface's address (only meaningful on the daemon's host).
    ifname = (bridge.get("Options") or {}).get("com.docker.network.bridge.name", "docker0")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            req = struct.pack("256s", ifname.encode()[:15])
            return socket.inet_ntoa(fcntl.ioctl(s.fileno(), _SIOCGIFADDR, req)[20:24])
    except OSError:
        return None


def _exit_reason(state: dict[str, Any], limits: NodeLimits | None) -> str:
    """A human reason for a stopped container's state (``container.attrs["State"]``)."""
    code = state.get("ExitCode")
    reason = f"exited with code {code}"
    if state.get("OOMKilled"):
        mem = f" of {limits.mem_mb} MiB" if limits and limits.mem_mb else ""
        reason += f" (OOM-killed: memory limit{mem} exceeded)"
    elif isinstance(code, int) and code > 128:
        try:
            reason += f" (killed by {signal.Signals(code - 128).name})"
        except ValueError:
            pass
    if state.get("Error"):
        reason += f": {state['Error']}"
    return reason


class DockerLauncher(Launcher):
    """Runs one run's federates as containers of ``image`` (one launcher per run)."""

    def __init__(self, client: Any | None = None, image: str = RUNTIME_IMAGE,
                 router_host: str | None = None, metrics_port: int | None = None,
                 log_tail_on_stop: int = 200, poll_interval_s: float = 0.25) -> None:
        """
        ``router_host``: how federates name the router's host; default ``COSIM5G_ROUTER_HOST``,
        else ``host.docker.internal`` (coordinator on the host). ``metrics_port``: a port on
        which federates serve Prometheus metrics, advertised to Prometheus' docker discovery
        by a label (default ``COSIM5G_FEDERATE_METRICS_PORT``; none: not scraped).
        ``poll_interval_s``: how stale ``dead()`` may be; a death is seen within this delay.
        """
        self.client = client if client is not None else docker_client()
        self.image = image
        given = settings()
        self.router_host = router_host or given.router_host or HOST_ALIAS
        self.metrics_port = metrics_port or given.federate_metrics_port
        self.log_tail_on_stop = log_tail_on_stop
        self.poll_interval_s = poll_interval_s
        self._last_poll = -float("inf")
        self.run_id: str | None = None
        self.run_dir: Path | None = None
        self.network: Any = None
        self._containers: dict[str, Any] = {}  # federate name -> Container
        self._limits: dict[str, NodeLimits] = {}
        self._hosted: dict[str, str] = {}  # federate served by another's container -> that one
        self._dead: dict[str, str] = {}
        self._logs: dict[str, list[str]] = {}  # last lines kept when containers are removed
        self._attached: list[Any] = []  # platform containers connected to the run network
        self._stopped = False

    # -- endpoints ----------------------------------------------------------------------------

    @property
    def coordinator_on_host(self) -> bool:
        return self.router_host == HOST_ALIAS

    def router_endpoint_for_federates(self, router_port: int) -> str:
        return f"tcp/{self.router_host}:{router_port}"

    def router_listen_endpoint(self, router_port: int) -> str:
        """Where the coordinator's router must listen so that the federates reach it.

        On the host: the default bridge's gateway (docker0), which ``host.docker.internal``
        resolves to inside the containers. In a container: every interface of the container,
        the run networks being attached to it at ``start``.
        """
        if not self.coordinator_on_host:
            return f"tcp/0.0.0.0:{router_port}"
        gateway = _default_bridge_address(self.client)
        if gateway is None:
            raise DockerRuntimeError(
                "cannot find the address of Docker's default bridge (docker0), which "
                f"{HOST_ALIAS} resolves to inside the containers; run the coordinator with "
                "docker-compose.yml instead, or check `docker network inspect bridge`")
        return f"tcp/{gateway}:{router_port}"

    # -- start --------------------------------------------------------------------------------

    def start(self, specs: list[FederateSpec], run_id: str, endpoint: str, scenario_path: Path,
              run_dir: Path) -> None:
        scenario = Path(scenario_path).absolute()
        rundir = Path(run_dir).absolute()
        if not scenario.is_relative_to(rundir):
            raise DockerRuntimeError(
                f"scenario {scenario} is outside the run directory {rundir}: containers see only "
                "the run directory; write the resolved scenario into it")
        self._start(specs, run_id, rundir, lambda spec: ["python", *spec.argv(
            run_id, endpoint, str(scenario), str(rundir))])

    def _start(self, specs: list[FederateSpec], run_id: str, run_dir: Path,
               command: Callable[[FederateSpec], list[str]]) -> None:
        """Start ``specs`` with ``command(spec)`` as their command (tests pass a stand-in)."""
        if self.run_id is not None:
            raise DockerRuntimeError(f"this launcher already ran run {self.run_id}: use a new one")
        names = [s.name for s in specs]
        for label in [run_id, *names]:
            if not _NAME_RE.match(label):
                raise ValueError(f"{label!r} cannot be part of a docker name: use letters, "
                                 "digits, '_', '.', '-' and start with a letter or digit")
        if len(set(names)) != len(names):
            raise ValueError(f"federate names must be unique, got {names}")
        limits_kw = {s.name: cgroup_limits(s.limits) for s in specs}  # validate before creating
        try:
            self.client.images.get(self.image)
        except ImageNotFound as e:
            raise DockerRuntimeError(f"image {self.image} missing: run `make images`") from e
        if not run_dir.is_dir():
            raise DockerRuntimeError(f"run directory {run_dir} does not exist")
        user = self._user_for(run_dir)

        owner = owner_id()
        net_labels = {LABEL_RUN: run_id, LABEL_OWNER: owner}
        try:
            network = self.client.networks.create(
                f"cosim5g-{run_id}", driver="bridge", labels=net_labels, check_duplicate=True)
        except APIError as e:
            # Not ours to clean up: the name may belong to a live run with the same id.
            raise DockerRuntimeError(
                f"cannot create network cosim5g-{run_id}: {e.explanation or e} (a leftover of "
                "an earlier run with this id? reap_dead_runs removes those)") from e
        # From here on, stop() removes whatever carries this run's label.
        self.run_id, self.run_dir, self.network = run_id, run_dir, network
        try:
            self._attach_platform_containers()
            for spec in specs:
                self._run_one(spec, run_id, run_dir, command(spec), user, owner,
                              limits_kw[spec.name])
        except BaseException:
            self.stop(grace_s=0)
            raise

    def _user_for(self, run_dir: Path) -> str:
        """The uid:gid federates run as: whoever owns the run directory, never root.

        Results then belong to the researcher who owns the run directory. A root coordinator
        with a root-owned run directory hands the directory to the image's user instead.
        """
        st = run_dir.stat()
        if st.st_uid != 0:
            return f"{st.st_uid}:{st.st_gid}"
        if os.geteuid() != 0:
            raise DockerRuntimeError(
                f"run directory {run_dir} belongs to root: federates do not run as root; "
                "give the directory to the user running the coordinator")
        for path in [run_dir, *run_dir.rglob("*")]:
            os.chown(path, IMAGE_UID, IMAGE_GID, follow_symlinks=False)
        return f"{IMAGE_UID}:{IMAGE_GID}"

    def _attach_platform_containers(self) -> None:
        """Connect the running platform containers (compose coordinator, Prometheus) to the run
        network, so the federates reach the router and Prometheus reaches the federates."""
        found_router = self.coordinator_on_host
        for c in self.client.containers.list(filters={"label": f"{LABEL_ATTACH}={ATTACH_RUN_NETWORKS}"}):
            alias = c.labels.get(LABEL_ALIAS)
            self.network.connect(c, aliases=[alias] if alias else None)
            self._attached.append(c)
            found_router = found_router or alias == self.router_host
        if not found_router:
            raise DockerRuntimeError(
                f"federates are to reach the router at {self.router_host!r} (COSIM5G_ROUTER_HOST) "
                f"but no running container is labelled {LABEL_ATTACH}={ATTACH_RUN_NETWORKS} and "
                f"{LABEL_ALIAS}={self.router_host}: start the platform with docker-compose.yml, "
                "or unset COSIM5G_ROUTER_HOST when the coordinator runs on the host")

    def _run_one(self, spec: FederateSpec, run_id: str, run_dir: Path, command: list[str],
                 user: str, owner: str, limits_kw: dict[str, Any]) -> None:
        labels = {LABEL_RUN: run_id, LABEL_FEDERATE: spec.name, LABEL_ROLE: spec.role,
                  LABEL_OWNER: owner}
        if self.metrics_port:
            labels[LABEL_METRICS_PORT] = str(self.metrics_port)
        env = {
            "MUJOCO_GL": "egl",
            "PYOPENGL_PLATFORM": "egl",
            "HOME": "/tmp",  # the root is read-only; an arbitrary uid has no home anyway
        }
        if self.metrics_port:
            env[env_name("metrics_port")] = str(self.metrics_port)  # fabric.metrics
        extra_hosts = {HOST_ALIAS: "host-gateway"} if self.coordinator_on_host else None
        try:
            container = self.client.containers.run(
                self.image,
                command=command,
                name=f"cosim5g-{run_id}-{spec.name}",
                hostname=spec.name,
                labels=labels,
                environment=env,
                user=user,
                detach=True,
                network=self.network.name,
                extra_hosts=extra_hosts,
                volumes={str(run_dir.resolve()): {"bind": str(run_dir), "mode": "rw"}},
                tmpfs={"/tmp": TMPFS_TMP},
                read_only=True,
                privileged=False,
                cap_drop=["ALL"],
                security_opt=["no-new-privileges"],
                pids_limit=PIDS_LIMIT,
                **limits_kw,
            )
        except APIError as e:
            raise DockerRuntimeError(
                f"cannot start federate {spec.name} ({spec.role}): {e.explanation or e}") from e
        self._containers[spec.name] = container
        self._limits[spec.name] = spec.limits
        for name, _ in spec.members:
            self._hosted[name] = spec.name

    # -- supervision --------------------------------------------------------------------------

    def container(self, name: str) -> Any:
        """The container of federate ``name`` (for inspection and tests)."""
        return self._containers[self._hosted.get(name, name)]

    def _with_members(self, dead: dict[str, str]) -> dict[str, str]:
        """``dead`` (by container) with the federates a dead container hosted."""
        out = dict(dead)
        out.update({name: f"{dead[host]} (container of {host})" for name, host in self._hosted.items()
                    if host in dead})
        return out

    def dead(self) -> dict[str, str]:
        """Federates that have exited. Cheap to call in a tight loop: the daemon is asked at most
        every ``poll_interval_s`` (the conductor calls this before every control message, and one
        inspect per container costs ~1.5 ms: polling each time would dominate a window)."""
        if self._stopped:  # our own stop() removed the containers: nothing new died
            return self._with_members(self._dead)
        now = time.monotonic()
        if self.run_id is None or now - self._last_poll < self.poll_interval_s:
            return self._with_members(self._dead)
        self._last_poll = now
        try:
            listed = self.client.containers.list(
                all=True, sparse=True, filters={"label": f"{LABEL_RUN}={self.run_id}"})
        except (APIError, DockerException) as e:
            log.warning("run %s: cannot ask the Docker daemon for container states: %s",
                        self.run_id, e)
            return self._with_members(self._dead)
        state_by_id = {c.id: c.attrs.get("State") for c in listed}
        for name, c in self._containers.items():
            if name in self._dead:
                continue
            state = state_by_id.get(c.id)
            if state is None:
                self._dead[name] = "container removed outside cosim5g"
            elif state in ("exited", "dead"):
                try:
                    c.reload()  # the list has no exit code / OOM flag: inspect the dead only
                    self._dead[name] = _exit_reason(c.attrs.get("State") or {},
                                                    self._limits.get(name))
                except NotFound:
                    self._dead[name] = "container removed outside cosim5g"
        return self._with_members(self._dead)

    def resource_note(self, name: str) -> str | None:
        """A node that hangs rather than dies at its memory limit (the kernel reclaiming its last
        pages instead of killing it) is named as out of memory."""
        name = self._hosted.get(name, name)
        c = self._containers.get(name)
        limits = self._limits.get(name)
        if c is None or limits is None or limits.mem_mb is None:
            return None
        try:
            mem = c.stats(stream=False).get("memory_stats") or {}
        except (APIError, DockerException):
            return None
        usage, limit = mem.get("usage"), mem.get("limit")
        if not usage or not limit or usage < MEMORY_FULL * limit:
            return None
        return f"at its memory limit of {limits.mem_mb} MiB ({usage / 2**20:.0f} MiB used): out of memory"

    def last_log_lines(self, name: str, n: int = 20) -> list[str]:
        name = self._hosted.get(name, name)
        if name not in self._containers:
            raise KeyError(f"no federate {name!r} in run {self.run_id}; "
                           f"known: {sorted(self._containers)}")
        try:
            raw = self._containers[name].logs(stdout=True, stderr=True, tail=n)
        except NotFound:
            return self._logs.get(name, [])[-n:] if n > 0 else []
        return raw.decode("utf-8", errors="replace").splitlines()[-n:] if n > 0 else []

    # -- stop ---------------------------------------------------------------------------------

    def stop(self, grace_s: float = 5.0) -> None:
        if self._stopped:
            # Second call: the containers are gone; only sweep by label once more, in case.
            if self.run_id is not None:
                for err in remove_run_objects(self.client, self.run_id):
                    log.error("run %s: could not remove %s", self.run_id, err)
            return
        self._last_poll = -float("inf")
        self.dead()  # record how federates ended before our SIGTERM muddles the picture
        self._stopped = True
        containers = dict(self._containers)
        # SIGTERM everything at once (tini forwards it), so the grace period is paid once.
        for c in containers.values():
            try:
                c.kill(signal="SIGTERM")
            except (NotFound, APIError):
                pass  # already stopped or gone
        deadline = time.monotonic() + max(grace_s, 0.0)
        pending = dict(containers)
        while pending and time.monotonic() < deadline:
            for name, c in list(pending.items()):
                try:
                    c.reload()
                    if c.status not in ("running", "restarting", "paused"):
                        del pending[name]
                except NotFound:
                    del pending[name]
            if pending:
                time.sleep(0.1)
        for name, c in containers.items():
            self._keep_logs(name, c)
        errors: list[str] = []
        for name, c in containers.items():
            try:
                c.remove(force=True, v=True)  # SIGKILLs what is still running
            except NotFound:
                pass
            except APIError as e:
                errors.append(f"container of {name}: {e.explanation or e}")
        if self.network is not None:
            for c in self._attached:
                try:
                    self.network.disconnect(c, force=True)
                except (NotFound, APIError):
                    pass
            self._attached.clear()
        if self.run_id is not None:
            # By label as well: catches anything created before a failure recorded it.
            errors += remove_run_objects(self.client, self.run_id)
        for err in errors:
            log.error("run %s: could not remove %s", self.run_id, err)

    def _keep_logs(self, name: str, container: Any) -> None:
        """Keep a federate's log past its container: last lines in memory, all in the run dir."""
        try:
            raw = container.logs(stdout=True, stderr=True)
        except (NotFound, APIError):
            return
        text = raw.decode("utf-8", errors="replace")
        self._logs[name] = text.splitlines()[-self.log_tail_on_stop:]
        if self.run_dir is None or not text:
            return
        try:
            logs_dir = self.run_dir / "logs"
            logs_dir.mkdir(exist_ok=True)
            tmp = logs_dir / f".{name}.container.log.tmp"
            tmp.write_text(text)
            tmp.replace(logs_dir / f"{name}.container.log")
        except OSError as e:
            log.warning("could not save the log of %s into %s: %s", name, self.run_dir, e)
