"""Measures what the abstract loops need from the detailed ones: the compressed frame sizes of the
real camera pipeline and the error of the real pose estimator, on frames rendered by our scene.

``python tools/measure_frames.py [--seconds S] [--out PATH] [--estimator NAME] [--scenario YAML]``
writes ``domain/data/frame_model.json`` or ``--out``: docs/perception.md, "Compression".
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from domain.codec import decode_frame
from domain.estimator import make_estimator
from domain.frame_model import PATH as FRAME_MODEL_PATH
from domain.frame_model import camera_settings
from scenario.schema import Scenario, load_scenario, parse_scenario
from training.perception.dataset import render_frames
from training.perception.evaluate import evaluate

DEFAULT_OUT = FRAME_MODEL_PATH


def measure(sc: Scenario, estimator: str) -> dict[str, Any]:
    times = list(range(0, sc.duration_us, sc.frame_period_us))
    frames, labels = render_frames(sc, times)
    sizes = [len(f) for f in frames]
    depth_bytes = [int.from_bytes(f[13:17], "big") for f in frames]  # header: depth part length
    ran: list[str] = []

    def make(k: Any, size: float) -> Any:
        est, fallback = make_estimator(estimator, k, size)
        ran.append(est.name if not fallback else f"{est.name} (fallback: {fallback})")
        return est

    m = evaluate(make, frames, labels)
    rgb0, depth0 = decode_frame(frames[-1])
    cam = sc.camera
    return {
        "settings": {**camera_settings(cam), "fps": cam.fps, "object_period_s": sc.work_cell.object_period_s},
        "frames": len(sizes),
        "frame_bytes": sizes,
        "mean_frame_bytes": float(np.mean(sizes)),
        "mean_depth_bytes": float(np.mean(depth_bytes)),
        "mean_rgb_bytes": float(np.mean(sizes) - np.mean(depth_bytes)),
        "bitrate_mbps_at_fps": float(np.mean(sizes)) * 8 * cam.fps / 1e6,
        "depth_invalid_fraction": float(np.mean(depth0 == 0)),
        "estimator_error_sd_m": m["error_sd_per_axis_m"],
        "estimator_error_median_m": m["error_median_mm"] / 1000,
        "estimator_error_p95_m": m["error_p95_mm"] / 1000,
        "estimator_miss_rate": 1.0 - m["detection_rate"],
        "estimator_false_positives_per_frame": m["false_positives_per_frame"],
        "estimator_parts_in_view": m["parts_in_view"],
        "estimator": m["estimator"],
        "estimator_note": ran[0] if ran else "",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--estimator", choices=["learned", "classical"], default=None,
                    help="default: the scenario default (edge.estimator)")
    ap.add_argument("--scenario", type=Path, default=None,
                    help="measure with this scenario's camera (and estimator) instead of the defaults")
    args = ap.parse_args(argv)
    default = parse_scenario({})
    base = load_scenario(args.scenario) if args.scenario else default
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sc = parse_scenario({"loops": 1, "detailed_loops": 1, "duration_s": args.seconds,
                         "work_cell": {"object_period_s": default.work_cell.object_period_s / 2},
                         "camera": base.camera.model_dump(), "edge": {"estimator": base.edge.estimator}})
    result = measure(sc, args.estimator or sc.edge.estimator)
    tmp = args.out.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    tmp.replace(args.out)
    print(f"{result['frames']} frames, mean {result['mean_frame_bytes']:.0f} B (rgb {result['mean_rgb_bytes']:.0f}, "
          f"depth {result['mean_depth_bytes']:.0f}), {result['bitrate_mbps_at_fps']:.2f} Mbit/s; "
          f"{result['estimator']} error median {result['estimator_error_median_m'] * 1000:.1f} mm, "
          f"sd/axis {result['estimator_error_sd_m'] * 1000:.1f} mm, miss rate {result['estimator_miss_rate']:.4f}")
    return 0
