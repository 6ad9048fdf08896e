"""Pick-and-place sensitivity to the pose channel (``python -m benchmarks.physics_sensitivity``).

Task success of the real controller fed each frame's ground-truth pose after a fixed delay, frames
lost independently, with and without the delay-aware correction (p + v * age). ``--pose-error-mm
X`` adds the abstract loops' path: error of sd X mm per axis, the Edge's tracker. Results:
docs/physics.md, "Tests and benchmarks"; writes ``results/bench/physics_sensitivity.md``, ``.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from scenario.schema import parse_scenario
from services.physics.ideal_loop import run_ideal

ROOT = Path(__file__).parents[1]
DELAYS_MS = (0, 20, 50, 100, 200)
LOSSES = (0.0, 0.5, 0.9)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--loops", type=int, default=4, help="cells simulated at once (default 4)")
    ap.add_argument("--seconds", type=float, default=40.0, help="simulated time per configuration")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="scenario override, e.g. work_cell.object_yaw_spread_deg=180 (repeatable)")
    ap.add_argument("--pose-error-mm", type=float, default=None,
                    help="also run with tracked poses of this error sd (mm per axis)")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench")
    args = ap.parse_args(argv)
    base = parse_scenario({"loops": args.loops, "detailed_loops": 0, "duration_s": args.seconds,
                           "seed": args.seed}, args.set)
    panels: list[tuple[str, float | None]] = [("ground-truth pose and velocity", None)]
    if args.pose_error_mm is not None:
        panels.append((f"tracked estimates, position error sd {args.pose_error_mm:g} mm",
                       args.pose_error_mm / 1000))
    results = []
    t0 = time.perf_counter()
    for panel, error in panels:
        for comp in (True, False):
            sc = base.model_copy(update={"robot": base.robot.model_copy(update={"delay_compensation": comp})})
            for loss in LOSSES:
                for delay in DELAYS_MS:
                    r = run_ideal(sc, delay_us=delay * 1000, frame_loss=loss, pose_error_sd_m=error)
                    results.append({"poses": panel, "delay_ms": delay, "frame_loss": loss,
                                    "compensation": comp, "tasks": len(r.tasks),
                                    "placed": sum(t["success"] for t in r.tasks),
                                    "success_rate": r.success_rate, "holds": r.holds})
                    print(f"  {panel}: delay {delay:>3} ms  loss {loss:.1f}  compensation "
                          f"{'on ' if comp else 'off'}  {results[-1]['placed']:>3}/{len(r.tasks):<3} placed",
                          flush=True)
    wall = time.perf_counter() - t0

    def cell(panel: str, delay: int, loss: float, comp: bool) -> str:
        r = next(x for x in results if x["poses"] == panel and x["delay_ms"] == delay
                 and x["frame_loss"] == loss and x["compensation"] == comp)
        return f"{100 * r['success_rate']:5.1f}"

    lines = []
    for panel, _ in panels:
        lines += [f"**{panel}**", "",
                  "| pose delay | " + " | ".join(f"loss {loss:.1f} {tag}" for loss in LOSSES
                                                  for tag in ("comp", "naive")) + " |",
                  "|---|" + "---:|" * (2 * len(LOSSES))]
        for d in DELAYS_MS:
            lines.append(f"| {d:>4} ms | " + " | ".join(cell(panel, d, loss, comp) for loss in LOSSES
                                                       for comp in (True, False)) + " |")
        lines.append("")
    tasks = sorted({r["tasks"] for r in results})
    notes = (f"Task success rate (%), a pose per camera frame at {base.camera.fps} frame/s, "
             f"{args.loops} cells x {args.seconds:g} s simulated per configuration "
             f"({tasks[0]}-{tasks[-1]} finished tasks each), seed {args.seed}, belt "
             f"{base.work_cell.belt_speed_m_s} m/s, a part every {base.work_cell.object_period_s} s, "
             f"estimates older than {base.robot.max_estimate_age_ms:g} ms make the arm hold. "
             f"comp: delay-aware prediction p + v * age; naive: last pose as is. "
             f"Overrides: {', '.join(args.set) or 'none'}. Wall time {wall:.0f} s.")
    table = "\n".join(lines).rstrip()
    print(table)
    print(notes)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "physics_sensitivity.md").write_text(
        "# Pick-and-place success vs pose delay and frame loss\n\n" + table + "\n\n" + notes + "\n")
    (args.out / "physics_sensitivity.json").write_text(json.dumps(
        {"loops": args.loops, "seconds": args.seconds, "seed": args.seed, "overrides": args.set,
         "pose_error_mm": args.pose_error_mm, "wall_s": wall, "results": results}, indent=1) + "\n")
    print(f"written to {args.out / 'physics_sensitivity.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
