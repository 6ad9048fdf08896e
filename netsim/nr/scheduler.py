"""Schedulers behind one interface: proportional fair, round robin, max rate.

A scheduler only ranks: given the UEs that could get a new transmission in a slot, it returns
them in service order; the cell then gives each, in turn, the PRBs its buffer needs until the
slot is full. Retransmissions are placed before any ranking. QoS priority is strict: a UE whose
most important non-empty flow has a lower ``priority`` value is always ranked first, the policy
orders UEs of equal priority. Ties break on the UE index, so ranking is deterministic.
"""

from __future__ import annotations

import heapq
from abc import ABC, abstractmethod
from collections.abc import Iterator
from typing import Literal

SchedulerKind = Literal["pf", "rr", "max_rate"]


class Scheduler(ABC):
    """Ranks candidate UEs (indices 0..``n_ue`` - 1) of one link; told afterwards what each
    served UE got."""

    def __init__(self, n_ue: int) -> None:
        self.n_ue = n_ue

    @abstractmethod
    def order(self, candidates: list[int], priority: list[int],
              rate: list[float], slot: int, urgency: list[float] | None = None) -> list[int]:
        """``candidates`` in service order in slot index ``slot``. ``priority[u]`` is UE u's QoS
        priority (lower first), ``rate[u]`` its achievable rate estimate (bits per PRB),
        ``urgency[u]`` the weight of its dynamic delay budget (None: all 1)."""

    def ranked(self, candidates: list[int], priority: list[int],
               rate: list[float], slot: int,
               urgency: list[float] | None = None) -> Iterator[int]:
        """``order`` of ``candidates`` (same ``priority``, ``rate``, ``slot`` and ``urgency``)
        as an iterator (the ranking is fixed when this is called): the cell usually takes only
        the first UE or two, so a policy may rank lazily."""
        return iter(self.order(candidates, priority, rate, slot, urgency))

    def served(self, ue: int, bits: int, slot: int) -> None:  # noqa: B027 - optional hook
        """UE ``ue`` got a new transmission of ``bits`` in ``slot``."""


class ProportionalFair(Scheduler):
    """argmax w_u r_u / T_u with T_u(t) = beta T_u(t-1) + (1 - beta) R_u(t), beta =
    ``forgetting_factor``, over ``n_ue`` UEs; w_u is the UE's urgency (1 unless a dynamic delay budget was signalled for its flow: PF weighted by urgency).

    T is kept lazily: (value, slot of the value); a UE not served for k slots decays by beta^k,
    which is the recursion with R = 0 without touching every UE every slot.
    """

    def __init__(self, n_ue: int, forgetting_factor: float) -> None:
        super().__init__(n_ue)
        self.beta = forgetting_factor
        self.avg_bits = [0.0] * n_ue
        self.avg_slot = [0] * n_ue
        # beta**k for the decay gaps seen most (the same float as computing it each time).
        self._powers = [forgetting_factor**k for k in range(256)]

    def average(self, ue: int, slot: int) -> float:
        """T_u(slot - 1) of UE index ``ue``, the average served bits per slot before slot index
        ``slot``."""
        return self.avg_bits[ue] * self.beta ** max(0, slot - 1 - self.avg_slot[ue])

    def _metrics(self, candidates: list[int], rate: list[float], slot: int,
                 urgency: list[float] | None) -> list[float]:
        """-w r / T per candidate (lower is served first within a priority class)."""
        # Inlined loop rather than a sort key function: this runs every slot for every
        # backlogged UE and is the scheduler's whole cost.
        avg, last = self.avg_bits, self.avg_slot
        powers = self._powers
        n_powers = len(powers)
        prev = slot - 1
        metrics: list[float] = []
        append = metrics.append
        for u in candidates:
            t = avg[u]
            w = 1.0 if urgency is None else urgency[u]
            if t > 1e-9:
                k = prev - last[u]
                if k > 0:
                    t *= powers[k] if k < n_powers else self.beta**k
            else:
                t = 0.0
            # A UE starved for thousands of slots has its average underflow to 0.0: it then
            # ranks as one never served (T = 0), first within its priority class.
            if t > 0.0:
                # -1.0 * r is exactly -r: the common unweighted case skips the product.
                append((-rate[u] if w == 1.0 else -w * rate[u]) / t)
            else:  # never served (T = 0): first within its priority class, the urgent first
                append(-1e300 * w)
        return metrics

    def order(self, candidates: list[int], priority: list[int],
              rate: list[float], slot: int, urgency: list[float] | None = None) -> list[int]:
        metrics = self._metrics(candidates, rate, slot, urgency)
        keyed = sorted(zip([priority[u] for u in candidates], metrics, candidates, strict=True))
        return [k[2] for k in keyed]

    def ranked(self, candidates: list[int], priority: list[int],
               rate: list[float], slot: int,
               urgency: list[float] | None = None) -> Iterator[int]:
        """``order`` of ``candidates`` by ``priority``, ``rate`` and ``urgency``, taken lazily:
        the cell rarely serves more than a UE or two a slot.

        The order is that of the keys (priority, metric, UE), all distinct. With one priority
        class (the usual case) the next UE is the smallest metric, the lowest UE among equal
        ones: found by one pass over the metrics rather than by comparing tuples."""
        metrics = self._metrics(candidates, rate, slot, urgency)
        prios = [priority[u] for u in candidates]
        if prios and prios.count(prios[0]) == len(prios):
            return self._pop_best(list(candidates), metrics)
        keyed = list(zip(prios, metrics, candidates, strict=True))
        heapq.heapify(keyed)
        return self._pop_all(keyed)

    @staticmethod
    def _pop_all(heap: list[tuple[int, float, int]]) -> Iterator[int]:
        pop = heapq.heappop
        while heap:
            yield pop(heap)[2]

    @staticmethod
    def _pop_best(ues: list[int], metrics: list[float]) -> Iterator[int]:
        # One plain pass per pick: compiled (fabric.native), it compares C doubles.
        while metrics:
            i = 0
            best = metrics[0]
            for j in range(1, len(metrics)):
                m = metrics[j]
                # A tie (equal metrics): the lowest UE index first.
                if m < best or (m == best and ues[j] < ues[i]):
                    best = m
                    i = j
            yield ues[i]
            del metrics[i], ues[i]

    def served(self, ue: int, bits: int, slot: int) -> None:
        self.avg_bits[ue] = self.beta * self.average(ue, slot) + (1 - self.beta) * bits
        self.avg_slot[ue] = slot


class RoundRobin(Scheduler):
    """The UE served longest ago goes first, among ``n_ue`` UEs."""

    def __init__(self, n_ue: int) -> None:
        super().__init__(n_ue)
        self.last_served = [-1] * n_ue

    def order(self, candidates: list[int], priority: list[int],
              rate: list[float], slot: int, urgency: list[float] | None = None) -> list[int]:
        last = self.last_served
        return sorted(candidates, key=lambda u: (priority[u], last[u], u))

    def served(self, ue: int, bits: int, slot: int) -> None:
        self.last_served[ue] = slot


class MaxRate(Scheduler):
    """The UE with the best channel goes first (maximises cell throughput, starves the edge)."""

    def order(self, candidates: list[int], priority: list[int],
              rate: list[float], slot: int, urgency: list[float] | None = None) -> list[int]:
        return sorted(candidates, key=lambda u: (priority[u], -rate[u], u))


def make_scheduler(kind: SchedulerKind, n_ue: int, pf_forgetting_factor: float) -> Scheduler:
    """The scheduler called ``kind`` for ``n_ue`` UEs (``pf_forgetting_factor``: PF's beta,
    unused by the others)."""
    if kind == "pf":
        return ProportionalFair(n_ue, pf_forgetting_factor)
    if kind == "rr":
        return RoundRobin(n_ue)
    if kind == "max_rate":
        return MaxRate(n_ue)
    raise ValueError(f"scheduler {kind!r} is not one of pf, rr, max_rate")
