"""Calibration of the NR cell: saturated uplink capacity and throughput/latency/loss vs load.

The two measurements and their results: docs/netsim.md, "Calibration". Writes
results/bench/netsim_calibration.{md,csv,png}; points above capacity depend on ``--duration-s``.

    python benchmarks/netsim_calibration.py [--duration-s 3] [--seeds 3]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from netsim.standalone import run_uplink_cameras  # noqa: E402
from scenario.nr import CALIBRATED_UL_CAPACITY_MBPS, NrConfig  # noqa: E402

LOADS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2)
SWEEP_UES = 21
CAPACITY_UES, CAPACITY_RATE_MBPS = 36, 8.5


def measure_capacity(duration_s: float, seeds: int) -> tuple[float, list[float]]:
    """Mean and per-seed saturated uplink IP throughput (Mbps) of the default NrConfig."""
    values = [run_uplink_cameras(CAPACITY_UES, CAPACITY_RATE_MBPS, duration_s,
                                 seed=s)["ul_throughput_mbps"] for s in range(seeds)]
    return float(np.mean(values)), values


def sweep(duration_s: float, seeds: int) -> list[dict]:
    rows = []
    for load in LOADS:
        rate = load * CALIBRATED_UL_CAPACITY_MBPS / SWEEP_UES
        runs = [run_uplink_cameras(SWEEP_UES, rate, duration_s, seed=s) for s in range(seeds)]
        sent = sum(r["sent_packets"] for r in runs)
        lost = {c: sum(r["lost_packets"][c] for r in runs) for c in runs[0]["lost_packets"]}
        rows.append({
            "load_percent": round(100 * load),
            "rate_mbps_per_ue": round(rate, 3),
            "offered_mbps": float(np.mean([r["offered_mbps"] for r in runs])),
            "throughput_mbps": float(np.mean([r["ul_throughput_mbps"] for r in runs])),
            "latency_p50_ms": float(np.mean([r["ip_latency_ms"]["p50"] for r in runs])),
            "latency_p99_ms": float(np.mean([r["ip_latency_ms"]["p99"] for r in runs])),
            "loss_ratio": sum(lost.values()) / sent if sent else 0.0,
            "lost_buffer_overflow": lost["buffer_overflow"],
            "lost_delay_budget": lost["delay_budget"],
            "lost_channel": lost["channel"],
            "sent_packets": sent,
            "bler_ul": float(np.mean([r["bler_ul"] for r in runs])),
            "prb_utilisation_ul": float(np.mean([r["prb_utilisation_ul"] for r in runs])),
        })
        print(f"load {rows[-1]['load_percent']:>3} %: {rows[-1]['throughput_mbps']:.1f} Mbps, "
              f"p50 {rows[-1]['latency_p50_ms']:.1f} ms, p99 {rows[-1]['latency_p99_ms']:.1f} "
              f"ms, loss {rows[-1]['loss_ratio']:.4f}", flush=True)
    return rows


def plot(rows: list[dict], capacity_mbps: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    load = [r["load_percent"] for r in rows]
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].plot(load, [r["offered_mbps"] for r in rows], "k--", label="offered")
    ax[0].plot(load, [r["throughput_mbps"] for r in rows], "o-", label="delivered")
    ax[0].axhline(capacity_mbps, color="grey", lw=0.8, label=f"capacity {capacity_mbps:.1f}")
    ax[0].set(xlabel="offered load (% of 178.6 Mbps)", ylabel="UL IP throughput (Mbps)")
    ax[0].legend()
    ax[1].semilogy(load, [r["latency_p50_ms"] for r in rows], "o-", label="p50")
    ax[1].semilogy(load, [r["latency_p99_ms"] for r in rows], "s-", label="p99")
    ax[1].set(xlabel="offered load (%)", ylabel="IP packet latency (ms)")
    ax[1].legend()
    ax[2].plot(load, [100 * r["loss_ratio"] for r in rows], "o-")
    ax[2].set(xlabel="offered load (%)", ylabel="packets lost (%)")
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle(f"netsim NR, {SWEEP_UES} uplink cameras, reference InF-SL hall")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=3.0, help="simulated s per run")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per point (0..n-1)")
    parser.add_argument("--capacity-seeds", type=int, default=5, help="seeds for the capacity")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "results" / "bench")
    args = parser.parse_args(argv)

    cfg = NrConfig()
    capacity, per_seed = measure_capacity(args.duration_s, args.capacity_seeds)
    print(f"capacity {capacity:.1f} Mbps (seeds {[round(v, 1) for v in per_seed]})", flush=True)
    rows = sweep(args.duration_s, args.seeds)

    args.out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = args.out_dir / "netsim_calibration.csv"
    with csv_path.with_suffix(".tmp").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    csv_path.with_suffix(".tmp").replace(csv_path)
    plot(rows, capacity, args.out_dir / "netsim_calibration.png")
    lines = [
        "# netsim NR calibration",
        "",
        f"Config: n_prb={cfg.n_prb}, slot = {cfg.dl_ctrl_symbols} PDCCH + {cfg.dl_data_symbols} "
        f"PDSCH + {cfg.guard_symbols} guard + {cfg.ul_data_symbols} PUSCH + "
        f"{cfg.ul_ctrl_symbols} PUCCH symbols ({cfg.dmrs_symbols} DMRS per data region), "
        f"MCS table {cfg.mcs_table}, scheduler {cfg.scheduler}, {args.duration_s:g} s per run.",
        "",
        f"Saturated UL capacity ({CAPACITY_UES} cameras x {CAPACITY_RATE_MBPS} Mbps, seeds "
        f"0-{args.capacity_seeds - 1}): **{capacity:.1f} Mbps** (target "
        f"{CALIBRATED_UL_CAPACITY_MBPS}; per seed {', '.join(f'{v:.1f}' for v in per_seed)}).",
        "",
        f"Load sweep: {SWEEP_UES} cameras, mean of seeds 0-{args.seeds - 1}.",
        "",
        "| load % | Mbps/UE | offered Mbps | delivered Mbps | p50 ms | p99 ms | loss % "
        "| overflow | budget | channel | UL BLER | PRB use |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['load_percent']} | {r['rate_mbps_per_ue']:.2f} | {r['offered_mbps']:.1f} | "
            f"{r['throughput_mbps']:.1f} | {r['latency_p50_ms']:.1f} | "
            f"{r['latency_p99_ms']:.1f} | {100 * r['loss_ratio']:.2f} | "
            f"{r['lost_buffer_overflow']} | {r['lost_delay_budget']} | {r['lost_channel']} | "
            f"{r['bler_ul']:.3f} | {r['prb_utilisation_ul']:.2f} |")
    lines += ["", "![throughput, latency and loss vs load](netsim_calibration.png)", ""]
    md = args.out_dir / "netsim_calibration.md"
    md.with_suffix(".tmp").write_text("\n".join(lines))
    md.with_suffix(".tmp").replace(md)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
