"""Configuration of the NR system-level cell (``NrConfig``), defaults = the study's calibration.

The defaults reproduce the reference study's cell (docs/netsim.md, "Configuration reference");
``n_prb`` and the DL/UL symbol split of the slot are the calibration knobs, set for about
178.6 Mbps of saturated uplink in the reference layout (docs/netsim.md, "Calibration").
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# The MCS tables of TS 38.214 5.1.3.1 that netsim.nr.phy loads.
McsTableName = Literal["qam64", "qam256", "qam64_low_se"]


SYMBOLS_PER_SLOT = 14

# Calibrated values (docs/netsim.md): saturated uplink IP throughput of the reference hall.
CALIBRATED_N_PRB = 468
CALIBRATED_UL_CAPACITY_MBPS = 178.6


# Integers at or beyond this travel in no message (msgpack carries 64 bits) and are no longer
# exact as floats: no field of any scenario section means anything there.
INT_LIMIT = 2**53


def bounded_int(v: Any) -> Any:
    """``v``, or ValueError if it is an integer of INT_LIMIT or more (a validator of every field)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= INT_LIMIT:
        raise ValueError(f"{v:.3g} is too large: integers here are below 2**53")
    return v


class NrConfig(BaseModel):
    """Every parameter of ``NrCell``; units are in the field names."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _bounded_ints(cls, v: Any) -> Any:
        return bounded_int(v)

    # --- carrier and numerology -------------------------------------------------------------
    carrier_frequency_hz: float = Field(
        default=3.5e9, gt=0.5e9, le=7.125e9,
        description="Carrier frequency; InF path loss is valid for 0.5-100 GHz, FR1 here.")
    bandwidth_hz: float = Field(
        default=100e6, gt=0, description="Channel bandwidth; n_prb * 12 * SCS must fit inside it.")
    subcarrier_spacing_hz: Literal[15000, 30000, 60000] = Field(
        default=15000, description="Subcarrier spacing (numerology 0/1/2); sets the slot duration.")
    n_prb: int = Field(
        default=CALIBRATED_N_PRB, ge=1, le=3300,
        description="PRBs of the carrier, a calibration knob: the study's 100 MHz at 15 kHz is "
        "treated as one wide carrier (TS 38.101-1 caps a real 15 kHz carrier at 270 PRB).")

    # --- self-contained TDD slot (symbols, in time order) ------------------------------------
    dl_ctrl_symbols: int = Field(default=1, ge=1, description="PDCCH symbols at the start of the slot.")
    dl_data_symbols: int = Field(
        default=4, ge=0, description="PDSCH symbols, DMRS included; calibration knob (DL/UL split).")
    guard_symbols: int = Field(default=1, ge=0, description="DL-to-UL switching guard symbols.")
    ul_data_symbols: int = Field(
        default=7, ge=0, description="PUSCH symbols, DMRS included; calibration knob (DL/UL split).")
    ul_ctrl_symbols: int = Field(
        default=1, ge=1, description="PUCCH symbols at the end of the slot (SR, HARQ-ACK).")
    dmrs_symbols: int = Field(
        default=1, ge=1, le=4, description="DMRS symbols in each data region (12 RE per PRB each).")
    overhead_re_per_prb: Literal[0, 6, 12, 18] = Field(
        default=0, description="N_oh of TS 38.214 5.1.3.2 (xOverhead), RE per PRB per slot.")
    mcs_table: McsTableName = Field(
        default="qam64", description="MCS table for PDSCH and PUSCH: qam64 (Table 5.1.3.1-1), qam256 "
        "(5.1.3.1-2) or qam64_low_se (5.1.3.1-3).")
    max_mcs: int | None = Field(
        default=None, ge=0, description="Highest MCS link adaptation may pick (None: top of the table).")

    # --- radio --------------------------------------------------------------------------------
    gnb_tx_power_dbm: float = Field(default=23.0, ge=-30, le=60, description="gNB transmit power over the carrier.")
    ue_tx_power_dbm: float = Field(
        default=23.0, ge=-40, le=33, description="UE maximum transmit power, spread over its allocated PRBs.")
    gnb_antenna_gain_dbi: float = Field(default=0.0, ge=-20, le=40, description="gNB antenna gain (SISO).")
    ue_antenna_gain_dbi: float = Field(default=0.0, ge=-20, le=40, description="UE antenna gain (SISO).")
    gnb_noise_figure_db: float = Field(default=5.0, ge=0, le=30, description="gNB receiver noise figure.")
    ue_noise_figure_db: float = Field(
        default=9.0, ge=0, le=30, description="UE receiver noise figure (InF calibration value).")
    noise_psd_dbm_per_hz: float = Field(default=-174.0, ge=-200, le=-150, description="Thermal noise density.")
    interference_margin_db: float = Field(
        default=0.0, ge=0, le=60, description="Extra interference over thermal; 0 for the study's single cell.")

    # --- channel: TR 38.901 InF-SL ------------------------------------------------------------
    hall_length_m: float = Field(
        default=120.0, gt=0, description="Hall extent along x; positions must lie in [0, length].")
    hall_width_m: float = Field(
        default=60.0, gt=0, description="Hall extent along y; positions must lie in [0, width].")
    hall_height_m: float = Field(default=10.0, gt=0, description="Hall height (z in [0, height]).")
    los_mode: Literal["stochastic", "los", "nlos"] = Field(
        default="stochastic", description="LOS state: drawn from the InF-SL LOS probability with "
        "spatial correlation, or forced for every UE.")
    clutter_density: float = Field(
        default=0.2, gt=0, lt=1, description="InF clutter density r (SL calibration: 0.2).")
    clutter_size_m: float = Field(
        default=10.0, gt=0, description="InF clutter size d_clutter (SL calibration: 10 m).")
    los_correlation_m: float = Field(
        default=5.0, gt=0, description="Correlation distance of the LOS state (d_clutter / 2).")
    shadowing_enabled: bool = Field(default=True, description="Log-normal shadowing on or off.")
    shadowing_decorrelation_m: float = Field(
        default=10.0, gt=0, description="Shadowing decorrelation distance (exponential correlation).")
    los_shadowing_std_db: float = Field(default=4.3, ge=0, le=30, description="Shadowing sigma in LOS.")
    nlos_shadowing_std_db: float = Field(default=5.7, ge=0, le=30, description="Shadowing sigma in InF-SL NLOS.")
    k_factor_mean_db: float = Field(default=7.0, ge=-30, le=40, description="Rician K-factor mean in LOS.")
    k_factor_std_db: float = Field(default=8.0, ge=0, le=30, description="Rician K-factor sigma in LOS.")
    fading: Literal["rician_rayleigh", "none"] = Field(
        default="rician_rayleigh", description="Small-scale fading per subband: Rician (LOS) / Rayleigh "
        "(NLOS) with AR(1) time correlation, or none (flat, static).")
    subband_prb: int = Field(
        default=20, ge=1, description="PRBs per fading subband (~ coherence bandwidth, 3.6 MHz).")
    ue_speed_kmh: float = Field(
        default=3.0, ge=0, le=500, description="Effective speed setting the Doppler f_D of the AR(1) fading.")
    channel_update_period_slots: int = Field(
        default=5, ge=1, description="Slots between fading updates; rho = J0(2 pi f_D period).")

    # --- MAC ----------------------------------------------------------------------------------
    scheduler: Literal["pf", "rr", "max_rate"] = Field(
        default="pf", description="Scheduler: proportional fair, round robin or max rate.")
    pf_forgetting_factor: float = Field(
        default=0.95, gt=0, lt=1, description="PF average-throughput factor beta (0.95-0.98 usual).")
    max_ul_ues_per_slot: int = Field(
        default=8, ge=1, description="UL grants per slot (PDCCH capacity), retransmissions included.")
    max_dl_ues_per_slot: int = Field(
        default=8, ge=1, description="DL assignments per slot (PDCCH capacity).")
    harq_processes: int = Field(default=16, ge=1, le=32, description="HARQ processes per UE and link.")
    harq_max_transmissions: int = Field(
        default=4, ge=1, description="Transmissions of a TB before residual loss (RV 0, 2, 3, 1).")
    harq_combining: Literal["chase", "none"] = Field(
        default="chase", description="Chase combining adds the effective SINRs of the transmissions; "
        "none decodes each transmission alone.")
    k1_slots: int = Field(
        default=1, ge=0, le=31, description="PDSCH to HARQ-ACK delay (UE capability 1 makes K1 >= 1 usual).")
    k2_slots: int = Field(
        default=1, ge=0, le=32, description="UL grant (PDCCH) to PUSCH delay; capability 1 needs K2 >= 1.")
    ul_access: Literal["grant_based", "configured_grant"] = Field(
        default="grant_based", description="Grant-based uplink (SR -> grant -> PUSCH with BSR) or a "
        "configured grant per UE plus dynamic grants from its BSRs.")
    sr_period_slots: int = Field(default=1, ge=1, le=640, description="SR occasion period per UE.")
    sr_grant_bytes: int = Field(
        default=1600, ge=16, description="Size of the first grant after an SR (gNB knows no size yet).")
    cg_period_slots: int = Field(
        default=1, ge=1, description="Configured-grant period per UE (UEs staggered over the period).")
    cg_prb: int = Field(default=8, ge=1, description="PRBs of each configured-grant occasion.")
    l2_header_bytes_per_segment: int = Field(
        default=5, ge=0, le=64, description="MAC subheader (3 B) + RLC/PDCP header share per packet segment.")
    bsr_bytes: int = Field(default=2, ge=0, le=64, description="Short BSR MAC CE with subheader, per UL TB.")

    # --- link adaptation ----------------------------------------------------------------------
    bler_target: float = Field(
        default=0.1, gt=0, lt=1, description="First-transmission TB BLER target of link adaptation.")
    olla_nack_step_db: float = Field(
        default=0.5, ge=0, description="OLLA offset increase on NACK; the ACK step is "
        "step * target / (1 - target), so the offset settles at the BLER target.")
    olla_min_offset_db: float = Field(
        default=-3.0, description="Lower clamp of the OLLA offset (most optimistic).")
    olla_max_offset_db: float = Field(
        default=15.0, description="Upper clamp of the OLLA offset (most conservative).")

    # --- control-channel errors (Polar-coded DCI / UCI, fixed probabilities) ------------------
    pdcch_miss_prob: float = Field(
        default=0.01, ge=0, lt=1, description="Probability a UE misses its DCI (grant or assignment).")
    ack_miss_prob: float = Field(
        default=0.01, ge=0, lt=1, description="Probability an ACK is read as NACK/DTX (wasted retx).")
    nack_to_ack_prob: float = Field(
        default=0.001, ge=0, lt=1, description="Probability a NACK is read as ACK (TB lost).")

    # --- buffers ------------------------------------------------------------------------------
    ul_buffer_limit_bytes: int = Field(
        default=1_000_000, ge=1, description="UE transmit buffer; a packet that does not fit is lost "
        "with cause buffer_overflow (1 MB ~ 1 s of an 8.5 Mbps camera).")
    dl_buffer_limit_bytes: int = Field(
        default=1_000_000, ge=1, description="gNB transmit buffer per UE.")

    @property
    def slot_us(self) -> int:
        """Slot duration in microseconds (1000 us at 15 kHz)."""
        return 1000 * 15000 // self.subcarrier_spacing_hz

    @property
    def ul_re_per_prb(self) -> int:
        """N'_RE of the PUSCH: 12 RE x data symbols minus DMRS and overhead."""
        return 12 * self.ul_data_symbols - 12 * self.dmrs_symbols - self.overhead_re_per_prb

    @property
    def dl_re_per_prb(self) -> int:
        """N'_RE of the PDSCH."""
        return 12 * self.dl_data_symbols - 12 * self.dmrs_symbols - self.overhead_re_per_prb

    @model_validator(mode="after")
    def _check(self) -> NrConfig:
        total = (self.dl_ctrl_symbols + self.dl_data_symbols + self.guard_symbols
                 + self.ul_data_symbols + self.ul_ctrl_symbols)
        if total != SYMBOLS_PER_SLOT:
            raise ValueError(
                f"dl_ctrl_symbols + dl_data_symbols + guard_symbols + ul_data_symbols + "
                f"ul_ctrl_symbols = {total}, a slot has {SYMBOLS_PER_SLOT} symbols")
        if self.ul_data_symbols > 0 and self.guard_symbols < 1 and self.dl_data_symbols > 0:
            raise ValueError("guard_symbols must be >= 1 when a slot has both DL and UL data")
        for name in ("ul", "dl"):
            symbols = getattr(self, f"{name}_data_symbols")
            if 0 < symbols <= self.dmrs_symbols or (
                    symbols > 0 and getattr(self, f"{name}_re_per_prb") <= 0):
                raise ValueError(
                    f"{name}_data_symbols={symbols} leaves no data RE after "
                    f"dmrs_symbols={self.dmrs_symbols} and overhead_re_per_prb")
        occupied_hz = self.n_prb * 12 * self.subcarrier_spacing_hz
        if occupied_hz > self.bandwidth_hz:
            raise ValueError(
                f"n_prb={self.n_prb} occupies {occupied_hz / 1e6:.2f} MHz at "
                f"{self.subcarrier_spacing_hz} Hz SCS, more than bandwidth_hz="
                f"{self.bandwidth_hz:g}; at most {int(self.bandwidth_hz // (12 * self.subcarrier_spacing_hz))} PRB fit")
        n_mcs = 28 if self.mcs_table == "qam256" else 29
        if self.max_mcs is not None and self.max_mcs >= n_mcs:
            raise ValueError(f"max_mcs={self.max_mcs} but {self.mcs_table} has MCS 0..{n_mcs - 1}")
        if self.olla_min_offset_db > self.olla_max_offset_db:
            raise ValueError(f"olla_min_offset_db ({self.olla_min_offset_db:g}) must be <= "
                             f"olla_max_offset_db ({self.olla_max_offset_db:g})")
        if self.cg_prb > self.n_prb:
            raise ValueError(f"cg_prb={self.cg_prb} exceeds n_prb={self.n_prb}")
        return self
