"""Conductor and federate base on the in-memory bus: ordering, idle jumps, count barrier."""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, ClassVar

import msgspec
import pytest

from coordinator.conductor import Conductor, RunFailed
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.driver import WindowDriver
from fabric.federate import CausalityError, Federate, FederateContext
from fabric.messages import Message
from scenario.schema import parse_scenario

W = 1000


class Ping(msgspec.Struct):
    """The test federates' message body."""

    KIND: ClassVar[str] = "ping"
    PLANE: ClassVar[str] = "sense"
    k: int = 0


class Pinger(Federate):
    """Sends bursts to its peers at its own tick times; logs what it processes."""

    def __init__(self, ctx: FederateContext, bus: InMemoryBus, peers: list[str], ticks: list[int],
                 latency_us: int) -> None:
        super().__init__(ctx, bus)
        self.peers, self.ticks, self.latency = peers, ticks, latency_us
        self.log: list[tuple[int, str, int, str]] = []

    def setup(self) -> None:
        for t in self.ticks:
            self.schedule(t, self.tick)

    def tick(self) -> None:
        self.log.append((self.now, self.name, -1, "tick"))
        for peer in self.peers:
            for k in range(3):  # several messages with equal time: seq must order them
                self.send(peer, self.now + self.latency, Ping(k))

    def handlers(self) -> Mapping[type, Callable[[Any, Message], None]]:
        return {Ping: self.on_ping}

    def on_ping(self, ping: Ping, msg: Message) -> None:
        self.log.append((msg.t_us, msg.src, msg.seq, msg.kind))


def federation(tmp_path: Path, hub: InMemoryHub, ticks: dict[str, list[int]], latency_us: int = W,
               end_us: int = 50_000) -> tuple[Conductor, dict[str, Pinger], list[threading.Thread]]:
    sc = parse_scenario({"duration_s": end_us / 1e6})
    names = sorted(ticks)
    feds = {}
    for n in names:
        ctx = FederateContext(n, "t1", sc, tmp_path)
        feds[n] = Pinger(ctx, InMemoryBus(hub), [p for p in names if p != n], ticks[n], latency_us)
    conductor = Conductor(InMemoryBus(hub), "t1", names, W, end_us, window_timeout_s=5)
    threads = [threading.Thread(target=WindowDriver(f).serve, daemon=True) for f in feds.values()]
    for t in threads:
        t.start()
    conductor.wait_ready(5)
    return conductor, feds, threads


def finish(conductor: Conductor, threads: list[threading.Thread]) -> str:
    stopped = conductor.stop("completed", timeout_s=5)
    for t in threads:
        t.join(5)
    return conductor.trace_hash(stopped)


def test_inputs_processed_in_time_source_seq_order(tmp_path: Path) -> None:
    hub = InMemoryHub()
    conductor, feds, threads = federation(tmp_path, hub, {"a": [0, 5000], "b": [0, 5000], "c": [2000]})
    conductor.run()
    finish(conductor, threads)
    for f in feds.values():
        received = [(t, s, q) for t, s, q, kind in f.log if kind == "ping"]
        assert received == sorted(received)
        assert len(received) == 3 * sum(len(feds[p].ticks) for p in feds if p != f.name)


def test_idle_stretches_are_jumped(tmp_path: Path) -> None:
    hub = InMemoryHub()
    conductor, feds, threads = federation(tmp_path, hub, {"a": [0, 40_000], "b": [20_000]},
                                          end_us=1_000_000)
    result = conductor.run()
    finish(conductor, threads)
    # Windows: 0, 1 (pings in flight), 20, 21, 40, 41 -- not 1000.
    assert result.windows == 6
    assert [e[0] for e in feds["b"].log if e[3] == "ping"] == [1000] * 3 + [41_000] * 3


class Counting(Pinger):
    """A Pinger that counts the windows it took part in."""

    windows_processed = 0

    def process_window(self, adv):  # type: ignore[no-untyped-def]
        self.windows_processed += 1
        return super().process_window(adv)


def test_federates_with_nothing_to_do_sit_windows_out(tmp_path: Path) -> None:
    """``clock`` has an event in every window; ``p`` pings ``b`` every 5 ms (5 ms latency);
    ``quiet`` has no event and nothing is sent to it. ``quiet`` takes part in the first window
    only, ``b`` in the first, in each one after ``p`` sent it something, and in those its pings
    land in."""
    sc = parse_scenario({"duration_s": 0.02})
    hub = InMemoryHub()

    def fed(name: str, peers: list[str], ticks: list[int]) -> Counting:
        return Counting(FederateContext(name, "t1", sc, tmp_path), InMemoryBus(hub), peers, ticks, 5 * W)

    feds = {"clock": fed("clock", [], list(range(0, 20_000, 1000))),
            "p": fed("p", ["b"], list(range(0, 20_000, 5000))),
            "b": fed("b", [], []), "quiet": fed("quiet", [], [])}
    conductor = Conductor(InMemoryBus(hub), "t1", sorted(feds), W, 20_000, window_timeout_s=5)
    threads = [threading.Thread(target=WindowDriver(f).serve, daemon=True) for f in feds.values()]
    for t in threads:
        t.start()
    conductor.wait_ready(5)
    result = conductor.run()
    finish(conductor, threads)
    assert result.windows == 20
    assert feds["clock"].windows_processed == 20
    assert feds["p"].windows_processed == 4  # its ticks: 0, 5, 10, 15 ms
    assert feds["quiet"].windows_processed == 1
    # b: window 0; 1, 6, 11, 16 (pings sent in the window before); 5, 10, 15 (pings land).
    assert feds["b"].windows_processed == 8
    assert [e[0] for e in feds["b"].log] == [5000] * 3 + [10_000] * 3 + [15_000] * 3


def test_barrier_holds_against_reordered_and_late_delivery(tmp_path: Path) -> None:
    ticks = {"a": list(range(0, 30_000, 1000)), "b": list(range(500, 30_000, 1500)), "c": [7000, 9000]}
    hub = InMemoryHub()
    conductor, feds, threads = federation(tmp_path, hub, ticks, end_us=30_000)
    conductor.run()
    reference = finish(conductor, threads)
    ref_logs = {n: list(f.log) for n, f in feds.items()}

    hub2 = InMemoryHub()
    rnd = random.Random(7)

    def late(items: list) -> None:
        data = [it for it in items if "/sense/" in it[1]]
        ctl = [it for it in items if "/sense/" not in it[1]]
        for cb, key, payload in ctl:
            cb(key, payload)
        for cb, key, payload in data:  # deliver data late, on another thread, in random order
            threading.Timer(rnd.uniform(0, 0.01), cb, (key, payload)).start()

    hub2.deliver = late
    conductor2, feds2, threads2 = federation(tmp_path, hub2, ticks, end_us=30_000)
    conductor2.run()
    assert finish(conductor2, threads2) == reference
    assert {n: f.log for n, f in feds2.items()} == ref_logs


def test_sending_inside_the_window_is_a_causality_error(tmp_path: Path) -> None:
    hub = InMemoryHub()
    sc = parse_scenario({})
    fed = Federate(FederateContext("a", "t1", sc, tmp_path), InMemoryBus(hub))
    fed.window_end = 5000
    with pytest.raises(CausalityError, match="inside the window"):
        fed.send("b", 4999, Ping())


def test_silent_federate_fails_the_window(tmp_path: Path) -> None:
    hub = InMemoryHub()
    conductor = Conductor(InMemoryBus(hub), "t1", ["ghost"], W, 10_000, window_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(RunFailed, match="ghost"):
        conductor.run()
    assert time.monotonic() - t0 < 5


def test_collecting_reports_ends_soon_after_the_only_ones_missing_are_of_dead_federates(tmp_path: Path) -> None:
    hub = InMemoryHub()
    conductor = Conductor(InMemoryBus(hub), "t1", ["ghost"], W, 10_000, window_timeout_s=0.3)
    t0 = time.monotonic()
    assert conductor.stop("completed", timeout_s=30, dead=lambda: ["ghost"]) == {}
    assert time.monotonic() - t0 < 5  # the report grace, not the 30 s
