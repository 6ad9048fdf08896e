"""Physics speed (``python -m benchmarks.physics_speed``): the hall's real-time factor for N cells
without rendering, its CPU time a cell and step and the speed that bounds on this host's cores,
and what rendering one detailed loop costs.

Every cell works as in a run; the real-time factor counts only the physics (``World`` stepping,
spawns, commands), the controllers' time is reported apart. Results: docs/physics.md, "Tests
and benchmarks"; writes ``results/bench/physics_speed.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from domain.world import World
from scenario.schema import Scenario, parse_scenario
from services.physics.ideal_loop import run_ideal

ROOT = Path(__file__).parents[1]


class TimedWorld(World):
    """A World that adds up the wall time and the CPU time (this thread's, which steps it) spent
    in the physics. The CPU time holds on a host busy with other work, where the wall time
    stretches."""

    physics_s = 0.0
    physics_cpu_s = 0.0

    def _timed(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        t0, c0 = time.perf_counter(), time.thread_time()
        out = fn(*args, **kwargs)
        self.physics_s += time.perf_counter() - t0
        self.physics_cpu_s += time.thread_time() - c0
        return out

    def advance_to(self, t_us: int) -> None:
        self._timed(super().advance_to, t_us)

    def spawn(self, *args: Any, **kwargs: Any) -> Any:
        return self._timed(super().spawn, *args, **kwargs)

    def command(self, *args: Any, **kwargs: Any) -> None:
        self._timed(super().command, *args, **kwargs)


def hall_speed(n: int, seconds: float, seed: int, hall: dict[str, Any] | None = None) -> dict[str, Any]:
    sc = parse_scenario({"loops": n, "detailed_loops": 0, "duration_s": seconds, "seed": seed,
                         "hall": hall or {}})
    t0 = time.perf_counter()
    world = TimedWorld(sc)
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = run_ideal(sc, world=world)
    total_s = time.perf_counter() - t0
    steps = sc.duration_us // sc.physics_timestep_us
    return {"cells": n, "sim_s": seconds, "build_s": build_s, "physics_s": world.physics_s,
            "physics_cpu_s": world.physics_cpu_s,
            "controllers_s": total_s - world.physics_s, "rtf_physics": seconds / world.physics_s,
            "rtf_closed_loop": seconds / total_s, "us_per_step": 1e6 * world.physics_s / steps,
            "us_per_step_per_cell": 1e6 * world.physics_s / steps / n,
            "cpu_us_per_step_per_cell": 1e6 * world.physics_cpu_s / steps / n, "tasks": len(res.tasks),
            "placed": sum(t["success"] for t in res.tasks), "nv": world.model.nv}


def physics_bound(h: dict[str, Any], cores: int) -> float:
    """The most simulated seconds per wall second any run of the hall's cells can reach on
    ``cores`` cores, were every core stepping physics and nothing else running: a run's
    physics is its hall's steps, whichever runtime or partitions carry them."""
    return cores * h["sim_s"] / h["physics_cpu_s"]


def render_cost(sc: Scenario, frames: int) -> float:
    """Wall ms per RGB + depth frame of one cell camera, over ``frames`` frames of a moving scene
    (the renderer's one-off set-up excluded)."""
    world = World(sc)
    world.spawn(0)
    world.advance_to(1_000_000)
    world.render(0, sc.camera.width_px, sc.camera.height_px)  # GL context and buffers
    spent = 0.0
    for k in range(frames):
        world.advance_to(1_000_000 + (k + 1) * sc.frame_period_us)
        t0 = time.perf_counter()
        world.render(0, sc.camera.width_px, sc.camera.height_px)
        spent += time.perf_counter() - t0
    world.finish()
    return 1000 * spent / frames


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, nargs="+", default=[1, 8, 16, 32])
    ap.add_argument("--seconds", type=float, default=8.0, help="simulated time per hall size")
    ap.add_argument("--frames", type=int, default=60, help="frames per render measurement")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--per-row", type=int, help="hall.work_cells_per_row (default: the scenario's); "
                    "a larger hall for more cells, e.g. 16 with --pitch-m 4 holds 240")
    ap.add_argument("--pitch-m", type=float, help="hall.work_cell_pitch_m, the same along x and y")
    ap.add_argument("--cores", type=int, default=os.cpu_count() or 1,
                    help="cores of the physics bound (default: this host's)")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    args = ap.parse_args(argv)

    hall: dict[str, Any] = {}
    if args.per_row is not None:
        hall["work_cells_per_row"] = args.per_row
    if args.pitch_m is not None:
        hall["work_cell_pitch_m"] = [args.pitch_m, args.pitch_m]
    halls = []
    for n in args.cells:
        halls.append(hall_speed(n, args.seconds, args.seed, hall))
        h = halls[-1]
        print(f"  {n:>3} cells: physics RTF {h['rtf_physics']:.2f}, {h['us_per_step']:.0f} us/step", flush=True)
    renders: list[dict[str, Any]] = []
    for label, cam in (("default 640x360", {}), ("smoke 424x240", {"width_px": 424, "height_px": 240})):
        sc = parse_scenario({"loops": 1, "detailed_loops": 1, "camera": cam})
        renders.append({"camera": label, "ms_per_frame": render_cost(sc, args.frames), "fps": sc.camera.fps})
        print(f"  render {label}: {renders[-1]['ms_per_frame']:.2f} ms per RGB-D frame", flush=True)

    one = next((h for h in halls if h["cells"] == 1), halls[0])
    lines = ["| cells | DOF | physics RTF | physics us / step | us / step / cell | CPU us / step / cell | "
             f"physics bound on {args.cores} cores | RTF with controllers | placed |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for h in halls:
        lines.append(f"| {h['cells']} | {h['nv']} | {h['rtf_physics']:.2f} | {h['us_per_step']:.0f} | "
                     f"{h['us_per_step_per_cell']:.1f} | {h['cpu_us_per_step_per_cell']:.1f} | "
                     f"{physics_bound(h, args.cores):.2f} | {h['rtf_closed_loop']:.2f} | "
                     f"{h['placed']}/{h['tasks']} |")
    lines += ["", "| render (RGB + depth, one detailed loop) | ms / frame | x physics of 1 cell | x physics of the largest hall |",
              "|---|---:|---:|---:|"]
    big = halls[-1]
    for r in renders:
        # Wall time per simulated second: rendering fps frames vs stepping the physics.
        render_per_s = r["ms_per_frame"] * r["fps"] / 1000
        lines.append(f"| {r['camera']} at {r['fps']} frame/s | {r['ms_per_frame']:.2f} | "
                     f"{render_per_s / (one['physics_s'] / one['sim_s']):.2f} | "
                     f"{render_per_s / (big['physics_s'] / big['sim_s']):.2f} |")
    notes = (f"Physics RTF: simulated seconds per wall second spent in the physics (stepping at "
             f"1 ms, belt drive, suction, task checks), {args.seconds:g} s simulated per hall with "
             f"every arm picking (ground-truth poses). 'x physics': wall time of rendering the "
             f"loop's frames for one simulated second over the physics wall time of one simulated "
             f"second. CPU us: the stepping thread's CPU time, which other work on a shared host "
             f"stretches less than the wall time. Physics bound: {args.cores} cores x simulated s / "
             f"physics CPU s, the speed no run of that many abstract loops exceeds on this host "
             f"(its controllers, radio and messages come on top). MuJoCo renders with EGL on this "
             f"host; numbers are for one shared machine.")
    table = "\n".join(lines)
    print(table)
    print(notes)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "physics_speed.md").write_text("# Physics speed\n\n" + table + "\n\n" + notes + "\n")
    (args.out / "physics_speed.json").write_text(json.dumps({"halls": halls, "render": renders}, indent=1) + "\n")
    print(f"written to {args.out / 'physics_speed.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
