"""Accuracy and cost of a pose estimator on a rendered, labelled split (no torch needed).

A part in view (top face at least 80% visible) is detected by an estimate within ``GATE_M`` of
its centre; estimates near no part are false positives; a part partly hidden (under the arm or
the hovering cup, not in it) is matched in the belt plane and its height error kept apart; cost
is ``detect``'s CPU time per frame on one thread, decoding apart (docs/perception.md, "Accuracy
and cost").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from domain.codec import decode_frame
from domain.work_cell import CameraIntrinsics

GATE_M = 0.04  # an estimate this close to a part's centre is that part's detection
IN_VIEW_VISIBLE = 0.8  # share of the top face's pixel area that must be visible
HIDDEN_VISIBLE = 0.3  # a part less visible than in view but at least this is partly hidden


def _on_screen(part: dict[str, Any], width: int, height: int) -> bool:
    return 0 <= part["u"] < width and 0 <= part["v"] < height


def in_view(part: dict[str, Any], width: int, height: int) -> bool:
    return part["visible"] >= IN_VIEW_VISIBLE and _on_screen(part, width, height)


def partly_hidden(part: dict[str, Any], width: int, height: int) -> bool:
    return (not part["gripped"] and HIDDEN_VISIBLE <= part["visible"] < IN_VIEW_VISIBLE
            and _on_screen(part, width, height))


def evaluate(make: Callable[[CameraIntrinsics, float], Any], frames: list[bytes],
             labels: list[dict[str, Any]]) -> dict[str, Any]:
    """Run the estimator built by ``make(intrinsics, nominal_size_m)`` on every frame."""
    cv2.setNumThreads(1)
    cache: dict[tuple[int, int, float, float], Any] = {}
    errors, err_xy, err_z, seen, found, fps = [], [], [], 0, 0, 0
    hidden, hidden_z = 0, []
    det_s, dec_s = [], []
    name = "?"
    for data, lab in zip(frames, labels, strict=True):
        key = (lab["width"], lab["height"], lab["fovy_deg"], lab["nominal_size_m"])
        if key not in cache:
            cache[key] = make(CameraIntrinsics(key[0], key[1], key[2]), key[3])
        est = cache[key]
        name = est.name
        t0 = time.process_time()
        rgb, depth = decode_frame(data)
        t1 = time.process_time()
        dets = est.detect(rgb, depth)
        det_s.append(time.process_time() - t1)
        dec_s.append(t1 - t0)
        ps = [d.p for d in dets]
        truths = [np.asarray(p["p"]) for p in lab["parts"]]
        for d in ps:
            if not truths or min(np.linalg.norm(d - t) for t in truths) > GATE_M:
                fps += 1
        for part, t in zip(lab["parts"], truths, strict=True):
            if not in_view(part, lab["width"], lab["height"]):
                if partly_hidden(part, lab["width"], lab["height"]):
                    hidden += 1
                    flat = [float(np.linalg.norm(d[:2] - t[:2])) for d in ps]
                    if flat and min(flat) <= GATE_M:
                        hidden_z.append(float(abs(ps[int(np.argmin(flat))][2] - t[2])))
                continue
            seen += 1
            if not ps:
                continue
            k = int(np.argmin([np.linalg.norm(d - t) for d in ps]))
            e = ps[k] - t
            if np.linalg.norm(e) <= GATE_M:
                found += 1
                errors.append(float(np.linalg.norm(e)))
                err_xy.append(float(np.linalg.norm(e[:2])))
                err_z.append(float(abs(e[2])))
    err = np.asarray(errors) if errors else np.zeros(1)
    return {
        "estimator": name, "frames": len(frames), "parts_in_view": seen, "detected": found,
        "detection_rate": found / seen if seen else 0.0,
        "false_positives_per_frame": fps / max(1, len(frames)),
        "error_median_mm": float(np.median(err) * 1000), "error_p95_mm": float(np.percentile(err, 95) * 1000),
        "error_xy_median_mm": float(np.median(err_xy or [0]) * 1000),
        "error_z_median_mm": float(np.median(err_z or [0]) * 1000),
        # Per-axis sd of a 3-D error e with E|e|^2 = 3 sd^2 (what the abstract loops draw).
        "error_sd_per_axis_m": float(np.sqrt(np.mean(err**2) / 3)),
        "hidden_parts": hidden, "hidden_detected": len(hidden_z),
        "hidden_error_z_p95_mm": float(np.percentile(hidden_z or [0], 95) * 1000),
        "hidden_error_z_max_mm": float(max(hidden_z or [0]) * 1000),
        "detect_ms_median": float(np.median(det_s) * 1000), "detect_ms_mean": float(np.mean(det_s) * 1000),
        "decode_ms_median": float(np.median(dec_s) * 1000),
    }
