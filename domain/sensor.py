"""What a D435-class RGB-D sensor makes of the rendered scene: stereo depth noise growing with
distance squared, invalid (zero) pixels where stereo cannot match, and colour shot and read
noise; the depth decimation filter; camera capture phases (the model: docs/perception.md)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from domain.work_cell import CameraIntrinsics
from scenario.schema import CameraConfig

MAX_SHADOW_PX = 48  # occlusion shadows wider than this are cut (arm very close to the camera)


@dataclass(frozen=True)
class SensorModel:
    """Noise and invalid-pixel parameters of a D435-class camera (docs/perception.md)."""

    f_px: float  # focal length at the configured resolution, pixels
    baseline_m: float = 0.05  # stereo baseline, m
    subpixel_px: float = 0.08  # disparity error sd of the stereo matcher, px
    white_fraction: float = 0.35  # share of the disparity error sd that is per pixel (rest correlated)
    corr_px: float = 6.0  # correlation length of the correlated part, px at 640 px width
    min_depth_m: float = 0.11  # closer surfaces are not measured
    edge_invalid_p: float = 0.5  # probability that a pixel at a depth discontinuity is invalid
    edge_jump_m: float = 0.02  # a step larger than this between neighbours is a discontinuity
    rgb_read_dn: float = 1.0  # read noise sd, 8-bit digital numbers
    rgb_gain_dn: float = 0.02  # shot noise: variance per digital number of signal

    def depth(self, depth_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Measured depth (uint16 mm, 0 = invalid) from the ideal depth ``depth_mm`` (uint16 HxW,
        mm), with noise drawn from ``rng``."""
        h, w = depth_mm.shape
        z = depth_mm.astype(np.float32) / 1000.0
        valid = z >= self.min_depth_m
        fb = self.f_px * self.baseline_m
        disp = np.where(valid, fb / np.maximum(z, 1e-3), 0.0).astype(np.float32)
        # Correlated part: white noise on a coarse grid, smoothly interpolated.
        scale = self.corr_px * w / 640.0
        gh, gw = max(2, int(round(h / scale)) + 1), max(2, int(round(w / scale)) + 1)
        sd_corr = self.subpixel_px * np.sqrt(1.0 - self.white_fraction**2)
        coarse = rng.standard_normal((gh, gw), dtype=np.float32)
        corr = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        corr *= sd_corr / max(float(corr.std()), 1e-6)  # interpolation lowers the variance between nodes
        white = rng.standard_normal((h, w), dtype=np.float32)
        white *= self.subpixel_px * self.white_fraction
        noisy = disp + corr
        noisy += white
        invalid = ~valid | (noisy <= 0.1)
        # Left band: columns u < d are outside the right imager's view.
        invalid |= np.arange(w, dtype=np.float32)[None, :] < disp
        invalid |= self._shadow(disp)
        invalid |= self._edges(z, rng)
        out = fb / np.maximum(noisy, 0.1, out=noisy)  # float64 where f_px is (the intrinsics')
        out *= 1000.0
        out[invalid] = 0.0
        np.rint(out, out=out)
        return np.clip(out, 0, 65535, out=out).astype(np.uint16)

    @staticmethod
    def _shadow(disp: np.ndarray) -> np.ndarray:
        """Pixels the right imager cannot see: a nearer surface k columns to the right projects
        onto the same right-image column (disparity larger by at least k). Computed for the
        pixels with a disparity; those without one are invalid anyway."""
        # A pixel can be hidden k columns away only if k is less than its row's disparity range
        # plus one half (and k <= MAX_SHADOW_PX): most rows need a few k, the rows with the arm
        # near the camera many. Sorted by that reach, each k compares only the rows it can reach.
        low = np.where(disp > 0, disp, np.inf).min(axis=1)
        spread = np.where(np.isfinite(low), disp.max(axis=1) - low, -1.0)
        reach = np.minimum(np.floor(spread) + 1, MAX_SHADOW_PX).astype(np.intp)
        order = np.argsort(-reach, kind="stable")
        rows = disp[order]
        reached = np.cumsum(np.bincount(reach)[::-1])[::-1]  # reached[k]: rows with reach >= k
        hidden = np.zeros(disp.shape, bool)
        for k in range(1, len(reached)):
            n = int(reached[k])
            hidden[:n, :-k] |= rows[:n, k:] - k > rows[:n, :-k] + 0.5
        occluded = np.empty_like(hidden)
        occluded[order] = hidden
        return occluded

    def _edges(self, z: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Unreliable matches where depth jumps between neighbouring pixels."""
        jump = np.zeros(z.shape, bool)
        dx = np.abs(np.diff(z, axis=1)) > self.edge_jump_m
        dy = np.abs(np.diff(z, axis=0)) > self.edge_jump_m
        jump[:, 1:] |= dx
        jump[:, :-1] |= dx
        jump[1:, :] |= dy
        jump[:-1, :] |= dy
        return jump & (rng.random(z.shape, dtype=np.float32) < self.edge_invalid_p)

    def rgb(self, rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``rgb`` (uint8 HxWx3) with shot and read noise drawn from ``rng``."""
        # The sd of each of the 256 levels, looked up per pixel: the same float32 values as the
        # square root taken per pixel, at a quarter of its cost; in place, no temporaries.
        sd = np.sqrt(self.rgb_read_dn**2 + self.rgb_gain_dn * np.arange(256, dtype=np.float32))
        out = rng.standard_normal(rgb.shape, dtype=np.float32)
        out *= sd[rgb]
        out += rgb
        np.rint(out, out=out)
        np.clip(out, 0, 255, out=out)
        return out.astype(np.uint8)


def decimate_depth(depth_mm: np.ndarray, factor: int) -> np.ndarray:
    """The RealSense SDK's decimation filter on ``depth_mm`` (uint16 HxW, mm, 0 = invalid): each
    ``factor`` x ``factor`` block becomes one pixel, the median of its valid pixels for factors 2
    and 3, their mean for larger factors, 0 where a block has no valid pixel. The image is
    cropped to a multiple of ``factor``."""
    if factor == 1:
        return depth_mm
    h, w = (depth_mm.shape[0] // factor) * factor, (depth_mm.shape[1] // factor) * factor
    tiles = depth_mm[:h, :w].reshape(h // factor, factor, w // factor, factor).swapaxes(1, 2)
    blocks = tiles.reshape(h // factor, w // factor, factor * factor).astype(np.float32)
    valid = blocks > 0
    n = valid.sum(axis=2)
    if factor <= 3:  # median of the valid pixels: zeros sort first, take the middle of the rest
        srt = np.sort(blocks, axis=2)
        idx = np.minimum((factor * factor - n) + np.maximum(n - 1, 0) // 2, factor * factor - 1)
        out = np.take_along_axis(srt, idx[..., None], axis=2)[..., 0]
    else:
        out = blocks.sum(axis=2) / np.maximum(n, 1)
    return np.where(n > 0, np.rint(out), 0).astype(np.uint16)


def sensor_for(cam: CameraConfig) -> SensorModel | None:
    """The sensor model of a scenario's camera section ``cam`` (None for ``ideal``)."""
    if cam.sensor_model == "ideal":
        return None
    f_px = CameraIntrinsics(cam.width_px, cam.height_px, cam.fovy_deg).f_px
    return SensorModel(f_px=f_px, subpixel_px=cam.depth_subpixel_px)


def sense(sensor: SensorModel | None, rgb: np.ndarray, depth_mm: np.ndarray,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, depth_mm) as ``sensor`` (None: ideal) delivers them from the rendered pair ``rgb``
    (uint8 HxWx3) and ``depth_mm`` (uint16 HxW, mm), with noise drawn from ``rng``."""
    if sensor is None:
        return rgb, depth_mm
    return sensor.rgb(rgb, rng), sensor.depth(depth_mm, rng)


def frame_offset_us(loop: int, loops: int, frame_period_us: int, step_us: int) -> int:
    """Capture phase (us) of the camera of loop ``loop`` of ``loops``: cameras are not
    synchronised, but spread over the frame period ``frame_period_us`` (us), on the grid of
    ``step_us`` (us) physics steps."""
    return (loop * frame_period_us // max(loops, 1)) // step_us * step_us


def sensor_depth_mm(depth_m: np.ndarray, noise_mm_at_1m: float,
                    rng: np.random.Generator | None) -> np.ndarray:
    """Stereo depth as a D435-class sensor reports ideal depth ``depth_m`` (m): uint16
    millimetres, noise of sd ``noise_mm_at_1m`` (mm) at 1 m growing with distance squared, zero
    where nothing is measured. A caller whose stream serves nothing else may pass ``rng=None``
    for noise-free depth: the same values, without drawing (and then multiplying by zero) a
    normal per pixel."""
    if rng is None:
        if noise_mm_at_1m != 0.0:
            raise ValueError(f"depth noise of {noise_mm_at_1m} mm at 1 m needs a random stream (rng=None)")
        mm = depth_m * 1000.0
    else:
        noise = rng.normal(0.0, 1.0, depth_m.shape).astype(np.float32) * (noise_mm_at_1m * depth_m**2)
        mm = depth_m * 1000.0 + noise
    return np.clip(np.rint(mm), 0, 65535).astype(np.uint16)
