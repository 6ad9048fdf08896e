"""The Edge node (co-located with the gNB): reassembles uplink frames, estimates part poses on its
throttled CPU, tracks them, sends the tracks to the robot and runs the co-design policy that sets
each camera's PDP_r and L_r, all downlink through netsim.
"""

from __future__ import annotations

from typing import Any

import cv2

from domain.codec import decode_frame, slot_after
from domain.edge_side import Edges, downlink_packet, lower_layer_qos, update_tracks
from domain.edges import load_plan
from domain.estimator import Detection, make_estimator
from domain.frame_model import RUN_FILE, miss_rate_for
from domain.partitions import load_route
from domain.policy import Qos
from domain.tracker import Tracker
from domain.work_cell import CameraIntrinsics
from fabric.compute import ComputeNode
from fabric.federate import Federate, Handlers
from fabric.job_queue import JobQueue
from fabric.messages import Message
from wire.bodies import EdgeCounts, Frame, Payload, Pose

PARTIAL_FRAME_TIMEOUT_US = 500_000  # a frame missing packets this long is given up


class EdgeFederate(Federate):
    role = "edge"

    def setup(self) -> None:
        sc = self.scenario
        self.cpu = ComputeNode(self.name, sc.nodes.edge, self.rng("compute"))
        self.poses = JobQueue(self.cpu, "pose", sc.edge.pose_queue, self.schedule, self._superseded)
        self.record_jobs(self.cpu)
        self.route = load_route(sc, self.results_dir)  # the netsim (partition) of each radio
        k = CameraIntrinsics(sc.camera.width_px, sc.camera.height_px, sc.camera.fovy_deg)
        # A learned estimator whose model cannot be loaded falls back to the classical one; the
        # warning is logged and the summary names the estimator that ran and why.
        self.estimator, self.estimator_fallback = make_estimator(sc.edge.estimator, k, sc.work_cell.object_size_m)
        self.loops = list(range(sc.detailed_loops))
        self.trackers = {i: Tracker((sc.work_cell.belt_speed_m_s, 0.0, 0.0)) for i in self.loops}
        # The Edge sides of these loops: one per gNB, or the central one (domain/edges.py); one
        # CPU serves them all.
        # The floor's miss rate is the abstract loops' (the frame model of this camera), so that
        # an Edge serving both kinds bounds them alike.
        self.edges = Edges(sc, load_plan(sc, self.results_dir), self.loops,
                           miss_rate_for(sc.camera, self.results_dir / RUN_FILE))
        # An Edge serving abstract loops too shares its counts with the abstract loops' federate.
        self.edges.share(range(sc.detailed_loops, sc.loops))
        self.partial: dict[tuple[int, int], dict[str, Any]] = {}
        self.last_frame_us: dict[int, int | None] = {i: None for i in self.loops}
        self.frames = self.table("frames")
        self.frames_estimated = 0
        self.frames_incomplete = 0
        self.frames_superseded = 0
        self.detections = 0
        cv2.setNumThreads(self.cpu.threads)  # OpenCV at the node's cores: one where cpus <= 1
        if self.loops:
            self.schedule(0, self._policy_tick)

    def handlers(self) -> Handlers:
        return {Frame: self._on_frame, EdgeCounts: self._on_counts}

    def _on_counts(self, counts: EdgeCounts, msg: Message) -> None:
        self.edges.peer(counts)

    def _close_edges(self) -> None:
        due, bodies = self.edges.close(self.now)
        self.send_bundle("loops", due, bodies)

    def _on_frame(self, frame: Frame, msg: Message) -> None:
        if self.edges.backhaul_us:  # a central Edge: the packet crosses the backhaul from the gNB
            self.schedule(self.now + self.edges.backhaul_us, self._frame_in, frame, msg.blob)
        else:
            self._frame_in(frame, msg.blob)

    def _frame_in(self, frame: Frame, blob: bytes | None) -> None:
        """A packet of ``frame`` (its bytes ``blob``) in at the Edge now."""
        key = (frame.loop, frame.frame_id)
        part = self.partial.get(key)
        if part is None:
            part = self.partial[key] = {"n": frame.n, "chunks": {}, "first_us": self.now,
                                        "capture_us": frame.capture_us, "seq": frame.seq}
            self.edges[frame.loop].monitor.started(frame.loop, frame.seq, self.now)
        part["chunks"][frame.idx] = blob or b""
        if len(part["chunks"]) == part["n"]:
            del self.partial[key]
            data = b"".join(part["chunks"][i] for i in range(part["n"]))
            self.poses.submit(self.now, frame.loop, self._estimate, (data,), self._estimated,
                              (*key, part["capture_us"], part["seq"], self.now))
        self._drop_stale_partials()

    def _estimated(self, loop: int, frame_id: int, capture_us: int, seq: int, complete_us: int,
                   detections: list[Detection], ready_us: int) -> None:
        self._frame_row(loop, frame_id, capture_us, complete_us, ready_us, len(detections), lost=False)
        self.frames_estimated += 1
        self.detections += len(detections)
        self.schedule(ready_us, self._publish, loop, capture_us, seq, detections)

    def _superseded(self, loop: int, frame_id: int, capture_us: int, seq: int, complete_us: int) -> None:
        # Complete, never estimated: a row with no ready time, as lost.
        self._frame_row(loop, frame_id, capture_us, complete_us, None, 0, lost=True)
        self.frames_superseded += 1
        self.edges[loop].monitor.dropped(loop, seq)

    def _frame_row(self, loop: int, frame_id: int, capture_us: int, complete_us: int | None,
                   ready_us: int | None, detections: int, lost: bool) -> None:
        self.frames.append({"loop": loop, "frame_id": frame_id, "capture_us": capture_us,
                            "complete_us": complete_us, "ready_us": ready_us, "detections": detections,
                            "estimator": self.estimator.name, "lost": lost})

    def _estimate(self, data: bytes) -> list[Detection]:
        rgb, depth = decode_frame(data)
        return self.estimator.detect(rgb, depth)

    def _drop_stale_partials(self) -> None:
        for key in [k for k, p in self.partial.items() if self.now - p["first_us"] > PARTIAL_FRAME_TIMEOUT_US]:
            p = self.partial.pop(key)
            self._frame_row(*key, p["capture_us"], None, None, 0, lost=True)
            self.frames_incomplete += 1

    def _publish(self, loop: int, capture_us: int, seq: int, detections: list[Detection]) -> None:
        # The frame counts for the load as its estimate is ready: queueing for the Edge's CPU
        # delays it as the cell's queues do (docs/policy.md, "The load as the Edge sees it").
        self.edges[loop].monitor.frame(loop, capture_us, self.now, seq)
        tracks = update_tracks(self.trackers[loop], capture_us, [d.p for d in detections])
        if tracks is None:
            return
        self.last_frame_us[loop] = capture_us
        self._downlink(f"robot-{loop}", "pose", self.scenario.edge.pose_packet_bytes,
                       Pose(loop=loop, tracks=tracks, capture_us=capture_us))

    def _policy_tick(self) -> None:
        sc = self.scenario
        for loop in self.loops:
            codesign = self.edges[loop]
            qos, ready = self.cpu.run("policy", self.now, codesign.decide, loop, self.now,
                                      self.trackers[loop], self.last_frame_us[loop])
            message = codesign.signal(loop, qos, self.now)
            if message is not None:
                self.schedule(ready, self._downlink, f"camera-{loop}", "qos", sc.edge.qos_packet_bytes, message)
                if sc.policy.signalling == "lower":
                    self.schedule(ready, self._lower_layer_qos, loop, qos)
        nxt = self.now + sc.edge.policy_period_ms * 1000
        if nxt < sc.duration_us:
            self.schedule(nxt, self._policy_tick)
            if self.edges.shared:
                self.schedule(nxt - self.edges.close_ahead_us, self._close_edges)

    def _lower_layer_qos(self, loop: int, qos: Qos) -> None:
        sc = self.scenario
        # A central Edge's control message crosses the backhaul to the gNB first.
        at, ctl = lower_layer_qos(loop, qos, self.now + self.edges.backhaul_us, sc.policy, sc.netsim.slot_us)
        self.send(self.route.netsim_of(ctl.ue), at, ctl)

    def _downlink(self, ue: str, what: str, size: int, app: Payload) -> None:
        # The Edge's packet enters its gNB after the backhaul (none at a per-gNB Edge).
        self.send(self.route.netsim_of(ue), slot_after(self.now + self.edges.backhaul_us, self.scenario.netsim.slot_us),
                  downlink_packet(ue, what, size, ue, app))

    def finish(self, reason: str) -> dict[str, Any]:
        done = self.frames_estimated
        # Frames complete and still waiting for the CPU at the end: a row each, not estimated
        # and not lost (in arrival order every complete frame has its row, its ready time later).
        waiting = self.poses.waiting_jobs()
        for loop, frame_id, capture_us, _, complete_us in waiting:
            self._frame_row(loop, frame_id, capture_us, complete_us, None, 0, lost=False)
        return {"frames_estimated": done, "frames_incomplete": self.frames_incomplete,
                "frames_superseded": self.frames_superseded, "frames_waiting": len(waiting),
                "compute_speed": self.cpu.speed_summary(self.now),
                "estimator": self.estimator.name, "estimator_requested": self.scenario.edge.estimator,
                "estimator_fallback_reason": self.estimator_fallback or "",
                "mean_detections": self.detections / done if done else 0.0,
                "edges": self.edges.summary()}
