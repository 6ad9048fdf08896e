"""Short soak and chaos (the full ones are `make soak` and `make chaos`): consecutive runs in one
coordinator leave nothing behind and do not grow it; a run with a fault ends in one state naming
the node, and leaves nothing behind."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]


def reliability(*args: str) -> tuple[int, dict]:
    proc = subprocess.run([sys.executable, "-m", "benchmarks.reliability", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=900)
    name = args[0]
    record = json.loads((ROOT / "results" / "bench" / f"{name}.json").read_text())
    print(proc.stdout)
    return proc.returncode, record


def test_short_soak_leaves_nothing_and_does_not_grow_the_coordinator() -> None:
    code, rec = reliability("soak", "--runs", "4", "--duration-s", "1.5")
    assert rec["statuses"] == {"process:completed": 4}, rec["failures"]
    assert rec["leftovers"] == []
    assert rec["fds_after_last"] <= rec["fds_after_warmup"]
    assert rec["rss_growth"] < 0.10
    assert code == 0


def test_short_chaos_every_run_ends_naming_the_node_and_leaves_nothing() -> None:
    code, rec = reliability("chaos", "--runs", "3", "--faults", "sigkill,sigstop,coordinator", "--seed", "7")
    runs = rec["runs"]
    assert [r["fault"] for r in runs] == ["sigkill", "sigstop", "coordinator"]
    for r in runs:
        assert r["leftovers"] == [], r
        assert r["ok"], r
    assert code == 0
