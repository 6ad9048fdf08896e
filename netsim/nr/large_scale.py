"""Large-scale channel of every (UE, gNB) link in a multi-gNB InF hall (TR 38.901 7.4-7.6):
distances, LOS state, path loss, shadowing and coupling loss as (n_ue, n_gnb) arrays, from
spatially consistent maps of each gNB; for UEs that move, the maps drawn once and read at each
new position (``InfMaps``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fabric.seeding import rng as named_rng
from netsim.nr.channel import (
    FIELD_STEP_M,
    exponential_field,
    inf_los_probability,
    inf_pathloss_db,
    normal_cdf,
)
from netsim.nr.layout import InfLayout
from scenario.nr import NrConfig


def link_geometry(layout: InfLayout, ue: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D and 3D distance (m) and LOS probability of every link between ``ue`` (n_ue, 3), metres,
    and the gNBs of ``layout``, each (n_ue, n_gnb)."""
    sub, gnb = layout.sub_scenario, layout.gnb_positions_m
    delta = ue[:, None, :] - gnb[None, :, :]
    d2d = np.hypot(delta[..., 0], delta[..., 1])
    d3d = np.sqrt(d2d**2 + delta[..., 2] ** 2)
    p_los = inf_los_probability(sub.name, d2d, sub.clutter_density, sub.clutter_size_m,
                                sub.clutter_height_m, gnb[None, :, 2], ue[:, None, 2])
    return d2d, d3d, p_los


def grid_index(ue: np.ndarray, nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """The nearest point of the maps' 1 m grid (nx x ny) to each of ``ue`` (n_ue, 3), metres."""
    ix = np.clip(np.rint(ue[:, 0] / FIELD_STEP_M).astype(int), 0, nx - 1)
    iy = np.clip(np.rint(ue[:, 1] / FIELD_STEP_M).astype(int), 0, ny - 1)
    return ix, iy


class InfLinks:
    """Large scale of every link between ``ue_positions_m`` (n_ue, 3) and the gNBs of
    ``layout``; ``carrier_hz`` in Hz, antenna gains in dBi.

    Each gNB has its own LOS and shadowing maps: Gaussian fields over the hall (1 m grid,
    exponential correlation, as the single-gNB ``channel.InfSlChannel``) drawn from streams named
    after the gNB id. So links to different gNBs are independent (TR 38.901 7.5: the large-scale
    parameters of different sites are uncorrelated), nearby UEs see similar values, and a link's
    values depend on the UE position, the gNB and the seed only, never on the other UEs. One value
    per pair serves DL and UL (reciprocity).

    ``los_mode`` forces every link LOS or NLOS ("los", "nlos") or draws it ("stochastic");
    ``shadowing_enabled`` False sets the shadowing to 0 dB. Attributes (n_ue, n_gnb): ``d2d_m``,
    ``d3d_m``, ``los_probability``, ``los``, ``pathloss_db``, ``shadowing_db`` and
    ``coupling_loss_db`` = path loss + shadowing - antenna gains (TR 38.901 7.8.1).
    """

    def __init__(self, layout: InfLayout, ue_positions_m: np.ndarray | Sequence[Sequence[float]],
                 carrier_hz: float, seed: int, stream_prefix: str = "inf",
                 gnb_antenna_gain_dbi: float = 0.0, ue_antenna_gain_dbi: float = 0.0,
                 los_mode: str = "stochastic", shadowing_enabled: bool = True) -> None:
        if los_mode not in ("stochastic", "los", "nlos"):
            raise ValueError(f"los_mode {los_mode!r} is not stochastic, los or nlos")
        sub = layout.sub_scenario
        ue = np.asarray(ue_positions_m, dtype=float).reshape(-1, 3)
        self.layout = layout
        self.n_ue, self.n_gnb = len(ue), len(layout.gnb_positions_m)
        self.d2d_m, self.d3d_m, self.los_probability = link_geometry(layout, ue)
        nx = int(math.floor(layout.hall_length_m / FIELD_STEP_M)) + 1
        ny = int(math.floor(layout.hall_width_m / FIELD_STEP_M)) + 1
        ix, iy = grid_index(ue, nx, ny)

        def field(gnb_id: str, name: str, decorrelation_m: float) -> np.ndarray:
            gen = named_rng(seed, f"{stream_prefix}/{gnb_id}/{name}")
            return exponential_field(nx, ny, FIELD_STEP_M, decorrelation_m, gen)[ix, iy]

        shape = (self.n_ue, self.n_gnb)
        if los_mode == "los":
            self.los = np.ones(shape, dtype=bool)
        elif los_mode == "nlos":
            self.los = np.zeros(shape, dtype=bool)
        else:
            z = np.column_stack([field(g, "los-field", sub.los_correlation_m)
                                 for g in layout.gnb_ids]) if self.n_ue else np.empty(shape)
            self.los = normal_cdf(z) < self.los_probability
        self.pathloss_db = inf_pathloss_db(sub.name, self.d3d_m, carrier_hz, self.los)
        if shadowing_enabled and self.n_ue:
            corr = sub.shadowing_decorrelation_m
            sf_los = np.column_stack([field(g, "shadowing-los", corr) for g in layout.gnb_ids])
            sf_nlos = np.column_stack([field(g, "shadowing-nlos", corr) for g in layout.gnb_ids])
            self.shadowing_db = np.where(self.los, sub.los_shadowing_std_db * sf_los,
                                         sub.nlos_shadowing_std_db * sf_nlos)
        else:
            self.shadowing_db = np.zeros(shape)
        self.coupling_loss_db = (self.pathloss_db + self.shadowing_db - gnb_antenna_gain_dbi
                                 - ue_antenna_gain_dbi)


def hall_links(layout: InfLayout, ue_positions_m: np.ndarray, cfg: NrConfig, seed: int,
               stream_prefix: str) -> InfLinks:
    """The large scale of the static radios at ``ue_positions_m`` (n_ue, 3) with every gNB of
    ``layout``, drawn from the streams ``<stream_prefix>/inf/...`` with ``cfg``'s carrier, antenna
    gains and LOS and shadowing modes: what ``MultiCell`` associates its UEs by, and what the
    coordinator resolves the same association with before a run."""
    return InfLinks(layout, ue_positions_m, cfg.carrier_frequency_hz, seed, f"{stream_prefix}/inf",
                    cfg.gnb_antenna_gain_dbi, cfg.ue_antenna_gain_dbi, cfg.los_mode,
                    cfg.shadowing_enabled)


class InfMaps:
    """The LOS and shadowing maps of every gNB of ``layout``, drawn once and read at any UE
    positions: the large scale of UEs that move.

    The maps, the streams they are drawn from and the way a position reads them (the nearest
    point of the 1 m grid) are those of ``InfLinks``, so ``links(p)`` equals
    ``InfLinks(layout, p, ...)`` with the same arguments, at any time and for any set of UEs: an
    AGV that stops where a static UE stands sees that UE's large scale (spatially consistent,
    TR 38.901 7.6.3). Arguments as ``InfLinks``.
    """

    def __init__(self, layout: InfLayout, carrier_hz: float, seed: int,
                 stream_prefix: str = "inf", gnb_antenna_gain_dbi: float = 0.0,
                 ue_antenna_gain_dbi: float = 0.0, los_mode: str = "stochastic",
                 shadowing_enabled: bool = True) -> None:
        if los_mode not in ("stochastic", "los", "nlos"):
            raise ValueError(f"los_mode {los_mode!r} is not stochastic, los or nlos")
        self.layout = layout
        self.carrier_hz = carrier_hz
        self.gnb_antenna_gain_dbi = gnb_antenna_gain_dbi
        self.ue_antenna_gain_dbi = ue_antenna_gain_dbi
        self.los_mode = los_mode
        self.shadowing_enabled = shadowing_enabled
        self.nx = int(math.floor(layout.hall_length_m / FIELD_STEP_M)) + 1
        self.ny = int(math.floor(layout.hall_width_m / FIELD_STEP_M)) + 1
        sub = layout.sub_scenario

        def fields(name: str, decorrelation_m: float) -> np.ndarray:
            return np.stack([
                exponential_field(self.nx, self.ny, FIELD_STEP_M, decorrelation_m,
                                  named_rng(seed, f"{stream_prefix}/{g}/{name}"))
                for g in layout.gnb_ids])

        # (n_gnb, nx, ny) each; only the maps the modes read are drawn (each from its own
        # stream, so which are drawn changes none of the others).
        self._los_field = (fields("los-field", sub.los_correlation_m)
                           if los_mode == "stochastic" else None)
        corr = sub.shadowing_decorrelation_m
        self._sf_los = fields("shadowing-los", corr) if shadowing_enabled else None
        self._sf_nlos = fields("shadowing-nlos", corr) if shadowing_enabled else None

    def links(self, ue_positions_m: np.ndarray | Sequence[Sequence[float]]) -> InfLinkState:
        """The large scale of every link between ``ue_positions_m`` (n_ue, 3), metres, and the
        gNBs."""
        return InfLinkState(self, np.asarray(ue_positions_m, dtype=float).reshape(-1, 3))

    def coupling_loss_db(self, ue_positions_m: np.ndarray | Sequence[Sequence[float]]
                         ) -> np.ndarray:
        """Coupling loss of every link, dB, shape (n_ue, n_gnb)."""
        return self.links(ue_positions_m).coupling_loss_db


class InfLinkState:
    """The large scale read from ``InfMaps`` at one set of UE positions: the attributes of
    ``InfLinks`` (``d2d_m``, ``d3d_m``, ``los_probability``, ``los``, ``pathloss_db``,
    ``shadowing_db``, ``coupling_loss_db``, each (n_ue, n_gnb))."""

    def __init__(self, maps: InfMaps, ue: np.ndarray) -> None:
        layout = maps.layout
        sub = layout.sub_scenario
        self.layout = layout
        self.n_ue, self.n_gnb = len(ue), len(layout.gnb_positions_m)
        self.d2d_m, self.d3d_m, self.los_probability = link_geometry(layout, ue)
        ix, iy = grid_index(ue, maps.nx, maps.ny)

        def read(f: np.ndarray) -> np.ndarray:
            return f[:, ix, iy].T  # (n_ue, n_gnb)

        shape = (self.n_ue, self.n_gnb)
        if maps._los_field is None:
            self.los = np.full(shape, maps.los_mode == "los")
        else:
            self.los = normal_cdf(read(maps._los_field)) < self.los_probability
        self.pathloss_db = inf_pathloss_db(sub.name, self.d3d_m, maps.carrier_hz, self.los)
        if maps._sf_los is not None and maps._sf_nlos is not None:
            self.shadowing_db = np.where(self.los, sub.los_shadowing_std_db * read(maps._sf_los),
                                         sub.nlos_shadowing_std_db * read(maps._sf_nlos))
        else:
            self.shadowing_db = np.zeros(shape)
        self.coupling_loss_db = (self.pathloss_db + self.shadowing_db
                                 - maps.gnb_antenna_gain_dbi - maps.ue_antenna_gain_dbi)
