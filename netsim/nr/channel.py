"""TR 38.901 InF-SL channel: path loss, LOS state, shadowing, subband fading, per-PRB SNR.

Large scale (fixed for static UEs): LOS probability and path loss of the indoor-factory sparse,
low-BS scenario (TR 38.901 Tables 7.4.1-1, 7.4.2-1), log-normal shadowing. LOS state and
shadowing are spatially consistent: each is read from a Gaussian random field over the hall
(1 m grid) with exponential correlation, so two UEs 2 m apart see similar shadowing, and the
value at a position does not depend on which other UEs exist.

Small scale: one complex gain per UE and subband of ``subband_prb`` PRBs (about the coherence
bandwidth of a 55 ns delay spread), Rician in LOS (K-factor drawn per UE, 7 +- 8 dB) and
Rayleigh in NLOS, evolving as an AR(1) process with rho = J0(2 pi f_D dt). The gain is the same
for DL and UL (TDD reciprocity). There is one cell and no interference, so SINR = SNR (minus an
optional interference margin).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fabric.seeding import rng as named_rng
from scenario.nr import NrConfig

SPEED_OF_LIGHT_M_S = 299_792_458.0
FIELD_STEP_M = 1.0  # grid of the spatially consistent random fields
FADING_BLOCK = 64  # fading innovations drawn per UE at a time (per-UE streams, amortised)


def inf_sl_pathloss_db(d3d_m: np.ndarray | float, carrier_hz: float, los: np.ndarray | bool
                       ) -> np.ndarray:
    """InF-SL path loss in dB (TR 38.901 Table 7.4.1-1), d_3D clamped to >= 1 m.

    LOS: 31.84 + 21.50 log10(d) + 19.00 log10(f_GHz);
    NLOS: max(PL_LOS, 33 + 25.5 log10(d) + 20 log10(f_GHz)).
    """
    d = np.maximum(np.asarray(d3d_m, dtype=float), 1.0)
    f_ghz = carrier_hz / 1e9
    pl_los = 31.84 + 21.50 * np.log10(d) + 19.00 * math.log10(f_ghz)
    pl_nlos = np.maximum(pl_los, 33.0 + 25.5 * np.log10(d) + 20.0 * math.log10(f_ghz))
    return np.where(los, pl_los, pl_nlos)


def inf_sl_los_probability(d2d_m: np.ndarray | float, clutter_density: float,
                           clutter_size_m: float) -> np.ndarray:
    """P_LOS = exp(-d_2D / k), k = -d_clutter / ln(1 - r) (TR 38.901 Table 7.4.2-1, InF-SL)."""
    k = -clutter_size_m / math.log(1.0 - clutter_density)
    return np.exp(-np.asarray(d2d_m, dtype=float) / k)


# The InF sub-scenarios with a calibration layout (TR 38.901 Table 7.2-4, Table 7.8-7): sparse or
# dense clutter, low or high BS.
INF_SUB_SCENARIOS: tuple[str, ...] = ("SL", "DL", "SH", "DH")
# Shadow fading sigma (TR 38.901 Table 7.4.1-1): one LOS value for every InF sub-scenario, one
# NLOS value each.
INF_LOS_SHADOWING_STD_DB = 4.3
INF_NLOS_SHADOWING_STD_DB: dict[str, float] = {"SL": 5.7, "DL": 7.2, "SH": 5.9, "DH": 4.0}
# NLOS path loss A + B log10(d_3D) + 20 log10(f_GHz) of each sub-scenario (Table 7.4.1-1).
_INF_NLOS_COEFFICIENTS: dict[str, tuple[float, float]] = {
    "SL": (33.0, 25.5), "DL": (18.6, 35.7), "SH": (32.4, 23.0), "DH": (33.63, 21.9)}


def _check_sub_scenario(sub_scenario: str) -> None:
    if sub_scenario not in INF_SUB_SCENARIOS:
        raise ValueError(f"InF sub-scenario {sub_scenario!r} is not one of "
                         f"{', '.join(INF_SUB_SCENARIOS)}")


def inf_pathloss_db(sub_scenario: str, d3d_m: np.ndarray | float, carrier_hz: float,
                    los: np.ndarray | bool) -> np.ndarray:
    """Path loss of an InF sub-scenario in dB (TR 38.901 Table 7.4.1-1), d_3D clamped to >= 1 m.

    ``sub_scenario`` is SL, DL, SH or DH; ``d3d_m`` in metres, ``carrier_hz`` in Hz, ``los`` the
    link state (arrays broadcast). LOS, every sub-scenario: 31.84 + 21.50 log10(d) + 19.00
    log10(f_GHz). NLOS: SL max(PL_LOS, 33 + 25.5 log10(d) + 20 log10(f)); DL max(PL_LOS, PL_SL,
    18.6 + 35.7 log10(d) + 20 log10(f)); SH max(PL_LOS, 32.4 + 23.0 log10(d) + 20 log10(f));
    DH max(PL_LOS, 33.63 + 21.9 log10(d) + 20 log10(f)). SL equals ``inf_sl_pathloss_db``.
    """
    _check_sub_scenario(sub_scenario)
    d = np.maximum(np.asarray(d3d_m, dtype=float), 1.0)
    log_f = math.log10(carrier_hz / 1e9)
    log_d = np.log10(d)
    pl_los = 31.84 + 21.50 * log_d + 19.00 * log_f
    a, b = _INF_NLOS_COEFFICIENTS[sub_scenario]
    pl_nlos = np.maximum(pl_los, a + b * log_d + 20.0 * log_f)
    if sub_scenario == "DL":
        a_sl, b_sl = _INF_NLOS_COEFFICIENTS["SL"]
        pl_nlos = np.maximum(pl_nlos, a_sl + b_sl * log_d + 20.0 * log_f)
    return np.where(los, pl_los, pl_nlos)


def inf_los_probability(sub_scenario: str, d2d_m: np.ndarray | float, clutter_density: float,
                        clutter_size_m: float, clutter_height_m: float,
                        bs_height_m: np.ndarray | float, ue_height_m: np.ndarray | float
                        ) -> np.ndarray:
    """LOS probability of an InF sub-scenario (TR 38.901 Table 7.4.2-1), P = exp(-d_2D / k).

    Low BS (SL, DL): k = -d_clutter / ln(1 - r). High BS (SH, DH): k = -d_clutter / ln(1 - r)
    x (h_BS - h_UT) / (h_c - h_UT): a BS above the clutter sees further. ``clutter_density`` r,
    sizes and heights in metres; heights broadcast against ``d2d_m``. A high BS needs
    h_UT < h_c < h_BS, the geometry the formula is written for.
    """
    _check_sub_scenario(sub_scenario)
    if not 0.0 < clutter_density < 1.0:
        raise ValueError(f"clutter density {clutter_density} must lie strictly between 0 and 1")
    k: np.ndarray | float = -clutter_size_m / math.log(1.0 - clutter_density)
    if sub_scenario in ("SH", "DH"):
        h_bs = np.asarray(bs_height_m, dtype=float)
        h_ut = np.asarray(ue_height_m, dtype=float)
        if np.any(h_ut >= clutter_height_m) or np.any(h_bs <= clutter_height_m):
            raise ValueError(
                f"InF-{sub_scenario} needs UT height < clutter height ({clutter_height_m} m) "
                f"< BS height")
        k = k * (h_bs - h_ut) / (clutter_height_m - h_ut)
    return np.exp(-np.asarray(d2d_m, dtype=float) / k)


def bessel_j0(x: float) -> float:
    """Bessel function J0 (numpy has none): J0(x) = (1/pi) int_0^pi cos(x sin t) dt.

    The integrand is smooth and periodic, so the trapezoid rule converges exponentially.
    """
    t = np.linspace(0.0, math.pi, 513)
    y = np.cos(x * np.sin(t))
    return float((y[0] / 2 + y[1:-1].sum() + y[-1] / 2) / 512)


def ar1_coefficient(doppler_hz: float, dt_s: float) -> float:
    """Clarke/Jakes time correlation rho = J0(2 pi f_D dt) used as the AR(1) coefficient."""
    return bessel_j0(2.0 * math.pi * doppler_hz * dt_s)


def exponential_field(nx: int, ny: int, step_m: float, decorrelation_m: float,
                      gen: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian field on an (nx, ny) grid with correlation
    exp(-|dx|/d) exp(-|dy|/d): a separable AR(1) filter along each axis.

    Separable correlation equals the TR 38.901 exponential model along the axes and decays a
    little faster diagonally (L1 instead of L2 distance) - an accepted shortcut.
    """
    a = math.exp(-step_m / decorrelation_m)
    b = math.sqrt(1.0 - a * a)
    f = gen.standard_normal((nx, ny))
    for i in range(1, nx):
        f[i] = a * f[i - 1] + b * f[i]
    for j in range(1, ny):
        f[:, j] = a * f[:, j - 1] + b * f[:, j]
    return f


def _normal_cdf(z: np.ndarray) -> np.ndarray:
    return np.array([0.5 * (1.0 + math.erf(v / math.sqrt(2.0))) for v in z])


def normal_cdf(z: np.ndarray) -> np.ndarray:
    """Standard normal CDF of an array of any shape (exact, through math.erf)."""
    z = np.asarray(z, dtype=float)
    return _normal_cdf(z.ravel()).reshape(z.shape)


class SubbandGains:
    """What a cell's CSI and counters read of its channel (``netsim.nr.csi``), per UE of the cell:
    ``gain[u, sb]`` (also ``gain_row(u)[sb]``), the small-scale power gain (mean 1) on subband
    ``sb`` of ``n_subbands``; ``ul_snr_fullband`` / ``dl_snr``, the mean linear SNR per PRB with
    the UE's (UL) or the gNB's (DL) whole power spread over every PRB of the carrier, and in dB
    ``ul_snr_fullband_db`` / ``dl_snr_db``; ``los`` and ``d3d_m`` (m) of the link. Implemented by
    ``InfSlChannel`` (one gNB) and ``netsim.nr.link_fading.ServingLinks`` (a gNB among several).
    """

    n_ue: int
    n_subbands: int
    gain: np.ndarray
    ul_snr_fullband: list[float]
    dl_snr: list[float]
    ul_snr_fullband_db: np.ndarray
    dl_snr_db: np.ndarray
    los: np.ndarray
    d3d_m: np.ndarray
    _rows: list[list[float] | None]

    def gain_row(self, ue: int) -> list[float]:
        """Subband gains of ``ue`` as a Python list (fast scalar access), converted on demand:
        most slots only touch the UEs they schedule."""
        row = self._rows[ue]
        if row is None:
            row = self._rows[ue] = self.gain[ue].tolist()
        return row

    def advance(self, slot: int) -> bool:
        """Bring the fading to slot index ``slot``; True if the gains changed."""
        raise NotImplementedError


class InfSlChannel(SubbandGains):
    """Channel between one gNB and a fixed set of UEs, advanced slot by slot.

    After ``advance(slot)``: ``gain[u, sb]`` (also ``gain_row(u)[sb]``) is the small-scale power
    gain (mean 1) of UE ``u`` on subband ``sb``; ``ul_snr_fullband`` / ``dl_snr`` the mean linear SNR per PRB when
    the UE spreads its power over all PRBs (UL) or the gNB over all PRBs (DL).
    """

    def __init__(self, config: NrConfig, gnb_position_m: Sequence[float],
                 ue_ids: Sequence[str], ue_positions_m: np.ndarray, seed: int,
                 stream_prefix: str) -> None:
        cfg = config
        self.config = cfg
        n = len(ue_ids)
        self.n_ue = n
        self.n_subbands = math.ceil(cfg.n_prb / cfg.subband_prb)
        pos = np.asarray(ue_positions_m, dtype=float).reshape(n, 3)
        gnb = np.asarray(gnb_position_m, dtype=float)
        delta = pos - gnb
        self.d2d_m = np.hypot(delta[:, 0], delta[:, 1])
        self.d3d_m = np.sqrt(self.d2d_m**2 + delta[:, 2] ** 2)

        # Spatially consistent fields over the hall, independent of the UE set.
        nx = int(math.floor(cfg.hall_length_m / FIELD_STEP_M)) + 1
        ny = int(math.floor(cfg.hall_width_m / FIELD_STEP_M)) + 1
        ix = np.clip(np.rint(pos[:, 0] / FIELD_STEP_M).astype(int), 0, nx - 1)
        iy = np.clip(np.rint(pos[:, 1] / FIELD_STEP_M).astype(int), 0, ny - 1)

        def field(name: str, decorrelation_m: float) -> np.ndarray:
            gen = named_rng(seed, f"{stream_prefix}/{name}")
            return exponential_field(nx, ny, FIELD_STEP_M, decorrelation_m, gen)[ix, iy]

        self.los_probability = inf_sl_los_probability(
            self.d2d_m, cfg.clutter_density, cfg.clutter_size_m)
        if cfg.los_mode == "los":
            self.los = np.ones(n, dtype=bool)
        elif cfg.los_mode == "nlos":
            self.los = np.zeros(n, dtype=bool)
        else:
            u = _normal_cdf(field("los-field", cfg.los_correlation_m))
            self.los = u < self.los_probability
        self.pathloss_db = inf_sl_pathloss_db(self.d3d_m, cfg.carrier_frequency_hz, self.los)
        if cfg.shadowing_enabled:
            sf_los = field("shadowing-los", cfg.shadowing_decorrelation_m)
            sf_nlos = field("shadowing-nlos", cfg.shadowing_decorrelation_m)
            self.shadowing_db = np.where(self.los, cfg.los_shadowing_std_db * sf_los,
                                         cfg.nlos_shadowing_std_db * sf_nlos)
        else:
            self.shadowing_db = np.zeros(n)

        # Mean SNR per PRB (linear), power spread over every PRB of the carrier.
        prb_bw_hz = 12 * cfg.subcarrier_spacing_hz
        noise_prb_dbm = cfg.noise_psd_dbm_per_hz + 10 * math.log10(prb_bw_hz)
        coupling_db = (cfg.gnb_antenna_gain_dbi + cfg.ue_antenna_gain_dbi - self.pathloss_db
                       - self.shadowing_db - cfg.interference_margin_db
                       - 10 * math.log10(cfg.n_prb))
        self.ul_snr_fullband_db = (cfg.ue_tx_power_dbm + coupling_db - noise_prb_dbm
                                   - cfg.gnb_noise_figure_db)
        self.dl_snr_db = cfg.gnb_tx_power_dbm + coupling_db - noise_prb_dbm - cfg.ue_noise_figure_db
        self.ul_snr_fullband = (10 ** (self.ul_snr_fullband_db / 10)).tolist()
        self.dl_snr = (10 ** (self.dl_snr_db / 10)).tolist()

        # Small-scale fading state.
        self._fading = cfg.fading != "none"
        self._ue_rngs = [named_rng(seed, f"{stream_prefix}/fading/{ue}") for ue in ue_ids]
        k_db = np.array([
            named_rng(seed, f"{stream_prefix}/k-factor/{ue}").normal(
                cfg.k_factor_mean_db, cfg.k_factor_std_db) for ue in ue_ids])
        k_lin = np.where(self.los, 10 ** (k_db / 10), 0.0)
        self.k_factor_db = np.where(self.los, k_db, -np.inf)
        los_amp = np.sqrt(k_lin / (k_lin + 1))[:, None]
        self._diffuse_amp = np.sqrt(1 / (k_lin + 1))[:, None]
        m = self.n_subbands
        phases = np.array([g.uniform(0, 2 * math.pi, m) for g in self._ue_rngs])
        self._los_term = los_amp * np.exp(1j * phases)  # static: the UEs do not move
        self._diffuse = np.array([self._complex_normal(g, (m,)) for g in self._ue_rngs])
        # Innovations, drawn FADING_BLOCK updates at a time per UE straight into this buffer
        # (real and imaginary parts side by side, unit variance each: scaled at use).
        self._innovations = np.empty((n, FADING_BLOCK, m, 2))
        self._innovations_c = self._innovations.view(complex)[..., 0]
        self._innovation_index = FADING_BLOCK
        doppler_hz = cfg.ue_speed_kmh / 3.6 * cfg.carrier_frequency_hz / SPEED_OF_LIGHT_M_S
        self.doppler_hz = doppler_hz
        self.rho_per_update = ar1_coefficient(
            doppler_hz, cfg.channel_update_period_slots * cfg.slot_us * 1e-6)
        self._period = cfg.channel_update_period_slots
        self._last_update_slot: int | None = None
        self.gain = np.ones((n, m))
        self._refresh_gain()

    @staticmethod
    def _complex_normal(gen: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        z = gen.standard_normal((*shape, 2))
        return (z[..., 0] + 1j * z[..., 1]) / math.sqrt(2.0)

    def _next_innovation(self) -> np.ndarray:
        """CN(0, 2) innovations for every UE and subband (per-UE streams)."""
        if self._innovation_index == FADING_BLOCK:
            for u, gen in enumerate(self._ue_rngs):
                gen.standard_normal(out=self._innovations[u])
            self._innovation_index = 0
        w = self._innovations_c[:, self._innovation_index, :]
        self._innovation_index += 1
        return w

    def _refresh_gain(self) -> None:
        if self._fading:
            h = self._los_term + self._diffuse_amp * self._diffuse
            self.gain = h.real**2 + h.imag**2
        self._rows = [None] * self.n_ue

    def advance(self, slot: int) -> bool:
        """Bring the fading to ``slot``; True if the gains changed.

        Updates happen on a fixed grid of ``channel_update_period_slots``; after an idle jump of
        k periods one AR(1) step with rho^k is taken (the same distribution as k steps).
        """
        if self._last_update_slot is None:
            self._last_update_slot = slot - slot % self._period
            return False
        steps = (slot - self._last_update_slot) // self._period
        if steps <= 0 or not self._fading:
            return False
        self._last_update_slot += steps * self._period
        rho = self.rho_per_update**steps
        # The innovations have variance 2 (two unit-variance parts): scale to CN(0, 1 - rho^2).
        self._diffuse = rho * self._diffuse + math.sqrt(max(0.0, 1 - rho * rho) / 2) * (
            self._next_innovation())
        self._refresh_gain()
        return True

    def prb_snr_db(self, ue: int, direction: str, n_prb_allocated: int | None = None
                   ) -> np.ndarray:
        """Per-PRB SNR (dB) of ``ue`` now: DL, or UL with the UE's power spread over
        ``n_prb_allocated`` PRBs (all PRBs if None)."""
        cfg = self.config
        sb_of_prb = np.arange(cfg.n_prb) // cfg.subband_prb
        if direction == "dl":
            mean_db = self.dl_snr_db[ue]
        else:
            n = n_prb_allocated or cfg.n_prb
            mean_db = self.ul_snr_fullband_db[ue] + 10 * math.log10(cfg.n_prb / n)
        return mean_db + 10 * np.log10(self.gain[ue, sb_of_prb])
