"""One co-design control loop as a Gymnasium environment (``cosim5g/PickLoop-v0``).

A work cell of the family (work_cells.py) runs in MuJoCo without rendering, its uplink is the
measured network model (network.py), one step is one policy period. Observation, action, load
and reward: docs/policy.md, "The environment".
"""

from __future__ import annotations

import heapq
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from domain.arm import SERVO_LAG_S
from domain.codec import slot_after
from domain.controller import PickController
from domain.edge_side import CoDesign, default_limits, update_tracks
from domain.frame_keep import FrameKeep
from domain.frame_model import load_frame_model
from domain.loop_state import LoopState
from domain.policy import Qos
from domain.policy_features import BUDGET_LEVELS_MS, N_FEATURES, OBS_LIMIT, PDP_LEVELS, features
from domain.tracker import Tracker
from domain.world import World, spawn_plan
from fabric.compute import DEFAULT_JOB_MODELS, draw_model_us
from fabric.seeding import rng
from scenario.schema import PolicyConfig, Scenario, WorkCellConfig
from training.policy.network import NetworkModel
from training.policy.work_cells import DEFAULT_FAMILY, WorkCellFamily

ENV_ID = "cosim5g/PickLoop-v0"
DEFAULT_LAMBDA = 10.0
EPISODE_S = 30.0
LOAD_TAU_S = 5.0  # averaging time of the mean-field PDP
SLOT_US = 1000  # NR slot at 15 kHz: packets enter the UE buffer at slot boundaries
HEADROOM = 0.8  # share of the cell's capacity under which camera traffic costs nothing


def congestion_price(utilisation: float) -> float:
    """The price of a second of camera traffic at the cell's offered load ``utilisation`` (a share
    of its capacity): nothing with headroom, then rising to 1 at capacity and beyond it."""
    return max(0.0, (utilisation - HEADROOM) / (1.0 - HEADROOM))


def action_qos(action: Any) -> Qos:
    """The QoS of an action (PDP level index, budget level index)."""
    a = np.asarray(action).reshape(-1)
    return Qos(PDP_LEVELS[int(a[0])], int(BUDGET_LEVELS_MS[int(a[1])] * 1000))


class PickLoopEnv(gym.Env):
    """A co-design loop of one cell; see the module docstring."""

    metadata = {"render_modes": []}

    def __init__(self, lam: float = DEFAULT_LAMBDA, episode_s: float = EPISODE_S,
                 family: WorkCellFamily = DEFAULT_FAMILY, cell: WorkCellConfig | None = None,
                 loops: int | None = None, network: NetworkModel | None = None,
                 floor: bool = True, load_control: bool = True) -> None:
        super().__init__()
        self.floor = floor
        self.use_load_control = load_control
        self.lam = float(lam)
        self.episode_s = float(episode_s)
        self.family = family
        self.fixed_cell = cell
        self.fixed_loops = loops
        self.net = network or NetworkModel()
        self.frame_model = load_frame_model()
        self.observation_space = spaces.Box(-OBS_LIMIT, OBS_LIMIT, (N_FEATURES,), np.float32)
        self.action_space = spaces.MultiDiscrete([len(PDP_LEVELS), len(BUDGET_LEVELS_MS)])
        self.sc: Scenario | None = None

    # ---- episode --------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        opts = options or {}
        drawn_cell, drawn_loops = self.family.draw(self.np_random)
        cell = opts.get("work_cell") or self.fixed_cell or drawn_cell
        loops = int(opts.get("loops") or self.fixed_loops or drawn_loops)
        ep_seed = int(self.np_random.integers(2**31 - 1))
        self.sc = sc = Scenario(seed=ep_seed, loops=1, detailed_loops=1, work_cell=cell,
                                duration_s=self.episode_s + 1.0)
        self.loops = loops
        self.world = World(sc)
        self.step_us = sc.physics_timestep_us
        self.period_us = sc.edge.policy_period_ms * 1000
        self.frame_us = sc.frame_period_us
        self.ctl = PickController(sc.robot, cell.object_size_m, SERVO_LAG_S)
        self.tracker = Tracker((cell.belt_speed_m_s, 0.0, 0.0))
        # The floor and the load control bound every policy's QoS here as at the Edge (the
        # policy named here is not consulted: the action, or a given QoS, is what is bounded).
        bounds = PolicyConfig(name="fixed", floor=self.floor, headroom=self.use_load_control,
                              guard=self.use_load_control)
        self.codesign = CoDesign(bounds, cell, loops, sc.camera.fps, default_limits(bounds, sc))
        self.rng = {name: rng(ep_seed, f"policy-env/{name}")
                    for name in ("keep", "net", "error", "compute", "phase")}
        self.keeper = FrameKeep(sc.camera.frame_keep, self.rng["keep"])  # as the scenario's cameras
        self.last_frame_us: int | None = None
        self.pdp_bar = float(self.rng["phase"].uniform(0.25, 1.0))  # the other loops' recent PDP
        self.qos_camera = Qos(1.0, None)  # what the camera applies until told otherwise
        self.qos = self.qos_camera
        self.t_us = 0
        self.end_us = int(self.episode_s * 1e6)
        self.queue: list[tuple[int, int, int, str, Any]] = []
        self.seq = 0
        for at, part in spawn_plan(sc, rng(ep_seed, "physics/spawn-c0"), self.step_us):
            self._push(at, 0, "spawn", part)
        phase = int(self.rng["phase"].integers(0, self.frame_us // self.step_us)) * self.step_us
        self._push(phase, 1, "frame", None)
        self._push(0, 3, "tick", None)
        self.stats = {"steps": 0, "placed": 0, "missed": 0, "dropped": 0, "frames": 0, "frames_kept": 0,
                      "frames_delivered": 0, "cost": 0.0, "pdp_sum": 0.0, "budget_ms_sum": 0.0,
                      "load_sum": 0.0}
        return self._obs(), {"work_cell": cell.model_dump(), "loops": loops, "seed": ep_seed}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        return self.step_qos(action_qos(action))

    def step_qos(self, qos: Qos) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply ``qos`` for one policy period (any policy's QoS, not only the action set's)."""
        self.codesign.period(self.t_us)
        qos = self.codesign.apply(0, self.loop_state(), qos)  # loop 0: never shed
        budget_ms = None if qos.pdb_us is None else qos.pdb_us / 1000
        load = self.load_mbps()
        self.qos = qos
        # The QoS message crosses the downlink before the camera applies it.
        self._push(slot_after(self.t_us, SLOT_US) + self.net.downlink(load, self.rng["net"]), 2, "qos", qos)
        t_next = self.t_us + self.period_us
        self._run_until(t_next)
        dt_s = self.period_us / 1e6
        price = congestion_price(load / self.net.capacity_mbps)
        cost = qos.pdp * price * (1.0 - self.net.byte_discard(load, budget_ms)) * dt_s
        self.pdp_bar += (qos.pdp * self.served() - self.pdp_bar) * min(1.0, dt_s / LOAD_TAU_S)
        ended = self.world.take_ended(self.world.t_us)
        placed = sum(1 for t in ended if t["outcome"] == "placed")
        missed = sum(1 for t in ended if t["outcome"] == "missed")
        dropped = sum(1 for t in ended if t["outcome"] == "dropped")
        reward = -cost + self.lam * (placed - missed - dropped)
        st = self.stats
        st["steps"] += 1
        st["placed"] += placed
        st["missed"] += missed
        st["dropped"] += dropped
        st["cost"] += cost
        st["pdp_sum"] += qos.pdp
        st["budget_ms_sum"] += budget_ms if budget_ms is not None else 0.0
        st["load_sum"] += load
        truncated = self.t_us >= self.end_us
        info: dict[str, Any] = {"pdp": qos.pdp, "budget_ms": budget_ms, "load_mbps": load, "cost": cost,
                                "placed": placed, "missed": missed, "dropped": dropped}
        if truncated:
            info["summary"] = self.summary()
        return self._obs(), float(reward), False, truncated, info

    def summary(self) -> dict[str, Any]:
        """The episode so far: tasks, mean PDP, injected camera traffic, cost."""
        st = self.stats
        n = max(1, st["steps"])
        ended = st["placed"] + st["missed"] + st["dropped"]
        return {"tasks": ended, "placed": st["placed"], "missed": st["missed"], "dropped": st["dropped"],
                "success": st["placed"] / ended if ended else 1.0, "mean_pdp": st["pdp_sum"] / n,
                "injected_mbps": st["pdp_sum"] / n * self.net.loop_rate_mbps,
                "mean_budget_ms": st["budget_ms_sum"] / n, "mean_load_mbps": st["load_sum"] / n,
                "cost": st["cost"], "frames": st["frames"], "frames_kept": st["frames_kept"],
                "frames_delivered": st["frames_delivered"], "holds": self.ctl.holds}

    def served(self) -> float:
        """The share of the cell's loops the load control serves (the others send nothing)."""
        return self.codesign.load.served if self.codesign.load is not None else 1.0

    def load_mbps(self) -> float:
        """Offered uplink load of the radio cell (mean field), Mbit/s."""
        return self.loops * self.net.loop_rate_mbps * self.pdp_bar

    def loop_state(self) -> LoopState:
        """What the Edge knows of the loop now (the policy's input)."""
        return self.codesign.state(0, self.t_us, self.tracker, self.last_frame_us)

    def _obs(self) -> np.ndarray:
        return features(self.loop_state())

    # ---- the loop's events ---------------------------------------------------------------------
    def _push(self, t: int, order: int, kind: str, payload: Any) -> None:
        heapq.heappush(self.queue, (t, order, self.seq, kind, payload))
        self.seq += 1

    def _job_us(self, kind: str) -> int:
        """A job's duration on its node: the platform's modelled distribution (``model`` timing)."""
        return draw_model_us(DEFAULT_JOB_MODELS[kind], self.rng["compute"])

    def _run_until(self, t_end: int) -> None:
        assert self.sc is not None
        sc, world, ctl = self.sc, self.world, self.ctl
        while self.queue and self.queue[0][0] < t_end:
            t, _, _, kind, payload = heapq.heappop(self.queue)
            world.advance_to(t)
            if kind == "spawn":
                world.spawn(0, **payload)
            elif kind == "frame":
                self._capture(t)
                self._push(t + self.frame_us, 1, "frame", None)
            elif kind == "edge":
                capture_us, positions = payload
                # Counted for the load as its estimate is ready, as at the federation's Edge.
                self.codesign.monitor.frame(0, capture_us, t)
                tracks = update_tracks(self.tracker, capture_us, positions)
                if tracks is not None:
                    self.last_frame_us = capture_us
                    dl = self.net.downlink(self.load_mbps(), self.rng["net"])
                    self._push(slot_after(t, SLOT_US) + dl, 2, "pose", tracks)
            elif kind == "pose":
                ctl.on_estimate(payload)
            elif kind == "qos":
                self.qos_camera = payload
            elif kind == "tick":
                js = world.joint_state(0)
                self._push(t + sc.robot.state_latency_us, 2, "state", (js["q"], js["gripped"]))
                q, suction = ctl.step(t)
                ready = t + self._job_us("control")
                self._push(ready + sc.robot.actuation_latency_us, 2, "command", ([float(v) for v in q], suction))
                self._push(t + sc.robot.control_period_us, 3, "tick", None)
            elif kind == "state":
                ctl.on_state(*payload)
            elif kind == "command":
                world.command(0, *payload)
        world.advance_to(t_end)
        self.t_us = t_end

    def _capture(self, t: int) -> None:
        """A camera frame at ``t``: kept with the camera's PDP, then compressed, sent and
        estimated, or dropped."""
        self.stats["frames"] += 1
        qos = self.qos_camera
        if not self.keeper.keep(qos.pdp):
            return
        self.stats["frames_kept"] += 1
        enter = slot_after(t + self._job_us("compress"), SLOT_US)
        budget_ms = None if qos.pdb_us is None else qos.pdb_us / 1000
        latency = self.net.frame(self.load_mbps(), budget_ms, self.rng["net"])
        if latency is None:
            self.codesign.monitor.lost(0)
            return
        self.stats["frames_delivered"] += 1
        positions = self.frame_model.estimate(self.world.objects(0), self.rng["error"])
        self._push(enter + latency + self._job_us("pose"), 2, "edge", (t, positions))


def register() -> None:
    """Register ``cosim5g/PickLoop-v0`` with Gymnasium (once)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="training.policy.env:PickLoopEnv",
                     max_episode_steps=None, disable_env_checker=False)


register()
