"""A run's processes never outlive it: a SIGKILLed coordinator takes its federates with it, and a
federate killed mid-run leaves its records up to the kill in the run directory."""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from support import MODEL_TIMING_SETS

from coordinator.conductor import Progress
from coordinator.run import execute_run, federate_specs
from coordinator.runtime_process import ProcessLauncher
from fabric.tables import TABLES, PartInfo, read_part
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
SMOKE = ROOT / "configs" / "scenarios" / "smoke.yaml"
ORPHAN_DEADLINE_S = 10.0  # the functional bound: a federate leaves this soon after its coordinator


def federate_pids(run_id: str) -> list[int]:
    """Federate processes of ``run_id`` (their command line names the run)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z" and b"services.main" in cmd and run_id.encode() in cmd:
            pids.append(int(entry.name))
    return pids


def sim_time_s(progress_file: Path) -> float:
    try:
        return float(json.loads(progress_file.read_text()).get("sim_time_s") or 0.0)
    except (OSError, ValueError, AttributeError):
        return 0.0


def test_sigkilled_coordinator_leaves_no_federate_behind(tmp_path: Path) -> None:
    run_id = f"orphans-{secrets.token_hex(4)}"  # unique: other test sessions may run alongside
    progress = tmp_path / "progress.json"
    log = tmp_path / "coordinator.log"
    with log.open("wb") as err:
        coordinator = subprocess.Popen(
            [sys.executable, "-m", "interfaces.cli", "run", str(SMOKE), "--quiet", "--results", str(tmp_path),
             "--run-id", run_id, "--progress-file", str(progress), "--set", "duration_s=120",
             *[a for o in MODEL_TIMING_SETS for a in ("--set", o)]],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
        )
    expected = len(federate_specs(load_scenario(SMOKE)))  # processes: a group serves several
    try:
        deadline = time.monotonic() + 300
        while not (len(federate_pids(run_id)) == expected and sim_time_s(progress) > 1.0):
            assert coordinator.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "the run did not get going"
            time.sleep(0.2)
        federates = federate_pids(run_id)
        os.kill(coordinator.pid, signal.SIGKILL)
        coordinator.wait()
        killed_at = time.monotonic()
        while federate_pids(run_id) and time.monotonic() - killed_at < ORPHAN_DEADLINE_S:
            time.sleep(0.1)
        assert federate_pids(run_id) == [], f"federates alive {ORPHAN_DEADLINE_S:.0f} s after the coordinator died"
    finally:
        if coordinator.poll() is None:
            coordinator.kill()
            coordinator.wait()
        for pid in federate_pids(run_id):  # only if the assertion above failed
            os.kill(pid, signal.SIGKILL)
    assert len(federates) == expected
    # They left the way they leave a run: their records written and closed.
    parts = sorted((tmp_path / run_id / "tables").glob("*.arrows"))
    assert {p.name.split("-", 1)[0] for p in parts} == set(TABLES)
    for path in parts:
        info = PartInfo()
        rows = sum(b.num_rows for b in read_part(path, info))
        assert info.complete and info.error is None, (path.name, info)
        assert rows == info.rows
    # `cosim5g salvage` closes the run: tables merged, kpis.json says how far it got.
    run_dir = tmp_path / run_id
    assert not (run_dir / "kpis.json").exists()
    out = subprocess.run([sys.executable, "-m", "interfaces.cli", "salvage", str(run_dir)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    kpis = json.loads((run_dir / "kpis.json").read_text())
    assert kpis["status"] == "failed" and kpis["reason"] == "coordinator stopped during the run"
    assert kpis["recorded"]["sim_time_reached_s"] > 0
    assert kpis["recorded"]["rows"]["packets"] > 0
    assert pq.read_table(run_dir / "packets.parquet").num_rows == kpis["recorded"]["rows"]["packets"]
    again = subprocess.run([sys.executable, "-m", "interfaces.cli", "salvage", str(run_dir)], cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "left as it is" in again.stdout


def test_a_federate_killed_mid_run_leaves_its_records_up_to_the_kill(tmp_path: Path) -> None:
    # netsim in a process of its own, so that the kill strikes it alone.
    sc = load_scenario(SMOKE, ["duration_s=30", "cohost=none", *MODEL_TIMING_SETS])
    launcher = ProcessLauncher()
    kill_us = 5_000_000
    struck: dict[str, int] = {}

    def on_progress(p: Progress) -> None:
        if p.t_us > kill_us and not struck:
            os.kill(launcher.procs["netsim"].pid, signal.SIGKILL)
            struck["t_us"] = p.t_us

    result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
    assert result.status == "failed" and result.kpis["failed_federate"] == "netsim"
    run_dir = result.run_dir
    # Every run table is there, with its columns, also after a failure.
    for name, schema in TABLES.items():
        table = pq.read_table(run_dir / f"{name}.parquet")
        assert table.schema.names == schema.names, name
    packets = pq.read_table(run_dir / "packets.parquet").to_pydict()
    assert packets["packet_id"], "netsim's packets flushed before the kill are lost"
    # Flushed at least every 2 simulated seconds: rows up to within a flush period of the kill.
    assert max(packets["enqueue_us"]) >= kill_us - 2_500_000
    assert max(packets["enqueue_us"]) <= struck["t_us"] + sc.window_us
    assert len(set(packets["packet_id"])) == len(packets["packet_id"])
    kpis = json.loads((run_dir / "kpis.json").read_text())
    recorded = kpis["recorded"]
    assert recorded["rows"]["packets"] == len(packets["packet_id"])
    assert all(recorded["rows"][t] > 0 for t in ("jobs", "frames", "packets"))
    netsim = next(p for p in recorded["parts"] if p["table"] == "packets" and p["federate"] == "netsim")
    assert not netsim["complete"] and netsim["upto_s"] >= (kill_us - 2_500_000) / 1e6
    # Every federate's records reach as far as the dead one's; the run itself got to the kill.
    assert recorded["sim_time_reached_s"] == netsim["upto_s"]
    assert kpis["sim_time_s"] >= kill_us / 1e6
    # The federates that were still alive closed their records when the run was stopped.
    assert all(p["complete"] for p in recorded["parts"] if p["federate"] != "netsim")
