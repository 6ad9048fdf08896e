"""A run split into netsim partitions by gNB, end to end: factory_small (4 gNBs, 40 abstract
loops) in the process runtime with model timing, as one netsim and as 2 and 4 partitions, each
a process of its own exchanging every slot's transmissions with the others: the same packets,
transmissions and tasks to the bit (``results_hash``); also with AGVs handing over between
partitions."""

from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
from support import MODEL_TIMING_SETS

from coordinator.run import execute_run
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
FACTORY_SMALL = Path(__file__).parents[2] / "configs" / "scenarios" / "factory_small.yaml"


def test_partitions_decide_the_run_as_one_netsim(tmp_path: Path) -> None:
    results = {}
    for n in (1, 2, 4):
        sc = load_scenario(FACTORY_SMALL, ["duration_s=1.5", f"partitions={n}", *MODEL_TIMING_SETS])
        result = execute_run(sc, tmp_path / f"p{n}")
        assert result.status == "completed", result.reason
        results[n] = result.kpis
    one, two, four = results[1], results[2], results[4]
    rows = one["recorded"]["rows"]
    assert rows["packets"] > 10_000 and rows["transmissions"] > 1_000
    assert two["recorded"]["rows"] == rows == four["recorded"]["rows"]
    assert one["results_hash"] == two["results_hash"] == four["results_hash"]
    # The processes differ: one netsim in the core group, or a process per partition.
    assert "netsim" in one["federates"] and "netsim-00" not in one["federates"]
    assert {f"netsim-{p:02d}" for p in range(4)} <= set(four["federates"])
    assert sum(four["federates"][f"netsim-{p:02d}"]["packets"] for p in range(4)) == rows["packets"]


def test_agvs_hand_over_between_partitions_as_in_one_netsim(tmp_path: Path) -> None:
    # Two AGVs driving across x = 60 m, between gNB 1 (x = 50 m) and gNB 2 (x = 70 m), which two
    # partitions hold apart; a short time to trigger, so that they hand over within the run.
    sets = ["duration_s=3", *MODEL_TIMING_SETS, "agvs.count=2", "agvs.speed_m_s=2",
            "agvs.waypoints_m=[[56, 30], [64, 30]]", "netsim.handover.hysteresis_db=1",
            "netsim.handover.time_to_trigger_ms=40"]
    results = {}
    for n in (1, 2):
        result = execute_run(load_scenario(FACTORY_SMALL, [*sets, f"partitions={n}"]), tmp_path / f"p{n}")
        assert result.status == "completed", result.reason
        results[n] = result
    handovers = pq.read_table(results[1].run_dir / "handovers.parquet").to_pylist()
    across = [h for h in handovers if {h["source"], h["target"]} == {1, 2}]
    assert across and across[0]["forwarded"] > 0, handovers  # with the packets held for it
    one, two = results[1].kpis, results[2].kpis
    assert one["recorded"]["rows"] == two["recorded"]["rows"]
    assert one["results_hash"] == two["results_hash"]
    # Each partition counts what it decided: the handovers into its gNBs, its AGV packets.
    for key in ("agvs.handovers_completed", "agvs.ul.delivered_packets", "agvs.dl.lost_packets"):
        assert sum(two["federates"][f"netsim-{p:02d}"][key] for p in range(2)) == one["federates"]["netsim"][key]
    assert one["federates"]["netsim"]["agvs.handovers_completed"] == len(handovers)

