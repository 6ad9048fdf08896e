"""The robot node: runs the pick-and-place controller every control period on its throttled CPU,
with pose estimates arriving from the Edge over netsim and joint states from the arm's drives;
commands go to the arm after the actuation latency.
"""

from __future__ import annotations

from typing import Any

from domain.arm import SERVO_LAG_S
from domain.controller import PickController
from fabric.compute import ComputeNode
from fabric.federate import Federate, Handlers
from fabric.messages import Message
from wire.bodies import Commands, JointState, Pose


class RobotFederate(Federate):
    role = "robot"

    def setup(self) -> None:
        sc = self.scenario
        self.loop = int(self.name.rsplit("-", 1)[1])
        self.cpu = ComputeNode(self.name, sc.nodes.robot, self.rng("compute"))
        self.record_jobs(self.cpu)
        self.ctl = PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S)
        self.estimates = 0
        self.schedule(0, self._tick)

    def handlers(self) -> Handlers:
        return {Pose: self._on_pose, JointState: self._on_state}

    def _on_pose(self, pose: Pose, msg: Message) -> None:
        self.ctl.on_estimate(pose.tracks)
        self.estimates += 1

    def _on_state(self, state: JointState, msg: Message) -> None:
        self.ctl.on_state(state.q, state.gripped)

    def _tick(self) -> None:
        sc = self.scenario
        (q, suction), ready = self.cpu.run("control", self.now, self.ctl.step, self.now)
        self.send("physics", ready + sc.robot.actuation_latency_us,
                  Commands([{"loop": self.loop, "q": [float(v) for v in q], "suction": bool(suction)}]))
        nxt = self.now + sc.robot.control_period_us
        if nxt < sc.duration_us:
            self.schedule(nxt, self._tick)

    def finish(self, reason: str) -> dict[str, Any]:
        return {"picks": self.ctl.picks, "estimates": self.estimates, "holds": self.ctl.holds,
                "compute_speed": self.cpu.speed_summary(self.now)}
