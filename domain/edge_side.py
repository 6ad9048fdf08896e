"""The Edge side of a control loop, run alike by the Edge federate (detailed loops) and the
abstract loops federate: folding a frame's estimates into the loop's tracker, the co-design step
(loop state -> policy -> QoS, signalled to the camera when it changed, and with lower-layer
signalling to the gNB too) and the downlink packet that carries a pose or a QoS through netsim.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from domain import cell_geometry as g
from domain.codec import slot_after
from domain.policy import LoopState, Qos, make_policy
from domain.policy_features import LIFTED_M, spawn_time_us
from domain.tracker import Tracker
from fabric import metrics
from scenario.schema import CellConfig, PolicyConfig, Scenario

# An unchanged QoS is signalled again this often: the downlink can lose it.
QOS_REFRESH_US = 1_000_000


def update_tracks(tracker: Tracker, capture_us: int, positions: list[np.ndarray]) -> list[dict] | None:
    """Fold one frame's part positions into ``tracker``; the tracks to send the robot, or None
    when an older frame finished after a newer one (its information is superseded)."""
    if tracker.last_update_us is not None and capture_us < tracker.last_update_us:
        return None
    tracker.update(capture_us, positions)
    return tracker.report(g.BELT_HALF_WIDTH)


class CoDesign:
    """The co-design policy for a set of loops, and which QoS each camera was last told.

    ``cell`` is the scenario's CellConfig (a bare belt speed in m/s is accepted too: the cell
    is then known by its speed only); ``loops`` is how many loops share the radio cell and
    ``fps`` the cameras' frame rate. Per loop it remembers when the newest part it has seen
    landed on the belt, so that a policy knows when the next one is due."""

    def __init__(self, cfg: PolicyConfig, cell: CellConfig | float, loops: int = 1,
                 fps: float = 30.0) -> None:
        self.policy = make_policy(cfg)
        self.controls = cfg.controls  # an ablation may apply only part of the policy's QoS
        self.object_period_s: float | None = None
        if isinstance(cell, CellConfig):
            self.belt_speed_m_s, self.object_period_s = cell.belt_speed_m_s, cell.object_period_s
        else:
            self.belt_speed_m_s = float(cell)
        self.loops = loops
        self.fps = fps
        self.sent: dict[int, tuple[Qos, int]] = {}
        self.last_spawn_us: dict[int, int] = {}

    @classmethod
    def for_scenario(cls, sc: Scenario) -> CoDesign:
        """The co-design of a scenario's loops: its policy, cell, loop count and camera rate."""
        return cls(sc.policy, sc.cell, sc.loops, sc.camera.fps)

    def state(self, loop: int, now_us: int, tracker: Tracker, last_frame_us: int | None) -> LoopState:
        """What the Edge knows of ``loop`` now."""
        tracks = tracker.report(g.BELT_HALF_WIDTH)
        for tr in tracks:
            if tr["p"][2] <= g.BELT_TOP_Z + LIFTED_M:  # a part riding the belt: when it landed
                spawn = spawn_time_us(tr, self.belt_speed_m_s)
                last = self.last_spawn_us.get(loop)
                if last is None or spawn > last:
                    self.last_spawn_us[loop] = spawn
        return LoopState(now_us, tracks, last_frame_us, self.belt_speed_m_s, self.object_period_s,
                         self.loops, self.fps, self.last_spawn_us.get(loop))

    def decide(self, loop: int, now_us: int, tracker: Tracker, last_frame_us: int | None) -> Qos:
        """The policy's QoS for ``loop`` from what the Edge knows of it now."""
        qos = self.policy.decide(self.state(loop, now_us, tracker, last_frame_us))
        if self.controls == "pdp":
            qos = Qos(qos.pdp, None)
        elif self.controls == "budget":
            qos = Qos(1.0, qos.pdb_us)
        metrics.LOOP_PDP.labels(str(loop)).set(qos.pdp)
        return qos

    def signal(self, loop: int, qos: Qos, now_us: int) -> dict[str, Any] | None:
        """The QoS message for the camera of ``loop`` if it must be sent now (changed, or not sent
        for QOS_REFRESH_US), else None."""
        last = self.sent.get(loop)
        if last is not None and last[0] == qos and now_us - last[1] < QOS_REFRESH_US:
            return None
        self.sent[loop] = (qos, now_us)
        return {"type": "qos", "loop": loop, "pdp": qos.pdp, "pdb_us": qos.pdb_us}


def lower_layer_qos(loop: int, qos: Qos, now_us: int, cfg: PolicyConfig, slot_us: int) -> tuple[int, dict[str, Any]]:
    """When, and with what, the gNB learns a loop's QoS with ``policy.signalling: lower``: a
    MAC-level control message (the camera flow's budget) that reaches the scheduler
    ``control_latency_us`` after the decision, at a slot boundary; sent alongside the camera's
    QoS message."""
    ue = f"camera-{loop}"
    return (slot_after(now_us + cfg.control_latency_us, slot_us),
            {"flow": f"{ue}/video", "ue": ue, "pdb_us": qos.pdb_us, "pdp": qos.pdp})


def downlink_packet(ue: str, what: str, size: int, dst: str, app: dict[str, Any]) -> dict[str, Any]:
    """The body of a downlink packet to ``ue`` (flow ``ue/what``), delivered to ``dst``."""
    return {"ue": ue, "dir": "dl", "flow": f"{ue}/{what}", "size": size, "dst": dst, "pdb_us": None,
            "app": app}
