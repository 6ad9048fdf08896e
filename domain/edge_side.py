"""The Edge side of a control loop, run alike by the Edge federate (detailed loops) and the
abstract loops federate: folding a frame's estimates into the loop's tracker, the co-design step
(loop state -> policy -> QoS, signalled to the camera when it changed, and with lower-layer
signalling to the gNB too) and the downlink packet that carries a pose or a QoS through netsim.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from domain import work_cell as g
from domain.codec import slot_after
from domain.congestion import LoadControl, PeriodCounts, UplinkMonitor
from domain.edges import EdgePlan, edge_name
from domain.frame_model import load_frame_model
from domain.loop_state import LoopState
from domain.policy import LearnedPolicy, Qos, check_family, make_policy, step_up
from domain.policy_features import LIFTED_M, spawn_time_us
from domain.safety_floor import FloorLimits, safety_floor
from domain.tracker import Tracker
from fabric import metrics
from scenario.schema import EdgeConfig, PolicyConfig, RobotConfig, Scenario, WorkCellConfig
from wire.bodies import EdgeCounts, Packet, Payload, QosCtl, QosSignal, Track

# An unchanged QoS is signalled again this often: the downlink can lose it.
QOS_REFRESH_US = 1_000_000


def update_tracks(tracker: Tracker, capture_us: int, positions: list[np.ndarray]) -> list[Track] | None:
    """Fold the part positions ``positions`` (m, cell frame) of the frame captured at
    ``capture_us`` (us) into ``tracker``; the tracks to send the robot, or None when an older
    frame finished after a newer one (its information is superseded)."""
    if tracker.last_update_us is not None and capture_us < tracker.last_update_us:
        return None
    tracker.update(capture_us, positions)
    return tracker.report(g.BELT_HALF_WIDTH)


class CoDesign:
    """The co-design policy for a set of loops, and which QoS each camera was last told.

    ``cfg`` is the scenario's policy section, ``cell`` its WorkCellConfig (a bare belt speed in
    m/s is accepted too: the cell is then known by its speed only); ``loops`` is how many loops
    share the radio cell and ``fps`` the cameras' frame rate (frame/s); ``limits`` what the
    safety floor protects (None: the scenario's defaults). Per loop it remembers when the newest
    part it has seen landed on the belt, so that a policy knows when the next one is due, and it
    watches the uplink's frames (``monitor``) for the floor's margins and the load control."""

    def __init__(self, cfg: PolicyConfig, cell: WorkCellConfig | float, loops: int = 1,
                 fps: float = 30.0, limits: FloorLimits | None = None, name: str = "edge") -> None:
        self.name = name  # the Edge's, as its metrics are labelled
        self.policy = make_policy(cfg)
        self.controls = cfg.controls  # an ablation may apply only part of the policy's QoS
        self.object_period_s: float | None = None
        self.object_jitter_s = 0.0
        if isinstance(cell, WorkCellConfig):
            self.belt_speed_m_s, self.object_period_s = cell.belt_speed_m_s, cell.object_period_s
            self.object_jitter_s = cell.object_jitter_s
            if isinstance(self.policy, LearnedPolicy):
                check_family(self.policy.info, self.policy.path, cell)
        else:
            self.belt_speed_m_s = float(cell)
        self.loops = loops
        self.fps = fps
        self.sent: dict[int, tuple[Qos, int]] = {}
        self.last_spawn_us: dict[int, int] = {}
        self.monitor = UplinkMonitor()
        # An Edge whose loops two federates serve (``Edges.share``) folds, each period, the
        # counts each of them closed a little before it (``close``, ``peer``).
        self.shared = False
        self._counts: list[PeriodCounts] = []
        codesign = cfg.name != "none"  # PDP 1 is the reference: never floored nor capped
        self.limits = (limits or default_limits(cfg)) if codesign and cfg.floor else None
        self.load = load_control(cfg) if codesign else None
        self._period_us: int | None = None
        # What the run's summary reports of this Edge: per loop the sum and count of the PDPs
        # decided, and the sums of its levels over the policy periods.
        self._pdp: dict[int, list[float]] = {}
        self._periods = 0
        self._levels = [0.0, 0.0, 0.0, 0.0]  # fill, cap, queueing delay (s), share of loops served

    @classmethod
    def for_scenario(cls, sc: Scenario) -> CoDesign:
        """The co-design of the loops of scenario ``sc``: its policy, cell, loop count and camera
        rate."""
        return cls(sc.policy, sc.work_cell, sc.loops, sc.camera.fps, default_limits(sc.policy, sc))

    def state(self, loop: int, now_us: int, tracker: Tracker, last_frame_us: int | None) -> LoopState:
        """What the Edge knows of ``loop`` at ``now_us`` (us): its ``tracker``'s tracks and when
        its last frame arrived (``last_frame_us``, us; None: none yet)."""
        tracks = tracker.report(g.BELT_HALF_WIDTH)
        for tr in tracks:
            if tr["p"][2] <= g.BELT_TOP_Z + LIFTED_M:  # a part riding the belt: when it landed
                spawn = spawn_time_us(tr, self.belt_speed_m_s)
                last = self.last_spawn_us.get(loop)
                if last is None or spawn > last:
                    self.last_spawn_us[loop] = spawn
        return LoopState(now_us, tracks, last_frame_us, self.belt_speed_m_s, self.object_period_s,
                         self.loops, self.fps, self.last_spawn_us.get(loop), self.object_jitter_s,
                         self.monitor.estimate(loop))

    def decide(self, loop: int, now_us: int, tracker: Tracker, last_frame_us: int | None) -> Qos:
        """The policy's QoS for ``loop`` from what the Edge knows of it at ``now_us`` (us; see
        ``state`` for ``tracker`` and ``last_frame_us``), bounded by the safety floor and the
        load control (the first decision of a policy period folds the uplink's last period into
        both first)."""
        return self.decide_many(now_us, [(loop, tracker, last_frame_us)])[0]

    def decide_many(self, now_us: int, loops: list[tuple[int, Tracker, int | None]]) -> list[Qos]:
        """``decide`` for each (loop, tracker, last frame time) of ``loops`` at ``now_us`` (us),
        the policy asked once for all of them."""
        if now_us != self._period_us:
            self._period_us = now_us
            self.period(now_us)
        states = [self.state(loop, now_us, tracker, last) for loop, tracker, last in loops]
        out = []
        for (loop, _, _), state, asked in zip(loops, states, self.policy.decide_many(states), strict=True):
            qos = self.apply(loop, state, asked)
            metrics.LOOP_PDP.labels(str(loop)).set(qos.pdp)
            acc = self._pdp.setdefault(loop, [0.0, 0])
            acc[0] += qos.pdp
            acc[1] += 1
            out.append(qos)
        return out

    def period(self, now_us: int) -> None:
        """A new policy period, starting at ``now_us`` (us): the uplink's last period folded into
        the cell's figures and the load control (a shared Edge's: the counts closed for it)."""
        if self.shared:
            queueing_s, loss = self.monitor.fold(self._counts)
            self._counts = []
        else:
            queueing_s, loss = self.monitor.period(now_us)
        if self.load is not None:
            self.load.update(now_us, queueing_s, loss, self.monitor.stalled)
            metrics.PDP_FILL.labels(self.name).set(self.load.fill)
            metrics.PDP_CAP.labels(self.name).set(self.load.cap)
            metrics.LOOPS_SERVED.labels(self.name).set(self.load.served)
        metrics.QUEUEING_DELAY.labels(self.name).set(queueing_s)
        self._periods += 1
        for i, level in enumerate(self.levels()[:3]):
            self._levels[i] += level
        self._levels[3] += self.served

    def close(self, now_us: int) -> PeriodCounts:
        """A shared Edge's counts of this federate's frames since the last close, at ``now_us``
        (us, shortly before the period ends: ``Edges.close_ahead_us``), kept for the period and
        sent to the other federate."""
        counts = self.monitor.close(now_us)
        self._counts.append(counts)
        return counts

    def peer(self, counts: PeriodCounts) -> None:
        """The other federate's counts of a shared Edge's frames, closed when this one's were."""
        self._counts.append(counts)

    def levels(self) -> tuple[float, float, float, float]:
        """The load control's fill and cap (PDP; 1 and 1 without load control), and the cell's
        smoothed queueing delay (s) and frame loss (share) as this Edge sees them now."""
        fill, cap = (self.load.fill, self.load.cap) if self.load is not None else (1.0, 1.0)
        return fill, cap, self.monitor.cell_queueing_s, self.monitor.cell_loss

    @property
    def served(self) -> float:
        """The share of the loops the load control serves now (1 without load control)."""
        return self.load.served if self.load is not None else 1.0

    def mean_pdp(self, loops: Iterable[int] | None = None) -> float | None:
        """The mean of the PDPs decided for ``loops`` (None: every loop) so far; None: none."""
        chosen = [self._pdp[i] for i in (self._pdp if loops is None else loops) if i in self._pdp]
        n = sum(int(a[1]) for a in chosen)
        return sum(a[0] for a in chosen) / n if n else None

    def summary(self) -> dict[str, Any]:
        """What this Edge saw and decided over the run: the mean PDP of its loops, the means of
        its levels over the policy periods (fill, cap, queueing delay in s, share of the loops
        served) and their last values."""
        fill, cap, queueing_s, loss = self.levels()
        n = self._periods
        return {"loops": self.loops, "mean_pdp": self.mean_pdp(),
                "mean_fill": self._levels[0] / n if n else None,
                "mean_cap": self._levels[1] / n if n else None,
                "mean_queueing_delay_s": self._levels[2] / n if n else None,
                "mean_served": self._levels[3] / n if n else None,
                "fill": fill, "cap": cap, "queueing_delay_s": queueing_s, "frame_loss": loss,
                "served": self.served}

    def apply(self, loop: int, state: LoopState, qos: Qos) -> Qos:
        """``qos``, the policy's decision for ``loop`` in ``state``, bounded by the safety floor
        and the load control, reduced to the ablation's ``controls``."""
        pdp = bounded_pdp(loop, state, qos.pdp, self.limits, self.load)
        if self.controls == "pdp":
            return Qos(pdp, None)
        if self.controls == "budget":
            return Qos(1.0, qos.pdb_us)
        return Qos(pdp, qos.pdb_us)

    def signal(self, loop: int, qos: Qos, now_us: int) -> QosSignal | None:
        """The message telling the camera of ``loop`` its QoS ``qos`` if it must be sent at
        ``now_us`` (us: changed, or not sent for QOS_REFRESH_US), else None."""
        last = self.sent.get(loop)
        if last is not None and last[0] == qos and now_us - last[1] < QOS_REFRESH_US:
            return None
        self.sent[loop] = (qos, now_us)
        return QosSignal(loop=loop, pdp=qos.pdp, pdb_us=qos.pdb_us)


class Edges:
    """The Edge sides of a federate's ``loops`` under ``plan`` (scenario ``sc``): a ``CoDesign``
    per Edge, each with its own uplink monitor, load control and policy state, over the loops it
    serves (at a per-gNB Edge the loops whose camera its gNB serves, at the central Edge all);
    its loop count is that Edge's over the whole scenario. ``plan.backhaul_us`` is the delay its
    federate adds to every uplink frame and downlink packet (0 at a per-gNB Edge)."""

    def __init__(self, sc: Scenario, plan: EdgePlan, loops: Iterable[int], miss_rate: float | None = None) -> None:
        self.plan = plan
        self.backhaul_us = plan.backhaul_us
        every = plan.groups()
        limits = default_limits(sc.policy, sc, miss_rate)
        self.by_edge: dict[str, CoDesign] = {}
        self._of_loop: dict[int, CoDesign] = {}
        for name, members in plan.groups(loops).items():
            codesign = CoDesign(sc.policy, sc.work_cell, len(every[name]), sc.camera.fps, limits, name)
            self.by_edge[name] = codesign
            self._of_loop.update(dict.fromkeys(members, codesign))
        self.window_us = sc.window_us
        self.shared: list[str] = []  # the Edges whose loops another federate serves too (``share``)
        self._codesign = sc.policy.name != "none"

    def __getitem__(self, loop: int) -> CoDesign:
        """The co-design of the Edge serving ``loop``."""
        return self._of_loop[loop]

    def share(self, others: Iterable[int]) -> list[str]:
        """Mark the Edges that serve loops among ``others`` too (another federate's: the Edge
        federate serves the detailed loops, the abstract loops' federate the rest) as shared, with
        a co-design policy; their names. A shared Edge is one Edge: each period both federates
        fold the same counts of its frames (``close_ahead_us`` before the period ends each closes
        its own and sends them to the other), so its cell figures and its load control are the
        same in both, and a detailed loop is steered as an abstract one beside it."""
        if self._codesign:
            self.shared = [name for name in self.plan.groups(others) if name in self.by_edge]
            for name in self.shared:
                self.by_edge[name].shared = True
        return self.shared

    @property
    def close_ahead_us(self) -> int:
        """How long before a policy period ends a shared Edge's counts are closed: sent a window
        after the close (no window is longer), they arrive a window before the period ends."""
        return 2 * self.window_us

    def close(self, now_us: int) -> tuple[int, list[EdgeCounts]]:
        """Close every shared Edge's counts at ``now_us`` (us): when they are due at the other
        federate (a window later) and the bodies that carry them."""
        bodies = []
        for name in self.shared:
            c = self.by_edge[name].close(now_us)
            bodies.append(EdgeCounts(edge=name, queued_s=c.queued_s, frames=c.frames, lost=c.lost,
                                     stalled=c.stalled))
        return now_us + self.window_us, bodies

    def peer(self, counts: EdgeCounts) -> None:
        """The other federate's counts of a shared Edge (``close``)."""
        self.by_edge[counts.edge].peer(PeriodCounts(counts.queued_s, counts.frames, counts.lost, counts.stalled))

    def summary(self) -> dict[str, Any]:
        """Per Edge what it saw and decided (``CoDesign.summary``, with its loops and gNBs), and
        per gNB the mean PDP decided for the loops whose camera it serves."""
        gnb_of = self.plan.gnb_of_loop
        edges = {}
        for name, codesign in self.by_edge.items():
            mine = sorted(i for i, c in self._of_loop.items() if c is codesign)
            edges[name] = {**codesign.summary(), "loops_here": mine,
                           "gnbs": sorted({gnb_of[i] for i in mine})}
        gnbs: dict[str, dict[str, Any]] = {}
        for gnb in sorted({gnb_of[i] for i in self._of_loop}):
            mine = [i for i in sorted(self._of_loop) if gnb_of[i] == gnb]
            known = [p for i in mine if (p := self._of_loop[i].mean_pdp([i])) is not None]
            gnbs[edge_name(gnb)] = {"loops": mine,
                                    "mean_pdp": sum(known) / len(known) if known else None}
        return {"placement": self.plan.placement, "backhaul_ms": self.backhaul_us / 1000,
                "edges": edges, "gnbs": gnbs}


def bounded_pdp(loop: int, state: LoopState, pdp: float, limits: FloorLimits | None,
                load: LoadControl | None) -> float:
    """``pdp`` of ``loop`` in ``state`` raised to the safety floor (``limits``; None: no floor)
    and to the fill of the load control ``load`` (PDP 1 while the cell has headroom), then capped
    by its cap (None: neither); 0 for a loop the load control sheds. Past capacity the cap wins:
    a floor raised by stale estimates must not feed the congestion that made them stale."""
    if load is not None and not load.serves(loop):
        return 0.0
    if limits is not None:
        pdp = max(pdp, safety_floor(state, limits))
    if load is not None:
        pdp = min(max(pdp, step_up(load.fill)), step_up(load.cap))
    return pdp


def load_control(cfg: PolicyConfig) -> LoadControl | None:
    """The load control ``cfg`` asks for: its headroom fill and its guard's cap (None: neither)."""
    if not cfg.headroom and not cfg.guard:
        return None
    return LoadControl(cfg.headroom_delay_ms / 1000 if cfg.headroom else None,
                       cfg.guard_delay_ms / 1000 if cfg.guard else None, cfg.guard_min_pdp,
                       cfg.guard_start_pdp)


def default_limits(cfg: PolicyConfig, sc: Scenario | None = None, miss_rate: float | None = None) -> FloorLimits:
    """What the safety floor protects in scenario ``sc`` (None: the schema's defaults): the
    robot's estimate age limit, the estimator's measured ``miss_rate`` (None: the shipped frame
    model's, measured for the default camera; ``frame_model.miss_rate_for`` gives a camera's),
    ``cfg.floor_risk`` and the policy period."""
    robot, edge = (sc.robot, sc.edge) if sc is not None else (RobotConfig(), EdgeConfig())
    miss = load_frame_model().miss_rate if miss_rate is None else miss_rate
    return FloorLimits(robot.max_estimate_age_ms / 1000, miss, cfg.floor_risk, edge.policy_period_ms / 1000)


def lower_layer_qos(loop: int, qos: Qos, now_us: int, cfg: PolicyConfig, slot_us: int) -> tuple[int, QosCtl]:
    """When (us), and with what, the gNB learns the QoS ``qos`` of ``loop`` decided at
    ``now_us`` (us) with ``policy.signalling: lower`` (``cfg``): a MAC-level control message (the
    camera flow's budget) that reaches the scheduler ``control_latency_us`` after the decision,
    at a boundary of the ``slot_us`` (us) slots; sent alongside the camera's QoS message."""
    ue = f"camera-{loop}"
    return (slot_after(now_us + cfg.control_latency_us, slot_us),
            QosCtl(flow=f"{ue}/video", ue=ue, pdb_us=qos.pdb_us, pdp=qos.pdp))


def downlink_packet(ue: str, what: str, size: int, dst: str, app: Payload) -> Packet:
    """A downlink packet of ``size`` bytes to ``ue`` (flow ``ue``/``what``) carrying ``app``,
    delivered to ``dst``."""
    return Packet(ue=ue, direction="dl", flow=f"{ue}/{what}", size=size, dst=dst, pdb_us=None, app=app)
