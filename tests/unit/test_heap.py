"""The garbage collector settings of a simulation process, and their undoing."""

from __future__ import annotations

import gc

from fabric.heap import THRESHOLDS, simulation_heap


def test_simulation_heap_freezes_set_up_and_gives_the_collector_back() -> None:
    before = gc.get_threshold()
    kept = [[] for _ in range(100)]  # set-up's objects, alive on entry
    with simulation_heap():
        assert gc.get_threshold() == THRESHOLDS
        assert gc.get_freeze_count() >= len(kept)
    assert gc.get_threshold() == before
    assert gc.get_freeze_count() == 0
