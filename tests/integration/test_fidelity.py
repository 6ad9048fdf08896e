"""What is simulated must not move when the platform gets faster or is restructured.

``tests/reference/fidelity.json`` holds the KPIs of the smoke scenario and of a 16-loop
``co_design`` scenario (one detailed loop) recorded with ``model`` compute timing before the speed
work (``co_design`` again when its policy changed: ``recorded_from`` says which commit); rerunning
them must place the same tasks (+-1) with packet latency p50/p99 and uplink throughput within 2%.
The abstract loops must look like the detailed one on the network, with a frame model measured
for the scenario's own camera.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from domain.frame_model import PATH as FRAME_MODEL
from domain.frame_model import RUN_FILE

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


def test_abstract_loops_look_like_the_detailed_one_on_the_network(tmp_path: Path) -> None:
    """In one run, the abstract loops' uplink (bytes and packets per frame, per-loop packet
    latency p50/p99) agrees with the detailed loop's within 10%."""
    proc = subprocess.run([sys.executable, "-m", "interfaces.cli", "run", "configs/scenarios/baseline.yaml",
                           "--set", "loops=6", "--set", "detailed_loops=1", "--set", "duration_s=20",
                           *[a for o in REFERENCE["overrides_all"] for a in ("--set", o)],
                           "--json", "--quiet", "--results", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    k = json.loads(proc.stdout.strip().splitlines()[-1])
    rows = pq.read_table(Path(k["results_dir"]) / "loops.parquet").to_pylist()

    def uplink(r: dict) -> dict[str, float]:
        kept = r["frames_kept"]
        return {"frame_bytes": r["ul_injected_mbps"] * k["sim_time_s"] * 1e6 / 8 / kept,
                "packets_per_frame": r["ul_packets"] / kept,
                "latency_p50_ms": r["ul_latency_p50_ms"], "latency_p99_ms": r["ul_latency_p99_ms"]}

    detailed = uplink(rows[0])
    abstract = [uplink(r) for r in rows[1:]]
    for key, value in detailed.items():
        mean = sum(a[key] for a in abstract) / len(abstract)
        assert mean == pytest.approx(value, rel=0.10), (key, value, [a[key] for a in abstract])


def test_a_camera_without_a_model_gets_one_measured_on_first_use(tmp_path: Path) -> None:
    """A run whose camera differs from the shipped model's measures a model for its own settings
    once (cached), and its abstract loops use that one."""
    env = {**os.environ, "COSIM5G_CACHE_DIR": str(tmp_path / "cache")}
    runs = []
    for i in range(2):
        proc = subprocess.run([sys.executable, "-m", "interfaces.cli", "run", "configs/scenarios/smoke.yaml",
                               "--set", "loops=3", "--set", "detailed_loops=1", "--set", "duration_s=2",
                               "--set", "camera.jpeg_quality=50", "--json", "--quiet", "--results",
                               str(tmp_path / f"run{i}")], cwd=ROOT, capture_output=True, text=True, timeout=1800,
                              env=env)
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    cached = list((tmp_path / "cache" / "frame-models").glob("*.json"))
    assert len(cached) == 1  # measured once, reused by the second run
    used = json.loads((Path(runs[1]["results_dir"]) / RUN_FILE).read_text())
    shipped = json.loads(FRAME_MODEL.read_text())
    assert used["settings"]["jpeg_quality"] == 50 and used == json.loads(cached[0].read_text())
    assert used["mean_frame_bytes"] < shipped["mean_frame_bytes"]  # a lower JPEG quality: smaller frames
