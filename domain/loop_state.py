"""What the Edge knows of a loop when its co-design policy runs: the input of every policy, of the
safety floor and of the learned policy's features."""

from __future__ import annotations

from dataclasses import dataclass

from domain.congestion import IDLE_LINK, LinkEstimate
from wire.bodies import Track


@dataclass(frozen=True)
class LoopState:
    """What the Edge knows of a loop when the policy runs."""

    now_us: int
    tracks: list[Track]  # tracker report
    last_frame_us: int | None  # capture time of the last frame that arrived
    belt_speed_m_s: float
    object_period_s: float | None = None  # the cell's nominal time between parts, s
    loops: int = 1  # loops sharing the radio cell (its load at PDP 1)
    fps: float = 30.0  # camera frame rate
    last_spawn_us: int | None = None  # when the newest part seen landed on the belt
    object_jitter_s: float = 0.0  # the cell's spawn jitter (+-), s
    link: LinkEstimate = IDLE_LINK  # the uplink's delay and loss as the Edge sees them
