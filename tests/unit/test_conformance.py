"""Window-protocol conformance of every federate class, on the in-memory bus.

A scripted conductor drives one federate alone through windows, handing it scripted inputs in a
shuffled arrival order (data before or after the advance, in any order), and checks that:

- nothing it sends is timed inside the window it was sent in;
- its ``done`` reports count what it really sent, and name a next event (and an earliest send)
  that is right: jumping idle stretches by them gives the same outputs as stepping every window;
- the same inputs and seed give the same outputs and trace, whatever the arrival order;
- a message it cannot handle (unexpected kind, malformed body, undecodable bytes) fails it with
  an error naming the federate and the message kind;
- it streams its records and closes them when stopped, and leaves (records closed) when its
  coordinator's liveliness token vanishes.

A new federate class joins with one line in ``CASES``, naming a function that gives its inputs.
"""

from __future__ import annotations

import dataclasses
import json
import queue
import random
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from test_conductor import Ping

from domain.codec import encode_frame, split_packets
from domain.frame_model import PATH as FRAME_MODEL
from domain.frame_model import RUN_FILE, camera_settings
from fabric import driver as driver_mod
from fabric import keys
from fabric.bus import InMemoryBus, InMemoryHub
from fabric.driver import EXIT_ORPHANED, WindowDriver, WindowReport
from fabric.federate import Federate, FederateContext
from fabric.messages import Advance, Done, Message, Stop, Stopped, decode_data
from fabric.tables import PartInfo, read_part
from netsim.federate import NetsimFederate
from scenario.schema import Scenario, parse_scenario
from services.camera.federate import CameraFederate
from services.edge.federate import EdgeFederate
from services.loops.federate import LoopsFederate
from services.physics.federate import PhysicsFederate
from services.robot.federate import RobotFederate

RUN = "conf"
W = 1000
END_US = 200_000
ANSWER_S = 60.0  # a window answered later than this is a hang, not slowness


@dataclass(frozen=True)
class Input:
    """A data message handed to the federate under test, delivered at ``t_us``."""

    t_us: int
    src: str
    plane: str
    kind: str
    body: dict[str, Any]
    blob: bytes | None = None


def tiny_scenario(**edge: Any) -> Scenario:
    """Two loops, the first detailed, tiny frames, model timing: fast and deterministic; ``edge``
    settings of the Edge beside the defaults."""
    model = {"cpus": 0.5, "timing": "model"}
    return parse_scenario({
        "name": "conformance", "seed": 3, "duration_s": END_US / 1e6, "loops": 2, "detailed_loops": 1,
        "camera": {"width_px": 64, "height_px": 48},
        "work_cell": {"first_object_s": 0.02, "object_period_s": 1.0},
        "nodes": {"camera": model, "edge": model, "robot": model},
        "edge": edge,
    })


def synthetic_frame(sc: Scenario, k: int) -> tuple[np.ndarray, np.ndarray]:
    """An RGB-D frame: a grey belt with a red square moving along it, depth a plane at 0.8 m."""
    h, w = sc.camera.height_px, sc.camera.width_px
    rgb = np.full((h, w, 3), 90, np.uint8)
    x = 8 + 4 * k
    rgb[18:30, x:x + 12] = (200, 30, 30)
    depth = np.full((h, w), 800, np.uint16)
    depth[18:30, x:x + 12] = 760
    return rgb, depth


def frame_times(sc: Scenario, start_us: int) -> list[int]:
    return list(range(start_us, END_US - 10_000, sc.frame_period_us))


ARM_Q = [0.0, -0.6, 1.2, 0.0, 0.6, 0.0]


# ---- scripted inputs, per federate class ---------------------------------------------------------
def physics_inputs(sc: Scenario) -> list[Input]:
    out = []
    for t in range(11_000, END_US, sc.robot.control_period_us):
        out.append(Input(t, "robot-0", "act", "command",
                         {"commands": [{"loop": 0, "q": ARM_Q, "suction": False}]}))
        out.append(Input(t + 1000, "loops", "act", "command",
                         {"commands": [{"loop": 1, "q": ARM_Q, "suction": t > 100_000}]}))
    return out


def camera_inputs(sc: Scenario) -> list[Input]:
    out = []
    for k, t in enumerate(frame_times(sc, 2000)):
        rgb, depth = synthetic_frame(sc, k)
        out.append(Input(t, "physics", "sense", "image",
                         {"loop": 0, "capture_us": t - 2000, "w": rgb.shape[1], "h": rgb.shape[0],
                          "truth": []}, rgb.tobytes() + depth.tobytes()))
    out.append(Input(70_000, "netsim", "net", "qos",
                     {"type": "qos", "loop": 0, "pdp": 0.5, "pdb_us": 80_000, "packet_id": 1}))
    return out


def edge_inputs(sc: Scenario) -> list[Input]:
    out = []
    for k, t in enumerate(frame_times(sc, 8000)):
        rgb, depth = synthetic_frame(sc, k)
        data = encode_frame(rgb, depth, sc.camera.jpeg_quality, sc.camera.depth_codec,
                            sc.camera.depth_decimation)
        sizes = split_packets(len(data), sc.camera.mtu_bytes)
        offset = 0
        for idx, size in enumerate(sizes):
            chunk = data[offset:offset + size - 40]
            offset += len(chunk)
            # Packets of a frame arrive over a few slots, the last ones first.
            out.append(Input(t + 1000 * (len(sizes) - idx), "netsim", "net", "frame",
                             {"type": "frame", "loop": 0, "frame_id": k, "capture_us": t - 6000,
                              "idx": idx, "n": len(sizes), "seq": k, "packet_id": 100 * k + idx}, chunk))
    return out


def edge_burst_inputs(sc: Scenario) -> list[Input]:
    """The frames of ``edge_inputs`` completing three at a time, 0.2 ms apart: the first is
    estimated at once, the third takes the place of the second while it waits."""
    period = sc.frame_period_us
    out = []
    for i in edge_inputs(sc):
        k = i.body["frame_id"]
        out.append(Input(i.t_us - (k % 3) * period + (k % 3) * 200, i.src, i.plane, i.kind, i.body, i.blob))
    return out


def _track(t: int) -> dict[str, Any]:
    return {"id": 1, "t_us": t, "p": [-0.3 + 0.2 * t / 1e6, 0.0, 0.03], "v": [0.2, 0.0, 0.0], "sd": 0.004}


def robot_inputs(sc: Scenario) -> list[Input]:
    out = [Input(t + 1000, "physics", "sense", "joint_state",
                 {"loop": 0, "t_us": t, "q": ARM_Q, "gripped": False})
           for t in range(0, END_US, sc.robot.control_period_us)]
    out += [Input(t, "netsim", "net", "pose",
                  {"type": "pose", "loop": 0, "tracks": [_track(t - 20_000)], "capture_us": t - 20_000,
                   "packet_id": t})
            for t in range(40_000, END_US, 33_000)]
    return out


def netsim_inputs(sc: Scenario) -> list[Input]:
    out = []
    for k, t in enumerate(frame_times(sc, 3000)):
        enter = t // sc.netsim.slot_us * sc.netsim.slot_us
        for idx in range(12):
            out.append(Input(enter, "camera-0", "net", "packet", {
                "ue": "camera-0", "dir": "ul", "flow": "camera-0/video", "size": 1500, "dst": "edge",
                "pdb_us": None if k < 3 else 60_000,
                "app": {"type": "frame", "loop": 0, "frame_id": k, "capture_us": t - 3000, "idx": idx,
                        "n": 12, "seq": k}}, bytes([idx]) * 64))
        out.append(Input(enter + 2000, "loops", "net", "packets", {
            "ue": "camera-1", "dir": "ul", "flow": "camera-1/video", "sizes": [120, 80], "dst": "loops",
            "pdb_us": None, "app": {"type": "aframe", "loop": 1, "frame_id": k, "n": 2}}))
        out.append(Input(enter + 9000, "edge", "net", "packet", {
            "ue": "robot-0", "dir": "dl", "flow": "robot-0/pose", "size": 120, "dst": "robot-0",
            "pdb_us": None, "app": {"type": "pose", "loop": 0, "tracks": [], "capture_us": t}}))
    return out


def loops_inputs(sc: Scenario) -> list[Input]:
    out = []
    for k, t in enumerate(frame_times(sc, 2000)):
        objects = [{"task_id": 0, "p": [-0.4 + 0.2 * t / 1e6, 0.0, 0.03], "v": [0.2, 0.0, 0.0],
                    "gripped": False}]
        out.append(Input(t, "physics", "sense", "truth", {"loop": 1, "capture_us": t - 2000,
                                                           "objects": objects}))
        # Every frame is kept (PDP 1): frame k's two packets arrive 30 ms after capture, in one
        # bundle as netsim delivers them.
        out.append(Input(t + 30_000, "netsim", "net", "bundle", {"items": [
            ["aframe", {"type": "aframe", "loop": 1, "frame_id": k, "idx": [idx], "n": 2,
                        "packet_ids": [2 * k + idx]}]
            for idx in range(2)]}))
    out += [Input(t + 1000, "physics", "sense", "joint_states",
                  {"t_us": t, "states": {"1": {"q": ARM_Q, "gripped": False}}})
            for t in range(0, END_US, sc.robot.control_period_us)]
    out.append(Input(60_000, "netsim", "net", "pose", {"type": "pose", "loop": 1, "tracks": [_track(40_000)]}))
    out.append(Input(90_000, "netsim", "net", "qos",
                     {"type": "qos", "loop": 1, "pdp": 1.0, "pdb_us": 50_000, "packet_id": 7}))
    return out


@dataclass(frozen=True)
class Case:
    name: str
    cls: type[Federate]
    inputs: Callable[[Scenario], list[Input]]
    edge: tuple[tuple[str, Any], ...] = ()  # Edge settings beside tiny_scenario's
    variant: str = ""

    def __str__(self) -> str:
        return f"{self.name}-{self.variant}" if self.variant else self.name

    def scenario(self) -> Scenario:
        return tiny_scenario(**dict(self.edge))


EDGE_NEWEST = Case("edge", EdgeFederate, edge_burst_inputs, (("pose_queue", "newest"),), "newest")


CASES = [
    Case("physics", PhysicsFederate, physics_inputs),
    Case("camera-0", CameraFederate, camera_inputs),
    Case("edge", EdgeFederate, edge_inputs),
    EDGE_NEWEST,
    Case("robot-0", RobotFederate, robot_inputs),
    Case("netsim", NetsimFederate, netsim_inputs),
    Case("loops", LoopsFederate, loops_inputs),
]



def test_every_registered_role_has_a_case() -> None:
    from services.roles import ROLES

    assert {c.cls for c in CASES} == {r.federate_class() for r in ROLES.values()}


# ---- the scripted conductor ----------------------------------------------------------------------
Output = tuple[int, str, str, int, str, str, Any, Any]  # t_us, src, dst, seq, plane, kind, body, blob


@dataclass
class Result:
    outputs: list[Output] = field(default_factory=list)
    windows: int = 0
    error: str | None = None
    stopped: Stopped | None = None
    exit_code: int | None = None


class ScriptedConductor:
    """Drives one federate through windows on its own in-memory bus and checks every report."""

    def __init__(self, case: Case, results_dir: Path, arrival_seed: int) -> None:
        self.case = case
        self.sc = case.scenario()
        self.hub = InMemoryHub()
        self.bus = InMemoryBus(self.hub)
        self.rnd = random.Random(arrival_seed)
        self.control: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self.sent: list[Message] = []
        self.bus.declare_token(keys.coordinator_alive(RUN))
        for what, pattern in (("done", keys.done_all(RUN)), ("stopped", keys.stopped_all(RUN)),
                              ("ready", keys.ready_all(RUN))):
            self.bus.subscribe(pattern, self._to_control(what))
        for plane in keys.DATA_PLANES:
            self.bus.subscribe(f"{keys.ROOT}/{RUN}/{plane}/*/{case.name}",
                               lambda k, p: self.sent.extend(decode_data(p)))
        if case.name == "loops":
            # What the coordinator puts into a run's directory: here the default camera's frame
            # sizes stand for the tiny camera's (the window protocol does not depend on them).
            model = json.loads(FRAME_MODEL.read_text())
            model["settings"].update(camera_settings(self.sc.camera))
            results_dir.mkdir(parents=True, exist_ok=True)
            (results_dir / RUN_FILE).write_text(json.dumps(model))
        self.fed = case.cls(FederateContext(case.name, RUN, self.sc, results_dir), InMemoryBus(self.hub))
        self.result = Result()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()
        self._wait("ready")
        self._seq: Counter[str] = Counter()
        self._delivered = 0

    def _to_control(self, what: str) -> Callable[[str, bytes], None]:
        return lambda key, payload: self.control.put((what, payload))

    def _serve(self) -> None:
        self.result.exit_code = WindowDriver(self.fed).serve()

    def _wait(self, what: str) -> bytes:
        while True:
            try:
                kind, payload = self.control.get(timeout=ANSWER_S)
            except queue.Empty:
                raise AssertionError(f"{self.case.name}: no {what} within {ANSWER_S:.0f} s") from None
            if kind == what:
                return payload

    def message(self, inp: Input, window: int) -> bytes:
        self._seq[inp.src] += 1
        return Message(inp.t_us, inp.src, self.case.name, self._seq[inp.src], inp.plane, inp.kind,
                       inp.body, inp.blob, window).encode()

    def window(self, k: int, t_start: int, data: list[tuple[str, bytes]]) -> Done:
        """Conduct window ``k``: the data (sent in window k-1) and the advance, in a shuffled
        arrival order; returns the checked done report."""
        self._delivered += len(data)
        t_end = t_start + W
        adv = Advance(window=k, t_start_us=t_start, t_end_us=t_end,
                      expected_in={self.case.name: self._delivered})
        arrivals = list(data)
        self.rnd.shuffle(arrivals)
        arrivals.insert(self.rnd.randint(0, len(arrivals)), (keys.advance(RUN), adv.encode()))
        before = len(self.sent)
        for key, payload in arrivals:
            self.bus.publish(key, payload)
        done = Done.decode(self._wait("done"))
        if done.error:
            return done
        name = self.case.name
        assert (done.federate, done.window, done.t_end_us) == (name, k, t_end)
        new = self.sent[before:]
        for m in new:
            assert m.window == k and m.src == name, (m.window, m.src)
            assert m.t_us >= t_end, f"{name}: {m.kind} to {m.dst} at {m.t_us} us, inside window [{t_start}, {t_end})"
        assert done.sent_to == dict(Counter(m.dst for m in self.sent)), f"{name}: sent_to miscounted"
        assert done.earliest_sent_us == (min(m.t_us for m in new) if new else None)
        assert done.next_event_us is None or done.next_event_us >= t_end, \
            f"{name}: next event {done.next_event_us} us reported before the window end {t_end} us"
        return done

    def run(self, inputs: list[Input], jump: bool) -> Result:
        """Every window to END_US (or, with ``jump``, only those the reports and inputs call for)."""
        pending = sorted(inputs, key=lambda i: i.t_us)
        assert all(i.t_us >= W for i in pending), "inputs are sent in an earlier window: t_us >= W"
        i, k, t_start = 0, 0, 0
        while t_start < END_US:
            data = []
            while i < len(pending) and pending[i].t_us < t_start + W:
                assert pending[i].t_us >= t_start, "the conductor jumped over an input"
                data.append((keys.data(RUN, pending[i].plane, self.case.name, pending[i].src),
                             self.message(pending[i], k - 1)))
                i += 1
            done = self.window(k, t_start, data)
            if done.error:
                self.result.error = done.error
                break
            k += 1
            t_end = t_start + W
            if not jump:
                t_start = t_end
                continue
            nexts = [t for t in (done.next_event_us, done.earliest_sent_us) if t is not None]
            if i < len(pending):
                nexts.append(pending[i].t_us)
            t_start = min(nexts) // W * W if nexts else END_US
        self.result.windows = k
        self.result.outputs = [(m.t_us, m.src, m.dst, m.seq, m.plane, m.kind, msgspec.msgpack.decode(m.body), m.blob)
                               for m in self.sent]
        return self.result

    def stop(self) -> Result:
        if self.result.error is None:
            self.bus.publish(keys.stop(RUN), Stop(reason="completed", t_us=END_US).encode())
            self.result.stopped = Stopped.decode(self._wait("stopped"))
        self.thread.join(ANSWER_S)
        assert not self.thread.is_alive(), f"{self.case.name} did not leave"
        return self.result


def drive(case: Case, results_dir: Path, arrival_seed: int, jump: bool,
          inputs: list[Input] | None = None) -> Result:
    conductor = ScriptedConductor(case, results_dir, arrival_seed)
    conductor.run(case.inputs(conductor.sc) if inputs is None else inputs, jump)
    return conductor.stop()


def parts(results_dir: Path) -> dict[str, PartInfo]:
    out = {}
    for path in sorted((results_dir / "tables").glob("*.arrows")):
        info = PartInfo()
        for _ in read_part(path, info):
            pass
        out[path.name] = info
    return out


# ---- the suite -----------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES, ids=str)
def test_window_protocol_determinism_and_next_events(case: Case, tmp_path: Path) -> None:
    first = drive(case, tmp_path / "a", arrival_seed=1, jump=False)
    assert first.error is None and first.exit_code == 0, first.error
    assert first.outputs, f"{case.name}: the script made it send nothing"
    again = drive(case, tmp_path / "b", arrival_seed=2, jump=False)
    assert again.outputs == first.outputs, f"{case.name}: outputs depend on arrival order or chance"
    assert first.stopped and again.stopped and again.stopped.trace_hash == first.stopped.trace_hash
    jumped = drive(case, tmp_path / "c", arrival_seed=3, jump=True)
    assert jumped.error is None, jumped.error
    assert jumped.outputs == first.outputs, f"{case.name}: its next-event reports skip events"
    assert jumped.windows <= first.windows
    # Records were streamed and closed; both runs wrote the same rows.
    written = parts(tmp_path / "a")
    assert all(p.complete and p.error is None for p in written.values()), written
    assert {n: p.rows for n, p in written.items()} == {n: p.rows for n, p in parts(tmp_path / "b").items()}
    assert first.stopped.summary["records"] == {
        n.removesuffix(f"-{case.name}.arrows"): p.rows for n, p in written.items()}


def _first(case: Case) -> Input:
    return min(case.inputs(case.scenario()), key=lambda i: i.t_us)


@pytest.mark.parametrize("fault", ["unexpected kind", "malformed body"])
@pytest.mark.parametrize("case", CASES, ids=str)
def test_a_message_it_cannot_handle_fails_it_naming_federate_and_kind(case: Case, fault: str,
                                                                     tmp_path: Path) -> None:
    good = _first(case)
    kind = "bogus" if fault == "unexpected kind" else good.kind
    bad = Input(good.t_us, "intruder", good.plane, kind, {})
    result = drive(case, tmp_path, arrival_seed=1, jump=False, inputs=[bad])
    assert result.error is not None, f"{case.name} accepted a {fault} message"
    assert case.name in result.error and repr(kind) in result.error, result.error
    assert result.exit_code == 1


def test_a_malformed_bundle_fails_it_naming_federate(tmp_path: Path) -> None:
    loops = next(c for c in CASES if c.name == "loops")
    bad = Input(W, "netsim", "net", "bundle", {"items": [["aframe"]]})
    result = drive(loops, tmp_path, arrival_seed=1, jump=False, inputs=[bad])
    assert result.error is not None and "loops" in result.error and "malformed bundle" in result.error
    assert result.exit_code == 1


def test_netsim_takes_a_frame_as_one_message_and_bundles_deliveries(tmp_path: Path) -> None:
    """A ``packets`` message enters one packet per size, and its packets delivered in one slot
    are one item; deliveries without payload bytes reach each destination as one bundle per
    delivery time, those with bytes one by one."""
    netsim = next(c for c in CASES if c.name == "netsim")
    result = drive(netsim, tmp_path, arrival_seed=1, jump=False)
    assert result.error is None, result.error
    to_loops = [o for o in result.outputs if o[2] == "loops"]
    assert to_loops and all(o[5] in ("bundle", "aframe") for o in to_loops)
    items = [b for o in to_loops for b in ([["aframe", o[6]]] if o[5] == "aframe" else o[6]["items"])]
    frames: dict[int, list[int]] = {}
    for kind, body in items:
        assert kind == "aframe" and body["n"] == 2 and len(body["idx"]) == len(body["packet_ids"])
        frames.setdefault(body["frame_id"], []).extend(body["idx"])
    assert frames and all(sorted(ix) == [0, 1] for ix in frames.values()), frames
    merged = [body for _, body in items if len(body["idx"]) == 2]
    assert merged, "a frame's packets delivered in one slot are one item"
    times = [o[0] for o in to_loops]
    assert len(times) == len(set(times)), "one bundle per destination and delivery time"
    to_edge = [o for o in result.outputs if o[2] == "edge"]
    assert to_edge and all(o[5] == "frame" and o[7] for o in to_edge), "payload bytes travel one by one"


@pytest.mark.parametrize("case", CASES, ids=str)
def test_undecodable_bytes_fail_it_naming_federate(case: Case, tmp_path: Path) -> None:
    conductor = ScriptedConductor(case, tmp_path, arrival_seed=1)
    plane = _first(case).plane
    key = keys.data(RUN, plane, case.name, "intruder")
    done = conductor.window(0, 0, [(key, b"\x93not a message")])
    assert done.error is not None and case.name in done.error and "undecodable data message" in done.error
    conductor.result.error = done.error
    assert conductor.stop().exit_code == 1


@pytest.mark.parametrize("case", CASES, ids=str)
def test_it_leaves_with_its_records_when_the_coordinator_vanishes(case: Case, tmp_path: Path) -> None:
    conductor = ScriptedConductor(case, tmp_path, arrival_seed=1)
    inputs = [i for i in case.inputs(conductor.sc) if i.t_us < 30_000]
    pending = sorted(inputs, key=lambda i: i.t_us)
    for k in range(30):
        data = [(keys.data(RUN, i.plane, case.name, i.src), conductor.message(i, k - 1))
                for i in pending if k * W <= i.t_us < (k + 1) * W]
        assert conductor.window(k, k * W, data).error is None
    conductor.bus.close()  # the coordinator's token vanishes with its session
    conductor.thread.join(10)
    assert not conductor.thread.is_alive(), f"{case.name} outlived its coordinator"
    assert conductor.result.exit_code == EXIT_ORPHANED
    assert all(p.complete for p in parts(tmp_path).values())


def test_a_federate_that_never_sees_a_coordinator_leaves(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(driver_mod, "COORDINATOR_WAIT_S", 0.2)
    fed = Federate(FederateContext("lonely", RUN, tiny_scenario(), tmp_path), InMemoryBus(InMemoryHub()))
    assert WindowDriver(fed).serve() == EXIT_ORPHANED


class HidesItsNextEvent(Federate):
    """Sends a message every 5 ms but reports no next event: wrong, and the suite must say so."""

    def setup(self) -> None:
        self.schedule(W, self.tick)

    def tick(self) -> None:
        self.send("netsim", self.now + W, Ping())
        self.schedule(self.now + 5 * W, self.tick)

    def process_window(self, adv: Advance) -> WindowReport:
        return dataclasses.replace(super().process_window(adv), next_event_us=None)


def test_the_suite_catches_a_federate_that_hides_its_next_event(tmp_path: Path) -> None:
    case = Case("hider", HidesItsNextEvent, lambda sc: [])
    stepped = drive(case, tmp_path / "a", arrival_seed=1, jump=False)
    jumped = drive(case, tmp_path / "b", arrival_seed=1, jump=True)
    assert len(stepped.outputs) == END_US // (5 * W)
    assert jumped.outputs != stepped.outputs


def test_an_edge_keeping_the_newest_frame_drops_the_one_waiting_for_its_cpu(tmp_path: Path) -> None:
    frames = len(frame_times(tiny_scenario(), 8000))
    newest = drive(EDGE_NEWEST, tmp_path / "newest", arrival_seed=1, jump=False)
    fifo = drive(Case("edge", EdgeFederate, edge_burst_inputs), tmp_path / "fifo", arrival_seed=1, jump=False)
    assert newest.stopped and fifo.stopped
    kept, every = newest.stopped.summary, fifo.stopped.summary
    # Of each three frames complete at once the second is dropped for the third.
    assert every["frames_estimated"] == frames and every["frames_superseded"] == 0
    assert kept["frames_superseded"] == frames // 3
    assert kept["frames_estimated"] + kept["frames_waiting"] == frames - frames // 3
    # Every complete frame has its row either way: estimated, dropped or waiting at the end.
    assert kept["records"]["frames"] == every["records"]["frames"] == frames, kept["records"]
