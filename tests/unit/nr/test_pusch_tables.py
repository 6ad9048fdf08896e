"""The uplink's BLER curves against the PUSCH link-level reference (make_tables.py, "Uplink")."""

from __future__ import annotations

import pytest

from netsim.nr.make_tables import MCS_TABLE_1, PUSCH_REFERENCE_TABLE_1, pusch_reference_deviations
from netsim.nr.phy import PhyAbstraction
from scenario.nr import McsTableName


def test_reference_index_follows_the_transform_precoding_table() -> None:
    # TS 38.214 Table 6.1.4.1-1: MCS 0..16 as Table 5.1.3.1-1 (bar pi/2-BPSK at 0..1), then one
    # step ahead: its MCS 17..27 are table 1's MCS 18..28.
    for i, (qm, r, *_) in PUSCH_REFERENCE_TABLE_1.items():
        assert (qm, r) == MCS_TABLE_1[i if i < 17 else i + 1], i


def test_anchors_agree_with_the_pusch_reference_at_equal_qm_and_rate() -> None:
    checks = pusch_reference_deviations()
    assert len(checks) == len(PUSCH_REFERENCE_TABLE_1)
    for c in checks:
        assert abs(c.anchor_24_minus_reference_db) <= 0.25, c
        # The monotone, floored curves may be more cautious than the reference, never more
        # optimistic than its reading noise.
        assert c.model_24_minus_reference_db >= -0.2, c
        lo, hi = c.reference_2000_db
        assert lo - 0.01 <= c.model_2000_db <= hi + 0.01, c


@pytest.mark.parametrize("table", ["qam64", "qam256", "qam64_low_se"])
def test_the_curves_a_pusch_decodes_with_cross_10_percent_where_the_reference_does(
        table: McsTableName) -> None:
    phy = PhyAbstraction(table)
    index = {(e.qm, round(e.rate * 1024, 1)): m for m, e in enumerate(phy.mcs)}
    matched = 0
    for qm, r, ref24, lo, hi in PUSCH_REFERENCE_TABLE_1.values():
        m = index.get((qm, float(r)))
        if m is None:
            continue
        matched += 1
        assert phy.bler.cb_bler(m, 24, ref24 - 0.2) >= 0.1, (table, m)
        assert phy.bler.cb_bler(m, 2000, lo) >= 0.1 >= phy.bler.cb_bler(m, 2000, hi), (table, m)
    assert matched >= 12  # every table shares most (Qm, R) entries with the reference
