"""The Edge side of a control loop, run alike by the Edge federate (detailed loops) and the
abstract loops federate: folding a frame's estimates into the loop's tracker, the co-design step
(loop state -> policy -> QoS, signalled to the camera when it changed) and the downlink packet
that carries a pose or a QoS through netsim.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from domain import cell_geometry as g
from domain.policy import LoopState, Qos, make_policy
from domain.tracker import Tracker
from fabric import metrics
from scenario.schema import PolicyConfig

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
    """The co-design policy for a set of loops, and which QoS each camera was last told."""

    def __init__(self, cfg: PolicyConfig, belt_speed_m_s: float) -> None:
        self.policy = make_policy(cfg)
        self.belt_speed_m_s = belt_speed_m_s
        self.sent: dict[int, tuple[Qos, int]] = {}

    def decide(self, loop: int, now_us: int, tracker: Tracker, last_frame_us: int | None) -> Qos:
        """The policy's QoS for ``loop`` from what the Edge knows of it now."""
        state = LoopState(now_us, tracker.report(g.BELT_HALF_WIDTH), last_frame_us, self.belt_speed_m_s)
        qos = self.policy.decide(state)
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


def downlink_packet(ue: str, what: str, size: int, dst: str, app: dict[str, Any]) -> dict[str, Any]:
    """The body of a downlink packet to ``ue`` (flow ``ue/what``), delivered to ``dst``."""
    return {"ue": ue, "dir": "dl", "flow": f"{ue}/{what}", "size": size, "dst": dst, "pdb_us": None,
            "app": app}
