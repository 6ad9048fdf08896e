"""Salvage leaves alone a run whose coordinator is still running it (its parts are being written)."""

from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

from coordinator.run import _started, coordinator_alive, salvage_run


def test_a_run_whose_coordinator_lives_is_not_salvaged_and_one_whose_coordinator_died_is(tmp_path: Path) -> None:
    other = subprocess.Popen(["sleep", "30"])  # stands for the coordinator of another process
    try:
        who = {"host": socket.gethostname(), "pid": other.pid, "started": _started(other.pid)}
        (tmp_path / "status.json").write_text(json.dumps({"run_id": "r", "status": "running", "coordinator": who}))
        assert coordinator_alive(tmp_path) == other.pid
        assert salvage_run(tmp_path, "coordinator gone") is None and not (tmp_path / "kpis.json").exists()
    finally:
        other.kill()
        other.wait()
    assert coordinator_alive(tmp_path) is None
    kpis = salvage_run(tmp_path, "coordinator gone")
    assert kpis is not None and kpis["status"] == "failed" and (tmp_path / "kpis.json").exists()
    # A pid taken again by another process (another start time) is not the coordinator.
    (tmp_path / "status.json").write_text(json.dumps({"coordinator": {**who, "pid": 1, "started": "0"}}))
    assert coordinator_alive(tmp_path) is None
