"""Several federates served by one process as one participant of the window protocol (the
``core`` group; docs/architecture.md sec. 3, "Groups" and "Long windows").

Members' events are merged, earliest first; a message between members is handed over in
memory, timed as on the bus. The conductor sees one participant, whose ``done`` counts only
messages leaving the group and carries the group's horizon; members may work ahead in a
background thread (``work_ahead``). Each member keeps its own records, trace and report.
"""

from __future__ import annotations

import heapq
import logging
import time
from typing import Any

from fabric import keys
from fabric.federate import EXIT_FAILED, Federate, FederateContext, MessageRejected
from fabric.messages import Advance, Done, Message

log = logging.getLogger(__name__)


class FederateGroup(Federate):
    """Serves ``members`` (built on this group's bus) as the participant ``ctx.name``."""

    role = "group"

    def __init__(self, ctx: FederateContext, bus: Any, members: list[Federate]) -> None:
        super().__init__(ctx, bus)
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

    def accept(self, msg: Message) -> None:
        member = self.members.get(msg.dst)
        if member is None:
            raise MessageRejected(f"{self.name}: data message for {msg.dst!r}, which this group does not host")
        member.accept(msg)
        heapq.heappush(self._outside_pending, msg.t_us)

    # ---- protocol -----------------------------------------------------------------------------
    def connect(self) -> None:
        run = self.ctx.run_id
        for m in self.members.values():
            for plane in m.data_planes:
                self.bus.subscribe(keys.inbox(run, plane, m.name), self._enqueue("data"))
            self.bus.declare_token(keys.alive(run, m.name))
        self.bus.subscribe(keys.advance(run), self._enqueue("advance"))
        self.bus.subscribe(keys.stop(run), self._enqueue("stop"))
        self.bus.watch_liveliness(keys.coordinator_alive(run), self._on_coordinator)
        self.bus.declare_token(keys.alive(run, self.name))

    def setup(self) -> None:
        for m in self.members.values():
            m.setup()

    def flush_outbox(self) -> None:
        for m in self.members.values():
            m.flush_outbox()

    def close(self) -> None:
        for m in self.members.values():
            try:
                m.close()
            except Exception:
                log.exception("%s: closing %s failed", self.name, m.name)

    def process_window(self, adv: Advance) -> Done:
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
            best._busy_s += time.perf_counter() - t0
        for m in members:
            self._current = m
            m.end_window(adv)
        self._current = None
        self._window = adv.window
        self.window_end = t_end
        self.now = max(m.now for m in members)
        sent: dict[str, int] = {}
        for m in members:
            for dst, n in m._sent_to.items():
                if dst not in self.members:
                    sent[dst] = sent.get(dst, 0) + n
        earliest = [m._earliest_sent for m in members if m._earliest_sent is not None]
        nexts = [k[0] for m in members if (k := m.next_event_key()) is not None]
        horizons = [m.external_horizon_us() for m in members]
        horizon = None if None in horizons else min(h for h in horizons if h is not None)
        pending = self._outside_pending
        while pending and pending[0] < t_end:
            heapq.heappop(pending)
        if horizon is not None and pending:
            horizon = min(horizon, pending[0])
        return Done(federate=self.name, window=adv.window, t_end_us=t_end, sent_to=sent,
                    next_event_us=min(nexts, default=None), earliest_sent_us=min(earliest, default=None),
                    horizon_us=horizon)

    def _fail(self, pending: Advance | None, error: str) -> int:
        """Report the failure under the name of the member that failed (if one did)."""
        name = self._current.name if self._current is not None else self.name
        window = pending.window if pending is not None else self._window
        t_end = pending.t_end_us if pending is not None else self.window_end
        done = Done(federate=name, window=window, t_end_us=t_end, sent_to={}, next_event_us=None,
                    earliest_sent_us=None, error=error)
        self.bus.publish(keys.done(self.ctx.run_id, self.name), done.encode())
        self._close_records()
        return EXIT_FAILED

    def _stop(self, reason: str, t_us: int) -> int:
        if self._stopped:
            return 0
        self._stopped = True
        for m in self.members.values():
            try:
                m._stop(reason, t_us)
            except Exception:
                log.exception("%s: stopping %s failed", self.name, m.name)
        return 0

    def _close_records(self, collect: bool = True, upto_us: int | None = None) -> None:
        for m in self.members.values():
            m._close_records(collect, upto_us)
