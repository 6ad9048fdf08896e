"""A run's objects in the Docker daemon: how they are labelled, which coordinator process owns
them, and their removal when that coordinator is gone (``reap_dead_runs``, called when a
coordinator starts)."""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from docker.errors import APIError, NotFound

log = logging.getLogger(__name__)

LABEL_RUN = "cosim5g.run_id"
LABEL_FEDERATE = "cosim5g.federate"
LABEL_ROLE = "cosim5g.role"
LABEL_OWNER = "cosim5g.owner"
LABEL_METRICS_PORT = "cosim5g.metrics_port"
# Platform containers (compose coordinator, Prometheus) that must reach every run's federates.
LABEL_ATTACH = "cosim5g.attach"
ATTACH_RUN_NETWORKS = "run-networks"
LABEL_ALIAS = "cosim5g.alias"



def _proc_start_ticks(pid: int) -> str | None:
    """The start time of ``pid`` in clock ticks since boot (tells a reused pid apart)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # Field 22; the command name (field 2) may hold spaces, so split after its closing ')'.
    return stat.rsplit(")", 1)[1].split()[19]


def owner_id() -> str:
    """``<hostname>/<pid>/<start ticks>`` of this process."""
    pid = os.getpid()
    return f"{socket.gethostname()}/{pid}/{_proc_start_ticks(pid) or '?'}"


def _owner_alive(owner: str, running_container_ids: Iterable[str]) -> bool:
    """Whether the coordinator that labelled a run with ``owner`` is still alive.

    Same host namespace (same hostname): its pid must exist with the same start time. Another
    hostname is usually a coordinator in a container (a container's hostname is its short id):
    alive while that container runs. Anything else cannot be checked from here and counts as
    dead: one coordinator per Docker daemon is the supported setup.
    """
    try:
        host, pid_s, ticks = owner.split("/")
        pid = int(pid_s)
    except ValueError:
        return False
    if host == socket.gethostname():
        return _proc_start_ticks(pid) == ticks
    return any(cid.startswith(host) for cid in running_container_ids)


def reap_dead_runs(client: Any, alive_run_ids: Iterable[str] = ()) -> list[str]:
    """Remove the containers and networks of runs that no live coordinator owns.

    A run is alive if its id is in ``alive_run_ids`` or the coordinator process that started it
    is still alive (``cosim5g.owner`` label). Call at coordinator start-up, when no run of this
    coordinator exists yet. Returns the reaped run ids.

    A coordinator that dies does not leave its federates running until then: each federate
    leaves within seconds of the coordinator's liveliness token vanishing (``services.main``), so
    what is left of a dead run is exited containers (kept for their logs and exit codes) and the
    run network, running or not alike removed here.
    """
    alive = set(alive_run_ids)
    containers = client.containers.list(all=True, filters={"label": LABEL_RUN})
    networks = client.networks.list(filters={"label": LABEL_RUN})
    running_ids = [c.id for c in client.containers.list()]
    owners: dict[str, set[str]] = {}
    for c in containers:
        owners.setdefault(c.labels[LABEL_RUN], set()).add(c.labels.get(LABEL_OWNER, ""))
    for n in networks:
        owners.setdefault(n.attrs["Labels"][LABEL_RUN], set()).add(
            n.attrs["Labels"].get(LABEL_OWNER, ""))
    dead = sorted(
        run for run, who in owners.items()
        if run not in alive and not any(_owner_alive(o, running_ids) for o in who if o)
    )
    for run in dead:
        log.warning("reaping leftovers of dead run %s", run)
        remove_run_objects(client, run)
    return dead


def remove_run_objects(client: Any, run_id: str) -> list[str]:
    """Force-remove every container, network and volume labelled with ``run_id``; returns errors."""
    errors: list[str] = []
    selector = {"label": f"{LABEL_RUN}={run_id}"}
    for c in client.containers.list(all=True, filters=selector):
        try:
            c.remove(force=True, v=True)
        except NotFound:
            pass
        except APIError as e:
            errors.append(f"container {c.name}: {e.explanation or e}")
    for n in client.networks.list(filters=selector):
        try:
            n.reload()
            # Platform containers attached for the run's lifetime would block the removal.
            for cid in (n.attrs.get("Containers") or {}):
                try:
                    n.disconnect(cid, force=True)
                except (NotFound, APIError):
                    pass
            n.remove()
        except NotFound:
            pass
        except APIError as e:
            errors.append(f"network {n.name}: {e.explanation or e}")
    # We create none, but a federate image with a VOLUME would leave anonymous ones behind.
    for v in client.volumes.list(filters=selector):
        try:
            v.remove(force=True)
        except NotFound:
            pass
        except APIError as e:
            errors.append(f"volume {v.name}: {e.explanation or e}")
    return errors
