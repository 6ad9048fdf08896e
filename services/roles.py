"""The federate roles: one registration each says which class serves the role, how many
federates of it a scenario has and what they are named, the compute node they are throttled to,
and whether they join the ``core`` group. The process entry point (``services.main``) and the
coordinator's launch plan (``coordinator.run``) read nothing else.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from domain.partitions import netsim_names
from scenario.schema import Scenario

if TYPE_CHECKING:
    from fabric.federate import Federate


@dataclass(frozen=True)
class Role:
    """``federate``: "module:Class", imported only when a process of the role starts (a camera
    process does not load MuJoCo). ``names(scenario)``: the role's federates. ``node``: the
    scenario's compute node profile (``nodes.<node>``) its federates are throttled to, if any.
    ``core``: served in the ``core`` group with ``cohost: core`` (no compute node to emulate,
    messages every window), unless ``apart(scenario)``: netsim split into partitions, each a
    process of its own beside the group."""

    name: str
    federate: str
    names: Callable[[Scenario], list[str]]
    node: str | None = None
    core: bool = False
    apart: Callable[[Scenario], bool] | None = None

    def in_core(self, scenario: Scenario) -> bool:
        """Whether the role's federates are members of the ``core`` group (with ``cohost: core``)."""
        return self.core and not (self.apart is not None and self.apart(scenario))

    def federate_class(self) -> type[Federate]:
        module, _, cls = self.federate.partition(":")
        return getattr(importlib.import_module(module), cls)  # type: ignore[no-any-return]


ROLES: dict[str, Role] = {}


def register(role: Role) -> Role:
    if role.name in ROLES or role.name == "group":
        raise ValueError(f"role {role.name!r} is taken")
    ROLES[role.name] = role
    return role


def role(name: str) -> Role:
    """The role called ``name``; ValueError naming the roles there are."""
    try:
        return ROLES[name]
    except KeyError:
        raise ValueError(f"unknown role {name!r}: {', '.join(ROLES)}") from None


def federates(scenario: Scenario) -> list[tuple[str, str]]:
    """(name, role) of every federate of ``scenario``, in registration order."""
    return [(name, r.name) for r in ROLES.values() for name in r.names(scenario)]


def _detailed(prefix: str) -> Callable[[Scenario], list[str]]:
    return lambda sc: [f"{prefix}-{i}" for i in range(sc.detailed_loops)]


register(Role("physics", "services.physics.federate:PhysicsFederate", lambda sc: ["physics"], core=True))
register(Role("netsim", "netsim.federate:NetsimFederate", netsim_names, core=True,
              apart=lambda sc: sc.partitions > 1))
register(Role("edge", "services.edge.federate:EdgeFederate", lambda sc: ["edge"], node="edge"))
register(Role("camera", "services.camera.federate:CameraFederate", _detailed("camera"), node="camera"))
register(Role("robot", "services.robot.federate:RobotFederate", _detailed("robot"), node="robot"))
register(Role("loops", "services.loops.federate:LoopsFederate",
              lambda sc: ["loops"] if sc.loops > sc.detailed_loops else [], core=True))
