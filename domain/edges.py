"""Which Edge serves each loop: the Edge of its camera's gNB (``edge.placement: per_gnb``) or one
central Edge for the hall behind a backhaul of ``edge.backhaul_ms`` (``central``), and the
association of each work cell to its gNB that decides it (docs/architecture.md sec. 7, "Edges").

With one gNB every loop is on gNB 0. With ``hall.inf_layout`` the association is netsim's (the
strongest RSRP, fixed for the run); the coordinator resolves it with netsim's own functions and
streams and writes it into the run directory (``EDGE_FILE``), where every Edge side reads it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fabric.tables import write_json
from scenario.schema import Scenario

EDGE_FILE = "edges.json"  # in a run's directory: each loop's gNB and the Edge placement
CENTRAL = "central"  # the name of the central Edge


def edge_name(gnb: int) -> str:
    """The name of the Edge at the gNB of layout index ``gnb`` (as netsim's ``gnb<i>`` KPIs)."""
    return f"gnb{gnb}"


@dataclass(frozen=True)
class EdgePlan:
    """Where each loop's Edge side runs. ``gnb_of_loop[i]``: the layout index of the gNB serving
    loop i's camera (the uplink its Edge measures and its PDP steers); ``placement``: ``per_gnb``
    or ``central``; ``backhaul_us``: the one-way delay between a gNB and the loop's Edge, us (0
    at a per-gNB Edge), applied to every uplink frame and every downlink packet."""

    placement: str
    backhaul_us: int
    gnb_of_loop: tuple[int, ...]

    def edge_of(self, loop: int) -> str:
        """The name of the Edge serving ``loop``: ``central``, or ``gnb<i>`` of its camera's gNB."""
        return CENTRAL if self.placement == CENTRAL else edge_name(self.gnb_of_loop[loop])

    def groups(self, loops: Iterable[int] | None = None) -> dict[str, list[int]]:
        """Edge name -> its loops among ``loops`` (None: every loop), both in ascending order."""
        chosen = range(len(self.gnb_of_loop)) if loops is None else sorted(loops)
        out: dict[str, list[int]] = {}
        for loop in chosen:
            out.setdefault(self.edge_of(loop), []).append(loop)
        return dict(sorted(out.items(), key=lambda kv: kv[1][0]))

    def to_json(self) -> dict[str, Any]:
        return {"placement": self.placement, "backhaul_us": self.backhaul_us,
                "gnb_of_loop": list(self.gnb_of_loop),
                "edges": self.groups()}


def make_plan(sc: Scenario, gnb_of_loop: Iterable[int]) -> EdgePlan:
    """The plan of ``sc``'s ``edge`` section with loop i's camera on gNB ``gnb_of_loop[i]``."""
    gnbs = tuple(int(g) for g in gnb_of_loop)
    if len(gnbs) != sc.loops:
        raise ValueError(f"the gNB of {len(gnbs)} loops given for a scenario of {sc.loops} loops")
    central = sc.edge.placement == CENTRAL
    backhaul_us = int(round(sc.edge.backhaul_ms * 1000)) if central else 0
    return EdgePlan(sc.edge.placement, backhaul_us, gnbs)


def single_gnb_plan(sc: Scenario) -> EdgePlan:
    """The plan of a scenario with one gNB (no ``hall.inf_layout``): every loop on gNB 0."""
    return make_plan(sc, [0] * sc.loops)


def write_plan(plan: EdgePlan, run_dir: Path) -> Path:
    """Write ``plan`` into ``run_dir`` (``EDGE_FILE``); its path."""
    return write_json(run_dir / EDGE_FILE, plan.to_json())


def load_plan(sc: Scenario, run_dir: Path) -> EdgePlan:
    """The Edge plan of a run of ``sc`` whose directory is ``run_dir``: with one gNB from the
    scenario alone, with several the association the coordinator wrote there (``EDGE_FILE``);
    ValueError naming the file when it is missing or does not fit the scenario."""
    if sc.hall.inf_layout is None:
        return single_gnb_plan(sc)
    path = run_dir / EDGE_FILE
    try:
        data = json.loads(path.read_text())
        gnbs = [int(g) for g in data["gnb_of_loop"]]
    except FileNotFoundError:
        raise ValueError(f"{path} is missing: with hall.inf_layout the coordinator writes each "
                         f"work cell's gNB there before the federates start") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} does not hold each loop's gNB: {exc}") from None
    if len(gnbs) != sc.loops:
        raise ValueError(f"{path} gives the gNB of {len(gnbs)} loops, the scenario has {sc.loops}")
    return make_plan(sc, gnbs)
