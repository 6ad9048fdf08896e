"""The federate base: every federate's side of the window protocol (docs/architecture.md sec. 3).

It waits for the messages counted in ``advance``, processes inputs and internal events in
(t_us, source, seq) order up to the window's end, sends (a message inside the window is a
``CausalityError``), replies ``done``, streams its records (``fabric.tables``), feeds its trace
hash, and leaves when its coordinator's liveliness token is gone. A message it cannot handle
fails it, naming the federate and the message kind.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import os
import queue
import resource
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack

from fabric import keys, metrics
from fabric.bus import Bus
from fabric.messages import (
    BUNDLE,
    Advance,
    Done,
    Message,
    MessageError,
    Ready,
    Stop,
    Stopped,
    decode_data,
    encode_batch,
)
from fabric.seeding import rng
from fabric.tables import FLUSH_EVERY_US, TABLES, TableWriter, part_path
from scenario.schema import Scenario

if TYPE_CHECKING:
    from fabric.compute import ComputeNode

log = logging.getLogger(__name__)


class CausalityError(RuntimeError):
    """A federate tried to deliver a message inside the current window or in the past."""


class MessageRejected(ValueError):
    """A message the federate cannot handle: unexpected kind or malformed body."""


EXIT_FAILED = 1
EXIT_ORPHANED = 3  # the coordinator vanished: records written, nobody to report to
# The coordinator's token must be seen this soon after connecting (it exists before any federate
# starts); a federate that never sees it was started for a run that is already gone.
COORDINATOR_WAIT_S = 10.0
_POLL_S = 0.5


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


@dataclass(frozen=True)
class FederateContext:
    """What a federate is given at start: who it is and where it runs."""

    name: str
    run_id: str
    scenario: Scenario
    results_dir: Path


# A horizon (``Federate.external_horizon_us``) that never comes: nothing will be sent outside.
NEVER_US = 2**62

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
        # Names become key segments (fabric.keys): refused here, once, rather than on every send.
        self.name = keys.check_name(ctx.name, "federate name")
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
        # Data messages sent in this window, per bus key, published as one batch per key when
        # the window is processed (before ``done``): one bus message per destination and window
        # instead of one per packet. The receiver counts and orders the batch's messages singly.
        self._outbox: dict[str, list[bytes]] = {}
        self._sent_by_plane: Counter[str] = Counter()
        # Metric series looked up once: a label lookup costs more than the update, every window.
        self._sent_series: dict[str, Any] = {}
        self._window_series = metrics.WINDOWS.labels(self.name)
        self._event_series = metrics.EVENTS.labels(self.name)
        self._out_seq = 0
        self._event_seq = 0
        self._earliest_sent: int | None = None
        self._trace = hashlib.sha256()
        self._events = 0
        self._events_before = 0
        self._stopped = False
        self._busy_s = 0.0  # wall time spent processing windows: where a slow run's time goes
        self._tables: dict[str, TableWriter] = {}
        self._job_nodes: list[ComputeNode] = []
        self._next_flush_us = FLUSH_EVERY_US
        self._coordinator_seen = False
        # Set by a ``fabric.group.FederateGroup`` hosting this federate: the names of the
        # federates it hosts, and how a message to one of them is handed over (the message
        # itself: it is encoded for the trace hash, never decoded; a sender does not touch a
        # body it has sent). Such a message needs only to arrive after the end of the
        # scenario's window in which it was sent (``base_window_us``): the group processes its
        # federates' events in time order.
        self.cohosted: frozenset[str] = frozenset()
        self.deliver_local: Callable[[Message], None] | None = None
        self.base_window_us = ctx.scenario.window_us
        # Called (from any thread) when the coordinator is lost, with the reason: the process
        # entry point arms a hard exit there, in case the federate is stuck in a window.
        self.on_orphaned: Callable[[str], None] | None = None

    # ---- for subclasses -------------------------------------------------------------------
    def setup(self) -> None:
        """Heavy initialisation (models, renderers) before the federate reports ready."""

    def on_message(self, msg: Message) -> None:
        """Handle one data message at ``self.now == msg.t_us``."""

    def finish(self, reason: str) -> dict[str, Any]:
        """Append the last records; return a summary for the coordinator (numbers, strings)."""
        return {}

    def close(self) -> None:
        """Release what must be released in the serving thread (e.g. a GL context), on every way
        out of ``serve``."""

    def external_horizon_us(self) -> int | None:
        """In a group (``fabric.group``): the earliest simulated time at which this federate may
        send a message to a federate outside the group, unless one arrives from outside first
        (``NEVER_US``: it never does); None (the default): no promise, it may at any time."""
        return None

    def work_ahead(self, until_us: int) -> None:
        """In a group, offered after every member's event: the group's thread turns to the
        members' next events. A member may start, in a background thread, work its later events
        would begin with, if that work depends on nothing with a time before ``until_us`` that it
        has not processed yet: no message can reach it before then (``next_send_us``). Its
        events must not see that work's effects before their time."""

    def working_ahead(self) -> bool:
        """In a group: whether work started by ``work_ahead`` still runs; the group then offers
        no more until it has ended."""
        return False

    def next_send_us(self, plane: str, now_us: int) -> int:
        """In a group: the earliest simulated time, from ``now_us`` (the group's time) on, at which
        this federate may send a message on ``plane``; with it the group tells a member working
        ahead until when no message can reach it. By default ``now_us``: at any time."""
        return now_us

    def collect_records(self) -> None:
        """Move records kept elsewhere (e.g. in a model) into the tables; called before every
        flush and before ``finish``."""

    # ---- records ------------------------------------------------------------------------------
    def table(self, name: str) -> TableWriter:
        """This federate's writer of the run table ``name`` (one of ``tables.TABLES``)."""
        writer = self._tables.get(name)
        if writer is None:
            if name not in TABLES:
                raise KeyError(f"{self.name}: no run table {name!r} (tables: {', '.join(TABLES)})")
            writer = TableWriter(part_path(self.results_dir, name, self.name), TABLES[name],
                                 name, lambda: self.now)
            self._tables[name] = writer
        return writer

    def record_jobs(self, *nodes: ComputeNode) -> None:
        """Stream the job records of ``nodes`` into the ``jobs`` table."""
        self._job_nodes.extend(nodes)
        self.table("jobs")

    def _drain_jobs(self) -> None:
        if not self._job_nodes:
            return
        columns: dict[str, list[Any]] = {}
        for node in self._job_nodes:
            node.publish_metrics()
            if node.records:
                node.add_record_columns(columns)
                node.records.clear()
        self.table("jobs").extend_columns(columns)

    def flush_records(self) -> None:
        """Write every table's buffered rows (a batch each): complete up to the window end."""
        self.collect_records()
        self._drain_jobs()
        for writer in self._tables.values():
            writer.flush(self.window_end)

    def _close_records(self, collect: bool = True, upto_us: int | None = None) -> None:
        """Write what is left and close every table; each table's error is logged, not raised,
        so that one broken table does not cost the others their rows. ``upto_us``: how far the
        records go (default: the last event processed)."""
        if collect:
            try:
                self.collect_records()
            except Exception:
                log.exception("%s: collecting the last records failed", self.name)
        try:
            self._drain_jobs()
        except Exception:
            log.exception("%s: collecting the last job records failed", self.name)
        for name, writer in self._tables.items():
            try:
                writer.close(upto_us)
            except Exception:
                log.exception("%s: closing table %s failed", self.name, name)

    def records_written(self) -> dict[str, int]:
        return {name: w.rows_written for name, w in sorted(self._tables.items())}

    def rng(self, component: str) -> Any:
        """The named random stream ``<federate>/<component>`` of this run."""
        return rng(self.scenario.seed, f"{self.name}/{component}")

    @property
    def results_dir(self) -> Path:
        return self.ctx.results_dir

    def schedule(self, t_us: int, fn: Callable[..., None], *args: Any,
                 after_inputs: bool = False) -> tuple[int, str, int]:
        """Run ``fn(*args)`` at simulated time ``t_us`` (>= now); the event's key, as
        ``next_event_key`` will give it. Events at equal times run in scheduling order;
        ``after_inputs`` puts the event after every input message of that time (e.g. a radio slot
        that must see every packet handed over at its start)."""
        if t_us < self.now:
            raise CausalityError(f"{self.name}: event scheduled at {t_us} us, before now {self.now} us")
        self._event_seq += 1
        src = _LAST if after_inputs else self.name
        heapq.heappush(self._heap, (t_us, src, self._event_seq, _EVENT, (fn, args)))
        return t_us, src, self._event_seq

    def send(self, dst: str, plane: str, kind: str, t_us: int, body: dict[str, Any] | None = None,
             blob: bytes | None = None) -> None:
        """Send a data message to ``dst`` to be delivered at ``t_us`` (>= end of this window)."""
        local = self.deliver_local is not None and dst in self.cohosted
        end = (self.now // self.base_window_us + 1) * self.base_window_us if local else self.window_end
        if t_us < end:
            raise CausalityError(
                f"{self.name}: {kind} to {dst} delivered at {t_us} us, inside the window ending "
                f"{end} us (latency below the window)"
            )
        self._out_seq += 1
        msg = Message(t_us, self.name, dst, self._out_seq, plane, kind, body or {}, blob, self._window)
        raw = msg.encode()
        self._trace.update(b"S")
        self._trace.update(raw)
        self._sent_by_plane[plane] += 1
        if local:
            assert self.deliver_local is not None
            self.deliver_local(msg)
            return
        self._sent_to[dst] += 1
        if self._earliest_sent is None or t_us < self._earliest_sent:
            self._earliest_sent = t_us
        key = keys.data(self.ctx.run_id, plane, dst, self.name)
        batch = self._outbox.get(key)
        if batch is None:
            self._outbox[key] = [raw]
        else:
            batch.append(raw)

    def send_bundle(self, dst: str, plane: str, t_us: int, items: list[tuple[str, dict[str, Any]]]) -> None:
        """Send several messages without payload bytes to ``dst``, all delivered at ``t_us``, as one: the
        receiver handles them one by one, in this order, as if each had been sent on its own
        (a cell delivering dozens of packets in one slot pays the per-message cost once)."""
        if len(items) == 1:
            self.send(dst, plane, items[0][0], t_us, items[0][1])
        elif items:
            self.send(dst, plane, BUNDLE, t_us, {"items": [[kind, body] for kind, body in items]})

    def flush_outbox(self) -> None:
        """Publish what was sent since the last flush: one bus message per destination key."""
        for key, raws in self._outbox.items():
            self.bus.publish(key, encode_batch(raws))
        self._outbox.clear()
        for plane, n in self._sent_by_plane.items():
            series = self._sent_series.get(plane)
            if series is None:
                series = self._sent_series[plane] = metrics.MESSAGES_SENT.labels(self.name, plane)
            series.inc(n)
        self._sent_by_plane.clear()

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
        self.bus.watch_liveliness(keys.coordinator_alive(run), self._on_coordinator)
        self.bus.declare_token(keys.alive(run, self.name))

    def _on_coordinator(self, key: str, alive: bool) -> None:
        if alive:
            self._coordinator_seen = True
        else:
            self.abandon("the coordinator's liveliness token vanished (coordinator died or "
                         "disconnected)")

    def abandon(self, reason: str) -> None:
        """Leave as soon as the current window is over: write the records, exit. Thread-safe
        (called from transport threads and signal handlers)."""
        self._inbox.put(("abandon", reason, b""))
        if self.on_orphaned is not None:
            self.on_orphaned(reason)

    def serve(self) -> int:
        """Run the federate until the coordinator stops it; returns a process exit code."""
        try:
            return self._serve()
        finally:
            self.close()

    def _serve(self) -> int:
        run = self.ctx.run_id
        self.connect()
        self.setup()
        self.flush_outbox()
        self.bus.publish(keys.ready(run, self.name), Ready(federate=self.name, pid=os.getpid()).encode())
        pending: Advance | None = None
        wait_until = time.monotonic() + COORDINATOR_WAIT_S
        while True:
            try:
                kind, key, payload = self._inbox.get(timeout=_POLL_S)
            except queue.Empty:
                if not self._coordinator_seen and time.monotonic() > wait_until:
                    self.abandon(f"no coordinator token ({keys.coordinator_alive(run)}) within "
                                 f"{COORDINATOR_WAIT_S:.0f} s of connecting")
                continue
            if kind == "abandon":
                return self._leave(key)
            try:
                if kind == "data":
                    for msg in decode_data(payload):
                        self.accept(msg)
                        self._received_by_window[msg.window] += 1
                elif kind == "advance":
                    adv = Advance.decode(payload)
                    if adv.federates is None or self.name in adv.federates:
                        pending = adv
                elif kind == "stop":
                    stop = Stop.decode(payload)
                    return self._stop(stop.reason, stop.t_us)
            except (MessageError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
                what = "data message" if kind == "data" else f"{kind} message"
                return self._fail(pending, f"{self.name}: undecodable {what} on {key}: {exc}")
            if pending is not None and self._received_before(pending.window) >= pending.expected_in.get(self.name, 0):
                try:
                    t0 = time.perf_counter()
                    done = self.process_window(pending)
                    self._busy_s += time.perf_counter() - t0
                except Exception as exc:
                    log.error("window %d failed:\n%s", pending.window, traceback.format_exc())
                    return self._fail(pending, f"{type(exc).__name__}: {exc}")
                self.bus.publish(keys.done(run, self.name), done.encode())
                pending = None

    def _fail(self, pending: Advance | None, error: str) -> int:
        """Report ``error`` to the coordinator as this window's ``done``, keep the records."""
        window = pending.window if pending is not None else self._window
        t_end = pending.t_end_us if pending is not None else self.window_end
        done = Done(federate=self.name, window=window, t_end_us=t_end, sent_to={}, next_event_us=None,
                    earliest_sent_us=None, error=error)
        self.bus.publish(keys.done(self.ctx.run_id, self.name), done.encode())
        self._close_records()
        return EXIT_FAILED

    def _leave(self, reason: str) -> int:
        """The coordinator is gone: write what was recorded up to now and exit."""
        log.warning("%s leaves at %d us: %s", self.name, self.now, reason)
        self._stop(f"coordinator lost: {reason}", self.now)
        return EXIT_ORPHANED

    def _received_before(self, window: int) -> int:
        """Data messages received that were sent in windows before ``window``."""
        for w in [w for w in self._received_by_window if w < window]:
            self._received_settled += self._received_by_window.pop(w)
        return self._received_settled

    def accept(self, msg: Message) -> None:
        """Take a received data message: it is processed at its time, in (t_us, src, seq) order."""
        heapq.heappush(self._heap, (msg.t_us, msg.src, msg.seq, _MESSAGE, msg))

    def process_window(self, adv: Advance) -> Done:
        """Process every event with time < ``adv.t_end_us`` in order; the done report."""
        self.begin_window(adv)
        heap = self._heap
        while heap and heap[0][0] < adv.t_end_us:
            self.process_next()
        self.end_window(adv)
        next_event = heap[0][0] if heap else None
        return Done(federate=self.name, window=adv.window, t_end_us=adv.t_end_us,
                    sent_to=dict(self._sent_to), next_event_us=next_event,
                    earliest_sent_us=self._earliest_sent)

    def begin_window(self, adv: Advance) -> None:
        self._window = adv.window
        self.window_end = adv.t_end_us
        self._earliest_sent = None
        self._events_before = self._events

    def next_event_key(self) -> tuple[int, str, int] | None:
        """(time, source, sequence) of the next event, or None."""
        return self._heap[0][:3] if self._heap else None

    def process_next(self) -> None:
        """Process the earliest event or message."""
        t_us, src, seq, kind, item = heapq.heappop(self._heap)
        if t_us < self.now:
            raise CausalityError(f"{self.name}: event at {t_us} us arrived after now {self.now} us")
        self.now = t_us
        self._events += 1
        if kind == _MESSAGE:
            self._trace.update(b"R")
            self._trace.update(msgpack.packb([t_us, src, seq, item.kind], use_bin_type=True))
            if item.kind == BUNDLE:
                for part in self._unbundle(item):
                    self._handle(part)
            else:
                self._handle(item)
        else:
            fn, args = item
            self._trace.update(b"E")
            self._trace.update(msgpack.packb([t_us, seq, fn.__name__], use_bin_type=True))
            fn(*args)

    def end_window(self, adv: Advance) -> None:
        """Publish what the window sent, count it, write the records when they are due."""
        self.flush_outbox()
        for node in self._job_nodes:
            node.publish_metrics()
        self._window_series.inc()
        self._event_series.inc(self._events - self._events_before)
        if adv.t_end_us >= self._next_flush_us:
            self.flush_records()
            self._next_flush_us = adv.t_end_us + FLUSH_EVERY_US

    def _handle(self, msg: Message) -> None:
        try:
            self.on_message(msg)
        except (CausalityError, MessageRejected):
            raise
        except Exception as exc:
            raise MessageRejected(
                f"{self.name}: cannot handle {msg.kind!r} message from {msg.src} at {msg.t_us} us: "
                f"{type(exc).__name__}: {exc}") from exc

    def _unbundle(self, bundle: Message) -> list[Message]:
        """The messages of a bundle (``send_bundle``), in sending order."""
        items = bundle.body.get("items")
        if not isinstance(items, list) or not all(
                isinstance(i, list) and len(i) == 2 and isinstance(i[0], str) and isinstance(i[1], dict)
                for i in items):
            raise MessageRejected(f"{self.name}: malformed bundle from {bundle.src} at {bundle.t_us} us: "
                                  "items must be [kind, body] pairs")
        return [Message(bundle.t_us, bundle.src, bundle.dst, bundle.seq, bundle.plane, kind, body,
                        None, bundle.window) for kind, body in items]

    def unexpected(self, msg: Message) -> MessageRejected:
        """The error for a message of a kind this federate does not take."""
        return MessageRejected(f"{self.name}: unexpected message kind {msg.kind!r} from {msg.src}")

    def _stop(self, reason: str, t_us: int) -> int:
        if self._stopped:
            return 0
        self._stopped = True
        try:
            self.collect_records()
            summary = self.finish(reason)
        finally:
            self._close_records(collect=False, upto_us=self.window_end)
        summary["busy_wall_s"] = round(self._busy_s, 3)
        # The process's CPU; a group's members share one process (and thread), where the time
        # spent processing each member's events is the closest figure of its own.
        summary["cpu_s"] = round(time.process_time(), 3) if self.deliver_local is None else summary["busy_wall_s"]
        summary["peak_rss_mb"] = round(peak_rss_mb(), 1)
        summary["records"] = self.records_written()
        record = Stopped(federate=self.name, trace_hash=self._trace.hexdigest(), events=self._events,
                         summary=summary)
        self.bus.publish(keys.stopped(self.ctx.run_id, self.name), record.encode())
        return 0

    @property
    def trace_hash(self) -> str:
        return self._trace.hexdigest()
