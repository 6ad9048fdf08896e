"""The abstract loops: the N-K loops not rendered, in one process (docs/architecture.md sec. 6).

Their frames cross netsim like any loop's; their Edge side takes ground truth plus the real
estimator's measured error, then the same tracker, policy and robot controller run; compute times
are the profiles' ``model`` draws.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from domain.codec import slot_after, split_packets
from domain.controller import PickController
from domain.edge_side import CoDesign, Edges, downlink_packet, lower_layer_qos, update_tracks
from domain.edges import load_plan
from domain.frame_keep import FrameKeep
from domain.frame_model import RUN_FILE, camera_settings, model_for
from domain.hall import SERVO_LAG_S
from domain.kinematics import ArmKinematics
from domain.partitions import load_route
from domain.policy import Qos
from domain.tracker import Tracker
from fabric.compute import ComputeNode
from fabric.federate import NEVER_US, Federate, Handlers
from fabric.job_queue import JobQueue
from fabric.messages import Message
from fabric.tables import write_table
from wire.bodies import (
    Aframe,
    Command,
    Commands,
    EdgeCounts,
    JointStates,
    Packets,
    Part,
    Payload,
    Pose,
    QosSignal,
    Truth,
)

# A frame not in this long after its capture is lost for good: no delay budget lets a packet
# wait that long, and the tracker has long dropped what it would show.
LOST_FRAME_US = 5_000_000


@dataclass
class AbstractLoop:
    index: int
    ctl: PickController
    tracker: Tracker
    keeper: FrameKeep
    size_rng: np.random.Generator
    error_rng: np.random.Generator
    camera_cpu: ComputeNode
    poses: JobQueue  # the frames waiting for pose estimation on the Edge's node (poses.node)
    robot_cpu: ComputeNode
    pdp: float = 1.0
    pdb_us: int | None = None
    frame_id: int = 0  # frames sent (kept): the sequence the Edge side counts lost frames by
    truth: dict[int, tuple[int, list[Part]]] = field(default_factory=dict)  # frame -> (capture, objs)
    arrived: dict[int, int] = field(default_factory=dict)  # frame -> packets arrived
    last_frame_us: int | None = None
    frames: int = 0
    frames_kept: int = 0
    frames_superseded: int = 0  # complete, replaced by a newer one before the Edge estimated them
    bytes_sent: int = 0


class LoopsFederate(Federate):
    role = "loops"

    def setup(self) -> None:
        sc = self.scenario
        # The model measured for this camera, put into the run directory by the coordinator.
        self.frame_model = model_for(camera_settings(sc.camera), self.results_dir / RUN_FILE)
        # The Edge sides of these loops: one per gNB, or the central one (domain/edges.py).
        self.edges = Edges(sc, load_plan(sc, self.results_dir), range(sc.detailed_loops, sc.loops),
                           self.frame_model.miss_rate)
        # An Edge serving detailed loops too shares its counts with the Edge federate.
        self.edges.share(range(sc.detailed_loops))
        self.next_close_us: int | None = None  # when the shared Edges' counts are closed next
        self.route = load_route(sc, self.results_dir)  # the netsim (partition) of each radio
        nodes = sc.nodes

        def modelled(profile: Any) -> Any:
            return profile.model_copy(update={"timing": "model"})

        self.kin = ArmKinematics()  # the arms' IK, all at once (every arm has the same model and base)
        self.loops: dict[int, AbstractLoop] = {}
        # With `shared` Edge compute, one node per Edge for all its abstract loops.
        share_edge = sc.edge.abstract_compute == "shared"
        shared: dict[str, JobQueue] = {}

        def pose_queue(node: ComputeNode) -> JobQueue:
            return JobQueue(node, "pose", sc.edge.pose_queue, self.schedule, self._superseded)

        for i in range(sc.detailed_loops, sc.loops):
            if share_edge:
                name = self.edges[i].name
                if name not in shared:
                    node = ComputeNode(f"edge-{name}", modelled(nodes.edge), self.rng(f"edge/{name}/compute"))
                    shared[name] = pose_queue(node)
                    self.record_jobs(node)
                poses = shared[name]
            else:
                poses = pose_queue(ComputeNode("edge", modelled(nodes.edge), self.rng(f"edge-{i}/compute")))
            self.loops[i] = AbstractLoop(
                index=i,
                ctl=PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S),
                tracker=Tracker((sc.work_cell.belt_speed_m_s, 0.0, 0.0)),
                keeper=FrameKeep(sc.camera.frame_keep, self.rng(f"camera-{i}/pdp")),
                size_rng=self.rng(f"camera-{i}/size"),
                error_rng=self.rng(f"edge-{i}/error"),
                camera_cpu=ComputeNode(f"camera-{i}", modelled(nodes.camera), self.rng(f"camera-{i}/compute")),
                poses=poses,
                robot_cpu=ComputeNode(f"robot-{i}", modelled(nodes.robot), self.rng(f"robot-{i}/compute")),
            )
            lp = self.loops[i]
            self.record_jobs(lp.camera_cpu, *(() if share_edge else (lp.poses.node,)), lp.robot_cpu)
        self.pose_queues = list({id(lp.poses): lp.poses for lp in self.loops.values()}.values())
        self.schedule(0, self._control_tick)
        self.next_tick_us = 0  # when ``_control_tick``, its only sender of commands, runs next
        self.schedule(0, self._policy_tick)

    def next_send_us(self, plane: str, now_us: int) -> int:
        return max(self.next_tick_us, now_us) if plane == "act" else now_us

    def external_horizon_us(self) -> int | None:
        # It sends only to physics and netsim, and the counts of the Edges it shares to the Edge
        # federate: nothing else leaves a group holding both.
        if not {"physics", *self.route.netsims} <= self.cohosted:
            return None
        return NEVER_US if self.next_close_us is None else self.next_close_us

    # ---- messages -----------------------------------------------------------------------------
    def handlers(self) -> Handlers:
        return {JointStates: self._on_states, Truth: self._on_truth, Aframe: self._on_aframe,
                Pose: self._on_pose, QosSignal: self._on_qos, EdgeCounts: self._on_counts}

    def _on_states(self, states: JointStates, msg: Message) -> None:
        for key, st in states.states.items():
            self.loops[int(key)].ctl.on_state(st["q"], st["gripped"])

    def _on_truth(self, truth: Truth, msg: Message) -> None:
        self._camera_frame(self.loops[truth.loop], truth.capture_us, truth.objects)

    def _on_aframe(self, frame: Aframe, msg: Message) -> None:
        lp, count = self.loops[frame.loop], len(frame.idx or ())
        if self.edges.backhaul_us:  # a central Edge: the packets cross the backhaul from the gNB
            self.schedule(self.now + self.edges.backhaul_us, self._frame_packets, lp, frame.frame_id,
                          frame.n, count)
        else:
            self._frame_packets(lp, frame.frame_id, frame.n, count)

    def _on_pose(self, pose: Pose, msg: Message) -> None:
        self.loops[pose.loop].ctl.on_estimate(pose.tracks)

    def _on_qos(self, qos: QosSignal, msg: Message) -> None:
        lp = self.loops[qos.loop]
        lp.pdp, lp.pdb_us = float(qos.pdp), qos.pdb_us

    def _on_counts(self, counts: EdgeCounts, msg: Message) -> None:
        self.edges.peer(counts)

    # ---- camera side ----------------------------------------------------------------------------
    def _camera_frame(self, lp: AbstractLoop, capture_us: int, objects: list[Part]) -> None:
        lp.frames += 1
        if not lp.keeper.keep(lp.pdp):
            return
        lp.frames_kept += 1
        fid = lp.frame_id
        lp.frame_id += 1
        # The draw ``choice`` makes (one bounded integer), without its argument checks.
        sizes = self.frame_model.frame_bytes
        size = int(sizes[lp.size_rng.integers(0, len(sizes))])
        _, ready = lp.camera_cpu.run("compress", self.now, int, size)
        lp.truth[fid] = (capture_us, objects)
        # Frames kept long ago and not in yet are given up here too, for a loop none of whose
        # frames gets through (trimmed only where one does, they grew for the whole run).
        while (oldest := next(iter(lp.truth))) != fid and lp.truth[oldest][0] < capture_us - LOST_FRAME_US:
            lp.truth.pop(oldest)
            lp.arrived.pop(oldest, None)
        self.schedule(ready, self._transmit, lp.index, fid, size)

    def _transmit(self, loop: int, fid: int, size: int) -> None:
        lp = self.loops[loop]
        packets = split_packets(size, self.scenario.camera.mtu_bytes)
        enter = slot_after(self.now, self.scenario.netsim.slot_us)
        ue = f"camera-{loop}"
        lp.bytes_sent += sum(packets)
        # One message for the frame's packets: they share the flow, the entry slot and the
        # destination, and no payload bytes travel for an abstract loop.
        self.send(self.route.netsim_of(ue), enter, Packets(
            ue=ue, direction="ul", flow=f"{ue}/video", sizes=packets, dst=self.name, pdb_us=lp.pdb_us,
            app=Aframe(loop=loop, frame_id=fid, n=len(packets)),
        ))

    # ---- edge side ------------------------------------------------------------------------------
    def _frame_packets(self, lp: AbstractLoop, fid: int, n: int, count: int) -> None:
        """``count`` of frame ``fid``'s ``n`` packets arrived (netsim delivers a frame's packets of
        one slot as one message); the frame goes to pose estimation when the last is in."""
        if fid not in lp.truth:  # given up for lost (LOST_FRAME_US)
            return
        got = lp.arrived.get(fid, 0) + count
        if fid not in lp.arrived:
            # Started also when it is whole at once: it may still wait for the Edge's CPU.
            self.edges[lp.index].monitor.started(lp.index, fid, self.now)
        if got < n:
            lp.arrived[fid] = got
            return
        lp.arrived.pop(fid, None)
        capture_us, objects = lp.truth.pop(fid)
        for old in [f for f in lp.truth if f < fid - 30]:  # frames that lost a packet long ago
            lp.truth.pop(old)
            lp.arrived.pop(old, None)
        lp.poses.submit(self.now, lp.index, self.frame_model.estimate, (objects, lp.error_rng),
                        self._estimated, (lp.index, capture_us, fid))

    def _estimated(self, loop: int, capture_us: int, fid: int, positions: list[np.ndarray],
                   ready_us: int) -> None:
        self.schedule(ready_us, self._publish, loop, capture_us, fid, positions)

    def _superseded(self, loop: int, capture_us: int, fid: int) -> None:
        self.loops[loop].frames_superseded += 1
        self.edges[loop].monitor.dropped(loop, fid)

    def _publish(self, loop: int, capture_us: int, fid: int, positions: list[np.ndarray]) -> None:
        lp = self.loops[loop]
        # The frame counts for the load as its estimate is ready: queueing for the Edge's CPU
        # delays it as the cell's queues do (docs/policy.md, "The load as the Edge sees it").
        self.edges[loop].monitor.frame(loop, capture_us, self.now, fid)
        tracks = update_tracks(lp.tracker, capture_us, positions)
        if tracks is None:
            return
        lp.last_frame_us = capture_us
        self._downlink(f"robot-{loop}", "pose", self.scenario.edge.pose_packet_bytes,
                       Pose(loop=loop, tracks=tracks))

    def _policy_tick(self) -> None:
        sc = self.scenario
        # Each Edge decides for all its loops at once (one inference of a learned policy);
        # the loops then signal in their order, as when each was decided alone.
        asked: dict[CoDesign, list[tuple[int, Tracker, int | None]]] = {}
        for lp in self.loops.values():
            asked.setdefault(self.edges[lp.index], []).append((lp.index, lp.tracker, lp.last_frame_us))
        decided = {loop: qos for codesign, loops in asked.items()
                   for (loop, _, _), qos in zip(loops, codesign.decide_many(self.now, loops), strict=True)}
        for lp in self.loops.values():
            codesign = self.edges[lp.index]
            qos = decided[lp.index]
            message = codesign.signal(lp.index, qos, self.now)
            if message is not None:
                # Modelled timing: the policy job's duration is drawn only when its QoS is sent.
                _, ready = lp.poses.node.run("policy", self.now, int, 0)
                self.schedule(ready, self._downlink, f"camera-{lp.index}", "qos", sc.edge.qos_packet_bytes,
                              message)
                if sc.policy.signalling == "lower":
                    self.schedule(ready, self._lower_layer_qos, lp.index, qos)
        nxt = self.now + sc.edge.policy_period_ms * 1000
        if nxt < sc.duration_us:
            self.schedule(nxt, self._policy_tick)
            if self.edges.shared:
                self.next_close_us = nxt - self.edges.close_ahead_us
                self.schedule(self.next_close_us, self._close_edges)

    def _close_edges(self) -> None:
        self.next_close_us = None
        due, bodies = self.edges.close(self.now)
        self.send_bundle("edge", due, bodies)

    def _lower_layer_qos(self, loop: int, qos: Qos) -> None:
        sc = self.scenario
        # A central Edge's control message crosses the backhaul to the gNB first.
        at, ctl = lower_layer_qos(loop, qos, self.now + self.edges.backhaul_us, sc.policy, sc.netsim.slot_us)
        self.send(self.route.netsim_of(ctl.ue), at, ctl)

    def _downlink(self, ue: str, what: str, size: int, app: Payload) -> None:
        # The Edge's packet enters its gNB after the backhaul (none at a per-gNB Edge).
        self.send(self.route.netsim_of(ue), slot_after(self.now + self.edges.backhaul_us, self.scenario.netsim.slot_us),
                  downlink_packet(ue, what, size, self.name, app))

    # ---- robot side -----------------------------------------------------------------------------
    def _control_tick(self) -> None:
        sc = self.scenario
        latest = self.now
        ctls = [lp.ctl for lp in self.loops.values()]
        tips = self.kin.tcp_positions(np.array([c.q for c in ctls])) if ctls else np.empty((0, 3))
        for lp, tip in zip(self.loops.values(), tips, strict=True):
            # Each arm's control step is ``PickController.step`` taken apart, to compute the cups'
            # positions and solve the IK of all arms in one call each. The job's duration is drawn
            # (modelled timing), so the thread time it keeps for information covers the plan only.
            _, ready = lp.robot_cpu.run("control", self.now, lp.ctl.plan, self.now, tip)
            latest = max(latest, ready)
        commands: list[Command] = []
        if ctls:
            qs, errs = self.kin.solve_many(np.array([c.p_sp for c in ctls]), ctls[0].rot,
                                           np.array([c.q_sp for c in ctls]))
            for lp, q, err in zip(self.loops.values(), qs, errs.tolist(), strict=True):
                commands.append({"loop": lp.index, "q": lp.ctl.command(q, err).tolist(),
                                 "suction": bool(lp.ctl.suction)})
        # One message for all arms: they share the latest compute completion of this tick.
        self.send("physics", latest + sc.robot.actuation_latency_us, Commands(commands))
        nxt = self.now + sc.robot.control_period_us
        self.next_tick_us = nxt if nxt < sc.duration_us else NEVER_US
        if nxt < sc.duration_us:
            self.schedule(nxt, self._control_tick)

    def _write_loop_counters(self) -> list[dict[str, Any]]:
        """Per-loop counters, one row per loop: rewritten whole (a few dozen rows) at each flush,
        so that a run that fails keeps them as of its last flush."""
        rows = [{"loop": lp.index, "frames": lp.frames, "frames_kept": lp.frames_kept,
                 "frames_superseded": lp.frames_superseded, "ul_bytes": lp.bytes_sent,
                 "picks": lp.ctl.picks} for lp in self.loops.values()]
        write_table(self.results_dir / "tables" / "abstract-loops.parquet", rows)
        return rows

    def collect_records(self) -> None:
        self._write_loop_counters()

    def finish(self, reason: str) -> dict[str, Any]:
        rows = self._write_loop_counters()
        return {"abstract_loops": len(self.loops), "frames_kept": sum(r["frames_kept"] for r in rows),
                "frames_superseded": sum(r["frames_superseded"] for r in rows),
                # Complete and still waiting for their Edge's CPU at the end (`newest`).
                "frames_waiting": sum(q.waiting for q in self.pose_queues),
                "edges": self.edges.summary()}
