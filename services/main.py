"""Entry point of every federate process: ``python -m services.main <role> --name ... ``.

Connects to the run's zenoh router, builds the federate of the given role and serves the window
protocol until the coordinator stops the run. Exit code 0 on a clean stop, 1 on a failure.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from services.common.federate import Federate, FederateContext
from services.common.scenario import ScenarioError, load_scenario


def federate_class(role: str) -> type[Federate]:
    # Imported lazily: a camera process does not need to load MuJoCo.
    if role == "physics":
        from services.physics.federate import PhysicsFederate
        return PhysicsFederate
    if role == "camera":
        from services.camera.federate import CameraFederate
        return CameraFederate
    if role == "edge":
        from services.edge.federate import EdgeFederate
        return EdgeFederate
    if role == "robot":
        from services.robot.federate import RobotFederate
        return RobotFederate
    if role == "netsim":
        from netsim.federate import NetsimFederate
        return NetsimFederate
    if role == "loops":
        from services.loops.federate import LoopsFederate
        return LoopsFederate
    raise ValueError(f"unknown role {role!r}: physics, camera, edge, robot, netsim or loops")


ROLES = ("physics", "camera", "edge", "robot", "netsim", "loops")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="services.main", description=__doc__)
    ap.add_argument("role", choices=ROLES)
    ap.add_argument("--name", required=True, help="federate name, e.g. camera-0")
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--endpoint", required=True, help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--scenario", required=True, help="resolved scenario YAML of the run")
    ap.add_argument("--results", required=True, help="run directory for result tables")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {args.name} %(levelname)s %(name)s: %(message)s")
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"{args.name}: invalid scenario {args.scenario}:\n{exc.format()}", file=sys.stderr)
        return 2
    from services.common.metrics import serve_from_env
    from services.common.zenoh_bus import ZenohBus

    serve_from_env()

    bus = ZenohBus(args.endpoint, mode="client")
    ctx = FederateContext(args.name, args.run_id, scenario, Path(args.results))
    fed = federate_class(args.role)(ctx, bus)
    try:
        code = fed.serve()
    except Exception:
        logging.getLogger(args.name).exception("federate failed")
        code = 1
    finally:
        bus.close()
    return code


if __name__ == "__main__":
    sys.exit(main())
