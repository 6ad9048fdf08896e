"""Which netsim partition holds each gNB and so serves each radio, for a run split into
``partitions`` (docs/architecture.md sec. 13, "Partitions"). The gNBs go to the partitions in
contiguous blocks of their layout order, balanced by the radios they serve, so that the
partitions' deliveries, merged by sender name, come in the order of the whole hall's.

The association is netsim's (the strongest RSRP, fixed for the run); the coordinator resolves it
once and writes the plan into the run directory (``PARTITION_FILE``), where every federate that
hands packets to netsim reads it: no federate imports another.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fabric.tables import write_json
from scenario.schema import Scenario

PARTITION_FILE = "partitions.json"  # in a run's directory: each gNB's partition, each radio's gNB
NETSIM = "netsim"  # the netsim federate of a run in one partition, and its streams' prefix always


def netsim_name(partition: int) -> str:
    """The netsim federate of ``partition`` in a partitioned run. Two digits: senders are ordered
    by name, and ``netsim-10`` must come after ``netsim-09`` as gNB 10 after gNB 9."""
    return f"{NETSIM}-{partition:02d}"


def netsim_names(sc: Scenario) -> list[str]:
    """The netsim federates of a run of ``sc``: ``netsim``, or one per partition."""
    return [NETSIM] if sc.partitions == 1 else [netsim_name(p) for p in range(sc.partitions)]


def split_gnbs(radios_per_gnb: list[int], count: int) -> tuple[int, ...]:
    """The partition of each gNB: ``count`` contiguous blocks of the gNBs in layout order, each
    with at least one gNB, cut where the radios served so far pass the next equal share."""
    n = len(radios_per_gnb)
    if not 1 <= count <= n:
        raise ValueError(f"{count} partitions for {n} gNBs: at least 1, at most one a gNB")
    total = max(1, sum(radios_per_gnb))
    out, part, served = [], 0, 0
    for g, radios in enumerate(radios_per_gnb):
        # Start the next partition where this one has its share, keeping a gNB for each left.
        if part < count - 1 and (served >= total * (part + 1) / count or n - g == count - 1 - part):
            part += 1
        out.append(part)
        served += radios
    return tuple(out)


@dataclass(frozen=True)
class PartitionPlan:
    """``gnb_partition[g]``: the partition holding gNB g; ``gnb_of_radio``: each radio's serving
    gNB (``camera-i``, ``robot-i``)."""

    gnb_partition: tuple[int, ...]
    gnb_of_radio: Mapping[str, int]

    @property
    def count(self) -> int:
        return max(self.gnb_partition) + 1

    def own_gnbs(self, partition: int) -> list[int]:
        """The gNBs of ``partition``, in layout order."""
        return [g for g, p in enumerate(self.gnb_partition) if p == partition]

    def netsim_of(self, radio: str) -> str:
        """The netsim federate that serves ``radio``."""
        try:
            return netsim_name(self.gnb_partition[self.gnb_of_radio[radio]])
        except KeyError:
            raise ValueError(f"no radio {radio!r} in the partition plan") from None

    def to_json(self) -> dict[str, Any]:
        return {"gnb_partition": list(self.gnb_partition), "gnb_of_radio": dict(self.gnb_of_radio)}


def make_plan(sc: Scenario, gnb_of_radio: Mapping[str, int], n_gnb: int) -> PartitionPlan:
    """The plan of ``sc``'s ``partitions`` over ``n_gnb`` gNBs, the radios served as given."""
    load = [0] * n_gnb
    for g in gnb_of_radio.values():
        load[g] += 1
    return PartitionPlan(split_gnbs(load, sc.partitions), dict(gnb_of_radio))


def write_plan(plan: PartitionPlan, run_dir: Path) -> Path:
    return write_json(run_dir / PARTITION_FILE, plan.to_json())


class Route:
    """Where a federate hands a radio's packets: ``netsim``, or the partition serving the radio."""

    def __init__(self, plan: PartitionPlan | None) -> None:
        self.plan = plan

    @property
    def netsims(self) -> list[str]:
        """Every netsim federate of the run."""
        return [NETSIM] if self.plan is None else [netsim_name(p) for p in range(self.plan.count)]

    def netsim_of(self, radio: str) -> str:
        return NETSIM if self.plan is None else self.plan.netsim_of(radio)


def load_route(sc: Scenario, run_dir: Path) -> Route:
    """The route of a run of ``sc`` whose directory is ``run_dir``: in one partition every packet
    goes to ``netsim``; else the plan the coordinator wrote there (ValueError naming the file
    when it is missing or does not fit the scenario)."""
    if sc.partitions == 1:
        return Route(None)
    return Route(load_plan(sc, run_dir))


def load_plan(sc: Scenario, run_dir: Path) -> PartitionPlan:
    path = run_dir / PARTITION_FILE
    try:
        data = json.loads(path.read_text())
        plan = PartitionPlan(tuple(int(p) for p in data["gnb_partition"]),
                             {str(r): int(g) for r, g in data["gnb_of_radio"].items()})
    except FileNotFoundError:
        raise ValueError(f"{path} is missing: with partitions > 1 the coordinator writes each "
                         f"gNB's partition there before the federates start") from None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path} does not hold a partition plan: {exc}") from None
    if plan.count != sc.partitions:
        raise ValueError(f"{path} splits the hall into {plan.count} partitions, the scenario into "
                         f"{sc.partitions}")
    return plan
