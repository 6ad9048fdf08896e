"""Learned part detection and pose estimation at the Edge: a tiny fully-convolutional network
(trained on frames rendered by our scene) run with ONNX Runtime, its heatmap peaks back-projected
through the full-resolution depth; no torch at run time (docs/perception.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from domain import work_cell as g
from domain.detection import PART_HSV_HIGH, PART_HSV_LOW, Detection
from domain.work_cell import CameraIntrinsics

MODEL_DIR = Path(__file__).parent / "models"
DEFAULT_MODEL = MODEL_DIR / "pose.onnx"
INPUT_W, INPUT_H = 160, 90  # network input, pixels (16:9 like the camera modes we use)
STRIDE = 2  # input pixels per output cell
GRID_W, GRID_H = INPUT_W // STRIDE, INPUT_H // STRIDE  # 80 x 45
CHANNELS = 5  # R, G, B, height above the belt, depth valid
HEIGHT_SCALE_M = 0.1  # the height channel is (height above belt) / this, clipped to [-2, 6]
SIZE_SCALE_M = 0.1  # the size output is the edge length / this
SCORE_THRESHOLD = 0.35  # heatmap probability of a part centre
MIN_SIZE_M, MAX_SIZE_M = 0.02, 0.15  # the scenario's part size limits
# A depth within this of where a resting part's top face would be is that face: the sensor's
# noise at 1 m (a few mm) plus the size estimate's error plus the parts' rocking on the belt.
ON_BELT_TOL_M = 0.02
RING_MIN_PX = 4  # fewer part-coloured pixels at the resting height are edge blends, not a face
# A part lifted in the cup shows at least this many part-coloured pixels above the resting height
# for each one at it (those are blends of its edge with the belt); a part under the hovering cup
# shows fewer (blends of its rim with the cup). In between, the face is too hidden to tell.
LIFTED_RATIO = 2.0


def model_input(rgb: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """The network's input (float32, 5 x 90 x 160) from a decoded frame: ``rgb`` (uint8 HxWx3),
    ``depth_mm`` (uint16 HxW, mm), at any 16:9-ish resolution."""
    small = cv2.resize(rgb, (INPUT_W, INPUT_H), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    dep = cv2.resize(depth_mm, (INPUT_W, INPUT_H), interpolation=cv2.INTER_NEAREST).astype(np.float32) / 1000.0
    valid = (dep > 0).astype(np.float32)
    height = np.clip((g.CAMERA_HEIGHT_ABOVE_BELT - dep) / HEIGHT_SCALE_M, -2.0, 6.0) * valid
    return np.concatenate([small.transpose(2, 0, 1), height[None], valid[None]], axis=0)


def grid_to_pixel(cx: float, cy: float, width: int, height: int) -> tuple[float, float]:
    """Pixel (u, v) of a ``width`` x ``height`` px image at grid position (``cx``, ``cy``) (cell
    units, cell centre at +0.5)."""
    return cx / GRID_W * width - 0.5, cy / GRID_H * height - 0.5


def pixel_to_grid(u: float, v: float, width: int, height: int) -> tuple[float, float]:
    """Inverse of ``grid_to_pixel``: the grid position of pixel (``u``, ``v``) of a ``width`` x
    ``height`` px image."""
    return (u + 0.5) / width * GRID_W, (v + 0.5) / height * GRID_H


def peaks(heat: np.ndarray, threshold: float) -> list[tuple[int, int]]:
    """(row, col) of the 3x3 local maxima of ``heat`` (H x W probabilities) above ``threshold``."""
    dil = cv2.dilate(heat, np.ones((3, 3), np.uint8))
    rows, cols = np.nonzero((heat >= dil) & (heat > threshold))
    return list(zip(rows.tolist(), cols.tolist(), strict=True))


class LearnedEstimator:
    """ONNX Runtime inference of the pose network at ``model_path`` on ``threads`` threads +
    depth back-projection through ``intrinsics``; ``object_size_m`` (m): the nominal part edge."""

    name = "learned"

    def __init__(self, intrinsics: CameraIntrinsics, object_size_m: float,
                 model_path: str | Path = DEFAULT_MODEL, threads: int = 1) -> None:
        import onnxruntime as ort  # imported here: the classical estimator must not need it

        self.k = intrinsics
        self.nominal_size = object_size_m
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads  # one emulated core: keep inference on one thread
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.session = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
        self.input_name = self.session.get_inputs()[0].name
        meta = Path(model_path).with_suffix(".json")
        self.info: dict[str, Any] = json.loads(meta.read_text()) if meta.is_file() else {}
        self.threshold = float(self.info.get("score_threshold", SCORE_THRESHOLD))

    def raw(self, rgb: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
        """The network output for one frame (``rgb``, ``depth_mm`` as for ``model_input``): (4,
        45, 80) = heatmap logit, offset x, offset y, size."""
        x = model_input(rgb, depth_mm)[None]
        return self.session.run(None, {self.input_name: x})[0][0]

    def detect(self, rgb: np.ndarray, depth_mm: np.ndarray) -> list[Detection]:
        """Parts in one decoded frame: ``rgb`` (uint8 HxWx3), ``depth_mm`` (uint16 HxW, mm, 0 =
        invalid)."""
        out = self.raw(rgb, depth_mm)
        heat = 1.0 / (1.0 + np.exp(-out[0]))
        h, w = depth_mm.shape
        dets = []
        for r, c in peaks(heat, self.threshold):
            gx, gy = c + 0.5 + float(out[1, r, c]), r + 0.5 + float(out[2, r, c])
            u, v = grid_to_pixel(gx, gy, w, h)
            size = float(np.clip(out[3, r, c] * SIZE_SCALE_M, MIN_SIZE_M, MAX_SIZE_M))
            z = top_face_depth(rgb, depth_mm, u, v, size, self.k.f_px)
            if z is None:
                continue
            top = self.k.back_project(u, v, z)
            area = int(round((size * self.k.f_px / z) ** 2))
            dets.append(Detection(p=top - np.array([0.0, 0.0, size / 2]), area_px=area))
        return dets


def top_face_depth(rgb: np.ndarray, depth_mm: np.ndarray, u: float, v: float, size_m: float,
                   f_px: float) -> float | None:
    """Distance (m) to the top face of a part of edge ``size_m`` (m) centred at pixel (``u``,
    ``v``) of a decoded frame (``rgb``, ``depth_mm`` as for ``model_input``) of a camera of focal
    length ``f_px``.

    The arm or the cup may hide part of the face, and their depth is not the part's. A part
    resting on the belt has its top face ``size_m`` above the belt: the median of the valid depths
    that agree with that within ``ON_BELT_TOL_M`` is used when they are a fair share of the middle
    of the face (a square of half its edge). When they are not, the cup is over the middle: either
    hovering over a resting part, whose face shows as a ring around it at the resting height, or
    holding the part up, whose face shows around it above that height. The part's colour tells
    which: if, over the whole face, at least as many part-coloured pixels lie at the resting height
    as above it, the part rests and their median is used; if ``LIFTED_RATIO`` times as many lie
    above it (or none shows the part's colour), the part is lifted and, of the depths above the
    belt, the farther quarter, i.e. the face around the cup, is used; in between, None: too little
    of the face shows to tell."""
    h, w = depth_mm.shape
    z_belt = g.CAMERA_HEIGHT_ABOVE_BELT - size_m  # top face of a part resting on the belt
    u0, v0 = int(round(u)), int(round(v))

    def window(frac: float) -> tuple[slice, slice]:
        # Clamped at both ends: a peak off the image gives an empty window, never a wrapped one.
        r = max(1, int(round(frac * size_m * f_px / z_belt)))
        return (slice(min(h, max(0, v0 - r)), max(0, min(h, v0 + r + 1))),
                slice(min(w, max(0, u0 - r)), max(0, min(w, u0 + r + 1))))

    mid = depth_mm[window(0.25)].astype(np.float64) / 1000.0
    mid = mid[mid > 0]
    on_belt = mid[np.abs(mid - z_belt) < ON_BELT_TOL_M]
    if on_belt.size and on_belt.size >= 0.3 * mid.size:
        return float(np.median(on_belt))
    rows, cols = window(0.45)
    face = depth_mm[rows, cols].astype(np.float64) / 1000.0
    if not face.size:
        return None  # the face lies off the image
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb[rows, cols]), cv2.COLOR_RGB2HSV)
    coloured = face[(cv2.inRange(hsv, PART_HSV_LOW, PART_HSV_HIGH) > 0) & (face > 0)]
    ring = coloured[np.abs(coloured - z_belt) < ON_BELT_TOL_M]
    raised = np.count_nonzero(coloured < z_belt - ON_BELT_TOL_M)
    if ring.size >= RING_MIN_PX and ring.size >= raised:
        return float(np.median(ring))
    if raised < LIFTED_RATIO * ring.size:
        return None  # the cup hides too much of the face to tell: no height to measure
    above = face[(face > 0) & (face < g.CAMERA_HEIGHT_ABOVE_BELT - 0.01)]
    if above.size:
        return float(np.percentile(above, 75))
    return float(np.median(mid)) if mid.size else None


def model_available(model_path: str | Path = DEFAULT_MODEL) -> str | None:
    """None if the learned estimator can run with the model at ``model_path``, else why not."""
    p = Path(model_path)
    if not p.is_file():
        return f"model file {p} not found (train it: python tools/train_perception.py)"
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return "onnxruntime is not installed"
    return None
