"""Shared fixtures of the netsim NR tests.

The repository is not necessarily pip-installed in the test environment (``pytest`` run from the
checkout), so the checkout root goes on sys.path when ``netsim`` is not importable yet.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

if importlib.util.find_spec("netsim") is None:  # pragma: no cover - depends on the install
    sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from scenario.nr import NrConfig  # noqa: E402

HALL_CENTRE = (60.0, 30.0, 1.5)


@pytest.fixture
def flat_config() -> NrConfig:
    """A deterministic radio: forced LOS, no shadowing, no fading, no control errors."""
    return NrConfig(los_mode="los", shadowing_enabled=False, fading="none",
                    pdcch_miss_prob=0.0, ack_miss_prob=0.0, nack_to_ack_prob=0.0)
