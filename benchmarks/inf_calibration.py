"""Large-scale calibration of the multi-gNB InF hall: coupling loss and geometry SINR CDFs.

Per TR 38.901 sub-scenario (InF-SL, DL, SH, DH) the Table 7.8-7 layout: the sub-scenario's hall
with 18 gNBs on the 6 x 3 lattice, UEs dropped uniformly at 1.5 m, 3.5 GHz, isotropic antennas,
serving gNB by strongest RSRP. Measured with netsim (netsim.nr.layout, large_scale,
interference): the serving link's coupling loss and the wideband DL geometry SINR (reuse 1), plus
DL reuse 3 and the UL geometry SINR under open-loop power control (no reference for those).

No numeric 3GPP calibration result was available (TR 38.901 7.8.4 points to R1-1909704, a
workbook not found in any stored copy), so the references are independent cross-checks:
- coupling loss: the exact CDF of the strongest of 18 independent links, integrated over a grid
  of UE positions (pitch D / 20): P(CL <= x) = 1 - mean over positions of prod_b (1 - F_b(x)), with
  F_b = P_LOS N((x - PL_LOS) / 4.3) + (1 - P_LOS) N((x - PL_NLOS) / sigma_NLOS);
- DL geometry SINR: a Monte Carlo with every link drawn independently (LOS by its probability,
  shadowing i.i.d.), no spatial fields, computed here without the netsim interference code.
Both use the Table 7.4.1-1 / 7.4.2-1 functions of netsim.nr.channel, which the unit tests check
by hand; they check everything built on them (fields, drops, association, interference sums).

Writes results/bench/inf_calibration.{md,csv,png}.

    python benchmarks/inf_calibration.py [--drops 10] [--ues-per-gnb 90]
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from fabric.seeding import rng as named_rng  # noqa: E402
from netsim.nr import interference as itf  # noqa: E402
from netsim.nr.channel import inf_los_probability, inf_pathloss_db  # noqa: E402
from netsim.nr.large_scale import InfLinks  # noqa: E402
from netsim.nr.layout import InfLayout, InfSubScenario, drop_ues  # noqa: E402

SUBS = ("SL", "DL", "SH", "DH")
CARRIER_HZ = 3.5e9
# Link budget of Table 7.8-7 as Sionna's calibration driver (test/unit/channel/
# tr38901_calibration.py, InFCalibrationConfig) and the MATLAB InF model of
# ClanceyWong/Flexible-3GPP-Channel-Modeling-and-Calibration-with-Spatial-Consistency
# (+scenarios/InF.m) both read it: 30 dBm per BS over 100 MHz, UT noise figure 9 dB, one
# isotropic element at each end. Geometry SINR is interference-limited, so these move only the
# lowest percentiles of the large halls; the coupling loss does not depend on them.
GNB_TX_POWER_DBM = 30.0
BANDWIDTH_HZ = 100e6
UE_NOISE_FIGURE_DB = 9.0
# UL: the study's carrier (scenario.nr defaults: 468 PRB at 15 kHz, gNB NF 5 dB, P_CMAX 23 dBm)
# and the power control defaults of hall.inf_layout (P0 -90 dBm per PRB, alpha 1).
UL_PRB, PRB_HZ, GNB_NOISE_FIGURE_DB, P_CMAX_DBM = 468, 180e3, 5.0, 23.0
UL_P0_DBM, UL_ALPHA = -90.0, 1.0
PERCENTILES = tuple(range(1, 100))
# Quadrature of the semi-analytic reference: UE positions on a grid of pitch D / 20 (1 m in the
# 120 x 60 m halls, 2.5 m in the 300 x 150 m ones: 7,200 points each).
GRID_PER_PITCH = 20
REPORTED = (5, 50, 95)


def measure(sub: str, drops: int, ues_per_gnb: int) -> dict[str, np.ndarray]:
    """netsim's samples over ``drops`` independent drops (seed = drop number)."""
    out: dict[str, list[np.ndarray]] = {k: [] for k in (
        "coupling_loss", "dl_sinr", "dl_sinr_reuse3", "ul_sinr", "ul_sinr_reuse3", "los",
        "los_probability")}
    for drop in range(drops):
        layout = InfLayout.calibration(sub)
        reuse3 = InfLayout.calibration(sub, reuse=3)
        n = ues_per_gnb * layout.n_gnb
        ue = drop_ues(n, layout.hall_length_m, layout.hall_width_m,
                      named_rng(drop, f"inf-calibration/{sub}/drop"), layout.gnb_positions_m)
        links = InfLinks(layout, ue, CARRIER_HZ, seed=drop, stream_prefix=f"inf-calibration/{sub}")
        cl = links.coupling_loss_db
        serving = itf.serving_gnb(cl)
        cl_serving = itf.serving_values(cl, serving)
        out["coupling_loss"].append(cl_serving)
        out["los"].append(links.los.ravel())
        out["los_probability"].append(links.los_probability.ravel())
        for key, lay in (("", layout), ("_reuse3", reuse3)):
            reuse = lay.reuse
            out["dl_sinr" + key].append(itf.dl_geometry_sinr_db(
                cl, serving, GNB_TX_POWER_DBM, lay.groups, BANDWIDTH_HZ, UE_NOISE_FIGURE_DB,
                reuse))
            n_prb = UL_PRB // reuse
            power = itf.ul_power_dbm(cl_serving, n_prb, UL_P0_DBM, UL_ALPHA, 0, P_CMAX_DBM)
            co = itf.co_scheduled_ues(serving, lay.n_gnb,
                                      named_rng(drop, f"inf-calibration/{sub}/co-scheduled"))
            out["ul_sinr" + key].append(itf.ul_geometry_sinr_db(
                cl, serving, power, lay.groups, n_prb, PRB_HZ, GNB_NOISE_FIGURE_DB, co))
    return {k: np.concatenate(v) for k, v in out.items()}


def _normal_cdf(z: np.ndarray) -> np.ndarray:
    """Vectorised standard normal CDF (Abramowitz and Stegun 7.1.26, |error| < 1.5e-7)."""
    x = np.abs(z) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (
        -1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-x * x)
    return 0.5 * (1.0 + np.sign(z) * erf)


def _link_parameters(sub: InfSubScenario, layout: InfLayout, ue: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P_LOS, PL_LOS and PL_NLOS of every (UE, gNB) pair."""
    gnb = layout.gnb_positions_m
    delta = ue[:, None, :] - gnb[None, :, :]
    d2d = np.hypot(delta[..., 0], delta[..., 1])
    d3d = np.sqrt(d2d**2 + delta[..., 2] ** 2)
    p_los = inf_los_probability(sub.name, d2d, sub.clutter_density, sub.clutter_size_m,
                                sub.clutter_height_m, gnb[None, :, 2], ue[:, None, 2])
    return (p_los, inf_pathloss_db(sub.name, d3d, CARRIER_HZ, True),
            inf_pathloss_db(sub.name, d3d, CARRIER_HZ, False))


def reference_coupling_loss(sub_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Semi-analytic CDF of the serving coupling loss: (x in dB, P(CL <= x))."""
    layout = InfLayout.calibration(sub_name)
    sub = layout.sub_scenario
    step = sub.bs_spacing_m / GRID_PER_PITCH
    gx, gy = np.meshgrid(np.arange(step / 2, layout.hall_length_m, step),
                         np.arange(step / 2, layout.hall_width_m, step), indexing="ij")
    ue = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 1.5)])
    near = np.hypot(ue[:, None, 0] - layout.gnb_positions_m[None, :, 0],
                    ue[:, None, 1] - layout.gnb_positions_m[None, :, 1]).min(axis=1) < 1.0
    ue = ue[~near]
    x = np.arange(30.0, 130.0, 0.25)
    none_below = np.zeros(len(x))
    for start in range(0, len(ue), 200):
        p_los, pl_los, pl_nlos = _link_parameters(sub, layout, ue[start:start + 200])
        f = (p_los[..., None] * _normal_cdf((x - pl_los[..., None]) / sub.los_shadowing_std_db)
             + (1 - p_los[..., None]) * _normal_cdf(
                 (x - pl_nlos[..., None]) / sub.nlos_shadowing_std_db))
        none_below += np.prod(1.0 - f, axis=1).sum(axis=0)
    return x, 1.0 - none_below / len(ue)


def reference_dl_sinr(sub_name: str, n: int, seed: int) -> np.ndarray:
    """DL geometry SINR with every link drawn independently (no fields), dB."""
    layout = InfLayout.calibration(sub_name)
    sub = layout.sub_scenario
    gen = np.random.default_rng(seed)
    ue = drop_ues(n, layout.hall_length_m, layout.hall_width_m, gen, layout.gnb_positions_m)
    p_los, pl_los, pl_nlos = _link_parameters(sub, layout, ue)
    los = gen.random(p_los.shape) < p_los
    sigma = np.where(los, sub.los_shadowing_std_db, sub.nlos_shadowing_std_db)
    cl = np.where(los, pl_los, pl_nlos) + sigma * gen.standard_normal(p_los.shape)
    rx_mw = 10 ** ((GNB_TX_POWER_DBM - cl) / 10)
    best = rx_mw.max(axis=1)
    noise_mw = 10 ** ((-174.0 + UE_NOISE_FIGURE_DB + 10 * math.log10(BANDWIDTH_HZ)) / 10)
    return 10 * np.log10(best / (rx_mw.sum(axis=1) - best + noise_mw))


def cdf_percentile(x: np.ndarray, cdf: np.ndarray, p: float) -> float:
    return float(np.interp(p / 100, cdf, x))


def plot(results: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.6))
    colours = dict(zip(SUBS, ("C0", "C1", "C2", "C3"), strict=True))
    q = np.linspace(0, 1, 201)
    for sub, r in results.items():
        c = colours[sub]
        s = r["netsim"]
        ax[0].plot(np.quantile(s["coupling_loss"], q), q, color=c, label=f"InF-{sub} netsim")
        ax[0].plot(r["ref_cl_x"], r["ref_cl_cdf"], color=c, ls="--", lw=1,
                   label=f"InF-{sub} semi-analytic")
        ax[1].plot(np.quantile(s["dl_sinr"], q), q, color=c, label=f"InF-{sub} netsim")
        ax[1].plot(np.quantile(r["ref_dl_sinr"], q), q, color=c, ls="--", lw=1,
                   label=f"InF-{sub} independent links")
        ax[2].plot(np.quantile(s["dl_sinr_reuse3"], q), q, color=c, label=f"InF-{sub} DL reuse 3")
        ax[2].plot(np.quantile(s["ul_sinr"], q), q, color=c, ls=":",
                   label=f"InF-{sub} UL reuse 1")
    ax[0].set(xlabel="coupling loss, serving link (dB)", ylabel="CDF", xlim=(35, 100))
    ax[1].set(xlabel="DL geometry SINR, reuse 1 (dB)", ylabel="CDF", xlim=(-10, 35))
    ax[2].set(xlabel="geometry SINR (dB)", ylabel="CDF", xlim=(-15, 45))
    ax[2].set_title(f"UL: P0 {UL_P0_DBM:g} dBm, alpha {UL_ALPHA:g}, one UE per other cell",
                    fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle("TR 38.901 InF calibration layouts (Table 7.8-7), 18 gNBs, 3.5 GHz: netsim "
                 "(solid) and independent cross-checks (dashed)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drops", type=int, default=10, help="independent drops per sub-scenario")
    parser.add_argument("--ues-per-gnb", type=int, default=90, help="UEs per gNB in each drop")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "results" / "bench")
    args = parser.parse_args(argv)

    results: dict[str, dict] = {}
    rows: list[dict] = []
    for sub in SUBS:
        netsim = measure(sub, args.drops, args.ues_per_gnb)
        x, cdf = reference_coupling_loss(sub)
        ref_sinr = reference_dl_sinr(sub, len(netsim["dl_sinr"]), seed=1000 + SUBS.index(sub))
        results[sub] = {"netsim": netsim, "ref_cl_x": x, "ref_cl_cdf": cdf,
                        "ref_dl_sinr": ref_sinr}
        for p in PERCENTILES:
            rows.append({
                "sub_scenario": f"InF-{sub}", "percentile": p,
                "coupling_loss_db": float(np.percentile(netsim["coupling_loss"], p)),
                "coupling_loss_reference_db": cdf_percentile(x, cdf, p),
                "dl_sinr_db": float(np.percentile(netsim["dl_sinr"], p)),
                "dl_sinr_reference_db": float(np.percentile(ref_sinr, p)),
                "dl_sinr_reuse3_db": float(np.percentile(netsim["dl_sinr_reuse3"], p)),
                "ul_sinr_db": float(np.percentile(netsim["ul_sinr"], p)),
                "ul_sinr_reuse3_db": float(np.percentile(netsim["ul_sinr_reuse3"], p)),
            })
        print(f"InF-{sub}: {len(netsim['coupling_loss'])} UEs", flush=True)

    args.out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = args.out_dir / "inf_calibration.csv"
    with csv_path.with_suffix(".tmp").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    csv_path.with_suffix(".tmp").replace(csv_path)
    plot(results, args.out_dir / "inf_calibration.png")

    def at(sub: str, p: int) -> dict:
        return next(r for r in rows if r["sub_scenario"] == f"InF-{sub}" and r["percentile"] == p)

    n = args.drops * args.ues_per_gnb * 18
    lines = [
        "# InF multi-gNB calibration (TR 38.901 Table 7.8-7)",
        "",
        f"18 gNBs per sub-scenario hall, {args.drops} drops x {args.ues_per_gnb * 18} UEs "
        f"({n} UEs), 3.5 GHz, {GNB_TX_POWER_DBM:g} dBm per gNB over {BANDWIDTH_HZ / 1e6:g} MHz, "
        f"UE NF {UE_NOISE_FIGURE_DB:g} dB, isotropic antennas, serving gNB by RSRP.",
        "References: coupling loss, semi-analytic CDF of the best of 18 independent links over "
        "a grid of UE positions (pitch D / 20); DL SINR, Monte Carlo with independent links (same "
        "UE count).",
        "",
        "| sub-scenario | metric | 5 % netsim / ref | 50 % netsim / ref | 95 % netsim / ref |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for sub in SUBS:
        for label, key in (("coupling loss (dB)", "coupling_loss"),
                           ("DL geometry SINR (dB)", "dl_sinr")):
            cells = [f"{at(sub, p)[key + '_db']:.1f} / {at(sub, p)[key + '_reference_db']:.1f}"
                     for p in REPORTED]
            lines.append(f"| InF-{sub} | {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"No reference (netsim only): DL reuse 3, UL reuse 1 and 3 (P0 {UL_P0_DBM:g} dBm, "
        f"alpha {UL_ALPHA:g}, {UL_PRB} PRB / reuse, one co-scheduled UE per other cell).",
        "",
        "| sub-scenario | DL reuse 3 5/50/95 % | UL reuse 1 5/50/95 % | UL reuse 3 5/50/95 % "
        "| LOS links netsim / E[P_LOS] |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for sub in SUBS:
        s = results[sub]["netsim"]
        trip = [" / ".join(f"{at(sub, p)[k]:.1f}" for p in REPORTED)
                for k in ("dl_sinr_reuse3_db", "ul_sinr_db", "ul_sinr_reuse3_db")]
        lines.append(f"| InF-{sub} | {trip[0]} | {trip[1]} | {trip[2]} | "
                     f"{s['los'].mean():.3f} / {s['los_probability'].mean():.3f} |")
    lines += ["", "![coupling loss and geometry SINR CDFs](inf_calibration.png)", ""]
    md = args.out_dir / "inf_calibration.md"
    md.with_suffix(".tmp").write_text("\n".join(lines))
    md.with_suffix(".tmp").replace(md)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
