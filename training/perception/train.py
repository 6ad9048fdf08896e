"""Train the Edge pose network on rendered frames and export it for ONNX Runtime.

    python tools/train_perception.py           # render the data set if missing, train, export
    python tools/train_perception.py --quick   # tiny budget (< 2 min) into a temporary directory

CPU only, torch and onnx needed here alone; what it records: docs/perception.md, "Training".
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from domain import pose_net as L
from domain.codec import decode_frame
from training.perception import dataset as D


def have_torch() -> str | None:
    """None if torch and onnx import, else what is missing."""
    missing = []
    for mod in ("torch", "onnx"):
        try:
            __import__(mod)
        except ImportError:
            missing.append(mod)
    return ", ".join(missing) or None


# ---- targets ---------------------------------------------------------------------------------
POSITIVE_VISIBLE = 0.5  # a part this visible is a centre to find
IGNORE_VISIBLE = 0.05  # a part between the two is neither found nor penalised


def targets(lab: dict[str, Any], flip_x: bool, flip_y: bool) -> tuple[np.ndarray, ...]:
    """Training targets of one frame on the 45 x 80 grid: heatmap, loss weight, regression mask,
    offsets (2), size."""
    gh, gw = L.GRID_H, L.GRID_W
    heat = np.zeros((gh, gw), np.float32)
    weight = np.ones((gh, gw), np.float32)
    mask = np.zeros((gh, gw), np.float32)
    off = np.zeros((2, gh, gw), np.float32)
    size = np.zeros((gh, gw), np.float32)
    w, h = lab["width"], lab["height"]
    f_px = (h / 2) / math.tan(math.radians(lab["fovy_deg"]) / 2)
    yy, xx = np.mgrid[0:gh, 0:gw].astype(np.float32) + 0.5
    for part in lab["parts"]:
        gx, gy = L.pixel_to_grid(part["u"], part["v"], w, h)
        if flip_x:
            gx = gw - gx
        if flip_y:
            gy = gh - gy
        inside = 0 <= gx < gw and 0 <= gy < gh
        if part["visible"] < POSITIVE_VISIBLE or not inside:
            if part["visible"] >= IGNORE_VISIBLE:
                c, r = int(np.clip(gx, 0, gw - 1)), int(np.clip(gy, 0, gh - 1))
                weight[max(0, r - 2):r + 3, max(0, c - 2):c + 3] = 0.0
            continue
        dz = 1.0 + part["size_m"]  # rough top-face distance: only sets the blob's spread
        size_cells = part["size_m"] * f_px / dz / w * gw
        sigma = float(np.clip(size_cells / 4, 0.5, 1.5))
        g = np.exp(-((xx - gx) ** 2 + (yy - gy) ** 2) / (2 * sigma**2))
        c, r = int(gx), int(gy)
        g[r, c] = 1.0
        heat = np.maximum(heat, g)
        for rr in range(max(0, r - 1), min(gh, r + 2)):
            for cc in range(max(0, c - 1), min(gw, c + 2)):
                mask[rr, cc] = 1.0
                off[0, rr, cc] = gx - (cc + 0.5)
                off[1, rr, cc] = gy - (rr + 0.5)
                size[rr, cc] = part["size_m"] / L.SIZE_SCALE_M
    return heat, weight, mask, off, size


def load_inputs(frames: list[bytes]) -> np.ndarray:
    """Decoded frames as network inputs (N x 5 x 90 x 160, float16 to halve the memory)."""
    out = np.empty((len(frames), L.CHANNELS, L.INPUT_H, L.INPUT_W), np.float16)
    for i, data in enumerate(frames):
        rgb, depth = decode_frame(data)
        out[i] = L.model_input(rgb, depth)
    return out


# ---- training --------------------------------------------------------------------------------
def train_model(x: np.ndarray, labels: list[dict[str, Any]], epochs: int, batch: int, lr: float,
                seed: int, threads: int, log: Any = print) -> tuple[Any, list[dict[str, float]]]:
    import torch

    from training.perception.model import PoseNet, focal_loss

    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    net = PoseNet(L.CHANNELS)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * math.ceil(len(x) / batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=max(1, steps), pct_start=0.15)
    history = []
    for ep in range(epochs):
        net.train()
        t0 = time.time()
        order = rng.permutation(len(x))
        totals = np.zeros(3)
        for s in range(0, len(order), batch):
            idx = order[s:s + batch]
            fx = rng.random(len(idx)) < 0.5
            fy = rng.random(len(idx)) < 0.5
            xb = x[idx].astype(np.float32)
            xb[fx] = xb[fx, :, :, ::-1]
            xb[fy] = xb[fy, :, ::-1, :]
            # Colour jitter: exposure and white balance beyond the rendered lighting.
            xb[:, :3] *= rng.uniform(0.8, 1.2, (len(idx), 3, 1, 1)).astype(np.float32)
            t = [targets(labels[i], bool(a), bool(b)) for i, a, b in zip(idx, fx, fy, strict=True)]
            heat, weight, mask, off, size = (torch.from_numpy(np.stack(z)) for z in zip(*t, strict=True))
            out = net(torch.from_numpy(np.ascontiguousarray(xb)))
            l_heat = focal_loss(out[:, 0], heat, weight)
            n = mask.sum().clamp(min=1.0)
            l_off = (torch.abs(out[:, 1:3] - off) * mask[:, None]).sum() / n
            l_size = (torch.abs(out[:, 3] - size) * mask).sum() / n
            loss = l_heat + l_off + l_size
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            totals += [l_heat.item() * len(idx), l_off.item() * len(idx), l_size.item() * len(idx)]
        totals /= len(x)
        rec = {"epoch": ep + 1, "heat": round(float(totals[0]), 4), "offset": round(float(totals[1]), 4),
               "size": round(float(totals[2]), 4), "seconds": round(time.time() - t0, 1)}
        history.append(rec)
        log(f"epoch {ep + 1}/{epochs}: heat {rec['heat']:.4f} offset {rec['offset']:.4f} "
            f"size {rec['size']:.4f} ({rec['seconds']} s)")
    net.eval()
    return net, history


def export_onnx(net: Any, path: Path) -> None:
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, L.CHANNELS, L.INPUT_H, L.INPUT_W)
    tmp = path.with_suffix(".onnx.tmp")
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of torch.export's, which needs the
        # onnxscript package; for a plain conv net both give the same graph.
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (dummy,), str(tmp), input_names=["input"], output_names=["output"],
                          opset_version=17, dynamic_axes={"input": {0: "batch"}, "output": {0: "batch"}},
                          dynamo=False)
    tmp.replace(path)


def validate(model_path: Path, frames: list[bytes], labels: list[dict[str, Any]]) -> dict[str, Any]:
    """Metrics of the exported model under ONNX Runtime (the runtime path)."""
    from training.perception.evaluate import evaluate

    return evaluate(lambda k, size: L.LearnedEstimator(k, size, model_path), frames, labels)


def run(args: argparse.Namespace) -> int:
    import torch

    t_start = time.time()
    data_dir: Path = args.data
    splits = {"train": args.episodes, "val": args.val_episodes}
    for split, n in splits.items():
        idx = data_dir / split / "index.json"
        if args.regenerate or not idx.is_file() or json.loads(idx.read_text())["episodes"] != n:
            print(f"rendering {split}: {n} episodes of {args.seconds} s ...", flush=True)
            D.generate(split, n, data_dir, args.seconds, workers=args.workers)
    frames, labels = D.load_split(data_dir, "train")
    vframes, vlabels = D.load_split(data_dir, "val")
    print(f"train {len(frames)} frames, val {len(vframes)} frames; decoding ...", flush=True)
    x = load_inputs(frames)
    net, history = train_model(x, labels, args.epochs, args.batch, args.lr, args.seed, args.threads)
    export_onnx(net, args.out)
    n_params = sum(p.numel() for p in net.parameters())
    metrics = validate(args.out, vframes, vlabels)
    print(f"val: detection rate {metrics['detection_rate']:.4f}, error median {metrics['error_median_mm']:.1f} mm, "
          f"p95 {metrics['error_p95_mm']:.1f} mm, {metrics['detect_ms_median']:.2f} ms/frame")
    train_index = json.loads((data_dir / "train" / "index.json").read_text())
    record = {
        "model": args.out.name, "architecture": "PoseNet: centre heatmap + offset + size FCN "
        "(training/perception/model.py)", "parameters": n_params, "bytes": args.out.stat().st_size,
        "input": {"channels": ["r", "g", "b", "height_above_belt", "depth_valid"],
                  "height": L.INPUT_H, "width": L.INPUT_W},
        "output": {"channels": ["heat_logit", "offset_x", "offset_y", "size"], "height": L.GRID_H,
                   "width": L.GRID_W, "size_scale_m": L.SIZE_SCALE_M},
        "score_threshold": L.SCORE_THRESHOLD,
        "data": {"generator": "training/perception/dataset.py", "train_seed": D.SPLIT_SEEDS["train"],
                 "val_seed": D.SPLIT_SEEDS["val"], "train_episodes": args.episodes,
                 "val_episodes": args.val_episodes, "seconds_per_episode": args.seconds,
                 "train_frames": len(frames), "val_frames": len(vframes),
                 "render_s": train_index.get("render_s")},
        "training": {"epochs": args.epochs, "batch": args.batch, "lr": args.lr, "seed": args.seed,
                     "threads": args.threads, "history": history,
                     "train_s": round(sum(h["seconds"] for h in history), 1)},
        "val_metrics": metrics,
        "torch_version": torch.__version__,
        "total_s": round(time.time() - t_start, 1),
        "command": "python tools/train_perception.py " + " ".join(sys.argv[1:]),
    }
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {args.out} ({record['bytes']} B, {n_params} parameters) and {args.out.with_suffix('.json')} "
          f"in {record['total_s']} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny budget into a temporary directory (CI)")
    ap.add_argument("--data", type=Path, default=D.DEFAULT_DIR, help="rendered data set directory")
    ap.add_argument("--out", type=Path, default=L.DEFAULT_MODEL, help="ONNX model to write")
    ap.add_argument("--episodes", type=int, default=30, help="training episodes to render")
    ap.add_argument("--val-episodes", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=16.0, help="simulated seconds per episode")
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--workers", type=int, default=2, help="rendering processes")
    ap.add_argument("--regenerate", action="store_true", help="render the data set even if present")
    args = ap.parse_args(argv)
    missing = have_torch()
    if missing:
        print(f"SKIP: training needs {missing} (pip install torch onnx); the runtime does not. "
              f"Nothing trained.")
        return 0
    if args.quick:
        with tempfile.TemporaryDirectory(prefix="pose-quick-") as tmp:
            args.data, args.out = Path(tmp) / "data", Path(tmp) / "pose.onnx"
            args.episodes, args.val_episodes, args.seconds, args.epochs = 2, 1, 4.0, 2
            args.regenerate = True
            return run(args)
    return run(args)
