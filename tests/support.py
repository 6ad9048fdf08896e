"""What several test modules share: scenario settings, a process scan and a local Ray cluster
(``benchmarks.local_cluster``, which ``make bench-cluster`` uses too)."""

from __future__ import annotations

from benchmarks.local_cluster import local_ray_cluster, processes_with

# Every compute node timed by its calibrated model: the same event trace on any host.
MODEL_TIMING = {"nodes.camera.timing": "model", "nodes.edge.timing": "model", "nodes.robot.timing": "model"}
MODEL_TIMING_SETS = [f"{field}={value}" for field, value in MODEL_TIMING.items()]

__all__ = ["MODEL_TIMING", "MODEL_TIMING_SETS", "local_ray_cluster", "processes_with"]
