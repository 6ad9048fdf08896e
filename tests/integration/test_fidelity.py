"""What is simulated must not move when the platform gets faster or is restructured.

``tests/reference/fidelity.json`` holds the KPIs of the smoke scenario and of a 16-loop
``co_design`` scenario (one detailed loop) recorded with ``model`` compute timing before the speed
work (``co_design`` again when its policy changed: ``recorded_from`` says which commit); rerunning
them must place the same tasks (+-1) with packet latency p50/p99 and uplink throughput within 2%.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]
ROOT = Path(__file__).parents[2]
REFERENCE = json.loads((ROOT / "tests" / "reference" / "fidelity.json").read_text())


@pytest.mark.parametrize("name", sorted(REFERENCE["runs"]))
def test_kpis_match_the_reference(name: str, tmp_path: Path) -> None:
    ref = REFERENCE["runs"][name]
    sets = [a for o in [*REFERENCE["overrides_all"], *ref["overrides"]] for a in ("--set", o)]
    proc = subprocess.run([sys.executable, "-m", "interfaces.cli", "run", ref["scenario"], *sets, "--json",
                           "--quiet", "--results", str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    k = json.loads(proc.stdout.strip().splitlines()[-1])
    assert abs(k["tasks_placed"] - ref["tasks_placed"]) <= 1, (k["tasks_placed"], ref["tasks_placed"])
    for group in ("ip_latency_ms", "ul_ip_latency_ms"):
        for q in ("p50", "p99"):
            assert k[group][q] == pytest.approx(ref[group][q], rel=0.02), (group, q)
    assert k["ul_throughput_mbps"] == pytest.approx(ref["ul_throughput_mbps"], rel=0.02)
