"""TR 38.901 InF-SL channel: path loss, LOS probability, correlated shadowing, fading, SNR."""

from __future__ import annotations

import math

import numpy as np
import pytest

from netsim.nr.channel import (
    InfSlChannel,
    ar1_coefficient,
    bessel_j0,
    exponential_field,
    inf_sl_los_probability,
    inf_sl_pathloss_db,
)
from scenario.nr import NrConfig

FC = 3.5e9


@pytest.mark.parametrize(("d_m", "los_db", "nlos_db"), [
    # 31.84 + 21.5 log10(d) + 19 log10(3.5) and 33 + 25.5 log10(d) + 20 log10(3.5), by hand.
    (1.0, 42.177, 43.881), (10.0, 63.677, 69.381), (30.0, 73.935, 81.548),
    (60.0, 80.407, 89.224)])
def test_inf_sl_pathloss(d_m: float, los_db: float, nlos_db: float) -> None:
    assert float(inf_sl_pathloss_db(d_m, FC, True)) == pytest.approx(los_db, abs=1e-3)
    assert float(inf_sl_pathloss_db(d_m, FC, False)) == pytest.approx(nlos_db, abs=1e-3)


def test_nlos_never_below_los_and_distance_clamped() -> None:
    d = np.array([0.2, 1.0, 5.0, 100.0, 600.0])
    los = inf_sl_pathloss_db(d, FC, np.ones(5, bool))
    nlos = inf_sl_pathloss_db(d, FC, np.zeros(5, bool))
    assert np.all(nlos >= los)
    assert los[0] == los[1]  # d_3D < 1 m is clamped to the model's validity range


def test_los_probability_sl_calibration() -> None:
    p = inf_sl_los_probability(np.array([0.0, 10.0, 30.0, 60.0]), 0.2, 10.0)
    assert p == pytest.approx([1.0, 0.80, 0.51, 0.26], abs=0.005)


def test_bessel_j0_and_ar1_coefficient() -> None:
    assert bessel_j0(0.0) == pytest.approx(1.0)
    assert bessel_j0(2.404825557695773) == pytest.approx(0.0, abs=1e-9)  # first zero
    assert bessel_j0(1.0) == pytest.approx(0.7651976865579666, abs=1e-12)
    # 3 km/h at 3.5 GHz: f_D = 9.7 Hz, nearly static over one 1 ms slot.
    f_d = 3 / 3.6 * FC / 299_792_458
    assert f_d == pytest.approx(9.73, abs=0.01)
    assert ar1_coefficient(f_d, 1e-3) == pytest.approx(0.99907, abs=1e-5)


def test_exponential_field_has_unit_variance_and_exponential_correlation() -> None:
    f = exponential_field(400, 400, 1.0, 10.0, np.random.default_rng(3))
    assert f.std() == pytest.approx(1.0, abs=0.1)
    for lag in (1, 5, 10):
        corr = np.mean(f[:-lag] * f[lag:]) / f.var()
        assert corr == pytest.approx(math.exp(-lag / 10.0), abs=0.08)


def _channel(cfg: NrConfig, positions: list[tuple[float, float, float]], seed: int = 1
             ) -> InfSlChannel:
    ids = [f"ue{i}" for i in range(len(positions))]
    return InfSlChannel(cfg, (60.0, 30.0, 1.5), ids, np.array(positions), seed, "test")


def test_snr_per_prb_includes_power_split_and_noise_figure() -> None:
    cfg = NrConfig(los_mode="los", shadowing_enabled=False, fading="none")
    ch = _channel(cfg, [(90.0, 30.0, 1.5)])  # 30 m, LOS
    noise_prb_dbm = -174 + 10 * math.log10(180e3)
    pl = 31.84 + 21.5 * math.log10(30) + 19 * math.log10(3.5)
    ul_full = 23 - 10 * math.log10(cfg.n_prb) - pl - noise_prb_dbm - 5.0
    dl = 23 - 10 * math.log10(cfg.n_prb) - pl - noise_prb_dbm - 9.0
    assert ch.ul_snr_fullband_db[0] == pytest.approx(ul_full, abs=1e-9)
    assert ch.dl_snr_db[0] == pytest.approx(dl, abs=1e-9)
    # All power on 10 PRBs: 10 log10(n_prb / 10) dB more per PRB.
    per_prb = ch.prb_snr_db(0, "ul", 10)
    assert per_prb.shape == (cfg.n_prb,)
    assert per_prb == pytest.approx(ul_full + 10 * math.log10(cfg.n_prb / 10))
    # The study's single SL cell is far from SNR-limited (median ~34 dB over 500 PRB).
    assert 30 < ul_full < 45


def test_shadowing_is_spatially_correlated_and_independent_of_other_ues() -> None:
    cfg = NrConfig(los_mode="nlos", fading="none")
    a = _channel(cfg, [(20.0, 10.0, 1.5), (21.0, 10.0, 1.5), (100.0, 50.0, 1.5)])
    b = _channel(cfg, [(20.0, 10.0, 1.5)])
    assert b.shadowing_db[0] == a.shadowing_db[0]  # same place, same value, whoever else exists
    assert abs(a.shadowing_db[0] - a.shadowing_db[1]) < 5.7  # 1 m apart: correlation 0.9


def test_shadowing_statistics_over_many_positions() -> None:
    cfg = NrConfig(los_mode="nlos", fading="none")
    rng = np.random.default_rng(0)
    pos = [(float(x), float(y), 1.5) for x, y in zip(rng.uniform(0, 120, 400),
                                                     rng.uniform(0, 60, 400), strict=True)]
    sf = np.concatenate([_channel(cfg, pos, seed).shadowing_db for seed in range(5)])
    assert sf.mean() == pytest.approx(0.0, abs=0.8)
    assert sf.std() == pytest.approx(5.7, rel=0.15)


def test_los_fraction_follows_los_probability() -> None:
    cfg = NrConfig(fading="none")
    near = [(60.0 + 3 * math.cos(a), 30.0 + 3 * math.sin(a), 1.5) for a in np.linspace(0, 6, 60)]
    far = [(5.0 + i * 0.5, 2.0 + (i % 5) * 12.0, 1.5) for i in range(60)]
    los_near = np.mean([_channel(cfg, near, s).los.mean() for s in range(10)])
    los_far = np.mean([_channel(cfg, far, s).los.mean() for s in range(10)])
    assert los_near > 0.8 and los_far < 0.5


def test_rayleigh_fading_has_unit_mean_and_ar1_time_correlation() -> None:
    cfg = NrConfig(los_mode="nlos", shadowing_enabled=False, ue_speed_kmh=30.0,
                   channel_update_period_slots=1)
    pos = [(10.0 + i, 10.0, 1.5) for i in range(40)]
    ch = _channel(cfg, pos)
    ch.advance(0)
    g0 = ch.gain.copy()
    assert ch.gain.shape == (40, math.ceil(cfg.n_prb / cfg.subband_prb))
    assert g0.mean() == pytest.approx(1.0, abs=0.15)
    assert ch.advance(1) and not ch.advance(1)
    rho = ar1_coefficient(ch.doppler_hz, 1e-3)
    # Power correlation of Rayleigh fading is rho^2.
    corr = np.corrcoef(g0.ravel(), ch.gain.ravel())[0, 1]
    assert corr == pytest.approx(rho**2, abs=0.05)
    assert ch.gain_row(3) == ch.gain[3].tolist()


def test_rician_fading_is_milder_than_rayleigh() -> None:
    pos = [(10.0 + i, 10.0, 1.5) for i in range(60)]
    los = _channel(NrConfig(los_mode="los", shadowing_enabled=False, k_factor_std_db=0.0,
                            k_factor_mean_db=10.0), pos).gain
    nlos = _channel(NrConfig(los_mode="nlos", shadowing_enabled=False), pos).gain
    assert los.std() < 0.6 * nlos.std()
    assert los.mean() == pytest.approx(1.0, abs=0.1)
