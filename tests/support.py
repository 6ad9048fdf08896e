"""What several test modules share: scenario settings and a process scan."""

from __future__ import annotations

import os
from pathlib import Path

# Every compute node timed by its calibrated model: the same event trace on any host.
MODEL_TIMING = {"nodes.camera.timing": "model", "nodes.edge.timing": "model", "nodes.robot.timing": "model"}
MODEL_TIMING_SETS = [f"{field}={value}" for field, value in MODEL_TIMING.items()]


def processes_with(text: str | Path) -> list[int]:
    """Processes (other than this one) whose command line contains ``text``."""
    needle = str(text).encode()
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if needle in (entry / "cmdline").read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids
