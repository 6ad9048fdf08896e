"""A federate that does nothing but exist every window: the load of the conductor benchmark.

Run as a process: ``python -m benchmarks.ticker NAME RUN_ID ENDPOINT WINDOW_US END_US``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from fabric.bus import Bus
from fabric.driver import WindowDriver
from fabric.federate import Federate, FederateContext
from scenario.schema import parse_scenario


class Ticker(Federate):
    """Schedules an empty event in every window so that no window can be skipped."""

    def __init__(self, ctx: FederateContext, bus: Bus, window_us: int) -> None:
        super().__init__(ctx, bus)
        self.window_us = window_us

    def setup(self) -> None:
        self.schedule(0, self.tick)

    def tick(self) -> None:
        if self.now + self.window_us < self.scenario.duration_us:
            self.schedule(self.now + self.window_us, self.tick)


def context(name: str, run_id: str, window_us: int, end_us: int) -> FederateContext:
    sc = parse_scenario({"duration_s": end_us / 1e6, "window_us": window_us})
    return FederateContext(name, run_id, sc, Path("."))


def main() -> int:
    name, run_id, endpoint, window_us, end_us = sys.argv[1:6]
    from fabric.zenoh_bus import ZenohBus

    bus = ZenohBus(endpoint)
    try:
        return WindowDriver(Ticker(context(name, run_id, int(window_us), int(end_us)), bus, int(window_us))).serve()
    finally:
        bus.close()


if __name__ == "__main__":
    sys.exit(main())
