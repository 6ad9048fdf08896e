"""Link adaptation: inner loop (the highest MCS whose predicted BLER meets the target) plus
outer loop (the OLLA offset, per UE and link, driven by first-transmission ACKs and NACKs);
docs/netsim.md, "PHY abstraction"."""

from __future__ import annotations

import math

from netsim.nr.phy import PhyAbstraction


class LinkAdaptation:
    """MCS selection and OLLA state for one link (UL or DL) of ``n_ue`` UEs, with ``phy``'s
    formats and BLER curves: first-transmission TB BLER target ``bler_target`` (a fraction), the
    OLLA offset raised by ``nack_step_db`` (dB) on a NACK and clamped to [``min_offset_db``,
    ``max_offset_db``] (dB), MCS at most ``max_mcs``."""

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
        """MCS for UE index ``ue`` on ``n_prb`` PRBs of ``n_re_per_prb`` data RE each, given
        the estimated effective SINR ``sinr_eff_linear`` (linear, not dB) minus its OLLA offset."""
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
        """Outer-loop update of UE index ``ue`` from the HARQ feedback (``ack``: ACK, else NACK)
        of a first transmission."""
        off = self.offset_db[ue] + (-self.down_db if ack else self.up_db)
        self.offset_db[ue] = min(self.max_db, max(self.min_db, off))
