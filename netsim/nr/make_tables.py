"""Generate the NR PHY lookup tables shipped as package data in ``netsim/nr/tables/``.

Run ``python tools/nr_tables.py`` to rewrite them, ``--check`` to verify that the shipped
files are what this script produces. Every number below is either transcribed from a 3GPP table
(TS 38.214 5.1.3.1, 5.1.3.2) or comes from the documented model in this file; nothing is fitted
at run time.

Files:

- ``mcs.json``: MCS tables 1-3 (TS 38.214 Tables 5.1.3.1-1/-2/-3) and the TBS table for small
  transport blocks (Table 5.1.3.2-1).
- ``eesm_beta.json``: EESM beta per MCS for each MCS table.
- ``bler_<table>.json``: code-block BLER vs SNR (dB) and code-block size for each MCS.

BLER model (one logistic curve per MCS and code-block size K, in SNR dB)::

    BLER(snr) = 1 / (1 + 9 * exp(a(K) * (snr - T10(mcs, K))))

so BLER(T10) = 10 %. Anchors:

- T10 at K = 2000 bits and at K = 24 bits for MCS table 1, MCS 3..28: the AWGN thresholds read from
  Sionna's PDSCH link-level tables (``T10_ANCHORS_TABLE_1`` below). MCS 0..2 have
  no anchor: T10 = 10 log10(2^SE - 1) + 1.0 dB (the Shannon-gap rule, gap measured at MCS 3),
  with the 24-bit penalty of MCS 3. The anchors are noisy (+-0.5 to 0.9 dB), so both anchor
  columns are made strictly increasing in MCS (at least 0.1 dB per step) and the short-block
  penalty is floored at 0.5 dB (short blocks never decode at a lower SNR than long ones).
- K dependence of T10: the finite-blocklength penalty scales as 1/sqrt(K) (normal
  approximation), so T10(K) = T10(2000) + penalty * (K^-1/2 - 2000^-1/2) / (24^-1/2 - 2000^-1/2).
- slope a(K) in 1/dB: long blocks fall from BLER 0.9 to 0.01 within ~1 dB (a = 6.8/dB at
  K = 2000), blocks of 24 bits within ~4 dB and 100 bits within ~3 dB; a(K) is the piecewise
  power law through those three points (log-log interpolation, extended beyond 2000 bits with
  the last segment).
- MCS tables 2 and 3: an entry with the same (Qm, R) as a table-1 entry reuses its anchors. New
  entries: QPSK below R = 120/1024 (table 3) use the Shannon-gap rule with MCS 0's gap and
  penalty; 256QAM (table 2) uses the Shannon-gap rule with the 64QAM gap at the same code rate
  (interpolated over table-1 64QAM entries) plus 0.5 dB for the denser constellation, and the
  64QAM short-block penalty at the same code rate.

Uplink: the PUSCH uses the same curves, indexed like the downlink by its MCS table's (Qm, R)
(TS 38.214 6.1.4.1: a CP-OFDM PUSCH, transform precoding disabled, uses Tables 5.1.3.1-1/-2/-3).
They are checked against Sionna's PUSCH link-level tables (NVlabs/sionna,
``src/sionna/sys/bler_tables/PUSCH_table1.json`` at commit
20d2bcaec8d43ec38f8ab6da6c390b5f84c237b4, category 0, table index 1; ``PUSCH_REFERENCE_TABLE_1``
below), whose MCS index follows TS 38.214 Table 6.1.4.1-1 (PUSCH with transform precoding):
its MCS 17..27 carry the (Qm, R) of table-1 MCS 18..28 (MCS 28 is reserved), so read by MCS
index it lies 0.3-1.6 dB above the curves here at MCS 17-27: one MCS step of these curves, not a
difference between the links. Matched by (Qm, R), the PUSCH and PDSCH link-level curves (the
latter ``PDSCH_table1.json`` beside it, category 1, at the same commit) agree within 0.2 dB wherever the reference grid resolves the 10 % point (86
points over 5 block sizes, mean difference 0.003 dB); against the PUSCH entries, the 24-bit
anchors above are within 0.25 dB and the 2000-bit ones inside the reference's bracket
(``pusch_reference_deviations``).

EESM beta: MCS table 1 uses the values of the reference (as in Sionna's eesm_beta_table.json).
For other tables, an entry with a table-1 (Qm, R) twin reuses its beta; otherwise beta comes from
a per-modulation log-linear fit of beta against R over table-1 entries (QPSK extrapolated to low
rates); 256QAM is the 64QAM fit times the mean 16QAM->64QAM ratio at equal code rate, which
extrapolates the observed growth of beta with constellation order.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path
from typing import Any

TABLES_DIR = Path(__file__).with_name("tables")

# TS 38.214 Table 5.1.3.1-1 (64QAM): (Qm, R x 1024) for MCS 0..28.
MCS_TABLE_1: list[tuple[int, float]] = [
    (2, 120), (2, 157), (2, 193), (2, 251), (2, 308), (2, 379), (2, 449), (2, 526), (2, 602),
    (2, 679), (4, 340), (4, 378), (4, 434), (4, 490), (4, 553), (4, 616), (4, 658), (6, 438),
    (6, 466), (6, 517), (6, 567), (6, 616), (6, 666), (6, 719), (6, 772), (6, 822), (6, 873),
    (6, 910), (6, 948),
]
# TS 38.214 Table 5.1.3.1-2 (256QAM): MCS 0..27.
MCS_TABLE_2: list[tuple[int, float]] = (
    [(2, r) for r in (120, 193, 308, 449, 602)]
    + [(4, r) for r in (378, 434, 490, 553, 616, 658)]
    + [(6, r) for r in (466, 517, 567, 616, 666, 719, 772, 822, 873)]
    + [(8, r) for r in (682.5, 711, 754, 797, 841, 885, 916.5, 948)]
)
# TS 38.214 Table 5.1.3.1-3 (64QAM, low spectral efficiency): MCS 0..28.
MCS_TABLE_3: list[tuple[int, float]] = (
    [(2, r) for r in (30.0, 40, 50, 64, 78, 99, 120, 157, 193, 251, 308, 379, 449, 526, 602)]
    + [(4, r) for r in (340, 378, 434, 490, 553, 616)]
    + [(6, r) for r in (438, 466, 517, 567, 616, 666, 719, 772)]
)
MCS_TABLES: dict[str, list[tuple[int, float]]] = {
    "qam64": MCS_TABLE_1, "qam256": MCS_TABLE_2, "qam64_low_se": MCS_TABLE_3}
MCS_TABLE_SPEC = {
    "qam64": "TS 38.214 Table 5.1.3.1-1",
    "qam256": "TS 38.214 Table 5.1.3.1-2",
    "qam64_low_se": "TS 38.214 Table 5.1.3.1-3",
}

# TS 38.214 Table 5.1.3.2-1: TBS for N_info <= 3824.
TBS_SMALL_BITS = [
    24, 32, 40, 48, 56, 64, 72, 80, 88, 96, 104, 112, 120, 128, 136, 144, 152, 160, 168, 176,
    184, 192, 208, 224, 240, 256, 272, 288, 304, 320, 336, 352, 368, 384, 408, 432, 456, 480, 504,
    528, 552, 576, 608, 640, 672, 704, 736, 768, 808, 848, 888, 928, 984, 1032, 1064, 1128, 1160,
    1192, 1224, 1256, 1288, 1320, 1352, 1416, 1480, 1544, 1608, 1672, 1736, 1800, 1864, 1928,
    2024, 2088, 2152, 2216, 2280, 2408, 2472, 2536, 2600, 2664, 2728, 2792, 2856, 2976, 3104,
    3240, 3368, 3496, 3624, 3752, 3824,
]

# EESM beta, MCS table 1, MCS 0..28 (reference; as in Sionna's eesm_beta_table.json).
BETA_TABLE_1 = [
    1.60, 1.61, 1.63, 1.65, 1.67, 1.70, 1.73, 1.76, 1.79, 1.82, 3.97, 4.27, 4.71, 5.16, 5.66,
    6.16, 6.50, 9.95, 10.97, 12.92, 14.96, 17.06, 19.33, 21.85, 24.51, 27.14, 29.94, 32.05, 34.28,
]

# AWGN SNR (dB) at 10 % BLER, MCS table 1, MCS 3..28: (2000-bit blocks, 24-bit blocks).
T10_ANCHORS_TABLE_1 = {
    3: (-2.9, -1.0), 4: (-2.4, 0.1), 5: (-1.1, 0.9), 6: (0.5, 2.1), 7: (0.7, 3.0),
    8: (2.3, 3.8), 9: (2.4, 4.4), 10: (2.8, 4.9), 11: (4.2, 5.5), 12: (4.5, 6.5),
    13: (6.0, 7.7), 14: (6.2, 8.2), 15: (7.8, 9.9), 16: (7.8, 10.0), 17: (8.7, 10.9),
    18: (9.7, 11.7), 19: (10.0, 12.7), 20: (11.6, 12.7), 21: (12.2, 14.0), 22: (13.4, 14.0),
    23: (14.3, 15.5), 24: (14.9, 15.7), 25: (16.5, 18.3), 26: (17.0, 18.3), 27: (18.3, 18.1),
    28: (19.0, 18.2),
}
# Sionna's PUSCH BLER tables (see the module docstring), AWGN, read per PUSCH MCS index i (TS 38.214
# Table 6.1.4.1-1): i -> (Qm, R x 1024, SNR dB at 10 % BLER for 24-bit blocks, and the two SNR
# grid points (dB) between which 2000-bit blocks cross 10 %). The reference grid steps by
# 25/14 = 1.79 dB from -5 dB; the 24-bit point interpolates log(BLER) linearly between the grid
# points around 10 %; long blocks fall from ~1 to ~0 within one step, hence a bracket.
PUSCH_REFERENCE_TABLE_1: dict[int, tuple[int, int, float, float, float]] = {
    3: (2, 251, -1.03, -3.21, -1.43), 4: (2, 308, 0.21, -3.21, -1.43),
    5: (2, 379, 0.96, -1.43, 0.36), 6: (2, 449, 2.15, 0.36, 2.14), 7: (2, 526, 2.96, 0.36, 2.14),
    8: (2, 602, 3.79, 2.14, 3.93), 9: (2, 679, 4.33, 2.14, 3.93), 10: (4, 340, 4.91, 2.14, 3.93),
    11: (4, 378, 5.47, 3.93, 5.71), 12: (4, 434, 6.55, 3.93, 5.71),
    13: (4, 490, 7.76, 5.71, 7.50), 14: (4, 553, 8.15, 5.71, 7.50),
    15: (4, 616, 9.92, 7.50, 9.29), 16: (4, 658, 9.90, 7.50, 9.29),
    17: (6, 466, 11.73, 9.29, 11.07), 18: (6, 517, 12.68, 9.29, 11.07),
    19: (6, 567, 12.69, 11.07, 12.86), 20: (6, 616, 14.04, 11.07, 12.86),
    21: (6, 666, 13.99, 12.86, 14.64), 22: (6, 719, 15.65, 12.86, 14.64),
    23: (6, 772, 15.56, 14.64, 16.43), 24: (6, 822, 18.29, 16.43, 18.21),
    25: (6, 873, 18.29, 16.43, 18.21), 26: (6, 910, 18.31, 18.21, 20.00),
    27: (6, 948, 18.18, 18.21, 20.00),
}
MIN_STEP_DB = 0.1  # strict increase of thresholds with MCS
MIN_SHORT_BLOCK_PENALTY_DB = 0.5
QAM256_EXTRA_GAP_DB = 0.5

# Slope anchors: (code-block bits, dB needed to fall from BLER 0.9 to 0.01).
LOGIT_SPAN = math.log(9.0) + math.log(99.0)  # logit(0.9) - logit(0.01) = 6.79
SLOPE_ANCHORS = [(24, 4.0), (100, 3.0), (2000, 1.0)]

# Lookup grids.
SNR_MIN_DB = -20.0
SNR_MAX_DB = 40.0
SNR_STEP_DB = 0.1
CBS_GRID_BITS = [24, 40, 64, 100, 160, 256, 400, 640, 1000, 1600, 2560, 4000, 6400, 8448]
BLER_FLOOR = 1e-7  # below this a curve is stored as 0, above 1 - this as 1


def _spectral_efficiency(qm: int, rate_x1024: float) -> float:
    return qm * rate_x1024 / 1024.0


def _round_half_up(x: float, digits: int) -> float:
    """Rounding as the 3GPP tables print it (7.40625 -> 7.4063), not Python's half-even."""
    return float(Decimal(x).quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP))


def _shannon_snr_db(se: float) -> float:
    return 10.0 * math.log10(2.0**se - 1.0)


def _interp(x: float, xs: list[float], ys: list[float]) -> float:
    """Linear interpolation, clamped at the ends."""
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    for i in range(1, len(xs)):
        if x <= xs[i]:
            f = (x - xs[i - 1]) / (xs[i] - xs[i - 1])
            return ys[i - 1] + f * (ys[i] - ys[i - 1])
    return ys[-1]


def _make_increasing(values: list[float], min_step: float) -> list[float]:
    out = list(values)
    for i in range(1, len(out)):
        out[i] = max(out[i], out[i - 1] + min_step)
    return out


def table1_anchors() -> tuple[list[float], list[float]]:
    """T10 (dB) at 2000 and at 24 bits for MCS table 1, MCS 0..28, monotone."""
    gap3 = T10_ANCHORS_TABLE_1[3][0] - _shannon_snr_db(_spectral_efficiency(*MCS_TABLE_1[3]))
    pen3 = T10_ANCHORS_TABLE_1[3][1] - T10_ANCHORS_TABLE_1[3][0]
    t2000: list[float] = []
    t24: list[float] = []
    for mcs, (qm, r) in enumerate(MCS_TABLE_1):
        if mcs in T10_ANCHORS_TABLE_1:
            a, b = T10_ANCHORS_TABLE_1[mcs]
        else:
            a = _shannon_snr_db(_spectral_efficiency(qm, r)) + gap3
            b = a + pen3
        t2000.append(a)
        t24.append(max(b, a + MIN_SHORT_BLOCK_PENALTY_DB))
    t2000 = _make_increasing(t2000, MIN_STEP_DB)
    t24 = [max(b, a + MIN_SHORT_BLOCK_PENALTY_DB) for a, b in zip(t2000, t24, strict=True)]
    return t2000, _make_increasing(t24, MIN_STEP_DB)


def anchors_for(table: str) -> tuple[list[float], list[float]]:
    """T10 (dB) at 2000 and 24 bits for every MCS of ``table``."""
    t2000_1, t24_1 = table1_anchors()
    if table == "qam64":
        return t2000_1, t24_1
    twin = {entry: i for i, entry in enumerate(MCS_TABLE_1)}
    qam64 = [(r, i) for i, (qm, r) in enumerate(MCS_TABLE_1) if qm == 6]
    r64 = [float(r) for r, _ in qam64]
    gap64 = [
        t2000_1[i] - _shannon_snr_db(_spectral_efficiency(6, r)) for r, i in qam64
    ]
    pen64 = [t24_1[i] - t2000_1[i] for _, i in qam64]
    gap0 = t2000_1[0] - _shannon_snr_db(_spectral_efficiency(*MCS_TABLE_1[0]))
    pen0 = t24_1[0] - t2000_1[0]
    t2000: list[float] = []
    t24: list[float] = []
    for qm, r in MCS_TABLES[table]:
        se = _spectral_efficiency(qm, r)
        if (qm, r) in twin:
            i = twin[(qm, r)]
            a, b = t2000_1[i], t24_1[i]
        elif qm == 8:
            a = _shannon_snr_db(se) + _interp(r, r64, gap64) + QAM256_EXTRA_GAP_DB
            b = a + _interp(r, r64, pen64)
        elif qm == 2:
            a = _shannon_snr_db(se) + gap0
            b = a + pen0
        else:  # pragma: no cover - every other entry has a table-1 twin
            raise ValueError(f"no BLER model for Qm={qm}, R={r}/1024 in {table}")
        t2000.append(a)
        t24.append(b)
    t2000 = _make_increasing(t2000, MIN_STEP_DB)
    t24 = [max(b, a + MIN_SHORT_BLOCK_PENALTY_DB) for a, b in zip(t2000, t24, strict=True)]
    return t2000, _make_increasing(t24, MIN_STEP_DB)


@dataclass(frozen=True)
class PuschCheck:
    """One entry of ``PUSCH_REFERENCE_TABLE_1`` against the table-1 curves of the same (Qm, R)."""

    pusch_mcs: int  # index in the reference (TS 38.214 Table 6.1.4.1-1)
    mcs: int  # table-1 MCS with the same (Qm, R)
    anchor_24_minus_reference_db: float  # T10_ANCHORS_TABLE_1 at 24 bits minus the reference
    model_24_minus_reference_db: float  # shipped curve (monotone, floored) minus the reference
    model_2000_db: float  # shipped curve's T10 at 2000 bits
    reference_2000_db: tuple[float, float]  # the reference's bracket at 2000 bits


def pusch_reference_deviations() -> list[PuschCheck]:
    """Each PUSCH reference entry against the table-1 MCS of the same (Qm, R), which is the curve
    a PUSCH at that (Qm, R) decodes with (MCS 0..2 have no reference entry)."""
    t2000, t24 = table1_anchors()
    twin = {entry: i for i, entry in enumerate(MCS_TABLE_1)}
    out = []
    for i, (qm, r, ref24, lo, hi) in sorted(PUSCH_REFERENCE_TABLE_1.items()):
        mcs = twin[(qm, r)]
        raw24 = T10_ANCHORS_TABLE_1[mcs][1]
        out.append(PuschCheck(i, mcs, round(raw24 - ref24, 3), round(t24[mcs] - ref24, 3),
                              round(t2000[mcs], 3), (lo, hi)))
    return out


def slope_per_db(cbs_bits: float) -> float:
    """Logistic slope a(K) (1/dB) for code blocks of ``cbs_bits`` bits."""
    pts = [(math.log(k), math.log(LOGIT_SPAN / span)) for k, span in SLOPE_ANCHORS]
    x = math.log(max(cbs_bits, SLOPE_ANCHORS[0][0]))
    if x <= pts[1][0]:
        (x0, y0), (x1, y1) = pts[0], pts[1]
    else:
        (x0, y0), (x1, y1) = pts[1], pts[2]
    return math.exp(y0 + (x - x0) * (y1 - y0) / (x1 - x0))


def threshold_db(t2000: float, t24: float, cbs_bits: float) -> float:
    """T10 for code blocks of ``cbs_bits`` bits (1/sqrt(K) finite-length penalty)."""
    w = (cbs_bits**-0.5 - 2000**-0.5) / (24**-0.5 - 2000**-0.5)
    return t2000 + w * (t24 - t2000)


def bler(snr_db: float, t10_db: float, slope: float) -> float:
    """The logistic code-block BLER curve, 10 % at ``t10_db``."""
    z = slope * (snr_db - t10_db)
    if z > 700:
        return 0.0
    return 1.0 / (1.0 + 9.0 * math.exp(z))


def _fit_loglinear(xs: list[float], ys: list[float]) -> tuple[float, float]:
    """Least-squares fit of log(y) = a + b x."""
    n = len(xs)
    ly = [math.log(y) for y in ys]
    mx, my = sum(xs) / n, sum(ly) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    b = sum((x - mx) * (y - my) for x, y in zip(xs, ly, strict=True)) / sxx
    return my - b * mx, b


def betas_for(table: str) -> list[float]:
    """EESM beta per MCS of ``table``."""
    if table == "qam64":
        return list(BETA_TABLE_1)
    twin = {entry: BETA_TABLE_1[i] for i, entry in enumerate(MCS_TABLE_1)}
    fits = {}
    for qm in (2, 4, 6):
        pts = [(r / 1024, BETA_TABLE_1[i]) for i, (q, r) in enumerate(MCS_TABLE_1) if q == qm]
        fits[qm] = _fit_loglinear([p[0] for p in pts], [p[1] for p in pts])

    def fit(qm: int, rate: float) -> float:
        a, b = fits[qm]
        return math.exp(a + b * rate)

    grid = [0.4 + 0.05 * i for i in range(6)]  # code rates covered by both 16QAM and 64QAM
    ratio = sum(fit(6, r) / fit(4, r) for r in grid) / len(grid)
    out = []
    for qm, r in MCS_TABLES[table]:
        if (qm, r) in twin:
            out.append(twin[(qm, r)])
        elif qm == 8:
            out.append(round(fit(6, r / 1024) * ratio, 2))
        else:
            out.append(round(fit(qm, r / 1024), 2))
    return out


def _fmt(x: float) -> float:
    return float(f"{x:.4g}")


def build() -> dict[str, Any]:
    """Every table file name -> its JSON content."""
    files: dict[str, Any] = {}
    files["mcs.json"] = {
        "description": "NR MCS tables (Qm, target code rate R x 1024, spectral efficiency) and "
        "the TBS table for N_info <= 3824",
        "source": {**MCS_TABLE_SPEC, "tbs_small_bits": "TS 38.214 Table 5.1.3.2-1"},
        "tables": {
            name: [
                {"mcs": i, "qm": qm, "rate_x1024": int(r) if float(r).is_integer() else r,
                 "spectral_efficiency":
                 _round_half_up(_spectral_efficiency(qm, r), 4)}
                for i, (qm, r) in enumerate(entries)
            ]
            for name, entries in MCS_TABLES.items()
        },
        "tbs_small_bits": TBS_SMALL_BITS,
    }
    files["eesm_beta.json"] = {
        "description": "EESM beta per MCS; qam64 as in the reference (Sionna's table), others "
        "from the model documented in netsim/nr/make_tables.py",
        "betas": {name: betas_for(name) for name in MCS_TABLES},
    }
    n_grid = round((SNR_MAX_DB - SNR_MIN_DB) / SNR_STEP_DB) + 1
    for name in MCS_TABLES:
        t2000, t24 = anchors_for(name)
        curves = []
        for mcs in range(len(MCS_TABLES[name])):
            per_k = []
            for k in CBS_GRID_BITS:
                t10 = threshold_db(t2000[mcs], t24[mcs], k)
                a = slope_per_db(k)
                values = [bler(SNR_MIN_DB + i * SNR_STEP_DB, t10, a) for i in range(n_grid)]
                first = next(i for i, v in enumerate(values) if v < 1.0 - BLER_FLOOR)
                last = max(i for i, v in enumerate(values) if v > BLER_FLOOR)
                per_k.append({"i0": first, "bler": [_fmt(v) for v in values[first : last + 1]]})
            curves.append(per_k)
        files[f"bler_{name}.json"] = {
            "description": f"code-block BLER vs SNR for {MCS_TABLE_SPEC[name]}; values before "
            "i0 are 1, after the stored run 0; model in netsim/nr/make_tables.py",
            "mcs_table": name,
            "snr_min_db": SNR_MIN_DB,
            "snr_step_db": SNR_STEP_DB,
            "snr_points": n_grid,
            "cbs_bits": CBS_GRID_BITS,
            "t10_db_at_2000_bits": [round(x, 3) for x in t2000],
            "t10_db_at_24_bits": [round(x, 3) for x in t24],
            "curves": curves,
        }
    return files


def _dump(content: Any) -> str:
    return json.dumps(content, separators=(",", ":")) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="verify the shipped tables instead of writing them")
    args = parser.parse_args(argv)
    stale = []
    for name, content in build().items():
        path = TABLES_DIR / name
        text = _dump(content)
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            TABLES_DIR.mkdir(exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(text)
            tmp.replace(path)
    if stale:
        print(f"stale tables (run python tools/nr_tables.py): {', '.join(stale)}",
              file=sys.stderr)
        return 1
    return 0
