"""The platform's real compute jobs, runnable alone for calibration, each as its federate runs it:
frame compression (camera: sensor model applied, then the scenario's codec), pose estimation
(Edge: decode + the scenario's estimator), a control step (robot), the host-speed scoring mix
and a pure-Python CPU-bound reference (``spin``).

``python tools/workloads.py --cpus C --jobs N`` runs every workload N times through a
``ComputeNode`` of C cpus in ``cpu`` timing, interleaved job by job (spin, compress, pose, ...,
then again) so that a drift of the host's speed hits every workload alike, and prints one JSON
object (last line of stdout): this process's environment, its measured host score, the idle-wake penalty of its core (see
``idle_wake_penalty``) and, per
workload, per job: the CPU time charged to the job (its thread + library workers), the thread's
own share, the process CPU clock (every thread: what jobs were charged before), wall time, the
emulated duration, CFS throttling (time and throttled periods) and involuntary context switches.
Durations use the reference core's score (scale 1), so they are the job's own CPU time over
cpus. ``coordinator.calibrate`` runs it with and without CPU quotas, in both runtimes.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

WORKLOADS = ("spin", "compress", "pose", "control", "score")


def _spin() -> int:
    """About 50 ms of pure-Python arithmetic on a server core: the CPU-bound reference job (its
    working set fits the L1 cache, so its CPU time follows the core's clock, not the caches)."""
    acc = 0
    for i in range(600_000):
        acc = (acc + i * i) % 1_000_003
    return acc


def idle_wake_penalty(pairs: int = 30, idle_s: float = 0.010) -> float:
    """Median, over pairs, of the thread CPU time of a 2 ms ``spin``-like loop run right after
    ``idle_s`` of sleep over the same loop run right after the thread was busy.

    The loop's working set fits the L1 cache, so a ratio above 1 is the core running slower after
    it idled (clock ramping up, idle states, a hypervisor's scheduling), which is what a node
    throttled by its CPU quota meets at the start of every period."""
    import statistics

    def loop(n: int) -> int:
        acc = 0
        for i in range(n):
            acc = (acc + i * i) % 1_000_003
        return acc

    loop(50_000)
    ratios = []
    for i in range(pairs):
        cpu = {}
        for after_idle in (True, False) if i % 2 else (False, True):
            if after_idle:
                time.sleep(idle_s)
            else:
                loop(50_000)
            t0 = time.thread_time_ns()
            loop(20_000)
            cpu[after_idle] = time.thread_time_ns() - t0
        ratios.append(cpu[True] / max(cpu[False], 1))
    return statistics.median(ratios)


def build_jobs(frames: int = 4) -> dict[str, Callable[[], Any]]:
    """Each workload as a closure over inputs prepared once (rendering and the sensor model are
    not timed, as in the federates); ``frames`` rendered captures are cycled through."""
    from domain.codec import decode_frame, encode_frame
    from domain.controller import PickController
    from domain.estimator import make_estimator
    from domain.hall import SERVO_LAG_S
    from domain.sensor import sense, sensor_depth_mm, sensor_for
    from domain.work_cell import CameraIntrinsics
    from domain.world import World
    from fabric import host_speed
    from fabric.seeding import rng
    from scenario.schema import parse_scenario

    sc = parse_scenario({"loops": 1})
    cam = sc.camera
    world = World(sc)
    world.spawn(0)
    sensor, noise = sensor_for(cam), rng(sc.seed, "workloads/sensor")
    captures = []
    for i in range(frames):
        world.advance_to(1_500_000 + i * 100_000)
        rgb, depth = world.render(0, cam.width_px, cam.height_px)
        assert depth is not None
        captures.append(sense(sensor, rgb, sensor_depth_mm(depth, cam.depth_noise_mm, noise), noise))
    encoded = [encode_frame(rgb, d, cam.jpeg_quality, cam.depth_codec, cam.depth_decimation)
               for rgb, d in captures]
    est, _ = make_estimator(sc.edge.estimator, CameraIntrinsics(cam.width_px, cam.height_px, cam.fovy_deg),
                            sc.work_cell.object_size_m)
    ctl = PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S)
    ctl.on_estimate([{"id": o["task_id"], "t_us": 1_500_000, "p": o["p"], "v": o["v"]}
                     for o in world.objects(0)])
    arm = world.joint_state(0)
    ctl.on_state(arm["q"], arm["gripped"])
    state = {"tick": 1_500_000, "frame": 0}

    def compress() -> bytes:
        rgb, depth = captures[state["frame"] % frames]
        state["frame"] += 1
        return encode_frame(rgb, depth, cam.jpeg_quality, cam.depth_codec, cam.depth_decimation)

    def pose() -> Any:
        state["frame"] += 1
        return est.detect(*decode_frame(encoded[state["frame"] % frames]))

    def control() -> Any:
        state["tick"] += sc.robot.control_period_us
        return ctl.step(state["tick"])

    return {"spin": _spin, "compress": compress, "pose": pose, "control": control,
            "score": host_speed.run_mix}


def _throttled_periods() -> int | None:
    """CFS periods in which this process's cgroup was throttled so far (None: not visible)."""
    from fabric.compute import read_cpu_stat

    stat = read_cpu_stat()
    return None if stat is None else stat.get("nr_throttled")


def measure(cpus: float | None, jobs: int, only: list[str] | None = None) -> dict[str, Any]:
    """Run the workloads ``jobs`` times each on a node of ``cpus`` (None: no limit, 1 cpu)."""
    import cv2

    from fabric import host_speed
    from fabric.compute import ComputeNode, CpuSample, ThreadCpuClock, read_cpu_quota
    from fabric.seeding import rng
    from scenario.schema import NodeProfile

    class Recording(ThreadCpuClock):
        last = CpuSample(0)

        def stop(self, token: Any) -> CpuSample:
            self.last = super().stop(token)
            return self.last

    clock = Recording()
    ref = host_speed.reference()
    profile = NodeProfile(cpus=cpus or 1.0, timing="cpu")
    node = ComputeNode("calibrate", profile, rng(0, "calibrate"), clock=clock,
                       host=host_speed.HostScore(score=ref.score, source="injected"),
                       probe=lambda: ref.score)
    cv2.setNumThreads(node.threads)  # as the federates do: the pools at the node's cores
    host = host_speed.measure()
    selected = {k: v for k, v in build_jobs().items() if not only or k in only}
    for job in selected.values():  # warm caches, lazy imports and pools
        job()
        job()
    out: dict[str, list[dict[str, Any]]] = {name: [] for name in selected}
    names = list(selected)
    for j in range(jobs):
        for k in range(len(names)):
            name = names[(j + k) % len(names)]  # rotate the order: no workload always follows another
            periods0 = _throttled_periods()
            ru0 = resource.getrusage(resource.RUSAGE_THREAD)
            p0 = time.process_time_ns()
            node.run(name, 0, selected[name])
            p1 = time.process_time_ns()
            ru1 = resource.getrusage(resource.RUSAGE_THREAD)
            periods1 = _throttled_periods()
            rec, sample = node.records[-1], clock.last
            out[name].append({
                "cpu_us": rec.cpu_us, "thread_us": sample.own_ns // 1000,
                "helper_us": sum(sample.helpers_ns) // 1000, "process_us": (p1 - p0) // 1000,
                "wall_us": rec.wall_us, "duration_us": rec.duration_us,
                "throttled_us": rec.throttled_us,
                "throttled_periods": None if periods0 is None or periods1 is None else periods1 - periods0,
                "nivcsw": ru1.ru_nivcsw - ru0.ru_nivcsw,
            })
            node.records.clear()
    quota = read_cpu_quota()
    return {
        "env": {**host_speed.environment(), "cpus": cpus, "pid": os.getpid(),
                "cpu_quota": None if quota is None else [quota.quota_us, quota.period_us],
                "host_score": host.score, "host_components_ms": host.components_ms,
                "cv2_threads": cv2.getNumThreads(), "idle_wake_penalty": idle_wake_penalty(),
                "omp_num_threads": os.environ.get("OMP_NUM_THREADS")},
        "workloads": out,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cpus", type=float, default=None, help="node cpus (default: no limit, as 1 cpu)")
    ap.add_argument("--jobs", type=int, default=10, help="jobs per workload")
    ap.add_argument("--only", nargs="*", choices=WORKLOADS, help="workload names (default: all)")
    ap.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = ap.parse_args(argv)
    result = json.dumps(measure(args.cpus, args.jobs, args.only))
    if args.out:
        args.out.write_text(result + "\n")
    print(result)
    return 0
