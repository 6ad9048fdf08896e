"""Every zenoh key expression of the platform, built in one place.

Layout: ``cosim/<run_id>/<plane>/...``, lower case, no trailing slash. Data planes address a
destination federate first so that one subscription per plane gives a federate its inbox:
``cosim/<run>/<plane>/<dst>/<src>``. Control keys live on ``ctl``, liveliness tokens on ``alive``.
"""

from __future__ import annotations

import re

ROOT = "cosim"
DATA_PLANES = ("sense", "act", "net")
_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]*$")


def check_name(name: str, what: str = "name") -> str:
    """``name`` if it is a valid key segment (lower-case letters, digits, ``-``, ``_``), else a
    ValueError calling it ``what`` and saying what is allowed."""
    if not _NAME.match(name):
        raise ValueError(
            f"{what} {name!r} is not a valid key segment: use lower-case letters, digits, '-' and '_'"
        )
    return name


def data(run_id: str, plane: str, dst: str, src: str) -> str:
    """Key of a data message of run ``run_id`` from federate ``src`` to federate ``dst`` on
    ``plane`` (one of ``DATA_PLANES``, else ValueError)."""
    if plane not in DATA_PLANES:
        raise ValueError(f"plane {plane!r} is not one of {DATA_PLANES}")
    return f"{ROOT}/{run_id}/{plane}/{dst}/{src}"


def inbox(run_id: str, plane: str, dst: str) -> str:
    """Key expression of every message of run ``run_id`` addressed to ``dst`` on ``plane``."""
    return f"{ROOT}/{run_id}/{plane}/{dst}/*"


def advance(run_id: str) -> str:
    """Key of the conductor's ``Advance`` records of run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/advance"


def stop(run_id: str) -> str:
    """Key of the conductor's ``Stop`` record of run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/stop"


def done(run_id: str, federate: str) -> str:
    """Key of the ``Done`` reports of participant ``federate`` (a federate or a group) in run
    ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/done/{federate}"


def done_all(run_id: str) -> str:
    """Key expression of every participant's ``Done`` reports of run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/done/*"


def ready(run_id: str, federate: str) -> str:
    """Key of the ``Ready`` record of ``federate`` in run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/ready/{federate}"


def ready_all(run_id: str) -> str:
    """Key expression of every federate's ``Ready`` record of run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/ready/*"


def stopped(run_id: str, federate: str) -> str:
    """Key of the ``Stopped`` record of ``federate`` in run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/stopped/{federate}"


def stopped_all(run_id: str) -> str:
    """Key expression of every federate's ``Stopped`` record of run ``run_id``."""
    return f"{ROOT}/{run_id}/ctl/stopped/*"


def alive(run_id: str, federate: str) -> str:
    """Liveliness token of ``federate`` (or of a group) in run ``run_id``."""
    return f"{ROOT}/{run_id}/alive/{federate}"


def alive_all(run_id: str) -> str:
    """Key expression of every liveliness token of run ``run_id``, the coordinator's included."""
    return f"{ROOT}/{run_id}/alive/*"


COORDINATOR = "coordinator"  # never a federate's name (scenario.schema names them)


def coordinator_alive(run_id: str) -> str:
    """The coordinator's liveliness token in run ``run_id``: federates leave when it vanishes."""
    return f"{ROOT}/{run_id}/alive/{COORDINATOR}"


def last_segment(key: str) -> str:
    """The last segment of ``key`` (the federate's name in ``ctl`` and ``alive`` keys)."""
    return key.rsplit("/", 1)[-1]


def record(run_id: str, federate: str, table: str) -> str:
    """Key of the bytes of ``federate``'s part of ``table`` in run ``run_id``, when its records
    are streamed to the coordinator (``fabric.records``)."""
    return f"{ROOT}/{run_id}/records/{federate}/{table}"


def records_all(run_id: str) -> str:
    """Key expression of every streamed table part of run ``run_id``."""
    return f"{ROOT}/{run_id}/records/*/*"
