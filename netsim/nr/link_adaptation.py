"""Link adaptation: inner loop (MCS from predicted BLER) plus outer loop (OLLA offset).

Inner loop: the highest MCS whose predicted TB BLER at the estimated effective SINR, minus the
OLLA offset, is at most the BLER target. The estimate is the EESM over the allocation of the
channel known at the scheduling decision (ideal SRS/CSI, aged by the grant delay); its beta is
that of the UE's previous MCS (EESM depends weakly on beta, one pass is enough).

Outer loop (per UE and link): offset += step on a NACK of a first transmission, -= step *
target / (1 - target) on an ACK, so at equilibrium the first-transmission BLER equals the
target; clamped to [min, max] so a long run of ACKs at the top MCS cannot make it reckless.
"""

from __future__ import annotations

import math

from netsim.nr.phy import PhyAbstraction


class LinkAdaptation:
    """MCS selection and OLLA state for one link (UL or DL) of every UE."""

    __slots__ = ("phy", "target", "up_db", "down_db", "min_db", "max_db", "max_mcs",
                 "offset_db", "last_mcs", "_floor_db")

    def __init__(self, phy: PhyAbstraction, n_ue: int, bler_target: float, nack_step_db: float,
                 min_offset_db: float, max_offset_db: float, max_mcs: int) -> None:
        self.phy = phy
        self.target = bler_target
        self.up_db = nack_step_db
        self.down_db = nack_step_db * bler_target / (1.0 - bler_target)
        self.min_db = min_offset_db
        self.max_db = max_offset_db
        self.max_mcs = max_mcs
        self.offset_db = [0.0] * n_ue
        self.last_mcs = [max_mcs] * n_ue
        # Below the point where the longest code block (the most robust one) reaches the
        # target, no TB of that MCS can meet it: a cheap rejection before the BLER lookup.
        self._floor_db = [
            phy.bler.cb_bler_threshold_db(m, 8448, bler_target) - 0.05
            for m in range(phy.max_mcs + 1)
        ]

    def select(self, ue: int, sinr_eff_linear: float, n_prb: int, n_re_per_prb: int) -> int:
        """MCS for ``n_prb`` PRBs given the estimated effective SINR (linear)."""
        snr_db = 10.0 * math.log10(sinr_eff_linear) - self.offset_db[ue] if (
            sinr_eff_linear > 0) else -100.0
        phy = self.phy
        bler = phy.bler
        floor = self._floor_db
        for m in range(self.max_mcs, 0, -1):
            if snr_db < floor[m]:
                continue
            fmt = phy.tb_format(n_prb, m, n_re_per_prb)
            if fmt.tbs_bits and bler.tb_bler(m, fmt.cbs_bits, fmt.n_cb, snr_db) <= self.target:
                return m
        return 0

    def feedback(self, ue: int, ack: bool) -> None:
        """Outer-loop update from the HARQ feedback of a first transmission."""
        off = self.offset_db[ue] + (-self.down_db if ack else self.up_db)
        self.offset_db[ue] = min(self.max_db, max(self.min_db, off))
