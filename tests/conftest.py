"""Test-wide settings: headless rendering, and `slow` tests that run only when asked for."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` (a minute or more) run with ``-m slow`` or COSIM5G_SLOW_TESTS=1."""
    if "slow" in (config.getoption("markexpr") or "") or os.environ.get("COSIM5G_SLOW_TESTS"):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow or COSIM5G_SLOW_TESTS=1")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
