"""The federate base: the event model every federate runs (docs/architecture.md sec. 3 and 4).

A window processes inputs and internal events in (t_us, source, seq) order up to its end, sends
(a message inside the window is a ``CausalityError``), streams the records (``fabric.tables``)
and feeds the trace hash; ``fabric.driver`` serves it the window protocol. A message it cannot
handle fails it, naming the federate and the message kind.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import resource
import sys
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack
import msgspec

from fabric import keys, metrics
from fabric.bus import Bus
from fabric.driver import WindowReport
from fabric.messages import (
    BUNDLE,
    Advance,
    Body,
    Bundle,
    Message,
    MessageError,
    Stopped,
    bundle_items,
    encode_batch,
)
from fabric.records import PartStream
from fabric.seeding import rng
from fabric.tables import FLUSH_EVERY_US, TABLES, TableWriter, part_path
from scenario.schema import Scenario

if TYPE_CHECKING:
    from fabric.compute import ComputeNode

# Job metrics are published at a window's end once this much simulated time has passed since
# they last were (and with every flush of the records): a dashboard scrapes every few wall
# seconds, and a partitioned run's 1-ms windows would otherwise publish every node's every job.
JOB_METRICS_EVERY_US = 100_000

log = logging.getLogger(__name__)


class CausalityError(RuntimeError):
    """A federate tried to deliver a message inside the current window or in the past."""


class MessageRejected(ValueError):
    """A message the federate cannot handle: unexpected kind or malformed body."""


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
    # Table parts sent to the coordinator as they are written (``fabric.records``), not written
    # into ``results_dir``: on a node that does not see the run directory.
    stream_records: bool = False


# A horizon (``Federate.external_horizon_us``) that never comes: nothing will be sent outside.
NEVER_US = 2**62

_EVENT = 0  # heap entry kinds; internal events sort with the federate's own name as source
_MESSAGE = 1
_LAST = "\uffff"  # sorts after every federate name


# The body types a federate takes (``wire`` structs: each names its ``KIND``), each with its
# handler, called with the decoded body and the message.
Handlers = Mapping[type[Any], Callable[[Any, Message], None]]


class Federate:
    """Base class. Subclasses override ``setup``, ``handlers``, ``finish``; they schedule
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
        self._busy_s = 0.0  # wall time spent processing windows: where a slow run's time goes
        self._tables: dict[str, TableWriter] = {}
        self._job_nodes: list[ComputeNode] = []
        self._nodes_ran: list[ComputeNode] = []  # those with jobs not yet in the metrics
        self._next_flush_us = FLUSH_EVERY_US
        self._next_job_metrics_us = 0
        self._dispatch: dict[str, tuple[Callable[[Any], Any], type, Callable[[Any, Message], None]]] | None = None
        # Set by a ``fabric.group.FederateGroup`` hosting this federate: the names of the
        # federates it hosts, and how a message to one of them is handed over (the message
        # itself: it is encoded for the trace hash, never decoded; a sender does not touch a
        # body it has sent). Such a message needs only to arrive after the end of the
        # scenario's window in which it was sent (``base_window_us``): the group processes its
        # federates' events in time order.
        self.cohosted: frozenset[str] = frozenset()
        self.deliver_local: Callable[[Message], None] | None = None
        self.base_window_us = ctx.scenario.window_us

    # ---- for subclasses -------------------------------------------------------------------
    def setup(self) -> None:
        """Heavy initialisation (models, renderers) before the federate reports ready."""

    def handlers(self) -> Handlers:
        """The body types this federate takes, each with its handler, called at
        ``self.now == msg.t_us`` with the decoded body and the message (source, blob). A kind
        not listed fails the federate, naming it."""
        return {}

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
            out = (PartStream(self.bus, keys.record(self.run_id, self.name, name)) if self.ctx.stream_records
                   else part_path(self.results_dir, name, self.name))
            writer = TableWriter(out, TABLES[name], name, lambda: self.now)
            self._tables[name] = writer
        return writer

    def record_jobs(self, *nodes: ComputeNode) -> None:
        """Stream the job records of ``nodes`` into the ``jobs`` table."""
        self._job_nodes.extend(nodes)
        for node in nodes:
            node.watch(self._nodes_ran)
        self.table("jobs")

    def _drain_jobs(self) -> None:
        if not self._job_nodes:
            return
        self._publish_jobs()
        columns: dict[str, list[Any]] = {}
        for node in self._job_nodes:
            if node.records:
                node.add_record_columns(columns)
                node.records.clear()
        self.table("jobs").extend_columns(columns)

    def _publish_jobs(self) -> None:
        """Move the jobs of the nodes that ran since the last call into the metrics."""
        for node in self._nodes_ran:
            node.publish_metrics()
        self._nodes_ran.clear()

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

    def send(self, dst: str, t_us: int, body: Body, blob: bytes | None = None) -> None:
        """Send ``body`` (a ``wire`` struct, which names its kind and plane) to ``dst``, delivered
        at ``t_us`` (>= end of this window), with ``blob``: payload bytes, if any."""
        self._send(dst, body.PLANE, body.KIND, t_us, body, blob)

    def send_bundle(self, dst: str, t_us: int, bodies: Sequence[Body]) -> None:
        """Send several bodies without payload bytes to ``dst``, all delivered at ``t_us``, as one
        message: the receiver handles them one by one, in this order, as if each had been sent on
        its own (a cell delivering dozens of packets in one slot pays the per-message cost once)."""
        if len(bodies) == 1:
            self.send(dst, t_us, bodies[0])
        elif bodies:
            self._send(dst, bodies[0].PLANE, BUNDLE, t_us, Bundle([(b.KIND, b) for b in bodies]), None)

    def _send(self, dst: str, plane: str, kind: str, t_us: int, body: Any, blob: bytes | None) -> None:
        local = self.deliver_local is not None and dst in self.cohosted
        end = (self.now // self.base_window_us + 1) * self.base_window_us if local else self.window_end
        if t_us < end:
            raise CausalityError(
                f"{self.name}: {kind} to {dst} delivered at {t_us} us, inside the window ending "
                f"{end} us (latency below the window)"
            )
        self._out_seq += 1
        msg = Message(t_us, self.name, dst, self._out_seq, plane, kind, body, blob, self._window)
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

    # ---- events ---------------------------------------------------------------------------------
    def accept(self, msg: Message) -> None:
        """Take a received data message: it is processed at its time, in (t_us, src, seq) order."""
        heapq.heappush(self._heap, (msg.t_us, msg.src, msg.seq, _MESSAGE, msg))

    def process_window(self, adv: Advance) -> WindowReport:
        """Process every event with time < ``adv.t_end_us`` in order; the window's report."""
        t0 = time.perf_counter()
        self.begin_window(adv)
        heap = self._heap
        while heap and heap[0][0] < adv.t_end_us:
            self.process_next()
        self.end_window(adv)
        self._busy_s += time.perf_counter() - t0
        return self.report()

    def report(self) -> WindowReport:
        """This window's report: what was sent, the next event (a federate alone promises no
        horizon; a group makes its promise from its members', ``external_horizon_us``)."""
        return WindowReport(sent_to=dict(self._sent_to), next_event_us=self._heap[0][0] if self._heap else None,
                            earliest_sent_us=self._earliest_sent)

    def add_busy(self, seconds: float) -> None:
        """Count wall time spent on this federate's events (a group measures its members')."""
        self._busy_s += seconds

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
        if adv.t_end_us >= self._next_job_metrics_us:
            self._publish_jobs()
            self._next_job_metrics_us = adv.t_end_us + JOB_METRICS_EVERY_US
        self._window_series.inc()
        self._event_series.inc(self._events - self._events_before)
        if adv.t_end_us >= self._next_flush_us:
            self.flush_records()
            self._next_flush_us = adv.t_end_us + FLUSH_EVERY_US

    def _handle(self, msg: Message) -> None:
        dispatch = self._dispatch
        if dispatch is None:
            dispatch = self._dispatch = {
                cls.KIND: (msgspec.msgpack.Decoder(cls).decode, cls, fn) for cls, fn in self.handlers().items()}
        entry = dispatch.get(msg.kind)
        if entry is None:
            raise self.unexpected(msg)
        decode, cls, fn = entry
        body = msg.body
        if not isinstance(body, cls):
            try:
                body = decode(body) if isinstance(body, msgspec.Raw) else msgspec.convert(body, cls)
            except (msgspec.DecodeError, msgspec.ValidationError) as exc:
                raise MessageRejected(f"{self.name}: malformed {msg.kind!r} message from {msg.src} at "
                                      f"{msg.t_us} us: {exc}") from exc
        try:
            fn(body, msg)
        except (CausalityError, MessageRejected):
            raise
        except Exception as exc:
            raise MessageRejected(
                f"{self.name}: cannot handle {msg.kind!r} message from {msg.src} at {msg.t_us} us: "
                f"{type(exc).__name__}: {exc}") from exc

    def _unbundle(self, bundle: Message) -> list[Message]:
        """The messages of a bundle (``send_bundle``), in sending order."""
        try:
            items = bundle_items(bundle.body)
        except MessageError as exc:
            raise MessageRejected(f"{self.name}: {exc}, from {bundle.src} at {bundle.t_us} us") from exc
        return [Message(bundle.t_us, bundle.src, bundle.dst, bundle.seq, bundle.plane, kind, body,
                        None, bundle.window) for kind, body in items]

    def unexpected(self, msg: Message) -> MessageRejected:
        """The error for a message of a kind this federate does not take."""
        return MessageRejected(f"{self.name}: unexpected message kind {msg.kind!r} from {msg.src}")

    def stop(self, reason: str, t_us: int | None = None) -> list[Stopped]:
        """Write the last records and summarise the run for the coordinator (``finish``); the run
        stopped at ``t_us`` (us; None: not known)."""
        # The records reach the end of the last window this federate took part in, and the
        # run's stop where that is later: the windows it sat out had nothing for it.
        upto_us = self.window_end if t_us is None else max(self.window_end, t_us)
        try:
            self.collect_records()
            summary = self.finish(reason)
        finally:
            self._close_records(collect=False, upto_us=upto_us)
        summary["busy_wall_s"] = round(self._busy_s, 3)
        # The process's CPU; a group's members share one process (and thread), where the time
        # spent processing each member's events is the closest figure of its own.
        summary["cpu_s"] = round(time.process_time(), 3) if self.deliver_local is None else summary["busy_wall_s"]
        summary["peak_rss_mb"] = round(peak_rss_mb(), 1)
        summary["records"] = self.records_written()
        if self.ctx.stream_records:
            summary["records_streamed"] = True
        return [Stopped(federate=self.name, trace_hash=self._trace.hexdigest(), events=self._events,
                        summary=summary)]

    # ---- as a participant of the window protocol (``fabric.driver``) ----------------------------
    @property
    def run_id(self) -> str:
        return self.ctx.run_id

    def hosted(self) -> list[Federate]:
        return [self]

    def culprit(self) -> str:
        return self.name

    def close_records(self) -> None:
        """Write what is left and close every table (after a failure)."""
        self._close_records()

    @property
    def trace_hash(self) -> str:
        return self._trace.hexdigest()
