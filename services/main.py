"""Entry point of every federate process: ``python -m services.main <role> --name ... ``.

Serves one federate of ``role`` (for ``group``, the ``--member NAME:ROLE`` federates as one
participant) until the coordinator stops the run; how it never outlives its coordinator, and its
exit codes: docs/architecture.md sec. 10, "Nothing outlives its run".
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from fabric.driver import EXIT_ORPHANED, Participant, WindowDriver
from fabric.federate import FederateContext
from fabric.heap import simulation_heap
from fabric.settings import env_name, settings
from scenario.schema import ScenarioError, load_scenario
from services.roles import ROLES

PARENT_PID_ENV = env_name("parent_pid")
PROFILE_DIR_ENV = env_name("profile_dir")  # where each federate writes its cProfile statistics
ORPHAN_GRACE_S = 3.0  # time to write the last records once the coordinator is gone
_PR_SET_PDEATHSIG = 1


def member(text: str) -> tuple[str, str]:
    """``NAME:ROLE`` of a group's member."""
    name, _, role = text.partition(":")
    if not name or role not in ROLES:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME:ROLE with ROLE one of {', '.join(ROLES)}")
    return name, role


def set_parent_death_signal(sig: int) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux only); whether
    it could."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return int(libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


class Lifeline:
    """Ends this process when its coordinator is gone: first asks the federate to leave (write
    its records), then exits hard after ``grace_s`` whatever the federate is doing."""

    def __init__(self, grace_s: float = ORPHAN_GRACE_S) -> None:
        self.grace_s = grace_s
        self.driver: WindowDriver | None = None
        self.reason: str | None = None
        self._armed = threading.Lock()

    def lost(self, reason: str) -> None:
        """The coordinator is gone (any thread, or a signal handler)."""
        if not self._armed.acquire(blocking=False):
            return  # already leaving
        self.reason = reason
        sys.stderr.write(f"leaving: {reason}\n")  # one write: other threads log to this stream too
        sys.stderr.flush()
        timer = threading.Timer(self.grace_s, os._exit, (EXIT_ORPHANED,))
        timer.daemon = True
        timer.start()
        if self.driver is not None:
            self.driver.abandon(reason)

    def attach(self, driver: WindowDriver) -> None:
        """From now on a loss makes ``driver``'s participant leave; a loss before this ends the
        process."""
        self.driver = driver
        driver.on_orphaned = self.lost
        if self.reason is not None:
            driver.abandon(self.reason)

    def on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.driver is None:  # nothing recorded yet: leave at once
            sys.exit(EXIT_ORPHANED)
        parent = settings().parent_pid
        if parent is not None and os.getppid() != parent:  # the parent-death signal
            self.lost(f"the coordinator (pid {parent}) died")
        else:
            self.lost(f"received {signal.Signals(signum).name}")

    def watch_parent(self) -> None:
        """Leave when the coordinator that started this process dies. The parent may already be
        gone by the time the death signal is set up: compare with the pid it announced."""
        expected = settings().parent_pid
        if expected is None:
            return  # not started by a coordinator directly (containers: tini is the parent)
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != expected:
            self.lost(f"the coordinator (pid {expected}) exited before this federate started")


def serve_profiled(driver: WindowDriver, profile_dir: Path | None) -> int:
    """Serve ``driver``'s participant; with ``profile_dir`` set, under cProfile, its statistics
    written to ``<profile_dir>/<participant>.pstats`` when it leaves (``benchmarks.speed --profile``)."""
    if profile_dir is None:
        return driver.serve()
    import cProfile

    prof = cProfile.Profile()
    try:
        return prof.runcall(driver.serve)
    finally:
        Path(profile_dir).mkdir(parents=True, exist_ok=True)
        prof.dump_stats(str(Path(profile_dir) / f"{driver.participant.name}.pstats"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="services.main", description=__doc__)
    ap.add_argument("role", choices=[*ROLES, "group"])
    ap.add_argument("--name", required=True, help="federate name, e.g. camera-0")
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--endpoint", required=True, help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--scenario", required=True, help="resolved scenario YAML of the run")
    ap.add_argument("--results", required=True, help="run directory for result tables")
    ap.add_argument("--records", choices=["files", "stream"], default="files",
                    help="write table parts into the run directory, or stream them to the coordinator "
                         "(a node that does not see the run directory)")
    ap.add_argument("--member", type=member, action="append", default=[], metavar="NAME:ROLE",
                    help="a federate of the group (role group; repeatable)")
    args = ap.parse_args(argv)
    if (args.role == "group") != bool(args.member):
        ap.error("--member goes with the role group, which needs at least one")
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {args.name} %(levelname)s %(name)s: %(message)s")
    lifeline = Lifeline()
    signal.signal(signal.SIGTERM, lifeline.on_signal)
    lifeline.watch_parent()
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"{args.name}: invalid scenario {args.scenario}:\n{exc.format()}", file=sys.stderr)
        return 2
    from fabric.metrics import serve_from_env
    from fabric.zenoh_bus import ZenohBus

    serve_from_env()

    bus = ZenohBus(args.endpoint, mode="client")
    stream = args.records == "stream"
    ctx = FederateContext(args.name, args.run_id, scenario, Path(args.results), stream)
    participant: Participant
    if args.role == "group":
        from fabric.group import FederateGroup

        members = [ROLES[r].federate_class()(FederateContext(name, args.run_id, scenario, Path(args.results), stream),
                                             bus) for name, r in args.member]
        participant = FederateGroup(ctx, bus, members)
    else:
        participant = ROLES[args.role].federate_class()(ctx, bus)
    driver = WindowDriver(participant)
    lifeline.attach(driver)
    try:
        with simulation_heap():
            code = serve_profiled(driver, settings().profile_dir)
    except Exception:
        logging.getLogger(args.name).exception("federate failed")
        code = 1
    finally:
        bus.close()
    return code


if __name__ == "__main__":
    sys.exit(main())
