"""Measures what the abstract loops need from the detailed ones: the compressed frame sizes of the
real camera pipeline and the error of the real pose estimator, on frames rendered by our scene.

``python -m services.camera.measure [--seconds S] [--out PATH]`` renders one cell with parts on the
moving belt, compresses every frame as the camera node does, runs the Edge estimator on the
decoded frame and compares with ground truth. Writes ``services/camera/data/frame_model.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.camera.codec import decode_frame, encode_frame
from services.common.scenario import Scenario, parse_scenario
from services.common.seeding import rng
from services.edge.estimator import ClassicalEstimator
from services.physics.cell_geometry import CameraIntrinsics
from services.physics.federate import sensor_depth_mm
from services.physics.world import World

DEFAULT_OUT = Path(__file__).parent / "data" / "frame_model.json"


def measure(sc: Scenario, seconds: float) -> dict:
    world = World(sc)
    noise = rng(sc.seed, "measure/depth-noise")
    k = CameraIntrinsics(sc.camera.width_px, sc.camera.height_px, sc.camera.fovy_deg)
    est = ClassicalEstimator(k, sc.cell.object_size_m)
    period_us = int(sc.cell.object_period_s * 1e6 / 2)  # denser than a run: more parts per frame
    sizes, errors, misses, seen = [], [], 0, 0
    t, next_spawn = 0, 0
    while t < seconds * 1e6:
        if t >= next_spawn:
            world.spawn(0)
            next_spawn += period_us
        world.advance_to(t)
        rgb, depth = world.render(0, sc.camera.width_px, sc.camera.height_px)
        assert depth is not None
        data = encode_frame(rgb, sensor_depth_mm(depth, sc.camera.depth_noise_mm, noise), sc.camera.jpeg_quality)
        sizes.append(len(data))
        rgb2, depth2 = decode_frame(data)
        dets = [d.p for d in est.detect(rgb2, depth2)]
        for obj in world.objects(0):
            p = np.asarray(obj["p"])
            if abs(p[0]) > 0.55:
                continue  # entering or leaving the belt: partly out of the scene
            seen += 1
            if not dets:
                misses += 1
                continue
            errors.append(min(np.linalg.norm(d - p) for d in dets))
        t += sc.frame_period_us
    err = np.asarray(errors)
    return {
        "settings": {"width_px": sc.camera.width_px, "height_px": sc.camera.height_px,
                     "jpeg_quality": sc.camera.jpeg_quality, "fps": sc.camera.fps,
                     "depth_noise_mm": sc.camera.depth_noise_mm},
        "frames": len(sizes),
        "frame_bytes": sizes,
        "mean_frame_bytes": float(np.mean(sizes)),
        "bitrate_mbps_at_fps": float(np.mean(sizes)) * 8 * sc.camera.fps / 1e6,
        # Per-axis sd of a 3-D error e with E|e|^2 = 3 sd^2.
        "estimator_error_sd_m": float(np.sqrt(np.mean(err**2) / 3)) if err.size else 0.005,
        "estimator_error_median_m": float(np.median(err)) if err.size else None,
        "estimator_miss_rate": misses / seen if seen else 0.0,
        "estimator": est.name,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    sc = parse_scenario({"loops": 1, "detailed_loops": 1})
    result = measure(sc, args.seconds)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{result['frames']} frames, mean {result['mean_frame_bytes']:.0f} B "
          f"({result['bitrate_mbps_at_fps']:.2f} Mbit/s), estimator error median "
          f"{(result['estimator_error_median_m'] or 0) * 1000:.1f} mm, miss rate {result['estimator_miss_rate']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
