"""Each radio's gNB, resolved once before a run starts, with netsim's own numbers: the large
scale of every (UE, gNB) link drawn from netsim's streams (``InfLinks``) and the strongest RSRP
(``serving_gnb``), as ``MultiCell`` associates the UEs. Written into the run directory as the
Edge plan (``domain.edges.EDGE_FILE``), where the Edge sides read it, and for a partitioned run
as the partition plan (``domain.partitions.PARTITION_FILE``), where every federate that hands
packets to netsim reads it: no federate imports another.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from domain import partitions
from domain.edges import EdgePlan, make_plan, single_gnb_plan, write_plan
from netsim.nr.interference import serving_gnb
from netsim.nr.large_scale import hall_links
from netsim.nr.layout import layout_from_hall
from scenario.schema import Scenario


def serving_gnbs(sc: Scenario) -> dict[str, int]:
    """UE id (``camera-i``, ``robot-i``) -> the layout index of the gNB serving it in a run of
    ``sc`` with ``hall.inf_layout``, as the netsim federate's ``MultiCell`` chooses it: the same
    UE positions, seed and streams (``netsim/nr/inf/...``, whatever the partitions)."""
    layout = layout_from_hall(sc.hall)
    if layout is None:
        raise ValueError("hall.inf_layout is not set: the one gNB serves every UE")
    positions = sc.ue_positions_m()
    links = hall_links(layout, np.array(list(positions.values()), dtype=float), sc.netsim.nr, sc.seed,
                       partitions.NETSIM + "/nr")
    serving = serving_gnb(links.coupling_loss_db)
    return {ue: int(g) for ue, g in zip(positions, serving.tolist(), strict=True)}


def resolve_plan(sc: Scenario) -> EdgePlan:
    """The Edge plan of ``sc``: each loop on the gNB serving its camera."""
    if sc.hall.inf_layout is None:
        return single_gnb_plan(sc)
    serving = serving_gnbs(sc)
    return make_plan(sc, [serving[f"camera-{i}"] for i in range(sc.loops)])


def provide_edge_plan(sc: Scenario, run_dir: Path) -> EdgePlan:
    """Resolve ``sc``'s Edge plan and write it into ``run_dir`` for the federates; with
    ``partitions`` > 1 the partition plan too."""
    plan = resolve_plan(sc)
    write_plan(plan, run_dir)
    if sc.partitions > 1:
        layout = layout_from_hall(sc.hall)
        assert layout is not None  # the scenario refuses partitions without an InF layout
        partitions.write_plan(partitions.make_plan(sc, serving_gnbs(sc), layout.n_gnb), run_dir)
    return plan
