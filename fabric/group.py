"""Several federates served by one process as one participant of the window protocol (the
``core`` group; docs/architecture.md sec. 3, "Groups" and "Long windows").

Members' events are merged, earliest first; a message between members is handed over in
memory, timed as on the bus. The conductor sees one participant, whose report counts only
messages leaving the group and carries the group's horizon; members may work ahead in a
background thread (``work_ahead``). Each member keeps its own records, trace and report.
"""

from __future__ import annotations

import heapq
import logging
import time
from collections.abc import Sequence

from fabric.bus import Bus
from fabric.driver import WindowReport
from fabric.federate import Federate, FederateContext, MessageRejected
from fabric.messages import Advance, Message, Stopped

log = logging.getLogger(__name__)


class FederateGroup:
    """Serves ``members`` (built on this group's bus) as the participant ``ctx.name``."""

    def __init__(self, ctx: FederateContext, bus: Bus, members: Sequence[Federate]) -> None:
        self.name = ctx.name
        self.run_id = ctx.run_id
        self.bus = bus
        self.base_window_us = ctx.scenario.window_us
        self.members = {m.name: m for m in members}
        names = frozenset(self.members)
        for m in members:
            m.cohosted = names
            m.deliver_local = self._deliver_local
        # Members that work ahead (``work_ahead``), with the other members and the planes that
        # may reach them.
        self._workers = [(m, [o for o in members if o is not m], m.data_planes)
                         for m in members if type(m).work_ahead is not Federate.work_ahead]
        self._current: Federate | None = None  # the member processing, to name it when it fails
        # Delivery times of the messages from outside not yet processed: a member's horizon
        # holds only until one of them arrives, which may make it send at once.
        self._outside_pending: list[int] = []

    def _deliver_local(self, msg: Message) -> None:
        self.members[msg.dst].accept(msg)

    # ---- as a participant of the window protocol (``fabric.driver``) ----------------------------
    def hosted(self) -> list[Federate]:
        return list(self.members.values())

    def culprit(self) -> str:
        return self._current.name if self._current is not None else self.name

    def accept(self, msg: Message) -> None:
        member = self.members.get(msg.dst)
        if member is None:
            raise MessageRejected(f"{self.name}: data message for {msg.dst!r}, which this group does not host")
        member.accept(msg)
        heapq.heappush(self._outside_pending, msg.t_us)

    def setup(self) -> None:
        for m in self.members.values():
            self._current = m
            m.setup()
        self._current = None

    def flush_outbox(self) -> None:
        for m in self.members.values():
            m.flush_outbox()

    def close(self) -> None:
        for m in self.members.values():
            try:
                m.close()
            except Exception:
                log.exception("%s: closing %s failed", self.name, m.name)

    def process_window(self, adv: Advance) -> WindowReport:
        members = list(self.members.values())
        t_end = adv.t_end_us
        base = self.base_window_us
        for m in members:
            m.begin_window(adv)
        while True:
            best, best_key = None, None
            for m in members:
                k = m.next_event_key()
                if k is not None and k[0] < t_end and (best_key is None or k < best_key):
                    best, best_key = m, k
            if best is None:
                break
            self._current = best
            t0 = time.perf_counter()
            best.process_next()
            now = best.now
            for worker, others, planes in self._workers:
                if worker.working_ahead():
                    continue
                # A message sent at s is delivered at the end of s's base window at the earliest.
                until = t_end
                for o in others:
                    for plane in planes:
                        until = min(until, (o.next_send_us(plane, now) // base + 1) * base)
                worker.work_ahead(until)
            best.add_busy(time.perf_counter() - t0)
        for m in members:
            self._current = m
            m.end_window(adv)
        self._current = None
        return self._report(t_end)

    def _report(self, t_end: int) -> WindowReport:
        """The members' reports as one: messages leaving the group, and the group's horizon."""
        reports = [m.report() for m in self.members.values()]
        sent: dict[str, int] = {}
        for r in reports:
            for dst, n in r.sent_to.items():
                if dst not in self.members:
                    sent[dst] = sent.get(dst, 0) + n
        horizons = [m.external_horizon_us() for m in self.members.values()]
        horizon = None if None in horizons else min(h for h in horizons if h is not None)
        pending = self._outside_pending
        while pending and pending[0] < t_end:
            heapq.heappop(pending)
        if horizon is not None and pending:
            horizon = min(horizon, pending[0])
        return WindowReport(
            sent_to=sent,
            next_event_us=min((r.next_event_us for r in reports if r.next_event_us is not None), default=None),
            earliest_sent_us=min((r.earliest_sent_us for r in reports if r.earliest_sent_us is not None),
                                 default=None),
            horizon_us=horizon)

    def stop(self, reason: str, t_us: int | None = None) -> list[Stopped]:
        records = []
        for m in self.members.values():
            try:
                records += m.stop(reason, t_us)
            except Exception:
                log.exception("%s: stopping %s failed", self.name, m.name)
        return records

    def close_records(self) -> None:
        for m in self.members.values():
            m.close_records()
