"""The network model of the co-design policy's training environment, measured on the NR cell.

``make policy-network`` (``python benchmarks/policy_network_table.py [--duration-s 8] [--seeds 2]``)
writes training/policy/data/network_table.json, frame latency and loss by offered uplink load and
latency budget, and prints a summary: docs/policy.md, "The environment", network model.
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from domain.codec import slot_after, split_packets  # noqa: E402
from domain.frame_model import load_frame_model  # noqa: E402
from fabric.seeding import rng as named_rng  # noqa: E402
from netsim.nr.radio_cell import NrCell  # noqa: E402
from netsim.radio_cell import FlowQos, Packet  # noqa: E402
from scenario.schema import Scenario  # noqa: E402

OUT = ROOT / "training" / "policy" / "data" / "network_table.json"
LOADS_MBPS = (10, 25, 50, 75, 100, 120, 140, 155, 165, 175, 185, 195, 210, 240, 280, 340)
BUDGETS_MS: tuple[float | None, ...] = (None, 25, 50, 100, 200)
QUANTILES = (0.0, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 0.99, 1.0)
BASE_CAMERAS = 24  # loops near the cell's capacity at PDP 1
FPS = 30
MTU = 1500
POSE_BYTES = 120
POSE_COMPUTE_US = 4_000  # Edge pose job between a frame's arrival and its pose packet


def loop_rate_mbps(sizes: np.ndarray) -> float:
    """Uplink IP rate of one camera at PDP 1 (payload + per-packet headers), Mbit/s."""
    ip = np.mean([sum(split_packets(int(s), MTU)) for s in sizes])
    return float(ip * 8 * FPS / 1e6)


def measure(n_cameras: int, pdp: float, budget_ms: float | None, duration_s: float, warmup_s: float,
            seed: int, sizes: np.ndarray) -> dict[str, Any]:
    """One run of the cell: frame-level latency and loss, bytes discarded, downlink latency."""
    sc = Scenario(loops=n_cameras, detailed_loops=0, seed=seed)
    ues = sc.ue_positions_m()
    cell = NrCell(sc.netsim.nr, sc.hall.gnb_position_m, ues, seed, stream_prefix="table/nr")
    slot = cell.slot_us
    period = 1_000_000 // FPS
    end = int(duration_s * 1e6) // slot * slot
    warm = int(warmup_s * 1e6)
    budget_us = None if budget_ms is None else int(budget_ms * 1000)
    keep = [named_rng(seed, f"table/camera-{i}/pdp") for i in range(n_cameras)]
    size_rng = named_rng(seed, "table/sizes")
    for i in range(n_cameras):
        cell.set_flow_qos(f"camera-{i}/video", FlowQos(delay_budget_us=budget_us))
    captures = [(int(named_rng(seed, f"table/camera-{i}/phase").integers(0, period)), i)
                for i in range(n_cameras)]
    heapq.heapify(captures)
    frames: dict[int, dict[str, Any]] = {}  # frame id -> enqueue, packets left, lost, counted
    poses: list[tuple[int, int]] = []  # (enqueue slot, loop) of pose packets to send
    pid = 0
    fid = 0
    injected = discarded = delivered_bytes = 0
    latencies: list[int] = []
    dl_latencies: list[int] = []
    lost = counted = 0
    for s in range(end // slot):
        t = s * slot
        while captures and captures[0][0] < t:
            cap, i = heapq.heappop(captures)
            heapq.heappush(captures, (cap + period, i))
            if keep[i].random() >= pdp:
                continue
            enq = slot_after(cap, slot)
            pkts = split_packets(int(size_rng.choice(sizes)), MTU)
            frames[fid] = {"enq": enq, "left": len(pkts), "lost": False, "count": warm <= enq}
            for size in pkts:
                pid += 1
                if warm <= enq:
                    injected += size
                out = cell.enqueue(Packet(pid, f"camera-{i}/video", f"camera-{i}", "ul", size, enq,
                                          ref=("ul", fid, i)))
                if out is not None:
                    frames[fid]["lost"] = True
                    frames[fid]["left"] -= 1
            fid += 1
        while poses and poses[0][0] <= t:
            enq, i = heapq.heappop(poses)
            pid += 1
            cell.enqueue(Packet(pid, f"robot-{i}/pose", f"robot-{i}", "dl", POSE_BYTES, enq,
                                ref=("dl", enq, i)))
        for o in cell.run_slot(t):
            kind, key, i = o.packet.ref
            if kind == "dl":
                if o.deliver_us is not None and key >= warm:
                    dl_latencies.append(o.deliver_us - key)
                continue
            fr = frames.get(key)
            if fr is None:
                continue
            fr["left"] -= 1
            if o.deliver_us is None:
                fr["lost"] = True
                if fr["count"] and o.cause == "delay_budget":
                    discarded += o.packet.size_bytes
            elif fr["count"]:
                delivered_bytes += o.packet.size_bytes
            if fr["left"] == 0:
                del frames[key]
                if fr["count"]:
                    counted += 1
                    if fr["lost"]:
                        lost += 1
                    else:
                        latencies.append(o.deliver_us - fr["enq"])
                if not fr["lost"] and o.deliver_us is not None:
                    heapq.heappush(poses, (slot_after(o.deliver_us + POSE_COMPUTE_US, slot), i))
    # Frames still queued at the end: above capacity without a budget they would arrive later
    # and later; the controller cannot use them in time.
    pending = sum(1 for fr in frames.values() if fr["count"])
    counted += pending
    lost += pending
    window_s = (end - warm) / 1e6
    lat = np.asarray(latencies, float) / 1000
    dl = np.asarray(dl_latencies, float) / 1000
    return {
        "cameras": n_cameras, "pdp": pdp, "seed": seed,
        "offered_mbps": injected * 8 / window_s / 1e6,
        "delivered_mbps": delivered_bytes * 8 / window_s / 1e6,
        "frames": counted, "frame_loss": lost / counted if counted else 0.0,
        "byte_discard": discarded / injected if injected else 0.0,
        "latency_ms": lat.tolist(), "dl_latency_ms": dl.tolist(),
    }


def point(load_mbps: float, budget_ms: float | None, rate: float, duration_s: float,
          warmup_s: float, seeds: int, sizes: np.ndarray) -> dict[str, Any]:
    """Table entry for one (load, budget): runs over ``seeds`` pooled."""
    n = max(BASE_CAMERAS, math.ceil(load_mbps / rate))
    pdp = min(1.0, load_mbps / (n * rate))
    runs = [measure(n, pdp, budget_ms, duration_s, warmup_s, seed, sizes) for seed in range(1, seeds + 1)]
    lat = np.concatenate([r["latency_ms"] for r in runs]) if runs else np.zeros(0)
    dl = np.concatenate([r["dl_latency_ms"] for r in runs])
    frames = sum(r["frames"] for r in runs)
    return {
        "load_mbps": load_mbps, "budget_ms": budget_ms, "cameras": n, "pdp": round(pdp, 4),
        "offered_mbps": round(float(np.mean([r["offered_mbps"] for r in runs])), 2),
        "delivered_mbps": round(float(np.mean([r["delivered_mbps"] for r in runs])), 2),
        "frames": frames,
        "frame_loss": round(sum(r["frame_loss"] * r["frames"] for r in runs) / max(1, frames), 5),
        "byte_discard": round(float(np.mean([r["byte_discard"] for r in runs])), 5),
        "latency_quantiles_ms": ([round(float(np.quantile(lat, q)), 3) for q in QUANTILES]
                                 if lat.size else None),
        "dl_latency_quantiles_ms": ([round(float(np.quantile(dl, q)), 3) for q in QUANTILES]
                                    if dl.size else None),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration-s", type=float, default=8.0, help="simulated seconds per run")
    ap.add_argument("--warmup-s", type=float, default=1.0, help="excluded start, s")
    ap.add_argument("--seeds", type=int, default=2, help="runs per point (seeds 1..N)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    sizes = load_frame_model().frame_bytes
    rate = loop_rate_mbps(sizes)
    t0 = time.time()
    points = []
    for budget in BUDGETS_MS:
        for load in LOADS_MBPS:
            p = point(load, budget, rate, args.duration_s, args.warmup_s, args.seeds, sizes)
            points.append(p)
            q = p["latency_quantiles_ms"] or [math.nan] * len(QUANTILES)
            print(f"L {budget or 'none':>4} ms, load {load:>3} Mbit/s ({p['cameras']} x PDP {p['pdp']:.2f}): "
                  f"delivered {p['delivered_mbps']:6.1f}, frame p50 {q[4]:7.1f} ms p95 {q[7]:7.1f} ms, "
                  f"frame loss {p['frame_loss']:.3f}, bytes discarded {p['byte_discard']:.3f}", flush=True)
    table = {
        "description": "frame-level uplink latency and loss of the NR cell vs offered load and "
                       "latency budget (benchmarks/policy_network_table.py)",
        "command": "python benchmarks/policy_network_table.py " + " ".join(argv or sys.argv[1:]),
        "loop_rate_mbps": round(rate, 4), "fps": FPS, "mtu_bytes": MTU,
        "duration_s": args.duration_s, "warmup_s": args.warmup_s, "seeds": args.seeds,
        "quantiles": list(QUANTILES), "loads_mbps": list(LOADS_MBPS), "budgets_ms": list(BUDGETS_MS),
        "points": points, "seconds": round(time.time() - t0, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(table, indent=1) + "\n")
    tmp.replace(args.out)
    print(f"wrote {args.out} in {table['seconds']} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
