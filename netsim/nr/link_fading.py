"""Small-scale fading of every (UE, gNB) link of a hall with several gNBs, and each gNB's view of
the links to its own UEs (``ServingLinks``, what its CSI and counters read).

Each link has the single-gNB channel's process (``channel.InfSlChannel``): one complex gain per
subband, Rician in LOS (K-factor drawn per link) and Rayleigh in NLOS, AR(1) in time on the grid
of ``channel_update_period_slots``. A link is brought up to date only when it is used (a serving
link of a cell that schedules, or an interfering link on PRBs in use), by one AR(1) step of
rho^k over the k grid updates since its last use: the distribution of k steps in one draw, the
single cell's rule for idle jumps. Every draw of a link comes from its own stream,
``<prefix>/fading/<ue>/<gnb id>``, so another gNB or UE changes no draw of that stream.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from fabric.seeding import rng as named_rng
from netsim.nr.channel import SPEED_OF_LIGHT_M_S, SubbandGains, ar1_coefficient
from scenario.nr import NrConfig

# AR(1) innovations drawn per link at a time, single precision: a generator call costs far more
# than the numbers it draws (at 18 gNBs x 20 UEs about 350 links step per slot), 32 steps of 24
# subbands take 6 kB per link.
INNOVATION_BLOCK = 32
# Gaps (grid updates between two uses of a link) whose AR(1) factors are tabulated.
RHO_TABLE = 64


class LinkFading:
    """Fading of the links between ``ue_ids`` and ``gnb_ids`` (``los``: (n_ue, n_gnb) LOS
    state) over ``n_subbands`` subbands, as configured by ``cfg`` (``fading``, K-factor, speed,
    update period); streams from the root ``seed`` under ``stream_prefix``.

    Links are numbered ``ue * n_gnb + gnb``; ``used`` (n_ue, n_gnb, bool) marks those that may
    carry a signal or interference, drawn here (their stream, K-factor, LOS phases and first
    state); the others never are. With ``used_dl_interference`` (n_ue, n_gnb, bool), the
    downlink interference at a UE from a gNB that does not serve it has a process of its own,
    numbered ``n_ue * n_gnb + ue * n_gnb + gnb`` (``dl_interference_offset``), stream
    ``<prefix>/fading-dl/<ue>/<gnb id>``: each process is then stepped by one gNB's cell only
    (docs/architecture.md sec. 13). After ``refresh(links, update)``, ``gain[link]`` holds each
    of those links' power gains per subband (mean 1) at grid update ``update`` (slot index //
    ``period``). With ``fading: none`` every gain is 1.
    """

    def __init__(self, ue_ids: list[str], gnb_ids: list[str], los: np.ndarray, n_subbands: int,
                 cfg: NrConfig, seed: int, stream_prefix: str, used: np.ndarray,
                 used_dl_interference: np.ndarray | None = None) -> None:
        n_ue, n_gnb = len(ue_ids), len(gnb_ids)
        self.dl_interference_offset = n_ue * n_gnb
        n_links = n_ue * n_gnb * (1 if used_dl_interference is None else 2)
        self.ue_ids = ue_ids
        self.gnb_ids = gnb_ids
        self.n_gnb = n_gnb
        self.n_subbands = n_subbands
        self.seed = seed
        self.prefix = stream_prefix
        self.enabled = cfg.fading != "none"
        self.k_mean_db = cfg.k_factor_mean_db
        self.k_std_db = cfg.k_factor_std_db
        self.los = np.asarray(los, dtype=bool).reshape(n_ue * n_gnb)
        self.period = cfg.channel_update_period_slots
        doppler_hz = cfg.ue_speed_kmh / 3.6 * cfg.carrier_frequency_hz / SPEED_OF_LIGHT_M_S
        self.rho = ar1_coefficient(doppler_hz, self.period * cfg.slot_us * 1e-6)
        # Single precision: a slot steps hundreds of links; the gains need no more.
        self.gain = np.ones((n_links, n_subbands), dtype=np.float32)
        self.updated = np.full(n_links, -1, dtype=np.int64)  # grid update of gain; -1: unused
        self._diffuse = np.zeros((n_links, n_subbands), dtype=np.complex64)
        self._los_term = np.zeros((n_links, n_subbands), dtype=np.complex64)
        self._diffuse_amp = np.ones(n_links, dtype=np.float32)
        self._mark = np.zeros(n_links, dtype=bool)  # scratch: the links a refresh steps
        self._gens: list[np.random.Generator | None] = [None] * n_links
        # Innovations, INNOVATION_BLOCK steps per link per draw (real and imaginary parts side by
        # side, unit variance each); memory is touched only for links in use.
        self._innovations = np.empty((n_links, INNOVATION_BLOCK, n_subbands, 2), dtype=np.float32)
        self._innovations_c = self._innovations.view(np.complex64)[..., 0]
        # The same memory, one row per (link, step): a step's innovations are gathered by row.
        self._innovation_rows = self._innovations_c.reshape(n_links * INNOVATION_BLOCK, n_subbands)
        self._next = np.full(n_links, INNOVATION_BLOCK, dtype=np.int64)
        # rho^k and the innovation's scale sqrt((1 - rho^2k) / 2) for the gaps k seen most, each as
        # refresh would compute it for that k. Real factors: refresh scales the real and imaginary
        # parts of the complex states (float32 views), the numbers of a complex product by a
        # factor of zero imaginary part, in fewer operations.
        rho_k = (self.rho ** np.arange(RHO_TABLE, dtype=np.int64)).astype(np.float32)
        self._rho_k = rho_k
        self._sigma_k = np.sqrt((1 - rho_k * rho_k) / 2)
        if self.enabled:
            marks = [np.asarray(used, dtype=bool).reshape(-1)]
            if used_dl_interference is not None:
                marks.append(np.asarray(used_dl_interference, dtype=bool).reshape(-1))
            for link in np.flatnonzero(np.concatenate(marks)).tolist():
                self._start(link)

    def refresh(self, links: np.ndarray, update: int) -> None:
        """Bring ``links`` (link numbers, repeats allowed) to grid update ``update``."""
        if not self.enabled:
            return
        updated = self.updated
        stale = links[updated[links] != update]
        if not stale.size:
            return
        if stale.size > 1:  # each link once, in order
            mark = self._mark
            mark[stale] = True
            stale = np.flatnonzero(mark)
            mark[stale] = False
        last = updated[stale]
        updated[stale] = update
        # A link's first use keeps the state drawn at the start; later ones step the AR(1).
        moved = last >= 0
        if not moved.all():
            stale, last = stale[moved], last[moved]
            if not stale.size:
                return
        gap = update - last
        if int(gap.max()) < RHO_TABLE and int(gap.min()) >= 0:
            rho = self._rho_k.take(gap)
            sigma = self._sigma_k.take(gap)
        else:
            rho = (self.rho ** gap).astype(np.float32)
            sigma = np.sqrt((1 - rho * rho) / 2)
        nxt = self._next
        pos = nxt[stale]
        spent = pos == INNOVATION_BLOCK
        if spent.any():
            for link in stale[spent].tolist():
                gen = self._gens[link]
                if gen is None:
                    raise ValueError(f"link {link} was not marked used")
                gen.standard_normal(out=self._innovations[link], dtype=np.float32)
            pos[spent] = 0
        nxt[stale] = pos + 1
        # The innovations have variance 2 (two unit-variance parts): scale to CN(0, 1 - rho^2k).
        # Row gathers (take) and in-place operations on the float32 views (real and imaginary
        # parts side by side): the same numbers as the plain expression rho d + sigma e, with
        # fewer passes over the links.
        d = self._diffuse.take(stale, axis=0)
        dv = d.view(np.float32)
        dv *= rho[:, None]
        e = self._innovation_rows.take(stale * INNOVATION_BLOCK + pos, axis=0)
        ev = e.view(np.float32)
        ev *= sigma[:, None]
        dv += ev
        self._diffuse[stale] = d
        dv *= self._diffuse_amp.take(stale)[:, None]
        h = self._los_term.take(stale, axis=0)
        hv = h.view(np.float32)
        hv += dv
        g = np.abs(h)
        g *= g
        self.gain[stale] = g

    def export(self, links: list[int]) -> dict[str, Any]:
        """Everything that decides the next gains of ``links``: their gains, states, grid update,
        innovations left and streams' positions (as ``load`` takes it). A process stepped by one
        partition of the hall until now and by another from now on moves with it."""
        idx = np.asarray(links, dtype=np.int64)
        gens = [self._gens[link] for link in links]
        return {"links": list(links), "updated": self.updated[idx].tolist(),
                "next": self._next[idx].tolist(), "gain": self.gain[idx].tobytes(),
                "diffuse": self._diffuse[idx].tobytes(),
                "innovations": self._innovations[idx].tobytes(),
                "streams": [json.dumps(g.bit_generator.state) if g is not None else "" for g in gens]}

    def load(self, state: dict[str, Any]) -> None:
        """Take over the processes ``export`` gave: from now on they continue here as they
        would have where they were."""
        links = list(state["links"])
        if not links:
            return
        idx = np.asarray(links, dtype=np.int64)
        n, m = len(links), self.n_subbands
        self.updated[idx] = state["updated"]
        self._next[idx] = state["next"]
        self.gain[idx] = np.frombuffer(state["gain"], dtype=np.float32).reshape(n, m)
        self._diffuse[idx] = np.frombuffer(state["diffuse"], dtype=np.complex64).reshape(n, m)
        self._innovations[idx] = np.frombuffer(state["innovations"], dtype=np.float32).reshape(
            n, INNOVATION_BLOCK, m, 2)
        for link, stream in zip(links, state["streams"], strict=True):
            gen = self._gens[link]
            if stream and gen is not None:
                gen.bit_generator.state = json.loads(stream)

    def _start(self, link: int) -> None:
        """First use of ``link``: its stream, K-factor, LOS phases and diffuse state."""
        pair = link % self.dl_interference_offset
        kind = "fading" if link < self.dl_interference_offset else "fading-dl"
        ue, gnb = divmod(pair, self.n_gnb)
        gen = named_rng(self.seed, f"{self.prefix}/{kind}/{self.ue_ids[ue]}/{self.gnb_ids[gnb]}")
        self._gens[link] = gen
        k_db = float(gen.normal(self.k_mean_db, self.k_std_db))
        k_lin = 10 ** (k_db / 10) if self.los[pair] else 0.0
        m = self.n_subbands
        phases = gen.uniform(0, 2 * math.pi, m)
        self._los_term[link] = math.sqrt(k_lin / (k_lin + 1)) * np.exp(1j * phases)
        self._diffuse_amp[link] = math.sqrt(1 / (k_lin + 1))
        z = gen.standard_normal((m, 2))
        self._diffuse[link] = (z[:, 0] + 1j * z[:, 1]) / math.sqrt(2.0)
        h = self._los_term[link] + self._diffuse_amp[link] * self._diffuse[link]
        self.gain[link] = np.abs(h) ** 2


class ServingLinks(SubbandGains):
    """One gNB's view of the links to its UEs: ``links`` (their link numbers in ``fading``, in
    the cell's UE order), with per UE the mean SNR per PRB with the whole power over the
    carrier, UL (``ul_snr_fullband_db``) and DL (``dl_snr_db``), the LOS state ``los`` and the
    distance ``d3d_m`` (m). ``advance`` brings their fading to a slot, as ``InfSlChannel`` does."""

    def __init__(self, fading: LinkFading, links: np.ndarray, ul_snr_fullband_db: np.ndarray,
                 dl_snr_db: np.ndarray, los: np.ndarray, d3d_m: np.ndarray) -> None:
        self.fading = fading
        self.links = links
        self.n_ue = len(links)
        self.n_subbands = fading.n_subbands
        self.ul_snr_fullband_db = ul_snr_fullband_db
        self.dl_snr_db = dl_snr_db
        self.ul_snr_fullband = (10 ** (ul_snr_fullband_db / 10)).tolist()
        self.dl_snr = (10 ** (dl_snr_db / 10)).tolist()
        self.los = los
        self.d3d_m = d3d_m
        self.gain = np.ones((self.n_ue, self.n_subbands))
        self._rows = [None] * self.n_ue
        self._update: int | None = None

    def move(self, u: int, ul_snr_fullband_db: float, dl_snr_db: float) -> None:
        """UE index ``u`` moved: its mean SNRs (dB, as the constructor's) are now these."""
        self.ul_snr_fullband_db[u] = ul_snr_fullband_db
        self.dl_snr_db[u] = dl_snr_db
        self.ul_snr_fullband[u] = 10 ** (ul_snr_fullband_db / 10)
        self.dl_snr[u] = 10 ** (dl_snr_db / 10)

    def advance(self, slot: int) -> bool:
        """Bring the links to slot index ``slot``; True if their gains changed (never without
        fading: then, as in ``InfSlChannel``, the gains stay 1)."""
        fading = self.fading
        update = slot // fading.period
        if update == self._update or not fading.enabled:
            return False
        self._update = update
        fading.refresh(self.links, update)
        self.gain = fading.gain.take(self.links, axis=0)
        self._rows = [None] * self.n_ue
        return True
