"""The platform's real compute jobs, runnable alone for calibration: frame compression (camera),
pose estimation (Edge), a control step (robot) and a pure-Python CPU-bound reference.

``python -m services.workloads --reps N`` prints one JSON object: per workload, the CPU time and
wall time of each repetition (ms). ``coordinator.calibrate`` runs it on the host and inside
CPU-limited containers.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")


def _spin() -> int:
    """About 70 ms of pure-Python arithmetic on a desktop core: the CPU-bound reference job."""
    acc = 0
    for i in range(1_500_000):
        acc = (acc + i * i) % 1_000_003
    return acc


def build_jobs() -> dict[str, Callable[[], Any]]:
    """Each workload as a closure over inputs prepared once (rendering is not timed)."""
    import cv2

    from services.camera.codec import decode_frame, encode_frame
    from services.common.scenario import parse_scenario
    from services.common.seeding import rng
    from services.edge.estimator import ClassicalEstimator
    from services.physics.cell_geometry import CameraIntrinsics
    from services.physics.federate import sensor_depth_mm
    from services.physics.scene import SERVO_LAG_S
    from services.physics.world import World
    from services.robot.controller import PickController

    cv2.setNumThreads(1)
    sc = parse_scenario({"loops": 1})
    world = World(sc)
    world.spawn(0)
    world.advance_to(1_500_000)
    rgb, depth = world.render(0, sc.camera.width_px, sc.camera.height_px)
    assert depth is not None
    depth_mm = sensor_depth_mm(depth, sc.camera.depth_noise_mm, rng(sc.seed, "workloads"))
    frame = encode_frame(rgb, depth_mm, sc.camera.jpeg_quality)
    est = ClassicalEstimator(CameraIntrinsics(sc.camera.width_px, sc.camera.height_px, sc.camera.fovy_deg),
                             sc.cell.object_size_m)
    ctl = PickController(sc.robot, sc.cell.object_size_m, SERVO_LAG_S)
    ctl.on_estimate([{"id": o["task_id"], "t_us": 1_500_000, "p": o["p"], "v": o["v"]}
                     for o in world.objects(0)])
    ctl.on_state(*world.joint_state(0).values())
    tick = [1_500_000]

    def control() -> Any:
        tick[0] += sc.robot.control_period_us
        return ctl.step(tick[0])

    return {
        "spin": _spin,
        "compress": lambda: encode_frame(rgb, depth_mm, sc.camera.jpeg_quality),
        "pose": lambda: est.detect(*decode_frame(frame)),
        "control": control,
    }


def measure(reps: int, only: list[str] | None = None) -> dict[str, dict[str, list[float]]]:
    jobs = build_jobs()
    out: dict[str, dict[str, list[float]]] = {}
    for name, job in jobs.items():
        if only and name not in only:
            continue
        job()  # warm caches and lazy imports
        cpu, wall = [], []
        for _ in range(reps):
            c0, w0 = time.process_time_ns(), time.perf_counter_ns()
            job()
            cpu.append((time.process_time_ns() - c0) / 1e6)
            wall.append((time.perf_counter_ns() - w0) / 1e6)
        out[name] = {"cpu_ms": cpu, "wall_ms": wall}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--only", nargs="*", help="workload names (default: all)")
    args = ap.parse_args(argv)
    print(json.dumps(measure(args.reps, args.only)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
