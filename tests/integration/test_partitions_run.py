"""A run split into netsim partitions by gNB, end to end: factory_small (4 gNBs, 40 abstract
loops) in the process runtime with model timing, as one netsim and as 2 and 4 partitions, each
a process of its own exchanging every slot's transmissions with the others: the same packets,
transmissions and tasks to the bit (``results_hash``)."""

from __future__ import annotations

from pathlib import Path

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
