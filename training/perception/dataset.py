"""Labelled RGB-D frames rendered by our physics scene, for training and testing the pose network.

Episodes, their randomised conditions and the labels: docs/perception.md, "Training".
``python tools/perception_dataset.py --split train --episodes 30 --out DIR`` writes
``DIR/<split>/frames.bin`` (compressed frames back to back) and ``DIR/<split>/index.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_DIR = Path("results/perception/data")
# Seeds of the splits: disjoint streams, so the test set shares no episode with training.
SPLIT_SEEDS = {"train": 1000, "val": 2000, "test": 3000}


@dataclass(frozen=True)
class EpisodeSpec:
    split: str
    index: int
    seconds: float
    frame_gap_s: tuple[float, float]


def _episode_conditions(r: np.random.Generator, split: str) -> dict[str, Any]:
    """Randomised conditions of one episode. The test split draws from wider ranges (other sizes,
    darker and brighter light) than training, from other seeds."""
    test = split == "test"
    w, h = ((640, 360), (424, 240))[int(r.random() < 0.3)]
    period = float(r.uniform(1.0, 2.5))
    size = float(r.uniform(0.045, 0.075))
    spread = float(r.uniform(0.0, 0.012 if test else 0.015))
    light = float(r.uniform(0.35, 1.2) if test else r.uniform(0.45, 1.1))
    tint = r.uniform(0.85, 1.0, 3)
    tilt = r.uniform(-0.7, 0.7, 2) if test else r.uniform(-0.6, 0.6, 2)
    return {
        "camera": {"width_px": w, "height_px": h, "jpeg_quality": int(r.integers(70, 93)),
                   "depth_subpixel_px": float(r.uniform(0.06, 0.1)),
                   "depth_decimation": int(r.choice([2, 4], p=[0.2, 0.8]))},
        "work_cell": {"object_period_s": period, "object_jitter_s": float(r.uniform(0.0, 0.4 * period)),
                 "object_size_m": size, "object_size_spread_m": spread,
                 "object_yaw_spread_deg": 45.0, "object_lateral_spread_m": float(r.uniform(0.02, 0.1)),
                 "belt_speed_m_s": float(r.uniform(0.15, 0.3)), "first_object_s": 0.2},
        "light": {"diffuse": (light * tint).tolist(), "dir": [float(tilt[0]), float(tilt[1]), -1.0],
                  "ambient": float(r.uniform(0.0, 0.25)), "head": float(r.uniform(0.15, 0.55))},
        "part_rgb": (np.array([0.95, 0.45, 0.05]) + r.uniform(-1, 1, 3) * [0.05, 0.07, 0.04]).clip(0, 1).tolist(),
    }


def _light_scene(world: Any, cond: dict[str, Any]) -> None:
    import mujoco

    m = world.model
    lc = cond["light"]
    m.light_diffuse[:] = lc["diffuse"]
    d = np.asarray(lc["dir"], float)
    m.light_dir[:] = d / np.linalg.norm(d)
    m.light_ambient[:] = lc["ambient"]
    m.vis.headlight.diffuse[:] = lc["head"]
    m.vis.headlight.ambient[:] = lc["ambient"] / 2
    mat = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_MATERIAL, "part")
    m.mat_rgba[mat, :3] = cond["part_rgb"]


def render_episode(spec: EpisodeSpec) -> tuple[list[bytes], list[dict[str, Any]]]:
    """Render one episode of a split under its randomised conditions: (compressed frames, labels)."""
    from fabric.seeding import rng
    from scenario.schema import parse_scenario

    seed = SPLIT_SEEDS[spec.split] + spec.index
    r = rng(seed, "dataset/conditions")
    cond = _episode_conditions(r, spec.split)
    sc = parse_scenario({"seed": seed, "loops": 1, "detailed_loops": 1, "duration_s": spec.seconds,
                         "work_cell": cond["work_cell"], "camera": cond["camera"]})
    times, t = [], 1_000_000
    while t < sc.duration_us:
        times.append(t)
        t += int(r.uniform(*spec.frame_gap_s) * 1e6) // 1000 * 1000
    frames, labels = render_frames(sc, times, cond)
    for lab in labels:
        lab["episode"] = spec.index
    return frames, labels


def render_frames(sc: Any, times_us: list[int], cond: dict[str, Any] | None = None
                  ) -> tuple[list[bytes], list[dict[str, Any]]]:
    """Render cell 0 of scenario ``sc`` working (seeded by ``sc.seed``) at ``times_us`` through
    the camera node's pipeline, lit as ``cond`` says (the model's own lights if None):
    (compressed frames, labels)."""
    import mujoco

    from domain import work_cell as g
    from domain.codec import encode_frame
    from domain.offline_render import working_cell
    from domain.sensor import sense, sensor_depth_mm, sensor_for
    from domain.work_cell import CameraIntrinsics
    from domain.world import World
    from fabric.seeding import rng

    seed = sc.seed
    cam = sc.camera
    world = World(sc)
    if cond is not None:
        _light_scene(world, cond)
    k = CameraIntrinsics(cam.width_px, cam.height_px, cam.fovy_deg)
    sensor = sensor_for(cam)
    noise = rng(seed, "dataset/sensor")
    m = world.model
    origin = np.array([*sc.hall.work_cell_origins(sc.loops)[0], 0.0])
    bodies: list[int] = []
    geoms: list[int] = []
    while (b := mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"c0_obj{len(bodies)}")) >= 0:
        bodies.append(b)
        geoms.append(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"c0_obj{len(geoms)}_geom"))
    seg = mujoco.Renderer(m, cam.height_px, cam.width_px)
    seg.enable_segmentation_rendering()
    cam_z = g.BELT_TOP_Z + g.CAMERA_HEIGHT_ABOVE_BELT
    cu, cv = k.centre
    frames, labels = [], []
    for t_us, w in working_cell(sc, rng(seed, "dataset/spawn"), times_us, world):
        rgb, depth = w.render(0, cam.width_px, cam.height_px)
        assert depth is not None
        seg.update_scene(w.data, camera="c0_camera")
        ids = seg.render()
        gid = np.where(ids[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), ids[..., 0], -1)
        counts = np.bincount(gid[gid >= 0].ravel(), minlength=m.ngeom)
        sizes = {tk.task_id: tk.size_m for tk in w.tasks if tk.cell == 0}
        parts = []
        for obj in w.objects(0):
            p = np.asarray(obj["p"])
            slot = int(np.argmin([np.linalg.norm(w.data.xpos[b] - origin - p) for b in bodies]))
            size = float(sizes[obj["task_id"]])
            rot = w.data.xmat[bodies[slot]].reshape(3, 3)
            kup = int(np.argmax(np.abs(rot[2])))
            top = p + rot[:, kup] * math.copysign(size / 2, rot[2, kup])
            dz = cam_z - top[2]
            u = cu + (top[0] - g.CAMERA_X) * k.f_px / dz
            v = cv - top[1] * k.f_px / dz
            expected = (size * k.f_px / dz) ** 2
            parts.append({"task_id": int(obj["task_id"]), "p": [float(x) for x in p], "size_m": size,
                          "u": float(u), "v": float(v), "gripped": bool(obj["gripped"]),
                          "visible": float(min(1.5, counts[geoms[slot]] / expected))})
        rgb_s, dep_s = sense(sensor, rgb, sensor_depth_mm(depth, cam.depth_noise_mm, noise), noise)
        frames.append(encode_frame(rgb_s, dep_s, cam.jpeg_quality, cam.depth_codec, cam.depth_decimation))
        labels.append({"t_us": t_us, "bytes": len(frames[-1]), "width": cam.width_px, "height": cam.height_px,
                       "fovy_deg": cam.fovy_deg, "nominal_size_m": sc.work_cell.object_size_m, "parts": parts})
    seg.close()
    world.finish()
    return frames, labels


def generate(split: str, episodes: int, out_dir: Path, seconds: float = 16.0,
             frame_gap_s: tuple[float, float] = (0.1, 0.25), workers: int = 2,
             first_episode: int = 0) -> dict[str, Any]:
    """Render ``episodes`` episodes of ``split`` into ``out_dir/split``; returns the index."""
    specs = [EpisodeSpec(split, i, seconds, frame_gap_s) for i in range(first_episode, first_episode + episodes)]
    t0 = time.time()
    frames: list[bytes] = []
    labels: list[dict[str, Any]] = []
    # Always in fresh processes: an EGL context and torch in one process can crash the renderer.
    with ProcessPoolExecutor(max(1, workers), mp_context=get_context("spawn")) as pool:
        results = list(pool.map(render_episode, specs))
    for f, lab in results:
        frames += f
        labels += lab
    d = out_dir / split
    d.mkdir(parents=True, exist_ok=True)
    offsets = np.cumsum([0] + [len(f) for f in frames]).tolist()
    tmp = d / "frames.bin.tmp"
    tmp.write_bytes(b"".join(frames))
    tmp.replace(d / "frames.bin")
    index = {"split": split, "seed": SPLIT_SEEDS[split], "episodes": episodes, "first_episode": first_episode,
             "seconds": seconds, "frames": len(frames), "offsets": offsets, "labels": labels,
             "render_s": round(time.time() - t0, 1)}
    (d / "index.json").write_text(json.dumps(index))
    return index


def load_split(out_dir: Path, split: str) -> tuple[list[bytes], list[dict[str, Any]]]:
    """(compressed frames, labels) of a generated split."""
    d = out_dir / split
    index = json.loads((d / "index.json").read_text())
    blob = (d / "frames.bin").read_bytes()
    offs = index["offsets"]
    return [blob[offs[i]:offs[i + 1]] for i in range(len(offs) - 1)], index["labels"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=sorted(SPLIT_SEEDS), default="train")
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=16.0, help="simulated seconds per episode")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=DEFAULT_DIR)
    args = ap.parse_args(argv)
    index = generate(args.split, args.episodes, args.out, args.seconds, workers=args.workers)
    print(f"{args.split}: {index['frames']} frames from {args.episodes} episodes in {index['render_s']} s "
          f"-> {args.out / args.split}")
    return 0
