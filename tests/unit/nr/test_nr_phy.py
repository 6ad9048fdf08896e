"""PHY abstraction: TBS (TS 38.214 5.1.3.2), LDPC segmentation, MCS tables, EESM, BLER curves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from netsim.nr import make_tables
from netsim.nr.phy import (
    TABLES_DIR,
    BlerTable,
    eesm,
    ldpc_base_graph,
    mcs_table,
    segment,
    tbs_small_table,
    transport_block_size,
)


def test_tbs_check_value_273_prb_4_layers_256qam() -> None:
    # 14 symbols with 1 DMRS symbol give N'_RE = 156 (the cap).
    assert transport_block_size(273, 156, 8, 948 / 1024, layers=4) == 1_277_992


@pytest.mark.parametrize(("n_prb", "expected_bits"), [(500, 335_976), (533, 352_440)])
def test_tbs_11_symbol_pusch_mcs28_beyond_275_prb(n_prb: int, expected_bits: int) -> None:
    # 11 PUSCH symbols including 1 DMRS symbol: N'_RE = 12 * 11 - 12 = 120.
    entry = mcs_table("qam64")[28]
    assert transport_block_size(n_prb, 120, entry.qm, entry.rate) == expected_bits


def test_tbs_small_blocks_come_from_table() -> None:
    table = tbs_small_table()
    assert len(table) == 93 and table[0] == 24 and table[-1] == 3824
    # 1 PRB, 120 RE, MCS 0 (QPSK, 120/1024): N_info = 28.1 -> N'_info = 8 floor(28.1 / 8) = 24.
    assert transport_block_size(1, 120, 2, 120 / 1024) == 24
    # 10 PRB: N_info = 281.25, n = 3 -> N'_info = 280 -> the next table entry is 288.
    assert transport_block_size(10, 120, 2, 120 / 1024) == 288
    for n_prb in range(1, 40):
        tbs = transport_block_size(n_prb, 72, 6, 948 / 1024)
        if n_prb * 72 * 6 * 948 / 1024 <= 3824:
            assert tbs in table
        else:
            assert tbs > 3824


def test_tbs_grows_with_prb_and_mcs() -> None:
    tbs = [transport_block_size(n, 72, 6, 948 / 1024) for n in range(1, 600)]
    assert all(b >= a for a, b in zip(tbs, tbs[1:], strict=False))
    entries = mcs_table("qam64")
    by_mcs = [transport_block_size(100, 72, e.qm, e.rate) for e in entries]
    assert by_mcs == sorted(by_mcs)


def test_tbs_is_byte_aligned_and_fits_code_blocks() -> None:
    for n_prb in (5, 50, 273, 464, 1000):
        tbs = transport_block_size(n_prb, 72, 6, 948 / 1024)
        assert tbs % 8 == 0
        seg = segment(tbs, 948 / 1024)
        # Segmentation of a 38.214 TBS fills its code blocks exactly.
        assert (tbs + seg.tb_crc_bits + seg.n_cb * seg.cb_crc_bits) == seg.n_cb * seg.k_prime_bits


@pytest.mark.parametrize(("mcs", "qm", "rate_x1024", "se"), [
    (0, 2, 120, 0.2344), (9, 2, 679, 1.3262), (10, 4, 340, 1.3281), (16, 4, 658, 2.5703),
    (17, 6, 438, 2.5664), (28, 6, 948, 5.5547)])
def test_mcs_table_1_entries(mcs: int, qm: int, rate_x1024: int, se: float) -> None:
    e = mcs_table("qam64")[mcs]
    assert (e.qm, e.rate * 1024, e.spectral_efficiency) == (qm, rate_x1024, se)


def test_mcs_tables_2_and_3() -> None:
    t2, t3 = mcs_table("qam256"), mcs_table("qam64_low_se")
    assert len(mcs_table("qam64")) == 29 and len(t2) == 28 and len(t3) == 29
    assert (t2[20].qm, t2[20].rate * 1024) == (8, 682.5)
    assert (t2[27].qm, t2[27].rate * 1024, t2[27].spectral_efficiency) == (8, 948, 7.4063)
    assert (t3[0].qm, t3[0].rate * 1024) == (2, 30)
    assert (t3[15].qm, t3[15].rate * 1024) == (4, 340)
    assert (t3[28].qm, t3[28].rate * 1024) == (6, 772)
    for table in (t2, t3):
        se = [e.spectral_efficiency for e in table]
        assert se == sorted(se)


@pytest.mark.parametrize(("tbs", "rate", "bg"), [
    (200, 0.9, 2), (292, 0.9, 2), (3000, 0.5, 2), (3000, 0.7, 1), (20_000, 0.2, 2),
    (20_000, 0.5, 1), (3824, 0.67, 2), (3832, 0.5, 1)])
def test_ldpc_base_graph(tbs: int, rate: float, bg: int) -> None:
    assert ldpc_base_graph(tbs, rate) == bg


def test_segmentation_limits() -> None:
    one = segment(8424 - 24, 0.9)  # B = 8424 <= 8448: one BG1 block, no CB CRC
    assert (one.base_graph, one.n_cb, one.cb_crc_bits) == (1, 1, 0)
    big = segment(335_976, 948 / 1024)
    assert (big.base_graph, big.n_cb, big.k_prime_bits, big.k_bits) == (1, 40, 8424, 8448)
    low = segment(20_000, 0.2)  # BG2: at most 3840 bits per block
    assert low.base_graph == 2 and low.k_prime_bits <= 3840 and low.n_cb == 6
    assert low.k_bits >= low.k_prime_bits


def test_eesm_of_equal_sinrs_is_that_sinr() -> None:
    for beta in (1.6, 9.95, 34.28):
        assert eesm(np.full(25, 37.5), beta) == pytest.approx(37.5, rel=1e-12)


def test_eesm_lies_between_min_and_mean_and_weights_count() -> None:
    s = np.array([1.0, 10.0, 100.0, 1000.0])
    for beta in (1.6, 10.0, 34.28):
        value = eesm(s, beta)
        assert s.min() <= value <= s.mean()
    # Weights act like repeated entries.
    assert eesm(np.array([2.0, 50.0]), 5.0, np.array([3, 1])) == pytest.approx(
        eesm(np.array([2.0, 2.0, 2.0, 50.0]), 5.0))
    # Very high SINRs must not underflow.
    assert eesm(np.array([1e5, 2e5]), 1.6) == pytest.approx(1e5 + 1.6 * np.log(2), rel=1e-9)


@pytest.fixture(scope="module")
def bler64() -> BlerTable:
    return BlerTable("qam64")


def test_bler_decreases_with_sinr(bler64: BlerTable) -> None:
    snr = np.arange(-15.0, 30.0, 0.05)
    for mcs in (0, 10, 20, 28):
        for cbs in (24, 300, 2000, 8448):
            curve = [bler64.cb_bler(mcs, cbs, x) for x in snr]
            assert all(b <= a + 1e-12 for a, b in zip(curve, curve[1:], strict=False))
            assert curve[0] == pytest.approx(1.0, abs=1e-6) and curve[-1] < 1e-6


def test_bler_increases_with_mcs(bler64: BlerTable) -> None:
    for snr in (-3.0, 5.0, 12.0, 18.5):
        for cbs in (24, 2000, 8448):
            values = [bler64.cb_bler(m, cbs, snr) for m in range(29)]
            assert all(b >= a - 1e-12 for a, b in zip(values, values[1:], strict=False))
            assert values[-1] > values[0]


def test_bler_10_percent_points_match_reference_thresholds(bler64: BlerTable) -> None:
    # Reference AWGN thresholds at 2000-bit blocks (nr-phy-mac.md), within the table grid.
    for mcs, t10 in ((4, -2.4), (12, 4.5), (20, 11.6), (28, 19.0)):
        assert bler64.cb_bler(mcs, 2000, t10) == pytest.approx(0.1, abs=0.01)
        assert bler64.cb_bler_threshold_db(mcs, 2000) == pytest.approx(t10, abs=0.05)


def test_short_blocks_need_more_snr_and_tb_bler_compounds(bler64: BlerTable) -> None:
    assert bler64.cb_bler_threshold_db(12, 24) > bler64.cb_bler_threshold_db(12, 2000) + 1.0
    p = bler64.cb_bler(20, 8000, 11.5)
    assert bler64.tb_bler(20, 8000, 10, 11.5) == pytest.approx(1 - (1 - p) ** 10)


def test_shipped_tables_match_the_generator() -> None:
    for name, content in make_tables.build().items():
        shipped = json.loads((TABLES_DIR / name).read_text())
        assert shipped == json.loads(json.dumps(content)), f"{name} is stale"
