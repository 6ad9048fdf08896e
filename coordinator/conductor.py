"""The conductor: advances simulated time for one run in windows, with a count-based barrier.

The window protocol, idle jumps and long windows: docs/architecture.md sec. 3; its liveliness
token and the health check it polls while it waits: sec. 4 and 10.
"""

from __future__ import annotations

import hashlib
import math
import queue
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from coordinator.run_state import RunState
from fabric import keys
from fabric.bus import Bus
from fabric.messages import Advance, Done, MessageError, Ready, Stop, Stopped


class RunFailed(Exception):
    """The run cannot go on; ``reason`` says which federate and why."""

    def __init__(self, reason: str, federate: str | None = None, status: RunState = RunState.FAILED) -> None:
        super().__init__(reason)
        self.reason = reason
        self.federate = federate
        self.status = status


@dataclass
class Progress:
    t_us: int
    end_us: int
    windows: int
    wall_s: float


@dataclass
class ConductorResult:
    windows: int
    t_end_us: int
    trace_hash: str
    stopped: dict[str, Stopped] = field(default_factory=dict)


HealthCheck = Callable[[], None]  # raises RunFailed
# A dead federate fails the run within this much wall time; checking before every control
# message (several a window) would cost more than the windows themselves.
HEALTH_EVERY_S = 0.05
# While reports are collected after the run: how often the processes yet to report are looked
# at, and how long a report of one that has exited may still take to arrive.
DEAD_EVERY_S = 0.5
REPORT_GRACE_S = 1.0


class Conductor:
    """``federates``: the participants of the window protocol. ``groups``: participants that serve
    several federates in one process (``fabric.group``), by name, with their members: messages
    sent to a member count for its group, and every member sends its own ``stopped`` report.
    ``long_window_us``: the longest window given to a participant that is alone with something
    to do and promised (``Done.horizon_us``) to send nothing to the others before its end
    (default: ``window_us``, i.e. never longer)."""

    def __init__(self, bus: Bus, run_id: str, federates: list[str], window_us: int, end_us: int,
                 window_timeout_s: float = 10.0, health: HealthCheck | None = None,
                 on_progress: Callable[[Progress], None] | None = None,
                 progress_every_s: float = 0.5, groups: dict[str, list[str]] | None = None,
                 long_window_us: int | None = None) -> None:
        self.bus = bus
        self.run_id = run_id
        self.federates = sorted(federates)
        self.groups = groups or {}
        self._participant = {m: g for g, members in self.groups.items() for m in members}
        self.reporters = sorted({m for f in self.federates for m in self.groups.get(f, [f])})
        self.long_window_us = long_window_us or window_us
        if self.long_window_us % window_us:
            raise ValueError(f"long_window_us ({long_window_us}) must be a multiple of window_us ({window_us})")
        self.window_us = window_us
        self.end_us = end_us
        self.window_timeout_s = window_timeout_s
        self.health = health or (lambda: None)
        self.on_progress = on_progress
        self.progress_every_s = progress_every_s
        self._inbox: queue.SimpleQueue[tuple[str, str, bytes]] = queue.SimpleQueue()
        self._health_at = -math.inf
        self._trace = hashlib.sha256()
        self.windows = 0
        self.t_us = 0
        bus.subscribe(keys.ready_all(run_id), lambda k, p: self._inbox.put(("ready", k, p)))
        bus.subscribe(keys.done_all(run_id), lambda k, p: self._inbox.put(("done", k, p)))
        bus.subscribe(keys.stopped_all(run_id), lambda k, p: self._inbox.put(("stopped", k, p)))
        bus.declare_token(keys.coordinator_alive(run_id))

    def _next(self, deadline: float, check_health: bool = True) -> tuple[str, str, bytes] | None:
        """Next control message, checking health at most every ``HEALTH_EVERY_S`` (and at least
        that often while waiting); None at the deadline."""
        while True:
            now = time.monotonic()
            if check_health and now - self._health_at >= HEALTH_EVERY_S:
                self._health_at = now
                self.health()
            left = deadline - now
            if left <= 0:
                return None
            try:
                return self._inbox.get(timeout=min(HEALTH_EVERY_S, left))
            except queue.Empty:
                continue

    def wait_ready(self, timeout_s: float) -> None:
        waiting = set(self.federates)
        deadline = time.monotonic() + timeout_s
        while waiting:
            item = self._next(deadline)
            if item is None:
                raise RunFailed(f"federates not ready within {timeout_s:.0f} s: {', '.join(sorted(waiting))}",
                                federate=sorted(waiting)[0])
            kind, key, payload = item
            if kind == "ready":
                waiting.discard(Ready.decode(payload).federate)
            elif kind == "done":  # a federate whose setup failed says which and why
                self._done(key, payload, in_window=False)

    def run(self) -> ConductorResult:
        """Conduct windows until the end time; raises RunFailed."""
        sent: dict[str, dict[str, int]] = {f: {} for f in self.federates}
        # What each federate reported of itself when it last took part in a window, and how many
        # messages had been sent to it by then: a federate whose next event lies beyond a window
        # and to which nothing was sent since sits that window out (no advance, no reply).
        next_event: dict[str, int | None] = {}
        horizons: dict[str, int | None] = {}
        seen_in: dict[str, int] = {}
        t_start = 0
        wall0 = time.monotonic()
        last_progress = 0.0
        while t_start < self.end_us:
            t_end = t_start + self.window_us
            expected = dict.fromkeys(self.federates, 0)
            for s in sent.values():
                for dst, n in s.items():
                    dst = self._participant.get(dst, dst)
                    if dst in expected:
                        expected[dst] += n
            active = [f for f in self.federates
                      if f not in seen_in or expected[f] > seen_in[f]
                      or ((nxt := next_event[f]) is not None and nxt < t_end)]
            alone = active[0] if len(active) == 1 else None
            if (alone is not None and expected[alone] == seen_in.get(alone)
                    and (horizon := horizons.get(alone)) is not None and horizon >= t_end):
                # The others have nothing to do and nothing coming before their next events; it
                # has been sent nothing new (its horizon holds only until something arrives) and
                # sends them nothing before its horizon: a long window, up to the earliest. What
                # it sends at its horizon arrives at the end of that base window at the earliest,
                # so the window may take in the base window of the horizon.
                others = [t for f, t in next_event.items() if f != alone and t is not None]
                last_end = -(-self.end_us // self.window_us) * self.window_us  # as with short windows
                sends_arrive = (horizon // self.window_us + 1) * self.window_us
                limit = min([t_start + self.long_window_us, last_end, sends_arrive, *others])
                t_end = max(t_end, limit // self.window_us * self.window_us)
            adv = Advance(window=self.windows, t_start_us=t_start, t_end_us=t_end, expected_in=expected,
                          federates=None if len(active) == len(self.federates) else active)
            self._trace.update(f"{self.windows}:{t_start}:{t_end};".encode())
            self.bus.publish(keys.advance(self.run_id), adv.encode())
            dones = self._collect_done(self.windows, active)
            for f in active:
                seen_in[f] = expected[f]
            for d in dones.values():
                sent[d.federate] = d.sent_to
                next_event[d.federate] = d.next_event_us
                horizons[d.federate] = d.horizon_us
            # The next window: the earliest of every federate's next event (sitting-out ones
            # included) and of the messages sent in this one.
            nexts = [t for t in next_event.values() if t is not None]
            nexts += [d.earliest_sent_us for d in dones.values() if d.earliest_sent_us is not None]
            self.windows += 1
            self.t_us = t_end
            if nexts:
                earliest = min(nexts)
                if earliest < t_end:
                    raise RunFailed(f"a federate reported an event at {earliest} us, before the window end {t_end} us")
                t_start = earliest // self.window_us * self.window_us
            else:
                t_start = self.end_us  # nothing will ever happen again
            now = time.monotonic()
            if self.on_progress and now - last_progress >= self.progress_every_s:
                last_progress = now
                self.on_progress(Progress(min(t_end, self.end_us), self.end_us, self.windows, now - wall0))
        # Every window is done, or nothing would happen in those left: the run has reached its end.
        self.t_us = max(self.t_us, self.end_us)
        if self.on_progress:
            self.on_progress(Progress(self.end_us, self.end_us, self.windows, time.monotonic() - wall0))
        return ConductorResult(self.windows, self.t_us, self._trace.hexdigest())

    def _collect_done(self, window: int, active: list[str]) -> dict[str, Done]:
        dones: dict[str, Done] = {}
        deadline = time.monotonic() + self.window_timeout_s
        while len(dones) < len(active):
            item = self._next(deadline)
            if item is None:
                silent = sorted(set(active) - set(dones))
                raise RunFailed(f"no answer to window {window} within {self.window_timeout_s:.0f} s from "
                                f"{', '.join(silent)} (hung)", federate=silent[0])
            kind, key, payload = item
            if kind != "done":
                continue
            d = self._done(key, payload)
            if d.window == window:
                dones[d.federate] = d
        return dones

    @staticmethod
    def _done(key: str, payload: bytes, in_window: bool = True) -> Done:
        """The done report ``payload`` (on ``key``); RunFailed naming the federate and its error
        for one that failed (in a window, or ``in_window`` False: in its setup)."""
        try:
            d = Done.decode(payload)
        except MessageError as exc:
            raise RunFailed(f"bad done report on {key}: {exc}") from None
        if d.error:
            where = f" failed in window {d.window}" if in_window else ""
            raise RunFailed(f"{d.federate}{where}: {d.error}", federate=d.federate)
        return d

    def stop(self, reason: str, timeout_s: float = 30.0, gone: Iterable[str] = (),
             dead: Callable[[], Iterable[str]] | None = None) -> dict[str, Stopped]:
        """Tell every federate to finish (write its results) and collect their reports, but for
        those known ``gone`` (dead or lost: none would come). ``dead()``: the federates whose
        process has ended; once every report still missing is theirs, the wait ends
        ``REPORT_GRACE_S`` later (a report sent just before the exit may still be on its way)."""
        self.bus.publish(keys.stop(self.run_id), Stop(reason=reason, t_us=self.t_us).encode())
        got: dict[str, Stopped] = {}
        expected = set(self.reporters) - set(gone)
        deadline = time.monotonic() + timeout_s
        while not expected <= got.keys():
            # Federates exit once they reported: no health check while collecting reports, only
            # whether those yet to report have died (a runtime may ask its daemon: not often).
            item = self._next(min(deadline, time.monotonic() + DEAD_EVERY_S), check_health=False)
            if item is None:
                now = time.monotonic()
                if now >= deadline:
                    break
                if dead is not None and expected - got.keys() <= set(dead()):
                    deadline = min(deadline, now + REPORT_GRACE_S)
                continue
            kind, key, payload = item
            if kind == "stopped":
                s = Stopped.decode(payload)
                got[s.federate] = s
        return got

    def trace_hash(self, stopped: dict[str, Stopped]) -> str:
        """One hash over the windows conducted and every federate's own trace."""
        h = hashlib.sha256(self._trace.digest())
        for name in sorted(stopped):
            h.update(f"{name}:{stopped[name].trace_hash};".encode())
        return h.hexdigest()
