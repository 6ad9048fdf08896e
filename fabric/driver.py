"""The window protocol's participant side: one driver serves a federate or a group of them
(docs/architecture.md sec. 3).

The driver takes the participant's inbox and the control keys, counts received messages by
sending window, starts a window once every message ``advance`` counted has arrived, replies
``done`` from the participant's window report, and leaves when the coordinator's liveliness
token is gone. The participant holds the events; the driver holds the protocol.
"""

from __future__ import annotations

import logging
import os
import queue
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from fabric import keys
from fabric.messages import Advance, Done, Message, MessageError, Ready, Stop, Stopped, decode_data

if TYPE_CHECKING:
    from fabric.bus import Bus

log = logging.getLogger(__name__)

EXIT_FAILED = 1
EXIT_ORPHANED = 3  # the coordinator vanished: records written, nobody to report to
# The coordinator's token must be seen this soon after connecting (it exists before any federate
# starts); a federate that never sees it was started for a run that is already gone.
COORDINATOR_WAIT_S = 10.0
_POLL_S = 0.5


@dataclass(frozen=True, slots=True)
class WindowReport:
    """What a participant tells the coordinator at the end of a window.

    ``sent_to``: data messages sent to each destination outside the participant, cumulative;
    ``next_event_us``: its earliest pending event or input (None: none); ``earliest_sent_us``:
    the earliest delivery time it sent in this window; ``horizon_us``: no message to another
    participant before this time unless one arrives first (None: no such promise).
    """

    sent_to: dict[str, int]
    next_event_us: int | None
    earliest_sent_us: int | None
    horizon_us: int | None = None


class Inbox(Protocol):
    """A federate as the driver sees it: its name and the data planes it takes messages on."""

    name: str
    data_planes: tuple[str, ...]


class Participant(Protocol):
    """What the driver serves: one federate (``fabric.federate``) or a group (``fabric.group``)."""

    name: str
    bus: Bus

    @property
    def run_id(self) -> str: ...

    def hosted(self) -> Sequence[Inbox]:
        """The federates whose inboxes and liveliness tokens it holds."""

    def setup(self) -> None: ...

    def flush_outbox(self) -> None: ...

    def accept(self, msg: Message) -> None: ...

    def process_window(self, adv: Advance) -> WindowReport: ...

    def culprit(self) -> str:
        """The name a failure in the current window is reported under."""

    def stop(self, reason: str, t_us: int | None = None) -> list[Stopped]:
        """Finish every hosted federate, the run stopped at ``t_us`` (us; None: not known, the
        coordinator is gone); their ``stopped`` records."""

    def close_records(self) -> None: ...

    def close(self) -> None: ...


class WindowDriver:
    """Serves ``participant`` until the coordinator stops it (``serve``)."""

    def __init__(self, participant: Participant) -> None:
        self.participant = participant
        self.run_id = participant.run_id
        self.bus = participant.bus
        self._inbox: queue.SimpleQueue[tuple[str, str, bytes]] = queue.SimpleQueue()
        # Received data messages counted by the window they were sent in: a message sent in the
        # current window that overtakes a late one from an earlier window must not satisfy the
        # barrier in its place.
        self._received_settled = 0
        self._received_by_window: Counter[int] = Counter()
        self._last: Advance | None = None  # the last window processed
        self._coordinator_seen = False
        self._stopped = False
        # Called (from any thread) when the coordinator is lost, with the reason: the process
        # entry point arms a hard exit there, in case the participant is stuck in a window.
        self.on_orphaned: Callable[[str], None] | None = None

    def _enqueue(self, kind: str) -> Callable[[str, bytes], None]:
        def put(key: str, payload: bytes) -> None:
            self._inbox.put((kind, key, payload))

        return put

    def connect(self) -> None:
        """Subscribe to the inboxes and control keys and declare the liveliness tokens."""
        run, bus = self.run_id, self.bus
        names = [self.participant.name]
        for fed in self.participant.hosted():
            for plane in fed.data_planes:
                bus.subscribe(keys.inbox(run, plane, fed.name), self._enqueue("data"))
            if fed.name not in names:
                names.append(fed.name)
        bus.subscribe(keys.advance(run), self._enqueue("advance"))
        bus.subscribe(keys.stop(run), self._enqueue("stop"))
        bus.watch_liveliness(keys.coordinator_alive(run), self._on_coordinator)
        for name in names:
            bus.declare_token(keys.alive(run, name))

    def _on_coordinator(self, key: str, alive: bool) -> None:
        if alive:
            self._coordinator_seen = True
        else:
            self.abandon("the coordinator's liveliness token vanished (coordinator died or disconnected)")

    def abandon(self, reason: str) -> None:
        """Leave as soon as the current window is over: write the records, exit. Thread-safe
        (called from transport threads and signal handlers)."""
        self._inbox.put(("abandon", reason, b""))
        if self.on_orphaned is not None:
            self.on_orphaned(reason)

    def serve(self) -> int:
        """Run the participant until the coordinator stops it; returns a process exit code."""
        try:
            return self._serve()
        finally:
            self.participant.close()

    def _serve(self) -> int:
        p, run = self.participant, self.run_id
        self.connect()
        try:
            p.setup()
        except Exception as exc:  # reported under the failing member's name, with its error
            log.error("setup failed:\n%s", traceback.format_exc())
            return self._fail(None, f"setup failed: {type(exc).__name__}: {exc}")
        p.flush_outbox()
        self.bus.publish(keys.ready(run, p.name), Ready(federate=p.name, pid=os.getpid()).encode())
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
                        p.accept(msg)
                        self._received_by_window[msg.window] += 1
                elif kind == "advance":
                    adv = Advance.decode(payload)
                    if adv.federates is None or p.name in adv.federates:
                        pending = adv
                elif kind == "stop":
                    stop = Stop.decode(payload)
                    self.stop(stop.reason, stop.t_us)
                    return 0
            except (MessageError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
                what = "data message" if kind == "data" else f"{kind} message"
                return self._fail(pending, f"{p.culprit()}: undecodable {what} on {key}: {exc}")
            if pending is not None and self._received_before(pending.window) >= pending.expected_in.get(p.name, 0):
                try:
                    report = p.process_window(pending)
                except Exception as exc:
                    log.error("window %d failed:\n%s", pending.window, traceback.format_exc())
                    return self._fail(pending, f"{type(exc).__name__}: {exc}")
                self._last = pending
                done = Done(federate=p.name, window=pending.window, t_end_us=pending.t_end_us,
                            sent_to=report.sent_to, next_event_us=report.next_event_us,
                            earliest_sent_us=report.earliest_sent_us, horizon_us=report.horizon_us)
                self.bus.publish(keys.done(run, p.name), done.encode())
                pending = None

    def _received_before(self, window: int) -> int:
        """Data messages received that were sent in windows before ``window``."""
        for w in [w for w in self._received_by_window if w < window]:
            self._received_settled += self._received_by_window.pop(w)
        return self._received_settled

    def _fail(self, pending: Advance | None, error: str) -> int:
        """Report ``error`` as this window's ``done``, under the name of the federate that failed;
        keep the records."""
        at = pending or self._last
        window, t_end = (at.window, at.t_end_us) if at is not None else (0, 0)
        done = Done(federate=self.participant.culprit(), window=window, t_end_us=t_end, sent_to={},
                    next_event_us=None, earliest_sent_us=None, error=error)
        self.bus.publish(keys.done(self.run_id, self.participant.name), done.encode())
        try:
            self.participant.close_records()
        except Exception:  # a setup that failed may have left tables half made
            log.exception("closing the records failed")
        return EXIT_FAILED

    def _leave(self, reason: str) -> int:
        """The coordinator is gone: write what was recorded up to now and exit."""
        log.warning("%s leaves: %s", self.participant.name, reason)
        self.stop(f"coordinator lost: {reason}")
        return EXIT_ORPHANED

    def stop(self, reason: str, t_us: int | None = None) -> None:
        """Finish the participant once (the run stopped at ``t_us``, us; None: not known) and
        publish its federates' ``stopped`` records."""
        if self._stopped:
            return
        self._stopped = True
        for record in self.participant.stop(reason, t_us):
            self.bus.publish(keys.stopped(self.run_id, record.federate), record.encode())
