"""Nothing written is lost: salvage leaves alone a run whose coordinator is still running it (its
parts are being written), and a run whose merged tables hold fewer rows than its federates wrote
fails."""

from __future__ import annotations

import json
import socket
import subprocess
from pathlib import Path

from coordinator.run import _started, coordinator_alive, records_short, salvage_run
from fabric.messages import Stopped


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


def test_merged_rows_short_of_what_a_federate_wrote_are_named() -> None:
    recorded = {"parts": [{"federate": "netsim", "table": "packets", "rows": 90},
                          {"federate": "physics", "table": "tasks", "rows": 2}]}
    stopped = {"netsim": Stopped(federate="netsim", trace_hash="", events=0, summary={"records": {"packets": 100, "handovers": 0}}),
               "physics": Stopped(federate="physics", trace_hash="", events=0, summary={"records": {"tasks": 2}})}
    assert records_short(recorded, stopped) == "netsim/packets 90 of 100"
    recorded["parts"][0]["rows"] = 100
    assert records_short(recorded, stopped) == ""
