"""The co-design policies in whole runs: the learned policy runs at the Edge of the smoke scenario;
on cells drawn from the randomised family and on a fast, dense one, neither ``heuristic`` nor
``learned`` costs a task that PDP 1 (``none``) places; past capacity both degrade gracefully."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from support import MODEL_TIMING_SETS

from training.policy.work_cells import DEFAULT_FAMILY

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
FAMILY_SEED = 14  # the cells of the check below


def run(scenario: str, sets: list[str], results: Path) -> dict[str, Any]:
    args = [a for s in sets for a in ("--set", s)]
    proc = subprocess.run([sys.executable, "-m", "interfaces.cli", "run", scenario, *args, "--json", "--quiet",
                           "--results", str(results)], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def outcomes(kpis: dict[str, Any]) -> dict[tuple[int, int], str]:
    """Each task's outcome (placed, missed, dropped, or unfinished when the run ended first)."""
    tasks = pq.read_table(Path(kpis["results_dir"]) / "tasks.parquet").to_pylist()
    return {(t["work_cell"], t["task_id"]): t["outcome"] for t in tasks}


def test_learned_policy_runs_at_the_edge_of_the_smoke_scenario(tmp_path: Path) -> None:
    k = run("configs/scenarios/smoke.yaml", ["policy.name=learned", *MODEL_TIMING_SETS], tmp_path)
    assert k["status"] == "completed" and k["policy"] == "learned"
    assert k["tasks"] >= 2 and k["tasks_placed"] == k["tasks"], k["task_outcomes"]
    # Two loops leave the radio cell idle: with headroom every loop sends at PDP 1, as `none`.
    none = run("configs/scenarios/smoke.yaml", ["policy.name=none", *MODEL_TIMING_SETS], tmp_path)
    assert k["ul_injected_mbps"] == pytest.approx(none["ul_injected_mbps"], rel=0.05)
    # Without the headroom fill the policy's own PDP applies: less traffic than every frame sent.
    bare = run("configs/scenarios/smoke.yaml", ["policy.name=learned", "policy.headroom=false",
                                               *MODEL_TIMING_SETS], tmp_path)
    assert bare["tasks_placed"] == bare["tasks"] and bare["ul_injected_mbps"] < 0.8 * none["ul_injected_mbps"]


# A fast, dense work cell of the family (belt 0.4 m/s, a part every 3 s): PDP 1 places every task
# up to 20 loops and collapses past them (25 % at 24 loops).
FAST_DENSE = ["work_cell.belt_speed_m_s=0.4", "work_cell.object_period_s=3.0", "work_cell.object_jitter_s=0.3",
              "detailed_loops=0", "duration_s=15", *MODEL_TIMING_SETS]


@pytest.mark.slow
def test_below_capacity_co_design_places_every_task_pdp_1_places(tmp_path: Path) -> None:
    sets = [*FAST_DENSE, "loops=20"]
    baseline = {t for t, o in outcomes(run("configs/scenarios/co_design.yaml", [*sets, "policy.name=none"],
                                           tmp_path)).items() if o == "placed"}
    assert len(baseline) >= 90
    for policy in ("heuristic", "learned"):
        got = outcomes(run("configs/scenarios/co_design.yaml", [*sets, f"policy.name={policy}"], tmp_path))
        lost = sorted(t for t in baseline if got.get(t) in ("missed", "dropped"))
        assert not lost, f"{policy} lost {lost} of the {len(baseline)} PDP 1 placed"


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["heuristic", "learned"])
def test_past_capacity_success_degrades_and_traffic_stays_near_what_the_cell_delivers(
        policy: str, tmp_path: Path) -> None:
    """At 48 loops, over twice PDP 1's capacity (20), where PDP 1 places no task: the congestion
    guard keeps the injected traffic near what the cell delivers and most tasks are placed."""
    k = run("configs/scenarios/co_design.yaml", [*FAST_DENSE, "loops=48", f"policy.name={policy}"], tmp_path)
    assert k["status"] == "completed"
    assert k["task_success_rate"] >= 0.6, k["task_outcomes"]
    assert k["ul_injected_mbps"] <= 1.3 * k["ul_throughput_mbps"], (k["ul_injected_mbps"], k["ul_throughput_mbps"])


@pytest.mark.slow
def test_co_design_places_every_task_pdp_1_places_on_cells_of_the_family(tmp_path: Path) -> None:
    """The invariant's domain is where PDP 1 places every task. A cell where PDP 1 itself misses
    some at 4 loops is limited by its arm, not the network: which of its tasks are missed then
    shifts with any change of timing (a QoS message, a compute draw), so it is left out, as the
    family evaluation leaves it out of the gains."""
    rng = np.random.default_rng(FAMILY_SEED)
    checked = []
    for i in range(4):
        cell, _ = DEFAULT_FAMILY.draw(rng)
        drawn = cell.model_dump(include={"belt_speed_m_s", "object_period_s", "object_jitter_s",
                                         "object_yaw_spread_deg", "object_size_spread_m",
                                         "object_mass_spread_kg"})
        sets = ["loops=4", "detailed_loops=0", "duration_s=40", f"seed={i + 1}", *MODEL_TIMING_SETS,
                *[f"cell.{name}={value}" for name, value in drawn.items()]]
        reference = outcomes(run("configs/scenarios/baseline.yaml", sets, tmp_path))
        baseline = {task for task, o in reference.items() if o == "placed"}
        if any(o in ("missed", "dropped") for o in reference.values()):
            continue  # limited by the arm
        checked.append(i)
        for policy in ("heuristic", "learned"):
            got = outcomes(run("configs/scenarios/co_design.yaml", [*sets, f"policy.name={policy}"], tmp_path))
            # Lost: missed or dropped. A task the run's end cut short (unfinished) is not lost.
            lost = sorted(t for t in baseline if got.get(t) in ("missed", "dropped"))
            assert not lost, f"cell {i} ({cell}): {policy} lost {lost} ({[got[t] for t in lost]})"
    assert len(checked) >= 2, f"only cells {checked} of 4 drawn are within PDP 1's reach; draw others"
