"""Several gNBs on one carrier: association by strongest RSRP, UL open-loop power control
(TS 38.213 7.1.1) and the DL and UL geometry SINR of every UE (TR 38.901 7.8.1), from the
(n_ue, n_gnb) coupling losses of ``large_scale.InfLinks``; a gNB is interfered with only by the
gNBs of its own frequency group (``layout.reuse_groups``)."""

from __future__ import annotations

import math

import numpy as np

THERMAL_NOISE_DBM_PER_HZ = -174.0


def serving_gnb(coupling_loss_db: np.ndarray, rs_power_dbm: np.ndarray | float = 0.0
                ) -> np.ndarray:
    """Index of the serving gNB of each UE, shape (n_ue,): the strongest RSRP, the
    reference-signal power per RE (``rs_power_dbm``, dBm, per gNB or one for all) minus the
    coupling loss; a tie goes to the lower index."""
    rsrp = np.asarray(rs_power_dbm, dtype=float) - np.asarray(coupling_loss_db, dtype=float)
    return np.argmax(np.broadcast_to(rsrp, np.shape(coupling_loss_db)), axis=1)


def serving_values(per_link: np.ndarray, serving: np.ndarray) -> np.ndarray:
    """The serving link's entry of a (n_ue, n_gnb) array, shape (n_ue,)."""
    return np.asarray(per_link)[np.arange(len(serving)), serving]


def ul_power_dbm(pathloss_db: np.ndarray | float, n_prb: int, p0_dbm: float, alpha: float,
                 numerology: int = 0, p_cmax_dbm: float = 23.0) -> np.ndarray:
    """PUSCH transmit power, dBm: min(P_CMAX, P0 + 10 log10(2^mu M_RB) + alpha PL) (TS 38.213
    7.1.1 without the transport-format and closed-loop terms, which are 0 here).

    ``pathloss_db`` is the UE's downlink path loss estimate (reference-signal power minus RSRP,
    the coupling loss to its serving gNB), ``n_prb`` = M_RB, ``p0_dbm`` the target received
    power per PRB, ``alpha`` the compensation factor, ``numerology`` mu (0 at 15 kHz).
    """
    open_loop = p0_dbm + 10 * math.log10(2**numerology * n_prb) + alpha * np.asarray(
        pathloss_db, dtype=float)
    return np.minimum(p_cmax_dbm, open_loop)


def dl_geometry_sinr_db(coupling_loss_db: np.ndarray, serving: np.ndarray,
                        gnb_tx_power_dbm: np.ndarray | float, groups: np.ndarray,
                        bandwidth_hz: float, ue_noise_figure_db: float, reuse: int = 1,
                        noise_psd_dbm_per_hz: float = THERMAL_NOISE_DBM_PER_HZ) -> np.ndarray:
    """Wideband DL geometry SINR of each UE, dB, shape (n_ue,): its serving gNB's received
    power over the received power of every other gNB of the same group plus the noise over the
    group's 1/``reuse`` of ``bandwidth_hz``; every gNB sends ``gnb_tx_power_dbm`` (one value or
    one per gNB) on its group's share of the carrier, ``ue_noise_figure_db`` in dB."""
    cl = np.asarray(coupling_loss_db, dtype=float)
    rx_mw = 10 ** ((np.broadcast_to(np.asarray(gnb_tx_power_dbm, dtype=float), cl.shape[1:])
                    - cl) / 10)
    groups = np.asarray(groups)
    rows = np.arange(len(serving))
    co_channel = groups[None, :] == groups[serving][:, None]
    co_channel[rows, serving] = False
    signal = rx_mw[rows, serving]
    interference = np.where(co_channel, rx_mw, 0.0).sum(axis=1)
    noise_mw = 10 ** ((noise_psd_dbm_per_hz + ue_noise_figure_db
                       + 10 * math.log10(bandwidth_hz / reuse)) / 10)
    return 10 * np.log10(signal / (interference + noise_mw))


def co_scheduled_ues(serving: np.ndarray, n_gnb: int, gen: np.random.Generator) -> np.ndarray:
    """For each UE u and gNB c, the UE gNB c schedules on u's PRBs: one of c's UEs drawn
    uniformly, or -1 if c serves nobody or c serves u. Shape (n_ue, n_gnb)."""
    n_ue = len(serving)
    out = np.full((n_ue, n_gnb), -1, dtype=int)
    for c in range(n_gnb):
        members = np.flatnonzero(serving == c)
        if len(members):
            out[:, c] = members[gen.integers(0, len(members), size=n_ue)]
    out[np.arange(n_ue), serving] = -1
    return out


def ul_geometry_sinr_db(coupling_loss_db: np.ndarray, serving: np.ndarray,
                        ue_power_dbm: np.ndarray, groups: np.ndarray, n_prb: int,
                        prb_bandwidth_hz: float, gnb_noise_figure_db: float,
                        co_scheduled: np.ndarray,
                        noise_psd_dbm_per_hz: float = THERMAL_NOISE_DBM_PER_HZ) -> np.ndarray:
    """UL geometry SINR of each UE at its serving gNB, dB, shape (n_ue,).

    The UE sends ``ue_power_dbm`` (its power-control power) on ``n_prb`` PRBs of
    ``prb_bandwidth_hz`` each; on the same PRBs every other gNB of its group receives one UE of
    its own, ``co_scheduled[u, c]`` (``co_scheduled_ues``), at that UE's power. Noise over the
    ``n_prb`` PRBs with the gNB noise figure.
    """
    cl = np.asarray(coupling_loss_db, dtype=float)
    power = np.asarray(ue_power_dbm, dtype=float)
    groups = np.asarray(groups)
    rows = np.arange(len(serving))
    signal = 10 ** ((power - cl[rows, serving]) / 10)
    active = (co_scheduled >= 0) & (groups[None, :] == groups[serving][:, None])
    other = np.where(active, co_scheduled, 0)
    # The co-scheduled UE of gNB c reaches u's serving gNB through its own link to it.
    rx_dbm = power[other] - cl[other, serving[:, None]]
    interference = np.where(active, 10 ** (rx_dbm / 10), 0.0).sum(axis=1)
    noise_mw = 10 ** ((noise_psd_dbm_per_hz + gnb_noise_figure_db
                       + 10 * math.log10(n_prb * prb_bandwidth_hz)) / 10)
    return 10 * np.log10(signal / (interference + noise_mw))
