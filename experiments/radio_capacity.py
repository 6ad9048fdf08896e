"""The cell's uplink capacity, measured: the line Fig. 5's traffic is held against.

The NR cell of the sweep's scenario is saturated by the standalone cell (36 cameras offering
about twice what a cell carries) and its delivered uplink IP throughput is the capacity; the
``simple`` cell's capacity is its configured rate.
"""

from __future__ import annotations

from typing import Any

from scenario.schema import Scenario

SATURATING_UES = 36
SATURATING_RATE_MBPS = 10.0  # per UE: 360 Mbit/s offered, about twice the default cell
DURATION_S = 2.0


def measure_ul_capacity(scenario: Scenario) -> dict[str, Any]:
    if scenario.netsim.model == "simple":
        return {"ul_capacity_mbps": scenario.netsim.ul_rate_mbps, "method": "netsim.ul_rate_mbps (simple cell)"}
    from netsim.standalone import run_uplink_cameras

    out = run_uplink_cameras(SATURATING_UES, SATURATING_RATE_MBPS, DURATION_S, seed=scenario.seed,
                             config=scenario.netsim.nr)
    return {"ul_capacity_mbps": out["ul_throughput_mbps"],
            "method": f"standalone NR cell of the scenario saturated by {SATURATING_UES} UEs x "
                      f"{SATURATING_RATE_MBPS} Mbit/s for {DURATION_S} s (seed {scenario.seed})",
            "offered_mbps": out["offered_mbps"], "prb_utilisation_ul": out["prb_utilisation_ul"]}
