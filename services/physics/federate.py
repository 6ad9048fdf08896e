"""The physics federate: steps every cell of the hall, renders RGB-D for the detailed loops, sends
joint states to the robot controllers, applies their commands and records task outcomes.

Sensor readout and actuation are local wires with fixed latencies (>= the window), not radio.
"""

from __future__ import annotations

import heapq
import logging
from typing import Any

import cv2
import numpy as np

from domain.sensor import frame_offset_us, sensor_depth_mm
from domain.world import World, spawn_plan
from fabric.federate import NEVER_US, Federate, Handlers
from fabric.messages import Message
from services.physics.stepper import Stepper, step_ahead
from wire.bodies import Commands, Image, JointState, JointStates, Truth

log = logging.getLogger(__name__)


class PhysicsFederate(Federate):
    role = "physics"
    data_planes = ("act",)  # it takes commands only

    def setup(self) -> None:
        sc = self.scenario
        self.detailed = list(range(sc.detailed_loops))
        self.abstract = list(range(sc.detailed_loops, sc.loops))
        self.world = World(sc)
        self.step_us = sc.physics_timestep_us
        self.frame_period = sc.frame_period_us
        # Without depth noise the stream would serve only draws multiplied by zero (4 ms a frame).
        self.noise_rng = self.rng("depth-noise") if sc.camera.depth_noise_mm else None
        self.frames_sent = 0
        self.tasks = self.table("tasks")
        self.tasks_ended = 0
        self.tasks_placed = 0
        self.snapshot_saved = False
        # When the next frame of each detailed loop and the next joint states are due: what
        # leaves a group holding physics and the abstract loops (``external_horizon_us``).
        self.next_out: dict[str, int] = {}
        # Keys of the pending events that change the world or read its live state: spawns,
        # commands and the detailed loops' frames (rendering reads the whole mjData). A step may
        # run ahead past the other events, which only observe (``World.hold_observations``),
        # but never past one of these.
        self._changes: list[tuple[int, str, int]] = []
        for i in range(sc.loops):
            for at, part in spawn_plan(sc, self.rng(f"spawn-c{i}"), self.step_us):
                heapq.heappush(self._changes, self.schedule(at, self._spawn, i, part))
            first = frame_offset_us(i, sc.loops, self.frame_period, self.step_us)
            key = self.schedule(first, self._frame, i)
            if i in self.detailed:
                heapq.heappush(self._changes, key)
                self.next_out[f"frame-{i}"] = first
        self.schedule(0, self._publish_states)
        # Stepping ahead in a group (``work_ahead``), made at the first offer; until when no
        # command can arrive, as the group last told.
        self._stepper: Stepper | None = None
        self._until = 0
        if self.detailed:
            self.next_out["states"] = 0
            # The renderer (GL context, shader compilation) is made before the run starts: on a
            # loaded host its first frame takes seconds, which the first window would spend.
            self.world.render(self.detailed[0], sc.camera.width_px, sc.camera.height_px)

    # ---- stepping ahead -----------------------------------------------------------------------
    def work_ahead(self, until_us: int) -> None:
        """Step the world in the background up to the next event that changes it (at most
        ``until_us``: every input before then is here already), several steps a handover where
        nothing in Python has to run between them (``World.steps_alone``). The events that only
        observe read the state at their time: each step holds the observations of its start
        (``World.hold_observations``), kept until the events of that step have observed them, so
        the steps need not wait for those events, and what they see is the same. ``mj_step``
        releases the GIL, so it runs beside the group's events on the second core."""
        self._until = until_us
        stepper = self._stepper
        if stepper is None:
            stepper = self._stepper = step_ahead(self.world, f"{self.name}-step")
        if stepper.running and not stepper.poll():
            return
        changes, world = self._changes, self.world
        # Never past the run's end, which the last window may overrun.
        until_us = min(until_us, self.scenario.duration_us)
        target = min(changes[0][0], until_us) if changes else until_us
        if world.t_us + self.step_us <= target:
            stepper.start(target, world.steps_alone())

    def working_ahead(self) -> bool:
        return self._stepper is not None and self._stepper.busy()

    def process_next(self) -> None:
        key = self.next_event_key()
        assert key is not None, "process_next with no event pending"
        t_us, changes = key[0], self._changes
        observes = not (changes and changes[0] == key)
        if not observes:
            heapq.heappop(changes)
        stepper, world = self._stepper, self.world
        if stepper is not None and stepper.running:  # in a group, stepping ahead
            if t_us >= stepper.end_us:
                stepper.wait()
            elif observes:
                stepper.reach(t_us)
            else:
                raise RuntimeError(f"{self.name}: a step ran ahead past a change to the world at {t_us} us")
        if not observes and world.t_us > t_us:
            raise RuntimeError(f"{self.name}: the world stepped past a change to it at {t_us} us")
        if stepper is None or not stepper.running:
            # Every event begins with the world at its time (stepped here if it is behind).
            world.advance_to(t_us)
            if observes and stepper is not None:
                # The next steps may run while this event observes the state at its time.
                self.work_ahead(self._until)
        if observes:
            world.observe_at(t_us)
        else:
            world.release_observations()
        super().process_next()

    # ---- events -------------------------------------------------------------------------------
    def _spawn(self, cell: int, part: dict[str, float]) -> None:
        if self.world.spawn(cell, **part) is None and self.world.cells[cell].skipped_spawns == 1:
            # Every part body of the cell is still in play (parts that never leave the belt or
            # the platform): the part is not simulated; the run's summary says how many were not.
            log.warning("%s: work cell %d has no free part body at %d us: a part is not spawned "
                        "(the first; the summary counts them)", self.name, cell, self.now)

    def _frame(self, loop: int) -> None:
        sc = self.scenario
        deliver = self.now + sc.camera.readout_latency_us
        if loop < sc.detailed_loops:
            rgb, depth = self.world.render(loop, sc.camera.width_px, sc.camera.height_px)
            assert depth is not None
            depth_mm = sensor_depth_mm(depth, sc.camera.depth_noise_mm, self.noise_rng)
            self.send(f"camera-{loop}", deliver,
                      Image(loop=loop, capture_us=self.now, w=rgb.shape[1], h=rgb.shape[0],
                            truth=self.world.objects(loop)),
                      rgb.tobytes() + depth_mm.tobytes())
            self.frames_sent += 1
            if loop == 0 and not self.snapshot_saved and self.world.objects(0) and self.now > 2_000_000:
                self._save_snapshot(rgb)
        else:
            self.send("loops", deliver, Truth(loop=loop, capture_us=self.now, objects=self.world.objects(loop)))
        nxt = self.now + self.frame_period
        if nxt < sc.duration_us:
            key = self.schedule(nxt, self._frame, loop)
            if loop < sc.detailed_loops:
                heapq.heappush(self._changes, key)
        if loop < sc.detailed_loops:
            self.next_out[f"frame-{loop}"] = nxt if nxt < sc.duration_us else NEVER_US

    def _publish_states(self) -> None:
        sc = self.scenario
        deliver = self.now + sc.robot.state_latency_us
        for i in self.detailed:
            arm = self.world.joint_state(i)
            self.send(f"robot-{i}", deliver, JointState(loop=i, t_us=self.now, q=arm["q"], gripped=arm["gripped"]))
        if self.abstract:
            self.send("loops", deliver,
                      JointStates(t_us=self.now, states={str(i): self.world.joint_state(i) for i in self.abstract}))
        nxt = self.now + sc.robot.control_period_us
        if nxt < sc.duration_us:
            self.schedule(nxt, self._publish_states)
        if self.detailed:
            self.next_out["states"] = nxt if nxt < sc.duration_us else NEVER_US

    def external_horizon_us(self) -> int | None:
        # The abstract loops' truth and joint states go to the loops federate: outside the
        # group only if it is not a member.
        if self.abstract and "loops" not in self.cohosted:
            return None
        return min(self.next_out.values(), default=NEVER_US)

    def accept(self, msg: Message) -> None:
        heapq.heappush(self._changes, (msg.t_us, msg.src, msg.seq))
        super().accept(msg)

    def handlers(self) -> Handlers:
        return {Commands: self._on_commands}

    def _on_commands(self, commands: Commands, msg: Message) -> None:
        for cmd in commands.commands:
            self.world.command(cmd["loop"], cmd["q"], cmd["suction"])

    def _save_snapshot(self, rgb: np.ndarray) -> None:
        out = self.results_dir / "frames"
        out.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / "camera-0.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        top, _ = self.world.render(0, 640, 480, camera="top", depth=False)
        cv2.imwrite(str(out / "top-0.png"), cv2.cvtColor(top, cv2.COLOR_RGB2BGR))
        self.snapshot_saved = True

    def _record_tasks(self, rows: list[dict[str, Any]]) -> None:
        for r in rows:
            self.tasks.append(r)
            if r["outcome"] != "unfinished":
                self.tasks_ended += 1
                self.tasks_placed += bool(r["success"])

    def close(self) -> None:
        stepper = getattr(self, "_stepper", None)  # absent when setup failed
        if stepper is not None:
            stepper.close()
        world = getattr(self, "world", None)
        if world is not None:
            world.close()

    def collect_records(self) -> None:
        # No wait for a step running ahead: tasks change only when it ends, in this thread.
        self._record_tasks(self.world.take_ended(self.now))

    def finish(self, reason: str) -> dict[str, Any]:
        if self._stepper is not None:
            self._stepper.wait()  # the steps running ahead, if any (their error is raised here)
        # A completed run ends at its duration, though the last windows had nothing for this
        # federate (none comes after them, so the world steps on as it was); any other at the
        # end of its last window, which no step ahead passes. Either way the same end however
        # far the steps ahead had got, and in a group or alone.
        end_us = self.scenario.duration_us
        if reason != "completed":
            end_us = min(max(self.now, self.window_end), end_us)
        self.world.advance_to(end_us)
        self._record_tasks(self.world.finish())
        return {"tasks": self.tasks_ended, "placed": self.tasks_placed,
                "frames_rendered": self.frames_sent,
                "parts_not_spawned": sum(c.skipped_spawns for c in self.world.cells)}
