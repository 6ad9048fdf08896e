"""AGVs in a run, end to end: factory_small with one AGV driving from one gNB's area into the
next, in the process runtime with model timing; its handover, packets and KPIs in the results."""

from __future__ import annotations

from pathlib import Path

import pytest
from support import MODEL_TIMING_SETS

from coordinator.run import execute_run
from fabric.tables import read_rows
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
FACTORY_SMALL = Path(__file__).parents[2] / "configs" / "scenarios" / "factory_small.yaml"


def test_an_agv_hands_over_between_gnbs_in_a_run(tmp_path: Path) -> None:
    # Geometry only (LOS, no shadowing) and A3 without hysteresis, filter or time to trigger:
    # the AGV, starting at x = 58 m towards x = 80 m at 2 m/s, leaves the gNB at x = 50 m for
    # the one at x = 70 m as it crosses x = 60 m, about 1 s in.
    sets = ["duration_s=2.5", "agvs.count=1", "agvs.speed_m_s=2",
            "agvs.waypoints_m=[[58, 28], [80, 28]]", "netsim.nr.los_mode=los",
            "netsim.nr.shadowing_enabled=false", "netsim.handover.hysteresis_db=0",
            "netsim.handover.time_to_trigger_ms=0", "netsim.handover.filter_k=0",
            *MODEL_TIMING_SETS]
    result = execute_run(load_scenario(FACTORY_SMALL, sets), tmp_path)
    assert result.status == "completed", result.reason
    handovers = read_rows(result.run_dir / "handovers.parquet")
    assert [(h["ue"], h["forwarded"] >= 0, h["lost"]) for h in handovers] == [("agv-0", True, 0)]
    h = handovers[0]
    assert h["target"] == h["source"] + 1  # the lattice's next gNB along x
    assert 0.7e6 < h["start_us"] < 1.5e6 and h["end_us"] - h["start_us"] == 50_000
    agv = [p for p in read_rows(result.run_dir / "packets.parquet") if p["ue"] == "agv-0"]
    assert agv and all(p["packet_id"] < 0 for p in agv)
    # Its packets are recorded with the gNB that served them: the source, then the target.
    served = [p["gnb"] for p in sorted(agv, key=lambda p: p["enqueue_us"])
              if p["deliver_us"] is not None]
    assert served[0] == h["source"] and served[-1] == h["target"]
    kpis = result.kpis["federates"]["netsim"]
    assert kpis["agvs.handovers_completed"] == 1 and kpis["agvs.ul.delivered_packets"] > 0
    assert "agv-0" not in result.kpis["camera_bitrate_mbps"]
