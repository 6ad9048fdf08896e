"""PHY abstraction: MCS tables, transport block size, LDPC segmentation, EESM and BLER lookup.

Everything a system-level simulator needs to decide whether one transport block (TB) is decoded,
without simulating bits: the TB size from TS 38.214 5.1.3.2, its LDPC code blocks from TS 38.212
5.2.2, the effective SINR of a frequency-selective allocation (EESM) and the code-block BLER of
an AWGN curve at that SINR. Lookup tables are package data (``tables/*.json``, written by
``make_tables.py``) so link-level curves can replace the model curves without touching code.
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from scenario.nr import McsTableName

# Beside the package's sources (a compiled build of this module lives elsewhere: fabric.native).
TABLES_DIR = Path(str(resources.files("netsim.nr") / "tables"))

# TS 38.212 Table 5.3.2-1: LDPC lifting sizes Z = a * 2^j <= 384, a in {2,3,5,7,9,11,13,15}.
LIFTING_SIZES = sorted(
    {a * 2**j for a in (2, 3, 5, 7, 9, 11, 13, 15) for j in range(8) if a * 2**j <= 384}
)


@dataclass(frozen=True, slots=True)
class McsEntry:
    """One MCS: modulation order Qm, target code rate R (not x1024), spectral efficiency."""

    qm: int
    rate: float
    spectral_efficiency: float


@dataclass(frozen=True, slots=True)
class Segmentation:
    """LDPC code-block segmentation of one TB (TS 38.212 5.2.2)."""

    base_graph: int  # 1 or 2
    n_cb: int  # C, number of code blocks
    k_prime_bits: int  # K', information bits per code block including its CRC
    k_bits: int  # K = 22 Zc (BG1) or 10 Zc (BG2), code-block size with filler bits
    lifting_size: int  # Zc
    tb_crc_bits: int  # 16 or 24
    cb_crc_bits: int  # 0 (C = 1) or 24


def _load(name: str) -> dict:
    with (TABLES_DIR / name).open() as f:
        return json.load(f)


@cache
def mcs_table(name: McsTableName) -> tuple[McsEntry, ...]:
    """The MCS table ``name`` (TS 38.214 Tables 5.1.3.1-1/-2/-3) as loaded from ``mcs.json``."""
    rows = _load("mcs.json")["tables"][name]
    return tuple(
        McsEntry(int(r["qm"]), r["rate_x1024"] / 1024.0, r["spectral_efficiency"]) for r in rows
    )


@cache
def tbs_small_table() -> tuple[int, ...]:
    """TS 38.214 Table 5.1.3.2-1 (TBS for N_info <= 3824)."""
    return tuple(_load("mcs.json")["tbs_small_bits"])


@cache
def eesm_betas(name: McsTableName) -> tuple[float, ...]:
    """EESM beta per MCS of table ``name``."""
    return tuple(_load("eesm_beta.json")["betas"][name])


def transport_block_size(
    n_prb: int, n_re_per_prb: int, qm: int, rate: float, layers: int = 1
) -> int:
    """TBS in bits per TS 38.214 5.1.3.2 (valid for any ``n_prb``, including > 275).

    ``n_re_per_prb`` is N'_RE before the cap of 156; ``qm`` the modulation order (bits per
    symbol); ``rate`` is R (e.g. 948/1024); ``layers`` the MIMO layers.
    """
    n_re = min(156, n_re_per_prb) * n_prb
    n_info = n_re * rate * qm * layers
    if n_info <= 0:
        return 0
    if n_info <= 3824:
        n = max(3, math.floor(math.log2(n_info)) - 6)
        n_info_q = max(24, 2**n * math.floor(n_info / 2**n))
        table = tbs_small_table()
        return table[bisect.bisect_left(table, n_info_q)]
    n = math.floor(math.log2(n_info - 24)) - 5
    # "round" in 38.214 breaks ties towards the larger integer, unlike Python's round().
    n_info_q = max(3840, 2**n * math.floor((n_info - 24) / 2**n + 0.5))
    if rate <= 0.25:
        c = math.ceil((n_info_q + 24) / 3816)
        return 8 * c * math.ceil((n_info_q + 24) / (8 * c)) - 24
    if n_info_q > 8424:
        c = math.ceil((n_info_q + 24) / 8424)
        return 8 * c * math.ceil((n_info_q + 24) / (8 * c)) - 24
    return 8 * math.ceil((n_info_q + 24) / 8) - 24


def ldpc_base_graph(tbs_bits: int, rate: float) -> int:
    """LDPC base graph (TS 38.212 7.2.2 / 6.2.2) of a TB of ``tbs_bits`` bits at code rate
    ``rate``: 2 for small or low-rate TBs, else 1."""
    if tbs_bits <= 292 or rate <= 0.25 or (tbs_bits <= 3824 and rate <= 0.67):
        return 2
    return 1


def segment(tbs_bits: int, rate: float) -> Segmentation:
    """Code-block segmentation of a TB of ``tbs_bits`` bits at code rate ``rate`` (TS 38.212
    5.2.2)."""
    bg = ldpc_base_graph(tbs_bits, rate)
    tb_crc = 24 if tbs_bits > 3824 else 16
    b = tbs_bits + tb_crc
    k_cb = 8448 if bg == 1 else 3840
    if b <= k_cb:
        cb_crc, n_cb, b_prime = 0, 1, b
    else:
        cb_crc = 24
        n_cb = math.ceil(b / (k_cb - cb_crc))
        b_prime = b + n_cb * cb_crc
    k_prime = math.ceil(b_prime / n_cb)
    if bg == 1:
        kb = 22
    elif b > 640:
        kb = 10
    elif b > 560:
        kb = 9
    elif b > 192:
        kb = 8
    else:
        kb = 6
    zc = LIFTING_SIZES[bisect.bisect_left(LIFTING_SIZES, math.ceil(k_prime / kb))]
    k = (22 if bg == 1 else 10) * zc
    return Segmentation(bg, n_cb, k_prime, k, zc, tb_crc, cb_crc)


def eesm(sinr_linear: np.ndarray, beta: float, weights: np.ndarray | None = None) -> float:
    """Effective SINR (linear) of per-PRB/subband SINRs ``sinr_linear`` (linear) by EESM with
    ``beta``, each SINR weighted by ``weights`` (None: equal).

    SINR_eff = -beta ln(sum_n w_n exp(-SINR_n / beta) / sum_n w_n). Computed relative to the
    smallest SINR so that high SINRs do not underflow the exponential.
    """
    s = np.asarray(sinr_linear, dtype=float)
    w = np.ones_like(s) if weights is None else np.asarray(weights, dtype=float)
    s_min = float(s.min())
    mean = float(np.sum(w * np.exp(-(s - s_min) / beta)) / np.sum(w))
    return s_min - beta * math.log(mean)


class BlerTable:
    """Code-block BLER vs SNR (dB) and code-block size for one MCS table (``bler_<name>.json``).

    Lookup is bilinear: linear in SNR on the 0.1 dB grid, linear in log(code-block size) between
    the tabulated sizes (clamped at the ends of both grids).
    """

    def __init__(self, name: McsTableName) -> None:
        raw = _load(f"bler_{name}.json")
        self.name = name
        self.snr_min_db = float(raw["snr_min_db"])
        self.snr_step_db = float(raw["snr_step_db"])
        n_snr = int(raw["snr_points"])
        self.cbs_bits = np.array(raw["cbs_bits"], dtype=float)
        self._log_cbs = [math.log(k) for k in raw["cbs_bits"]]
        n_mcs = len(raw["curves"])
        grid = np.zeros((n_mcs, len(self._log_cbs), n_snr))
        for m, per_k in enumerate(raw["curves"]):
            for j, curve in enumerate(per_k):
                i0, values = curve["i0"], curve["bler"]
                grid[m, j, :i0] = 1.0
                grid[m, j, i0 : i0 + len(values)] = values
        self.grid = grid
        # Python lists index faster than numpy scalars in the per-TB hot path; typed, so that
        # compiled (fabric.native) the lookups read C doubles.
        self._rows: list[list[list[float]]] = grid.tolist()
        self._n_snr = n_snr
        # Grid position per code-block size: a TB's few sizes recur in every slot.
        self._cbs_pos: dict[float, tuple[int, float]] = {}
        self.n_mcs = n_mcs
        self.t10_db_2000 = tuple(raw["t10_db_at_2000_bits"])

    def cb_bler(self, mcs: int, cbs_bits: float, snr_db: float) -> float:
        """BLER of one code block of ``cbs_bits`` information bits at MCS ``mcs`` and
        ``snr_db`` (dB)."""
        x = (snr_db - self.snr_min_db) / self.snr_step_db
        if x <= 0.0:
            return 1.0
        if x >= self._n_snr - 1:
            return 0.0
        i = int(x)
        fx = x - i
        pos = self._cbs_pos.get(cbs_bits)
        if pos is None:
            pos = self._cbs_pos[cbs_bits] = self._cbs_position(cbs_bits)
        j, fk = pos
        rows = self._rows[mcs]
        lo, hi = rows[j], rows[j + 1]
        a = lo[i] + fx * (lo[i + 1] - lo[i])
        b = hi[i] + fx * (hi[i + 1] - hi[i])
        return a + fk * (b - a)

    def _cbs_position(self, cbs_bits: float) -> tuple[int, float]:
        """Where ``cbs_bits`` falls on the code-block size grid: the lower neighbour's index and
        the fraction of the way (in log size) to the next one, clamped at the ends."""
        lk = self._log_cbs
        lc = math.log(cbs_bits)
        if lc <= lk[0]:
            return 0, 0.0
        if lc >= lk[-1]:
            return len(lk) - 2, 1.0
        j = bisect.bisect_right(lk, lc) - 1
        return j, (lc - lk[j]) / (lk[j + 1] - lk[j])

    def cb_bler_threshold_db(self, mcs: int, cbs_bits: float, bler: float = 0.1) -> float:
        """SNR (dB) at which one code block of ``cbs_bits`` bits at MCS ``mcs`` reaches
        ``bler`` (bisection; the curves are monotone in SNR)."""
        lo, hi = self.snr_min_db, self.snr_min_db + (self._n_snr - 1) * self.snr_step_db
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if self.cb_bler(mcs, cbs_bits, mid) > bler:
                lo = mid
            else:
                hi = mid
        return hi

    def tb_bler(self, mcs: int, cbs_bits: float, n_cb: int, snr_db: float) -> float:
        """BLER of a TB of ``n_cb`` code blocks of ``cbs_bits`` bits at MCS ``mcs`` and
        ``snr_db`` (dB): 1 - (1 - BLER_cb)^C."""
        p = self.cb_bler(mcs, cbs_bits, snr_db)
        if n_cb == 1 or p <= 0.0 or p >= 1.0:
            return p
        # math.pow: the same C pow() as float ** int, without a generic call when compiled.
        return 1.0 - math.pow(1.0 - p, n_cb)


@dataclass(frozen=True, slots=True)
class TbFormat:
    """What the PHY needs to know about a TB: its size and its code blocks."""

    tbs_bits: int
    cbs_bits: int  # K' per code block
    n_cb: int


class PhyAbstraction:
    """MCS table, EESM betas and BLER curves of MCS table ``table``, for ``layers`` MIMO
    layers, with cached TB formats."""

    def __init__(self, table: McsTableName, layers: int = 1) -> None:
        self.table_name = table
        self.mcs = mcs_table(table)
        self.betas = eesm_betas(table)
        self.bler = BlerTable(table)
        self.layers = layers
        self.max_mcs = len(self.mcs) - 1
        if not len(self.betas) == len(self.mcs) == self.bler.n_mcs:
            raise ValueError(f"tables for {table} disagree on the number of MCS")
        self._formats: dict[tuple[int, int, int], TbFormat] = {}

    def tb_format(self, n_prb: int, mcs: int, n_re_per_prb: int) -> TbFormat:
        """TBS and segmentation for ``n_prb`` PRBs of ``n_re_per_prb`` data RE each at ``mcs``
        (cached: allocations repeat)."""
        key = (n_prb, mcs, n_re_per_prb)
        fmt = self._formats.get(key)
        if fmt is None:
            e = self.mcs[mcs]
            tbs = transport_block_size(n_prb, n_re_per_prb, e.qm, e.rate, self.layers)
            seg = segment(tbs, e.rate)
            fmt = TbFormat(tbs, seg.k_prime_bits, seg.n_cb)
            self._formats[key] = fmt
        return fmt

    def bits_per_prb(self, mcs: int, n_re_per_prb: int) -> float:
        """Information bits per PRB at ``mcs`` with ``n_re_per_prb`` data RE, before TBS
        quantisation (N_RE R Qm layers)."""
        e = self.mcs[mcs]
        return min(156, n_re_per_prb) * e.rate * e.qm * self.layers
