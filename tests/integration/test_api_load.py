"""The REST API under a short burst of mixed requests from 8 clients (``make load`` runs 1 000):
no 5xx, the queue limit reached and never passed, every accepted job in the store with an end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]


def test_a_burst_of_mixed_requests_loses_nothing_and_keeps_the_queue_limit() -> None:
    proc = subprocess.run([sys.executable, "-m", "benchmarks.api_load", "--requests", "160", "--clients", "8",
                           "--max-queued", "3", "--seed", "2", "--json"], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    assert rec["errors_5xx"] == 0 and rec["failed_connections"] == 0, rec["answers"]
    assert rec["most_active_at_once"] == 3, rec  # reached, never passed
    assert rec["lost"] == [] and rec["unfinished"] == [], rec
    answers = rec["answers"]
    assert answers.get("no_token 401") and answers.get("too_large 413") and answers.get("invalid 422"), answers
    assert answers.get("start_run 429", 0) + answers.get("start_sweep 429", 0) > 0, answers
