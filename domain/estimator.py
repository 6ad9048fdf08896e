"""Classical part pose estimation from one RGB-D frame: the parts' orange segmented by hue and
saturation, each blob's median depth (its top face) back-projected to the part's centre in the
cell frame; and the choice between it and the learned estimator."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from domain.detection import PART_HSV_HIGH, PART_HSV_LOW, Detection
from domain.work_cell import CameraIntrinsics

log = logging.getLogger(__name__)

MIN_BLOB_PX = 30  # smaller blobs are noise (a 6 cm part at 1 m covers ~400 px at 640x360)


class Estimator(Protocol):
    """What the Edge needs of a pose estimator."""

    name: str

    def detect(self, rgb: np.ndarray, depth_mm: np.ndarray) -> list[Detection]:
        """Parts in one decoded frame: ``rgb`` (uint8 HxWx3), ``depth_mm`` (uint16 HxW, mm, 0 =
        invalid)."""
        ...


class ClassicalEstimator:
    """HSV segmentation + depth back-projection through ``intrinsics``; a part's centre is half
    the nominal edge ``object_size_m`` (m) below its top face."""

    name = "classical"

    def __init__(self, intrinsics: CameraIntrinsics, object_size_m: float) -> None:
        self.k = intrinsics
        self.half = object_size_m / 2

    def detect(self, rgb: np.ndarray, depth_mm: np.ndarray) -> list[Detection]:
        """Parts in one decoded frame: ``rgb`` (uint8 HxWx3), ``depth_mm`` (uint16 HxW, mm, 0 =
        invalid)."""
        hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
        mask = cv2.inRange(hsv, PART_HSV_LOW, PART_HSV_HIGH)
        n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
        out = []
        for i in range(1, n):
            area = int(stats[i, cv2.CC_STAT_AREA])
            if area < MIN_BLOB_PX:
                continue
            d = depth_mm[labels == i]
            d = d[d > 0]
            if d.size == 0:
                continue
            z = float(np.median(d)) / 1000.0
            u, v = centroids[i]
            top = self.k.back_project(float(u), float(v), z)
            out.append(Detection(p=top - np.array([0.0, 0.0, self.half]), area_px=area))
        return out


def make_estimator(name: str, intrinsics: CameraIntrinsics, object_size_m: float,
                   model_path: str | Path | None = None) -> tuple[Estimator, str | None]:
    """The estimator called ``name`` (``learned`` or ``classical``) for a camera of
    ``intrinsics`` and parts of nominal edge ``object_size_m`` (m), the learned one from
    ``model_path`` (default: the shipped model), and, when another one had to stand in, why:
    ``learned`` falls back to ``classical`` when its model cannot be loaded."""
    if name == "classical":
        return ClassicalEstimator(intrinsics, object_size_m), None
    if name == "learned":
        from domain import pose_net

        path = Path(model_path) if model_path is not None else pose_net.DEFAULT_MODEL
        reason = pose_net.model_available(path)
        if reason is None:
            try:
                return pose_net.LearnedEstimator(intrinsics, object_size_m, path), None
            except Exception as exc:  # a corrupt or incompatible model file
                reason = f"cannot load {path}: {exc}"
        log.warning("learned estimator unavailable (%s); using the classical estimator", reason)
        return ClassicalEstimator(intrinsics, object_size_m), reason
    raise ValueError(f"unknown estimator {name!r}; valid: learned, classical")
