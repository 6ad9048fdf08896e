"""The frame model a run's abstract loops use (``domain.frame_model``): the one measured for the
scenario's camera settings, found in the cache or the shipped data, or else measured now -- on
first use, by ``training.measure_frames`` with the run's scenario (about a minute), under
a lock so that parallel runs of a sweep measure it once -- and copied into the run directory,
where the loops federate reads it in either runtime.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

from domain.frame_model import RUN_FILE, FrameModelMissing, cache_path, camera_settings, find_model
from scenario.schema import Scenario

log = logging.getLogger(__name__)

MEASURE_TIMEOUT_S = 1800.0
# The measurement runs in a process of its own, from the installed package (no script needed);
# its arguments follow in sys.argv[1:].
MEASURE = "import sys; from training.measure_frames import main; sys.exit(main(sys.argv[1:]))"


class FrameModelError(RuntimeError):
    """The frame model for a run's camera could not be measured."""


def provide_frame_model(scenario: Scenario, scenario_path: Path, run_dir: Path) -> Path | None:
    """Put the frame model for ``scenario``'s camera into ``run_dir`` (measuring it if none
    exists yet); its path, or None when the run has no abstract loop."""
    if scenario.loops <= scenario.detailed_loops:
        return None
    settings = camera_settings(scenario.camera)
    try:
        source = find_model(settings)
    except FrameModelMissing:
        source = _measure(settings, scenario_path)
    target = run_dir / RUN_FILE
    tmp = target.with_suffix(".tmp")
    shutil.copyfile(source, tmp)
    tmp.replace(target)
    return target


def _measure(settings: dict[str, object], scenario_path: Path) -> Path:
    out = cache_path(settings)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another run of the sweep may be measuring it
        try:
            return find_model(settings)
        except FrameModelMissing:
            pass
        log.info("measuring the abstract loops' frame model for camera %s (first use)", settings)
        env = dict(os.environ)
        env.setdefault("MUJOCO_GL", "egl")
        try:
            proc = subprocess.run([sys.executable, "-c", MEASURE, "--scenario", str(scenario_path),
                                   "--out", str(out)], capture_output=True, text=True, env=env,
                                  timeout=MEASURE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise FrameModelError(f"measuring the frame model for camera {settings} took over "
                                  f"{MEASURE_TIMEOUT_S:.0f} s") from None
        if proc.returncode != 0:
            raise FrameModelError(f"measuring the frame model for camera {settings} failed "
                                  f"(exit {proc.returncode}): {proc.stderr.strip()[-1500:]}")
        return find_model(settings)
