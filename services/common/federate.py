"""The federate base: the conservative window protocol of DESIGN 3, shared by every federate.

A federate receives ``advance(t_end, expected_in)``, waits until it holds every data message sent
to it so far (count-based barrier), then processes every input and internal event with time
< t_end in (t_us, source, seq) order -- never arrival order -- and replies ``done`` with the
cumulative count of messages it sent per destination and its next event time. Every message it
sends must be delivered at or after the end of the current window; breaking that is a bug and
fails the federate at once. Each processed and sent event feeds the federate's trace hash.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import os
import queue
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from services.common import keys, metrics
from services.common.bus import Bus
from services.common.messages import Advance, Done, Message, Ready, Stop, Stopped
from services.common.scenario import Scenario
from services.common.seeding import rng

log = logging.getLogger(__name__)


class CausalityError(RuntimeError):
    """A federate tried to deliver a message inside the current window or in the past."""


@dataclass(frozen=True)
class FederateContext:
    """What a federate is given at start: who it is and where it runs."""

    name: str
    run_id: str
    scenario: Scenario
    results_dir: Path


_EVENT = 0  # heap entry kinds; internal events sort with the federate's own name as source
_MESSAGE = 1
_LAST = "\uffff"  # sorts after every federate name


class Federate:
    """Base class. Subclasses override ``setup``, ``on_message``, ``finish``; they schedule
    internal events with ``schedule`` and send with ``send``; ``now`` is the current time."""

    role = "federate"
    data_planes: tuple[str, ...] = ("sense", "act", "net")

    def __init__(self, ctx: FederateContext, bus: Bus) -> None:
        self.ctx = ctx
        self.name = ctx.name
        self.scenario = ctx.scenario
        self.bus = bus
        self.now = 0
        self.window_end = 0
        self._heap: list[tuple[int, str, int, int, Any]] = []
        self._inbox: queue.SimpleQueue[tuple[str, str, bytes]] = queue.SimpleQueue()
        # Received data messages counted by the window they were sent in: a message sent in the
        # current window that overtakes a late one from an earlier window must not satisfy the
        # barrier in its place.
        self._received_settled = 0
        self._received_by_window: Counter[int] = Counter()
        self._window = 0
        self._sent_to: Counter[str] = Counter()
        self._out_seq = 0
        self._event_seq = 0
        self._earliest_sent: int | None = None
        self._trace = hashlib.sha256()
        self._events = 0
        self._stopped = False
        self._busy_s = 0.0  # wall time spent processing windows: where a slow run's time goes

    # ---- for subclasses -------------------------------------------------------------------
    def setup(self) -> None:
        """Heavy initialisation (models, renderers) before the federate reports ready."""

    def on_message(self, msg: Message) -> None:
        """Handle one data message at ``self.now == msg.t_us``."""

    def finish(self, reason: str) -> dict[str, Any]:
        """Write results; return a summary for the coordinator (numbers, strings)."""
        return {}

    def rng(self, component: str) -> Any:
        """The named random stream ``<federate>/<component>`` of this run."""
        return rng(self.scenario.seed, f"{self.name}/{component}")

    @property
    def results_dir(self) -> Path:
        return self.ctx.results_dir

    def schedule(self, t_us: int, fn: Callable[..., None], *args: Any, after_inputs: bool = False) -> None:
        """Run ``fn(*args)`` at simulated time ``t_us`` (>= now). Events at equal times run in
        scheduling order; ``after_inputs`` puts the event after every input message of that
        time (e.g. a radio slot that must see every packet handed over at its start)."""
        if t_us < self.now:
            raise CausalityError(f"{self.name}: event scheduled at {t_us} us, before now {self.now} us")
        self._event_seq += 1
        src = _LAST if after_inputs else self.name
        heapq.heappush(self._heap, (t_us, src, self._event_seq, _EVENT, (fn, args)))

    def send(self, dst: str, plane: str, kind: str, t_us: int, body: dict[str, Any] | None = None,
             blob: bytes | None = None) -> None:
        """Send a data message to ``dst`` to be delivered at ``t_us`` (>= end of this window)."""
        if t_us < self.window_end:
            raise CausalityError(
                f"{self.name}: {kind} to {dst} delivered at {t_us} us, inside the window ending "
                f"{self.window_end} us (latency below the window)"
            )
        self._out_seq += 1
        msg = Message(t_us, self.name, dst, self._out_seq, plane, kind, body or {}, blob, self._window)
        raw = msg.encode()
        self._trace.update(b"S")
        self._trace.update(raw)
        self._sent_to[dst] += 1
        if self._earliest_sent is None or t_us < self._earliest_sent:
            self._earliest_sent = t_us
        self.bus.publish(keys.data(self.ctx.run_id, plane, dst, self.name), raw)
        metrics.MESSAGES_SENT.labels(self.name, plane).inc()

    # ---- protocol -----------------------------------------------------------------------------
    def _enqueue(self, kind: str) -> Callable[[str, bytes], None]:
        def put(key: str, payload: bytes) -> None:
            self._inbox.put((kind, key, payload))

        return put

    def connect(self) -> None:
        """Subscribe to the inbox and control keys and declare the liveliness token."""
        run = self.ctx.run_id
        for plane in self.data_planes:
            self.bus.subscribe(keys.inbox(run, plane, self.name), self._enqueue("data"))
        self.bus.subscribe(keys.advance(run), self._enqueue("advance"))
        self.bus.subscribe(keys.stop(run), self._enqueue("stop"))
        self.bus.declare_token(keys.alive(run, self.name))

    def serve(self) -> int:
        """Run the federate until the coordinator stops it; returns a process exit code."""
        run = self.ctx.run_id
        self.connect()
        self.setup()
        self.bus.publish(keys.ready(run, self.name), Ready(federate=self.name, pid=os.getpid()).encode())
        pending: Advance | None = None
        while True:
            kind, key, payload = self._inbox.get()
            if kind == "data":
                msg = Message.decode(payload)
                heapq.heappush(self._heap, (msg.t_us, msg.src, msg.seq, _MESSAGE, msg))
                self._received_by_window[msg.window] += 1
            elif kind == "advance":
                pending = Advance.decode(payload)
            elif kind == "stop":
                stop = Stop.decode(payload)
                return self._stop(stop.reason, stop.t_us)
            if pending is not None and self._received_before(pending.window) >= pending.expected_in.get(self.name, 0):
                try:
                    t0 = time.perf_counter()
                    done = self.process_window(pending)
                    self._busy_s += time.perf_counter() - t0
                except Exception as exc:
                    log.error("window %d failed:\n%s", pending.window, traceback.format_exc())
                    done = Done(federate=self.name, window=pending.window, t_end_us=pending.t_end_us,
                                sent_to={}, next_event_us=None, earliest_sent_us=None,
                                error=f"{type(exc).__name__}: {exc}")
                    self.bus.publish(keys.done(run, self.name), done.encode())
                    return 1
                self.bus.publish(keys.done(run, self.name), done.encode())
                pending = None

    def _received_before(self, window: int) -> int:
        """Data messages received that were sent in windows before ``window``."""
        for w in [w for w in self._received_by_window if w < window]:
            self._received_settled += self._received_by_window.pop(w)
        return self._received_settled

    def process_window(self, adv: Advance) -> Done:
        """Process every event with time < ``adv.t_end_us`` in order; the done report."""
        self._window = adv.window
        self.window_end = adv.t_end_us
        self._earliest_sent = None
        events_before = self._events
        heap = self._heap
        while heap and heap[0][0] < adv.t_end_us:
            t_us, src, seq, kind, item = heapq.heappop(heap)
            if t_us < self.now:
                raise CausalityError(f"{self.name}: event at {t_us} us arrived after now {self.now} us")
            self.now = t_us
            self._events += 1
            if kind == _MESSAGE:
                self._trace.update(b"R")
                self._trace.update(msgpack.packb([t_us, src, seq, item.kind], use_bin_type=True))
                self.on_message(item)
            else:
                fn, args = item
                self._trace.update(b"E")
                self._trace.update(msgpack.packb([t_us, seq, fn.__name__], use_bin_type=True))
                fn(*args)
        metrics.WINDOWS.labels(self.name).inc()
        metrics.EVENTS.labels(self.name).inc(self._events - events_before)
        next_event = heap[0][0] if heap else None
        return Done(federate=self.name, window=adv.window, t_end_us=adv.t_end_us,
                    sent_to=dict(self._sent_to), next_event_us=next_event,
                    earliest_sent_us=self._earliest_sent)

    def _stop(self, reason: str, t_us: int) -> int:
        if self._stopped:
            return 0
        self._stopped = True
        summary = self.finish(reason)
        summary["busy_wall_s"] = round(self._busy_s, 3)
        summary["cpu_s"] = round(time.process_time(), 3)
        record = Stopped(federate=self.name, trace_hash=self._trace.hexdigest(), events=self._events,
                         summary=summary)
        self.bus.publish(keys.stopped(self.ctx.run_id, self.name), record.encode())
        return 0

    @property
    def trace_hash(self) -> str:
        return self._trace.hexdigest()
