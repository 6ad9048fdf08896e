"""Handover of moving UEs between the gNBs of a hall: layer-3 filtered RSRP per gNB (TS 38.331
5.5.3.2), event A3 held for the time to trigger (5.5.4.4), then an interruption during which the
UE has no cell and the packets held for it are forwarded to the target cell or lost.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from fabric.seeding import rng as named_rng
from scenario.schema import FILTER_COEFFICIENTS, TIME_TO_TRIGGER_MS, HandoverConfig

# X of TS 38.331 5.5.3.2, the input period the filter coefficient k assumes: one FR1
# intra-frequency L1 measurement period without DRX, max(200 ms, ceil(5 Kp) x SMTC period) x
# CSSF in TS 38.133 Table 9.2.5.2-1, 200 ms for an SMTC of up to 40 ms on one carrier.
L1_MEASUREMENT_PERIOD_MS = 200.0


def filter_weight(k: int, period_ms: float,
                  l1_period_ms: float = L1_MEASUREMENT_PERIOD_MS) -> float:
    """The weight a of F_n = (1 - a) F_{n-1} + a M_n for one measurement every ``period_ms``.

    a = 1/2^(k/4) at the input period ``l1_period_ms`` (X) that k assumes; at another period the
    filter keeps its time characteristics (TS 38.331 5.5.3.2: "adapt the filter such that the
    time characteristics of the filter are preserved at different input rates"): the memory left
    after X ms stays (1 - a), so a' = 1 - (1 - a)^(period / X). k = 0 is no filtering (a = 1).
    """
    if k not in FILTER_COEFFICIENTS:
        raise ValueError(f"filter coefficient k = {k} is not a TS 38.331 filterCoefficient: "
                         f"allowed {', '.join(map(str, FILTER_COEFFICIENTS))}")
    if not period_ms > 0:
        raise ValueError(f"measurement period {period_ms} ms must be positive")
    a = 2.0 ** (-k / 4)
    return 1.0 - (1.0 - a) ** (period_ms / l1_period_ms)


class L3Filter:
    """Layer-3 filter of every (UE, gNB) measurement, in dB (TS 38.331 5.5.3.2 NOTE 2:
    logarithmic filtering of logarithmic quantities): F_1 = M_1, then
    F_n = (1 - a) F_{n-1} + a M_n with ``a`` from ``filter_weight``."""

    def __init__(self, a: float) -> None:
        if not 0.0 < a <= 1.0:
            raise ValueError(f"filter weight a = {a} must lie in (0, 1]")
        self.a = a
        self.values: np.ndarray | None = None

    def update(self, measured: np.ndarray) -> np.ndarray:
        """Feed one measurement of every entry (any shape, the same each time); the filtered
        values."""
        m = np.asarray(measured, dtype=float)
        if self.values is None:
            self.values = m.copy()
        else:
            self.values = (1.0 - self.a) * self.values + self.a * m
        return self.values


@dataclass(frozen=True)
class HandoverParams:
    """The handover settings (``scenario.schema.HandoverConfig``), in the units the control
    uses: dB, integer milliseconds for the trigger and measurement period."""

    filter_k: int = 4
    a3_offset_db: float = 0.0
    hysteresis_db: float = 3.0
    time_to_trigger_ms: int = 256
    interruption_ms: float = 50.0
    forward: bool = True
    measurement_period_ms: int = 20
    measurement_noise_db: float = 0.0

    def __post_init__(self) -> None:
        if self.time_to_trigger_ms not in TIME_TO_TRIGGER_MS:
            raise ValueError(
                f"time_to_trigger_ms = {self.time_to_trigger_ms} is not a TS 38.331 "
                f"TimeToTrigger: allowed {', '.join(map(str, TIME_TO_TRIGGER_MS))} ms")
        filter_weight(self.filter_k, self.measurement_period_ms)
        for name, value in (("hysteresis_db", self.hysteresis_db),
                            ("interruption_ms", self.interruption_ms),
                            ("measurement_noise_db", self.measurement_noise_db)):
            if not value >= 0:
                raise ValueError(f"{name} = {value} must be >= 0")

    @classmethod
    def from_config(cls, cfg: HandoverConfig) -> HandoverParams:
        """The settings of a scenario's ``netsim.handover``."""
        return cls(cfg.filter_k, cfg.a3_offset_db, cfg.hysteresis_db, cfg.time_to_trigger_ms,
                   cfg.interruption_ms, cfg.forward, cfg.measurement_period_ms,
                   cfg.measurement_noise_db)

    @property
    def filter_a(self) -> float:
        return filter_weight(self.filter_k, self.measurement_period_ms)

    @property
    def measurement_period_us(self) -> int:
        return self.measurement_period_ms * 1000

    @property
    def time_to_trigger_us(self) -> int:
        return self.time_to_trigger_ms * 1000

    @property
    def interruption_us(self) -> int:
        return int(round(self.interruption_ms * 1000))


class CellQueues(Protocol):
    """What a radio cell offers the handover control, per UE (named as the cell names it).

    ``detach(ue, t_us)``: the UE leaves the cell at ``t_us``; the cell stops scheduling it, drops
    its state (HARQ, grants) and returns the packets it held for it, oldest first (which ones, DL
    at the gNB and/or UL data not yet received, is the cell's choice).
    ``attach(ue, t_us, packets)``: the UE joins the cell at ``t_us``; ``packets`` (possibly none)
    enter its queues in order, as if they arrived at ``t_us``.
    """

    def detach(self, ue: str, t_us: int) -> list[Any]: ...

    def attach(self, ue: str, t_us: int, packets: list[Any]) -> None: ...


@dataclass(eq=False)
class Handover:
    """One handover of UE ``ue`` from gNB ``source`` to gNB ``target``: the UE has no cell from
    ``start_us`` (the A3 event fired) to ``end_us``. ``held`` gathers the packets detached from
    the source and those reaching the UE meanwhile (``HandoverControl.hold``); at the end they
    are ``forwarded`` to the target, or ``lost``."""

    ue: str
    source: int
    target: int
    start_us: int
    end_us: int
    held: list[Any] = field(default_factory=list)
    forwarded: int = 0
    lost: list[Any] = field(default_factory=list)
    done: bool = False


@dataclass
class TickOutcome:
    """What one ``HandoverControl.tick`` did: the handovers it started and completed, in time
    order (a completed one with ``lost`` packets leaves their loss to be recorded)."""

    started: list[Handover] = field(default_factory=list)
    completed: list[Handover] = field(default_factory=list)


class HandoverControl:
    """Measurement, A3 evaluation and handover execution for a fixed set of UEs.

    ``ue_ids`` name the UEs (as the cells and the random streams know them), ``serving`` their
    gNB index at the start (e.g. ``interference.serving_gnb``), ``n_gnb`` the gNBs. Measurements
    happen every ``params.measurement_period_ms`` from ``first_measurement_us``. Measurement
    errors, if ``params.measurement_noise_db`` > 0, come from the stream
    ``<stream_prefix>/<ue id>`` of ``seed``, one per UE, so a UE's draws do not depend on the
    others.

    ``serving[u]`` is the UE's gNB, -1 while a handover interrupts it. The control keeps every
    handover in ``handovers``, running and done, in start order.
    """

    def __init__(self, params: HandoverParams, ue_ids: Sequence[str],
                 serving: Sequence[int] | np.ndarray, n_gnb: int, seed: int = 0,
                 stream_prefix: str = "handover", first_measurement_us: int = 0) -> None:
        self.params = params
        self.ue_ids = list(ue_ids)
        self.index = {ue: u for u, ue in enumerate(self.ue_ids)}
        if len(self.index) != len(self.ue_ids):
            raise ValueError("UE ids must be unique")
        self.n_gnb = n_gnb
        self.serving = np.asarray(serving, dtype=int).copy()
        if self.serving.shape != (len(self.ue_ids),):
            raise ValueError(f"{self.serving.shape} serving gNBs for {len(self.ue_ids)} UEs")
        if np.any((self.serving < 0) | (self.serving >= n_gnb)):
            raise ValueError(f"serving gNBs must lie in 0..{n_gnb - 1}")
        self.filter = L3Filter(params.filter_a)
        self.next_measurement_us = first_measurement_us
        # Since when the A3 entering condition has held without a break, per (UE, gNB); -1: not.
        self._since_us = np.full((len(self.ue_ids), n_gnb), -1, dtype=np.int64)
        self._rngs = ([named_rng(seed, f"{stream_prefix}/{ue}") for ue in self.ue_ids]
                      if params.measurement_noise_db > 0 else [])
        self._running: dict[int, Handover] = {}
        self.handovers: list[Handover] = []

    # --- queries -------------------------------------------------------------------------

    def serving_of(self, ue: str) -> int | None:
        """The gNB serving ``ue`` now, None during a handover."""
        g = int(self.serving[self.index[ue]])
        return None if g < 0 else g

    def in_handover(self, ue: str) -> bool:
        return self.index[ue] in self._running

    def running(self, ue: str) -> Handover | None:
        """``ue``'s handover under way, None if it has a cell."""
        return self._running.get(self.index[ue])

    def next_event_us(self) -> int:
        """The next time ``tick`` has something to do (a measurement or a handover's end)."""
        ends = [h.end_us for h in self._running.values()]
        return min([self.next_measurement_us, *ends])

    # --- inputs --------------------------------------------------------------------------

    def hold(self, ue: str, packets: Sequence[Any]) -> None:
        """Packets reaching ``ue`` during its handover (DL for it, or UL it produced): kept with
        its held packets, forwarded or lost with them."""
        h = self._running.get(self.index[ue])
        if h is None:
            raise ValueError(f"{ue} is not in a handover: its packets go to its cell")
        h.held.extend(packets)

    def tick(self, t_us: int, rsrp_dbm: Callable[[int], np.ndarray],
             cells: Sequence[CellQueues]) -> TickOutcome:
        """Do everything due up to and including ``t_us``, in time order: handovers ending
        (attach to the target, or lose the held packets) before measurements at the same time,
        and every measurement instant (``rsrp_dbm(t)``: the RSRP of every (UE, gNB) link at
        time t, dBm, shape (n_ue, n_gnb); ``cells[g]``: gNB g's cell)."""
        out = TickOutcome()
        while True:
            ending = min(self._running.items(), key=lambda item: (item[1].end_us, item[0]),
                         default=None)
            end_us = math.inf if ending is None else ending[1].end_us
            if ending is not None and end_us <= t_us and end_us <= self.next_measurement_us:
                out.completed.append(self._complete(ending[0], cells))
            elif self.next_measurement_us <= t_us:
                t = self.next_measurement_us
                self.next_measurement_us += self.params.measurement_period_us
                out.started.extend(self._measure(t, rsrp_dbm(t), cells))
            else:
                return out

    # --- internals -----------------------------------------------------------------------

    def _measure(self, t_us: int, rsrp_dbm: np.ndarray, cells: Sequence[CellQueues]
                 ) -> list[Handover]:
        p = self.params
        m = np.array(rsrp_dbm, dtype=float)
        if m.shape != (len(self.ue_ids), self.n_gnb):
            raise ValueError(f"RSRP of shape {m.shape}, expected {(len(self.ue_ids), self.n_gnb)}")
        if self._rngs:
            m += p.measurement_noise_db * np.array(
                [g.standard_normal(self.n_gnb) for g in self._rngs])
        f = self.filter.update(m)
        connected = self.serving >= 0
        rows = np.arange(len(self.ue_ids))
        fs = f[rows, np.where(connected, self.serving, 0)]
        # A3 entering condition (TS 38.331 5.5.4.4, no frequency or cell offsets):
        # Mn - Hys > Mp + Off, for every neighbour of every connected UE.
        enter = (f - p.hysteresis_db > (fs + p.a3_offset_db)[:, None]) & connected[:, None]
        enter[rows[connected], self.serving[connected]] = False
        self._since_us = np.where(enter, np.where(self._since_us >= 0, self._since_us, t_us), -1)
        fired = enter & (t_us - self._since_us >= p.time_to_trigger_us)
        started = []
        for u in np.flatnonzero(fired.any(axis=1)):
            target = int(np.argmax(np.where(fired[u], f[u], -np.inf)))
            started.append(self._start(int(u), target, t_us, cells))
        return started

    def _start(self, u: int, target: int, t_us: int, cells: Sequence[CellQueues]) -> Handover:
        ue, source = self.ue_ids[u], int(self.serving[u])
        h = Handover(ue, source, target, t_us, t_us + self.params.interruption_us,
                     list(cells[source].detach(ue, t_us)))
        self.serving[u] = -1
        self._since_us[u] = -1
        self._running[u] = h
        self.handovers.append(h)
        return h

    def _complete(self, u: int, cells: Sequence[CellQueues]) -> Handover:
        h = self._running.pop(u)
        if self.params.forward:
            cells[h.target].attach(h.ue, h.end_us, h.held)
            h.forwarded = len(h.held)
        else:
            cells[h.target].attach(h.ue, h.end_us, [])
            h.lost = h.held
        h.held = []
        h.done = True
        self.serving[u] = h.target
        self._since_us[u] = -1
        return h


def ping_pongs(handovers: Sequence[Handover], min_stay_us: int = 1_000_000,
               into: Container[int] | None = None) -> int:
    """Handovers back to the cell a UE left less than ``min_stay_us`` before (measured from the
    end of the handover that brought it to the cell it leaves); with ``into``, only those into
    these gNBs (a partition's; ``handovers`` must still hold every one of the UE's)."""
    count = 0
    last: dict[str, Handover] = {}
    for h in sorted(handovers, key=lambda h: h.start_us):
        prev = last.get(h.ue)
        if (prev is not None and h.target == prev.source and h.start_us - prev.end_us < min_stay_us
                and (into is None or h.target in into)):
            count += 1
        last[h.ue] = h
    return count
