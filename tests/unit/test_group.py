"""Federates served as one group (``fabric.group``): every member processes and sends exactly what
it would on its own, also in the long windows a group is given up to its horizon; failures name
the member."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from test_conductor import Ping, Pinger, W

from coordinator.conductor import Conductor, RunFailed
from fabric import keys
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.driver import Participant, WindowDriver, WindowReport
from fabric.federate import NEVER_US, FederateContext
from fabric.group import FederateGroup
from fabric.messages import Advance, Message
from scenario.schema import parse_scenario

TICKS = {"a": [0, 3000, 7000, 20_000], "b": [0, 5000, 5000], "c": [2000, 9000], "d": [1000, 30_000]}


class Promising(Pinger):
    """A pinger that promises to send nothing outside its group (true when its peers are members)."""

    def external_horizon_us(self) -> int | None:
        return NEVER_US


class Announcing(Pinger):
    """A pinger that promises its next tick, when it sends next, as its horizon."""

    def external_horizon_us(self) -> int | None:
        ticked = sum(1 for entry in self.log if entry[3] == "tick")
        return self.ticks[ticked] if ticked < len(self.ticks) else NEVER_US


class Breaker(Pinger):
    """A pinger that raises at b's second tick."""

    def tick(self) -> None:
        if self.name == "b" and self.now > 0:
            raise KeyError("broken on purpose")
        super().tick()


class SetupBreaker(Pinger):
    """A pinger whose setup fails for b."""

    def setup(self) -> None:
        if self.name == "b":
            raise FileNotFoundError("no model for b")
        super().setup()


class Ahead(Pinger):
    """A pinger that records the bounds up to which the group lets it work ahead, each with how
    many messages it had accepted by then."""

    def accept(self, msg: Message) -> None:
        self.__dict__.setdefault("accepted", []).append(msg.t_us)
        super().accept(msg)

    def work_ahead(self, until_us: int) -> None:
        self.__dict__.setdefault("ahead", []).append((until_us, len(self.__dict__.get("accepted", []))))


class AheadAnnouncing(Ahead):
    """A pinger working ahead that promises, on every plane, to send nothing before its next tick,
    and nothing outside its group (true when its peers are members)."""

    def external_horizon_us(self) -> int | None:
        return NEVER_US

    def next_send_us(self, plane: str, now_us: int) -> int:
        ticked = sum(1 for entry in self.log if entry[3] == "tick")
        return max(now_us, self.ticks[ticked]) if ticked < len(self.ticks) else NEVER_US


def run(tmp_path: Path, grouped: list[str], latency_us: int = W,
        peers: dict[str, list[str]] | None = None, kind: type[Pinger] = Pinger,
        windows: list[tuple[int, int]] | None = None,
        ) -> tuple[Conductor, dict[str, Pinger], dict[str, str]]:
    """Run the pingers of TICKS, those in ``grouped`` as the group ``g``; their logs and the
    stopped reports' trace hashes. ``windows`` collects the windows conducted (start, end)."""
    hub = InMemoryHub()
    if windows is not None:
        def on_advance(key: str, payload: bytes) -> None:
            adv = Advance.decode(payload)
            windows.append((adv.t_start_us, adv.t_end_us))
        InMemoryBus(hub).subscribe(keys.advance("t1"), on_advance)
    sc = parse_scenario({"duration_s": 0.05})
    names = sorted(TICKS)
    feds = {n: kind(FederateContext(n, "t1", sc, tmp_path / n), InMemoryBus(hub),
                    (peers or {}).get(n, [p for p in names if p != n]), TICKS[n], latency_us)
            for n in names}
    serving: list[Participant] = [f for n, f in feds.items() if n not in grouped]
    groups = {}
    if grouped:
        group_bus = InMemoryBus(hub)
        members = [kind(FederateContext(n, "t1", sc, tmp_path / n), group_bus,
                        (peers or {}).get(n, [p for p in names if p != n]), TICKS[n], latency_us)
                   for n in grouped]
        feds.update({m.name: m for m in members})
        serving.append(FederateGroup(FederateContext("g", "t1", sc, tmp_path / "g"), group_bus, members))
        groups = {"g": list(grouped)}
    participants = sorted([n for n in names if n not in grouped] + (["g"] if grouped else []))
    conductor = Conductor(InMemoryBus(hub), "t1", participants, W, 50_000, window_timeout_s=5, groups=groups,
                          long_window_us=20 * W)
    threads = [threading.Thread(target=WindowDriver(f).serve, daemon=True) for f in serving]
    for t in threads:
        t.start()
    conductor.wait_ready(5)
    try:
        conductor.run()
    finally:
        stopped = conductor.stop("completed", timeout_s=5)
        for t in threads:
            t.join(5)
    return conductor, feds, {n: s.trace_hash for n, s in stopped.items()}


def test_members_process_and_send_what_they_would_alone(tmp_path: Path) -> None:
    _, alone, alone_traces = run(tmp_path / "alone", [])
    conductor, grouped, traces = run(tmp_path / "grouped", ["a", "b", "c"])
    assert sorted(traces) == ["a", "b", "c", "d"]  # every member reports for itself
    for n in TICKS:
        assert grouped[n].log == alone[n].log, n
    assert traces == alone_traces  # same windows: the same events and the same bytes sent


def test_a_group_that_sends_nothing_out_takes_long_windows_with_the_same_result(tmp_path: Path) -> None:
    # a, b, c talk only to each other; d has its own ticks.
    peers = {"a": ["b", "c"], "b": ["a", "c"], "c": ["a", "b"], "d": []}
    base, alone, _ = run(tmp_path / "alone", [], peers=peers)
    long, grouped, _ = run(tmp_path / "grouped", ["a", "b", "c"], peers=peers, kind=Promising)
    for n in TICKS:
        assert grouped[n].log == alone[n].log, n
    assert long.windows < base.windows / 2


def test_a_member_sending_out_of_a_long_window_fails_the_run(tmp_path: Path) -> None:
    # c promises to send nothing out, but sends to d: its message would land inside the long window.
    peers = {"a": ["b"], "b": ["a"], "c": ["d"], "d": []}
    with pytest.raises(RunFailed, match="c: ping to d delivered at .* inside the window") as err:
        run(tmp_path, ["a", "b", "c"], peers=peers, kind=Promising)
    assert err.value.federate == "c"


def test_a_long_window_takes_in_the_base_window_of_the_horizon(tmp_path: Path) -> None:
    # c sends to d at its ticks (2000, 9000), delivered a base window later: the window in which
    # it sends may end there, not at the tick. Everything is processed as without long windows.
    peers = {"a": ["b"], "b": ["a"], "c": ["d"], "d": []}
    _, alone, _ = run(tmp_path / "alone", [], peers=peers)
    windows: list[tuple[int, int]] = []
    _, grouped, _ = run(tmp_path / "grouped", ["a", "b", "c"], peers=peers, kind=Announcing, windows=windows)
    for n in TICKS:
        assert grouped[n].log == alone[n].log, n
    # After 8000 the group's horizon is c's send at 9000: the window runs to 10 000, where that
    # send arrives (up to 9000 only before).
    assert (8000, 10_000) in windows


def test_a_failing_member_is_named(tmp_path: Path) -> None:
    with pytest.raises(RunFailed, match="KeyError") as err:
        run(tmp_path, ["a", "b", "c"], kind=Breaker)
    assert err.value.federate == "b"


def test_a_member_whose_setup_fails_is_named_with_its_error(tmp_path: Path) -> None:
    with pytest.raises(RunFailed, match=r"^b: setup failed: FileNotFoundError: no model for b") as err:
        run(tmp_path, ["a", "b", "c"], kind=SetupBreaker)
    assert err.value.federate == "b"


def test_a_message_from_outside_bounds_the_horizon_until_it_is_processed(tmp_path: Path) -> None:
    # A member may answer a message from outside as soon as it arrives: the group promises
    # nothing beyond a pending one's delivery time, whatever its members promise.
    sc = parse_scenario({"duration_s": 0.05})
    bus = InMemoryBus(InMemoryHub())
    member = Promising(FederateContext("a", "t1", sc, tmp_path / "a"), bus, [], [], W)
    group = FederateGroup(FederateContext("g", "t1", sc, tmp_path / "g"), bus, [member])
    group.setup()
    group.accept(Message(7 * W, "d", "a", 0, "sense", "ping", Ping()))

    def window(i: int, start: int, end: int) -> WindowReport:
        return group.process_window(Advance(window=i, t_start_us=start, t_end_us=end, expected_in={}))

    assert window(0, 0, W).horizon_us == 7 * W
    assert window(1, W, 8 * W).horizon_us == NEVER_US  # delivered: only the members' promise is left
    assert member.log == [(7 * W, "d", 0, "ping")]


def test_a_member_may_work_ahead_up_to_the_end_of_the_base_window_after_every_event(tmp_path: Path) -> None:
    # After each event of any member, the group offers every member the time until which no
    # message can reach it: with no promise from its peers, the end of that event's base window.
    _, alone, _ = run(tmp_path / "alone", [], kind=Ahead)
    _, grouped, _ = run(tmp_path / "grouped", ["a", "b", "c"], kind=Ahead)
    times = sorted(entry[0] for n in "abc" for entry in grouped[n].log)  # the group's events
    for n in "abc":
        assert [until for until, _ in grouped[n].__dict__["ahead"]] == [(t // W + 1) * W for t in times], n
        assert grouped[n].log == alone[n].log, n
    assert all("ahead" not in f.__dict__ for f in alone.values())  # served alone: never offered


def test_peers_promising_their_next_send_let_a_member_work_further_ahead(tmp_path: Path) -> None:
    # a, b, c talk only to each other, so the group is given long windows.
    peers = {"a": ["b", "c"], "b": ["a", "c"], "c": ["a", "b"], "d": []}
    _, alone, _ = run(tmp_path / "alone", [], peers=peers, kind=Ahead)
    _, grouped, _ = run(tmp_path / "grouped", ["a", "b", "c"], peers=peers, kind=AheadAnnouncing)
    times = sorted(entry[0] for n in "abc" for entry in grouped[n].log)
    beyond = 0
    for n in "abc":
        member = grouped[n]
        assert member.log == alone[n].log, n
        offers = member.__dict__["ahead"]
        beyond += sum(until > (t // W + 1) * W for (until, _), t in zip(offers, times, strict=True))
        # Every message delivered before an offer's bound had arrived when it was made.
        received = sorted(entry[0] for entry in member.log if entry[3] != "tick")
        for until, accepted in offers:
            assert sum(t < until for t in member.__dict__["accepted"][:accepted]) == \
                sum(t < until for t in received), (n, until)
    assert beyond > 0  # the promises reached past the base window
