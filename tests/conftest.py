"""Shared fixtures: an in-memory federation harness and scenario helpers."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
