"""The scenario schema: everything a run needs, validated before anything starts.

Unknown fields are rejected, units are in field names, every field has a description, and the
cross-field rules of the time contract (every cross-federate latency >= the window) are checked
here, so the CLI and the REST API reject the same mistakes with the same messages.
"""

from __future__ import annotations

import copy
import math
import reprlib
import warnings
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from scenario.lattice import GNB_COUNTS, lattice_points_m, lattice_subset
from scenario.nr import NrConfig, bounded_int


class Strict(BaseModel):
    # No field takes an infinite or NaN number: a limit, a rate or a timeout must be a finite one.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _bounded_ints(cls, v: Any) -> Any:  # as NrConfig's: integers below 2**53
        return bounded_int(v)


class JobModel(Strict):
    """Distribution of a job's emulated duration in ``model`` timing (a normal, clipped at a tenth
    of its mean)."""

    mean_us: int = Field(gt=0, description="mean emulated duration, microseconds")
    sd_us: int = Field(default=0, ge=0, description="standard deviation, microseconds")


# The compute jobs of a run (docs/architecture.md sec. 5), the kinds a node's model_us may time.
JOB_KINDS = ("compress", "pose", "policy", "control")


class NodeProfile(Strict):
    """A compute node's capacity and how its job durations are obtained (docs/architecture.md sec. 5, docs/compute.md).

    ``cpus`` count reference cores, not this host's: each host scores its own speed against the
    reference core (fabric/host_speed.py) and job CPU times are scaled by it, so one
    scenario gives the same compute latencies on any host."""

    cpus: float = Field(ge=0.001, le=64, description="speed in reference cores (fabric/data/"
                        "reference_core.json): 0.25 is a quarter of the reference core on any host; "
                        "in the docker runtime also the container's CPU quota, in host cores")
    mem_mb: int = Field(default=1024, ge=64, description="memory limit, MiB")
    timing: Literal["wall", "cpu", "model"] = Field(
        default="cpu", description="cpu: the job's own CPU time (its thread and library workers) "
        "x host speed / cpus; wall: wall time in the node's CPU-limited cgroup (docker runtime; "
        "refused for jobs shorter than 5 CFS periods); model: seeded draw (host-independent)"
    )
    model_us: dict[str, JobModel] = Field(
        default_factory=dict, description="per job kind, the duration distribution in model timing, "
        "absolute (cpus does not scale it); a kind not given draws from its work fitted from measured "
        "jobs (fabric/data/job_models.json) over cpus"
    )


class Nodes(Strict):
    """Compute node profiles, in reference cores; ``model`` timing falls back to the platform's
    measured job models."""

    camera: NodeProfile = Field(default_factory=lambda: NodeProfile(cpus=0.25, mem_mb=512),
                                description="camera node profile")
    edge: NodeProfile = Field(default_factory=lambda: NodeProfile(cpus=1.0, mem_mb=2048),
                              description="Edge node profile")
    robot: NodeProfile = Field(default_factory=lambda: NodeProfile(cpus=0.25, mem_mb=512),
                               description="robot node profile")

    @model_validator(mode="after")
    def _job_kinds(self) -> Nodes:
        for node in ("camera", "edge", "robot"):
            unknown = [k for k in getattr(self, node).model_us if k not in JOB_KINDS]
            if unknown:
                raise ValueError(f"nodes.{node}.model_us: {_given(unknown[0])} is not a job kind; "
                                 f"job kinds: {', '.join(JOB_KINDS)}")
        return self


# gNB height of each InF sub-scenario, TR 38.901 Table 7.8-7 (netsim/nr/layout.py holds the whole
# table; tests/unit/nr/test_layout.py keeps the two equal).
INF_BS_HEIGHT_M = {"SL": 1.5, "DL": 1.5, "SH": 8.0, "DH": 8.0}
# Path loss compensation factors alpha of TS 38.213 7.1.1 (TS 38.331 Alpha).
UL_ALPHAS = (0.0, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


class InfLayoutConfig(Strict):
    """Several gNBs in the hall (docs/netsim.md, "Several gNBs in one hall"): a TR 38.901 InF
    sub-scenario for the propagation, a subset of its 6 x 3 gNB lattice or explicit positions,
    the frequency reuse and the UL open-loop power control (TS 38.213 7.1.1)."""

    sub_scenario: Literal["SL", "DL", "SH", "DH"] = Field(
        default="SL", description="InF sub-scenario (TR 38.901 Table 7.2-4): sparse/dense clutter, "
        "low (1.5 m)/high (8 m) gNB; sets path loss, LOS probability, shadowing and gNB height")
    gnb_count: int = Field(
        default=18, description="gNBs taken from the 6 x 3 lattice (pitch length/6 x width/3, "
        "half a pitch from the walls): 1, 2, 4, 6, 9 or 18 (docs/netsim.md lists which points); "
        "ignored with gnb_positions_m")
    gnb_positions_m: list[tuple[float, float, float]] | None = Field(
        default=None, min_length=1, description="explicit gNB positions (x, y, z), metres; "
        "replaces the lattice")
    reuse: Literal[1, 3] = Field(
        default=1, description="frequency reuse: 1 (every gNB on the whole carrier) or 3 (three "
        "groups on a third each)")
    ul_p0_dbm: float = Field(
        default=-90.0, ge=-202, le=24, description="UL power control P0, target received power "
        "per PRB, dBm (TS 38.331 p0-NominalWithGrant range -202..24)")
    ul_alpha: float = Field(
        default=1.0, description="UL power control path loss compensation alpha: 0, 0.4, 0.5, "
        "0.6, 0.7, 0.8, 0.9 or 1")

    @field_validator("gnb_count")
    @classmethod
    def _lattice_subset(cls, count: int) -> int:
        if count not in GNB_COUNTS:
            raise ValueError(
                f"gnb_count = {count} is not a subset of the 6 x 3 gNB lattice: allowed "
                f"{', '.join(map(str, GNB_COUNTS))}, or list the positions in gnb_positions_m")
        return count

    @field_validator("ul_alpha")
    @classmethod
    def _ts38213_alpha(cls, alpha: float) -> float:
        if alpha not in UL_ALPHAS:
            raise ValueError(f"ul_alpha = {alpha:g} is not a TS 38.213 alpha: allowed "
                             f"{', '.join(f'{a:g}' for a in UL_ALPHAS)}")
        return alpha


# The floor a work cell takes (m, along x and y): its belt (1.2 m long), the arm on its pedestal
# 0.55 m off the belt axis with the reach of a UR5e-class arm, and the platform (domain/work_cell.py).
# Work cells nearer than this overlap: their arms, which do not collide with each other, would
# reach through each other's belts.
WORK_CELL_FOOTPRINT_M = 2.0


class HallConfig(Strict):
    """The factory hall and where the work cells and the gNB stand in it (gives netsim its UE
    positions)."""

    length_m: float = Field(default=120.0, gt=0, le=1000, description="hall length (x), metres")
    width_m: float = Field(default=60.0, gt=0, le=1000, description="hall width (y), metres")
    height_m: float = Field(default=10.0, gt=0, le=100, description="hall height, metres")
    gnb_position_m: tuple[float, float, float] = Field(
        default=(60.0, 30.0, 1.5), description="gNB (and Edge) position, metres"
    )
    work_cell_pitch_m: tuple[float, float] = Field(
        default=(8.0, 8.0), description="distance between neighbouring work cells along x and y, metres"
    )
    work_cells_per_row: int = Field(default=8, ge=1, description="work cells per row along x")
    work_cell_fill: Literal["centre", "gnbs"] = Field(
        default="centre", description="where the loops' work cells stand: `centre`, one grid of "
        "work_cells_per_row a row centred on gnb_position_m, filled row by row; `gnbs` (with "
        "inf_layout), dealt to the gNBs in turn (work cell i to gNB i mod their number), each "
        "gNB's in rows of work_cells_per_row on both sides of it, nearest first, so that any load "
        "spreads over every gNB")
    ue_height_m: float = Field(default=1.5, gt=0, description="camera and robot modem height")
    inf_layout: InfLayoutConfig | None = Field(
        default=None, description="several gNBs on a TR 38.901 InF layout; none: the one gNB at "
        "gnb_position_m")

    @field_validator("work_cell_pitch_m")
    @classmethod
    def _pitch_positive(cls, pitch: tuple[float, float]) -> tuple[float, float]:
        if min(pitch) <= 0:
            raise ValueError(f"work_cell_pitch_m = ({pitch[0]:g}, {pitch[1]:g}) m: each must be positive "
                             f"(at least {WORK_CELL_FOOTPRINT_M:g} m where two work cells stand along it)")
        return pitch

    @model_validator(mode="after")
    def _gnbs_in_hall(self) -> HallConfig:
        layout = self.inf_layout
        size = f"0..{self.length_m:g} x 0..{self.width_m:g} x 0..{self.height_m:g} m"

        def inside(x: float, y: float, z: float) -> bool:
            return 0 <= x <= self.length_m and 0 <= y <= self.width_m and 0 <= z <= self.height_m

        if layout is None:
            if self.work_cell_fill == "gnbs":
                raise ValueError("hall.work_cell_fill = gnbs places the work cells around several "
                                 "gNBs: set hall.inf_layout, or work_cell_fill = centre")
            if not inside(*self.gnb_position_m):
                x, y, z = self.gnb_position_m
                raise ValueError(f"hall.gnb_position_m = ({x:g}, {y:g}, {z:g}) is outside the hall ({size})")
            return self
        for i, (x, y, z) in enumerate(layout.gnb_positions_m or ()):
            if not inside(x, y, z):
                raise ValueError(
                    f"hall.inf_layout.gnb_positions_m[{i}] = ({x:g}, {y:g}, {z:g}) m lies outside "
                    f"the hall ({size}): every gNB must stand inside it")
        height = INF_BS_HEIGHT_M[layout.sub_scenario]
        if layout.gnb_positions_m is None and height > self.height_m:
            raise ValueError(
                f"hall.inf_layout.sub_scenario = {layout.sub_scenario} puts the gNBs at "
                f"{height:g} m, above hall.height_m = {self.height_m:g}: raise the hall or take a "
                f"low-gNB sub-scenario (SL, DL)")
        return self

    def gnb_positions(self) -> list[tuple[float, float, float]]:
        """Where the gNBs stand, metres: ``inf_layout``'s (its positions, or its lattice subset at
        the sub-scenario's BS height), else the one gNB at ``gnb_position_m``."""
        layout = self.inf_layout
        if layout is None:
            return [self.gnb_position_m]
        if layout.gnb_positions_m is not None:
            return list(layout.gnb_positions_m)
        points = lattice_points_m(self.length_m, self.width_m, INF_BS_HEIGHT_M[layout.sub_scenario])
        return [points[k] for k in lattice_subset(layout.gnb_count)]

    def work_cell_origins(self, n: int) -> list[tuple[float, float]]:
        """Work cell centres (``work_cell_fill``): one row-major grid of ``work_cells_per_row`` a
        row centred on the gNB, or work cell i at gNB i mod G, in rows around it."""
        if self.work_cell_fill == "centre":
            return self._grid(n, (self.gnb_position_m[0], self.gnb_position_m[1]))
        gnbs = self.gnb_positions()
        px, py = self.work_cell_pitch_m
        per_row = self.work_cells_per_row
        # Nearest first, so that a light load sits next to its gNB: columns from the middle of the
        # row outwards, rows alternately above and below the gNB, which stands in the aisle
        # between the first two (never under a work cell). A work cell's place does not depend on
        # how many there are.
        columns = sorted((j - (per_row - 1) / 2 for j in range(per_row)), key=lambda o: (abs(o), -o))
        out = []
        for i in range(n):
            x, y, _ = gnbs[i % len(gnbs)]
            row, column = divmod(i // len(gnbs), per_row)
            side = 1 if row % 2 == 0 else -1
            out.append((x + columns[column] * px, y + side * (row // 2 + 0.5) * py))
        return out

    def _grid(self, n: int, centre: tuple[float, float]) -> list[tuple[float, float]]:
        rows = math.ceil(n / self.work_cells_per_row)
        px, py = self.work_cell_pitch_m
        per_row = min(n, self.work_cells_per_row)
        x0 = centre[0] - (per_row - 1) * px / 2
        y0 = centre[1] - (rows - 1) * py / 2
        return [(x0 + (i % self.work_cells_per_row) * px, y0 + (i // self.work_cells_per_row) * py)
                for i in range(n)]


AGV_SPEED_RANGE_M_S = (0.5, 2.0)


class AgvConfig(Strict):
    """Automated guided vehicles: moving radios driving closed routes over the hall floor, each
    with an uplink video and a downlink control stream (docs/netsim.md, "Mobility and
    handover"). They need several gNBs (``hall.inf_layout``)."""

    count: int = Field(default=0, ge=0, le=128, description="number of AGVs; 0: none")
    speed_m_s: float = Field(default=1.0, description="driving speed of every AGV, m/s "
                             "(0.5 to 2)")
    waypoints_m: list[tuple[float, float]] | None = Field(
        default=None, min_length=2, description="one closed route (x, y) on the hall floor, "
        "metres, driven by every AGV, spaced evenly along it; none: rectangular loops along the "
        "aisles around the rows of work cells, AGVs shared out over them")
    ul_rate_mbps: float = Field(default=8.5, gt=0, le=1000, description="uplink video of each "
                                "AGV, Mbit/s (default: one work cell's camera stream)")
    dl_rate_mbps: float = Field(default=0.096, gt=0, le=1000, description="downlink control "
                                "stream of each AGV, Mbit/s (default: 100 pose-sized packets/s)")
    ul_packet_bytes: int = Field(default=1500, ge=40, le=9000,
                                 description="IP size of an uplink video packet, bytes")
    dl_packet_bytes: int = Field(default=120, ge=40, le=9000,
                                 description="IP size of a downlink control packet, bytes")
    delay_budget_ms: float | None = Field(default=150.0, ge=0.001, le=10000, description="packet "
                                          "delay budget of both streams, ms (whole microseconds "
                                          "at least): older packets are "
                                          "discarded at the sender (default 150: 5QI 2's "
                                          "live video budget, TS 23.501 Table 5.7.4-1); none: none")

    @field_validator("waypoints_m")
    @classmethod
    def _route_has_length(cls, points: list[tuple[float, float]] | None
                          ) -> list[tuple[float, float]] | None:
        if points is not None and len(set(points)) < 2:
            raise ValueError("waypoints_m needs at least two different points: a route to drive")
        return points

    @field_validator("speed_m_s")
    @classmethod
    def _agv_speed(cls, speed: float) -> float:
        lo, hi = AGV_SPEED_RANGE_M_S
        if not lo <= speed <= hi:
            raise ValueError(f"speed_m_s = {speed:g} m/s is outside the AGV speeds: allowed "
                             f"{lo:g} to {hi:g} m/s")
        return speed


class WorkCellConfig(Strict):
    """One work cell: a conveyor belt bringing parts, its arm's pick zone (one control loop)."""

    belt_speed_m_s: float = Field(default=0.2, ge=0.01, le=1.0, description="belt speed, m/s")
    object_period_s: float = Field(default=4.0, gt=0.5, le=3600, description="time between objects, s")
    object_jitter_s: float = Field(default=0.0, ge=0, description="uniform jitter on spawn times, s")
    first_object_s: float = Field(default=0.5, ge=0, le=86400, description="spawn time of the first object, s")
    first_object_spread_s: float = Field(
        default=0.0, ge=0, le=86400, description="each cell's first object comes later by uniform(0, this), drawn "
        "per cell, s: belts out of phase (0: every belt's first object at first_object_s)"
    )
    object_size_m: float = Field(default=0.06, gt=0.02, le=0.15, description="object edge length, m")
    object_mass_kg: float = Field(default=0.3, gt=0, le=5.0, description="object mass, kg")
    object_size_spread_m: float = Field(
        default=0.0, ge=0, description="each object's edge length is object_size_m + uniform(+-this), m"
    )
    object_mass_spread_kg: float = Field(
        default=0.0, ge=0, description="each object's mass is object_mass_kg + uniform(+-this), kg"
    )
    object_yaw_spread_deg: float = Field(
        default=0.0, ge=0, le=180, description="each object lies on the belt at yaw uniform(+-this), deg"
    )
    object_lateral_spread_m: float = Field(
        default=0.03, ge=0, le=0.1, description="objects land uniform(+-this) across the belt axis, m"
    )

    @model_validator(mode="after")
    def _jitter_fits(self) -> WorkCellConfig:
        if self.object_jitter_s >= self.object_period_s / 2:
            raise ValueError(
                f"object_jitter_s ({self.object_jitter_s}) must be below half object_period_s "
                f"({self.object_period_s}) so that objects keep their order"
            )
        return self

    @model_validator(mode="after")
    def _spreads_fit(self) -> WorkCellConfig:
        size, ds = self.object_size_m, self.object_size_spread_m
        if size - ds <= 0.02 or size + ds > 0.15:
            raise ValueError(
                f"object_size_m +- object_size_spread_m ({size} +- {ds}) must stay within (0.02, 0.15] m; "
                f"lower object_size_spread_m"
            )
        if self.object_mass_spread_kg >= self.object_mass_kg or self.object_mass_kg + self.object_mass_spread_kg > 5.0:
            raise ValueError(
                f"object_mass_kg +- object_mass_spread_kg ({self.object_mass_kg} +- "
                f"{self.object_mass_spread_kg}) must stay within (0, 5] kg; lower object_mass_spread_kg"
            )
        return self


# Which frames a camera keeps at its PDP (domain/frame_keep.py).
FrameKeepMode = Literal["bernoulli", "spaced"]


class CameraConfig(Strict):
    """The cell cameras: a D435-class RGB-D sensor and the camera node's compression.

    The defaults give about 35 kB per frame, 8.5 Mbit/s per loop at 30 frame/s, with the sensor
    model on (measured by ``python tools/measure_frames.py``, docs in docs/perception.md)."""

    fps: int = Field(default=30, ge=1, le=90, description="frames per second")
    width_px: int = Field(default=640, ge=64, le=1920, description="image width, pixels")
    height_px: int = Field(default=360, ge=48, le=1080, description="image height, pixels")
    fovy_deg: float = Field(default=58.0, gt=10, lt=120, description="vertical field of view, deg")
    jpeg_quality: int = Field(default=84, ge=10, le=100, description="JPEG quality of the RGB image")
    depth_codec: Literal["delta-zlib", "png"] = Field(
        default="delta-zlib", description="lossless depth codec: `delta-zlib` (2-D difference + zlib, "
        "smallest at PNG's CPU cost) or `png` (16-bit PNG, level 1)")
    depth_decimation: Literal[1, 2, 4] = Field(
        default=4, description="depth decimation filter on the camera node (RealSense SDK semantics): "
        "depth is sent at 1/this of the colour resolution per axis")
    sensor_model: Literal["d435", "ideal"] = Field(
        default="d435", description="`d435`: stereo depth noise growing with distance squared, invalid "
        "pixels (left band, occlusion shadows, depth edges), colour shot and read noise "
        "(domain/sensor.py); `ideal`: the rendered images as they are")
    depth_subpixel_px: float = Field(
        default=0.08, ge=0, le=1.0, description="`d435`: stereo disparity error sd, px (RMS depth error "
        "= z^2 * this / (focal px * 50 mm baseline))")
    depth_noise_mm: float = Field(
        default=0.0, ge=0, le=100, description="extra white depth noise sd at 1 m added by the physics renderer, "
        "mm, on top of `sensor_model` (noise makes 16-bit depth nearly incompressible)")
    readout_latency_us: int = Field(default=2000, ge=1, description="capture to camera node, us")
    mtu_bytes: int = Field(default=1500, ge=576, le=9000, description="IP packet size limit, bytes")
    frame_keep: FrameKeepMode = Field(
        default="bernoulli", description="which frames the camera keeps at its PDP: `bernoulli`, each "
        "independently with probability PDP; `spaced`, a share PDP of them spread evenly (a credit "
        "of the PDPs, started at a random phase; domain/frame_keep.py)")


class RobotConfig(Strict):
    control_period_us: int = Field(default=10000, ge=1000, description="controller period, us")
    state_latency_us: int = Field(default=1000, ge=1, description="joint state physics->robot, us")
    actuation_latency_us: int = Field(default=1000, ge=1, description="robot->physics command, us")
    max_estimate_age_ms: float = Field(
        default=400.0, ge=1, le=60_000, description="older pose estimates make the arm hold back"
    )
    delay_compensation: bool = Field(
        default=True, description="predict the object to now from the estimate's capture time"
    )


class EdgeConfig(Strict):
    estimator: Literal["learned", "classical"] = Field(
        default="learned", description="pose estimator: `learned` (a small CNN trained on rendered "
        "frames, domain/models/pose.onnx, run with ONNX Runtime; falls back to `classical` "
        "with a logged reason when the model is missing) or `classical` (colour segmentation)")
    policy_period_ms: int = Field(default=50, ge=1, description="co-design policy period, ms")
    pose_packet_bytes: int = Field(default=120, ge=40, le=9000, description="IP size of a pose packet")
    qos_packet_bytes: int = Field(default=60, ge=40, le=9000, description="IP size of a QoS packet")
    placement: Literal["per_gnb", "central"] = Field(
        default="per_gnb", description="where the Edges stand with several gNBs "
        "(`hall.inf_layout`): `per_gnb`, an Edge at each gNB for the loops whose camera it serves, "
        "each with its own load control and policy state; `central`, one Edge for every loop, "
        "reached over a backhaul of `backhaul_ms` (docs/architecture.md sec. 7). With one gNB "
        "both give one Edge, `central` behind the backhaul")
    backhaul_ms: float = Field(
        default=1.0, ge=0, le=1000, description="`central`: one-way latency of the backhaul "
        "between a gNB and the Edge, ms: every uplink frame reaches the Edge this long after its "
        "gNB delivered it, every downlink packet enters its gNB this long after the Edge sent it "
        "(0 to 1000); ignored with `per_gnb`")
    abstract_compute: Literal["per_loop", "shared"] = Field(
        default="per_loop", description="where the abstract loops' Edge jobs (pose, policy) run: "
        "`per_loop`, each loop's on a node of its own of nodes.edge.cpus, so that no loop waits for "
        "another's (an Edge that grows with its loops: the radio cell is what limits them); "
        "`shared`, every abstract loop of an Edge on that Edge's one node, queueing as the detailed "
        "loops do in the Edge federate (the Edge's compute limits them too)")
    pose_queue: Literal["fifo", "newest"] = Field(
        default="fifo", description="which frames an Edge estimates when its CPU falls behind: "
        "`fifo`, every complete frame, in the order they came in, however long it waits; `newest`, "
        "at most one frame per loop waits for the CPU, a newer one taking its place (the older "
        "dropped, counted as lost), as a pipeline that keeps each camera's latest image "
        "(docs/compute.md, \"Which frames a busy Edge estimates\")")


class PolicyConfig(Strict):
    """The co-design policy (docs/architecture.md sec. 7)."""

    name: Literal["none", "fixed", "heuristic", "learned"] = Field(
        default="none", description="policy: `none` (PDP 1, no budget), `fixed` (constant `pdp`), "
        "`heuristic` (rules on the belt's kinematics and the tracker's sd, domain/policy.py) or "
        "`learned` (a network trained with deep RL, run with ONNX Runtime: `learned_model`)")
    pdp: float = Field(default=1.0, gt=0, le=1, description="`fixed`: the PDP it asks for; like every "
                       "co-design policy's, it is raised to 1 while the cell has headroom and bounded "
                       "by the floor and the cap, so a PDP held constant also needs `headroom`, "
                       "`floor` and `guard` false")
    idle_pdp: float = Field(default=0.2, gt=0, le=1,
                            description="`heuristic`: PDP while the belt is empty and no part is due")
    track_pdp: float = Field(default=0.5, gt=0, le=1,
                             description="`heuristic`: lowest PDP while a part is tracked upstream")
    approach_s: float = Field(default=1.0, gt=0, description="`heuristic`: PDP 1 from this long (in "
                              "belt travel time) before a part reaches the pick window")
    stale_ms: float = Field(default=150.0, gt=0, description="`heuristic`: an upstream part's estimate "
                            "older than this is refreshed before the part's approach starts")
    latency_budget_ms: float = Field(default=100.0, ge=1.0, le=10_000,
                                     description="L_r signalled with the PDP (`fixed`, `heuristic`); at "
                                     "least a slot (1 ms): a packet waits for a slot boundary and is "
                                     "delivered at a slot end")
    learned_model: str | None = Field(
        default=None, min_length=1, description="`learned`: the ONNX model (its model card, the .json beside it, "
        "must be there too); default domain/models/policy.onnx, made by `make train-policy`")
    load_feature: Literal["live", "idle"] = Field(
        default="live", description="`learned`: the load its network observes (the cell's queueing delay "
        "at the Edge): `live`, as measured; `idle`, frozen at an idle cell's (no queueing delay), an "
        "ablation of how much its choices read the load (the floor and the load control still see it)")
    signalling: Literal["app", "lower"] = Field(
        default="app", description="how the QoS reaches the network: `app`, to the camera only, as "
        "application data over the downlink (the camera drops frames by PDP, stamps the budget on "
        "its packets); `lower`, to the gNB as well, as a MAC-level control message, and the "
        "scheduler weighs each UE by the urgency of its budget (docs/netsim.md)")
    controls: Literal["both", "pdp", "budget"] = Field(
        default="both", description="which part of the policy's QoS is applied (an ablation): "
        "`both`; `pdp` (the PDP only: no latency budget, so no packet is discarded late and the "
        "scheduler sees no urgency); `budget` (the budget only: PDP 1, every frame sent, stale "
        "packets discarded)")
    control_latency_us: int = Field(
        default=1000, ge=0, le=100_000, description="`lower`: latency of the control message from "
        "the Edge's policy to the gNB's scheduler (both in the gNB site), us")
    floor: bool = Field(
        default=True, description="bound every co-design policy's PDP (all but `none`) by the safety "
        "floor from the work cell's kinematics, the tracker's state and the uplink's delay and loss "
        "(domain/safety_floor.py); false for ablations")
    floor_risk: float = Field(
        default=0.01, gt=0, lt=0.5, description="the floor's accepted chance that no useful frame "
        "comes before one of its deadlines")
    headroom: bool = Field(
        default=True, description="let every co-design policy's loops (all but `none`) send at PDP 1 "
        "while the radio cell has headroom, as the Edge sees it in the queueing delay of the frames "
        "it receives (domain/congestion.py): traffic is saved only where that buys capacity; false "
        "for ablations")
    headroom_delay_ms: float = Field(
        default=25.0, gt=0, le=1000, description="`headroom`: the cell has headroom while the smoothed "
        "queueing delay of the frames at the Edge (delay above each loop's smallest) stays under "
        "this, ms (under 20 up to the cell's capacity, where PDP 1 still places every task; "
        "hundreds past it)")
    guard: bool = Field(
        default=True, description="cap every co-design policy's PDP (all but `none`) when the queueing "
        "delay or the loss of the frames at the Edge says the radio cell is past capacity "
        "(domain/congestion.py): past capacity the cap wins over the floor; false for ablations")
    guard_delay_ms: float = Field(
        default=60.0, gt=0, le=1000, description="`guard`: the cap falls while the smoothed queueing "
        "delay of the frames at the Edge exceeds this, ms")
    guard_min_pdp: float = Field(default=0.1, gt=0, le=1, description="`guard`: the cap never falls below this; "
                                 "past it the guard sheds loops instead")
    guard_start_pdp: float = Field(
        default=0.1, gt=0, le=1, description="`guard`: the cap a run starts from, doubled every policy "
        "period until the first sign of congestion (stalled frames too) or 1 (a slow start: the Edge "
        "knows nothing of the cell's capacity yet); at least `guard_min_pdp`; 1: every loop starts at PDP 1")

    @model_validator(mode="after")
    def _start_above_least(self) -> PolicyConfig:
        if self.guard_start_pdp < self.guard_min_pdp:
            raise ValueError(f"guard_start_pdp ({self.guard_start_pdp:g}) must be at least "
                             f"guard_min_pdp ({self.guard_min_pdp:g}): the cap never falls below that")
        return self


# TS 38.331 TimeToTrigger (ms) and FilterCoefficient (k of the layer-3 filter) values.
TIME_TO_TRIGGER_MS = (0, 40, 64, 80, 100, 128, 160, 256, 320, 480, 512, 640, 1024, 1280, 2560,
                      5120)
FILTER_COEFFICIENTS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 13, 15, 17, 19)


def _half_db(name: str, value: float) -> float:
    """TS 38.331 signals offsets and hysteresis in steps of 0.5 dB."""
    if (2 * value) != round(2 * value):
        raise ValueError(f"{name} = {value:g} dB is not a multiple of 0.5 dB (TS 38.331 step)")
    return value


class HandoverConfig(Strict):
    """Handover of moving radios between the gNBs of ``hall.inf_layout`` (docs/netsim.md,
    "Mobility and handover"): layer-3 filtered RSRP (TS 38.331 5.5.3.2), event A3 held for the
    time to trigger (5.5.4.4), then an interruption with the held packets forwarded or lost."""

    filter_k: int = Field(default=4, description="layer-3 filter coefficient k, a = 1/2^(k/4) "
                          "(TS 38.331 filterCoefficient: 0-9, 11, 13, 15, 17, 19; 0: no "
                          "filtering; default fc4)")
    a3_offset_db: float = Field(default=0.0, ge=-15, le=15, description="A3 offset Off, dB "
                                "(TS 38.331 a3-Offset: -15 to 15 in 0.5 dB steps)")
    hysteresis_db: float = Field(default=3.0, ge=0, le=15, description="A3 hysteresis Hys, dB "
                                 "(TS 38.331 hysteresis: 0 to 15 in 0.5 dB steps)")
    time_to_trigger_ms: int = Field(default=256, description="time the A3 entering condition "
                                    "must hold before the handover, ms (a TS 38.331 "
                                    "TimeToTrigger value)")
    interruption_ms: float = Field(default=50.0, ge=0, le=1000, description="time a UE has no "
                                   "cell during a handover, ms")
    forward: bool = Field(default=True, description="the packets held for the UE in the source "
                          "cell and those reaching it during the interruption go to the target "
                          "cell (true) or are lost (false)")
    measurement_period_ms: int = Field(default=20, ge=1, le=1000, description="time between "
                                       "two RSRP measurements of a UE (the filter's input "
                                       "rate), ms")
    measurement_noise_db: float = Field(default=0.0, ge=0, le=10, description="standard "
                                        "deviation of each RSRP measurement's error, dB")

    @field_validator("filter_k")
    @classmethod
    def _filter_coefficient(cls, k: int) -> int:
        if k not in FILTER_COEFFICIENTS:
            raise ValueError(f"filter_k = {k} is not a TS 38.331 filterCoefficient: allowed "
                             f"{', '.join(map(str, FILTER_COEFFICIENTS))}")
        return k

    @field_validator("time_to_trigger_ms")
    @classmethod
    def _time_to_trigger(cls, ttt: int) -> int:
        if ttt not in TIME_TO_TRIGGER_MS:
            raise ValueError(f"time_to_trigger_ms = {ttt} is not a TS 38.331 TimeToTrigger: "
                             f"allowed {', '.join(map(str, TIME_TO_TRIGGER_MS))} ms")
        return ttt

    @field_validator("a3_offset_db", "hysteresis_db")
    @classmethod
    def _half_db_steps(cls, value: float, info: Any) -> float:
        return _half_db(info.field_name, value)


class NetsimConfig(Strict):
    model: Literal["nr", "simple"] = Field(
        default="nr", description="cell model: `nr` (5G NR system-level: channel, HARQ, link "
        "adaptation, scheduling) or `simple` (shared capacity per slot)")
    slot_us: int = Field(default=1000, ge=125, description="slot duration, us (1000 at 15 kHz)")
    nr: NrConfig = Field(
        default_factory=NrConfig,
        description="`nr`: every NR cell parameter (scenario/nr.py); the hall size comes from `hall`")
    ul_rate_mbps: float = Field(default=178.6, gt=0, le=1e6, description="`simple`: uplink capacity, Mbit/s")
    dl_rate_mbps: float = Field(default=150.0, gt=0, le=1e6, description="`simple`: downlink capacity, Mbit/s")
    loss_probability: float = Field(default=0.0, ge=0, lt=1, description="`simple`: per-packet loss")
    buffer_bytes: int = Field(default=1_000_000, ge=1500, description="`simple`: sender buffer per UE, bytes")
    handover: HandoverConfig = Field(
        default_factory=HandoverConfig,
        description="`nr` with `hall.inf_layout`: handover of moving radios (`agvs`) between gNBs")

    @model_validator(mode="after")
    def _nr_slot(self) -> NetsimConfig:
        if self.model == "nr" and self.nr.slot_us != self.slot_us:
            raise ValueError(
                f"netsim.slot_us ({self.slot_us}) must equal the NR slot at "
                f"{self.nr.subcarrier_spacing_hz} Hz SCS ({self.nr.slot_us} us)"
            )
        return self


class WatchdogConfig(Strict):
    ready_timeout_s: float = Field(default=120.0, ge=1, description="all federates ready within")
    window_timeout_s: float = Field(default=10.0, ge=0.1, description="a federate answers a window within")
    run_timeout_s: float = Field(default=3600.0, gt=0, description="wall-clock limit of the run")


# A name becomes part of directory names (run ids); a seed's low 32 bits seed the streams
# (fabric/seeding.py), so larger seeds would repeat smaller ones.
NAME_MAX = 64
SEED_LIMIT = 2**32


class Scenario(Strict):
    """A complete run description."""

    name: str = Field(default="scenario", pattern=r"^[a-z0-9][a-z0-9_-]*$", max_length=NAME_MAX,
                      description=f"scenario name (at most {NAME_MAX} characters)")
    seed: int = Field(default=1, ge=0, lt=SEED_LIMIT, description="root seed of every random stream")
    runtime: Literal["process", "docker", "ray"] = Field(
        default="process", description="where federates run: local processes, containers, or Ray actors "
        "on a Ray cluster (docs/architecture.md sec. 8)")
    cohost: Literal["core", "none"] = Field(
        default="core",
        description="core: physics, netsim and the abstract loops (the federates without a compute "
                    "node profile) share one process or container and its serving thread, their "
                    "events merged in time order and their messages to each other carried in memory; none: every federate in a process of its own. "
                    "What is simulated is the same either way")
    partitions: int = Field(
        default=1, ge=1, le=100, description="netsim split by gNB into this many processes, each holding "
        "the radio cells of a contiguous block of the gNBs and exchanging each slot's "
        "transmissions with the others (needs hall.inf_layout; at most one a gNB). The same seed "
        "gives the same results with any number (docs/architecture.md sec. 13)")
    duration_s: float = Field(default=10.0, gt=0, le=86400, description="simulated duration, s")
    window_us: int = Field(default=1000, ge=10, description="lookahead window W, us")
    loops: int = Field(default=2, ge=1, le=1024, description="number of control loops N")
    detailed_loops: int = Field(default=1, ge=0, description="loops simulated in detail K <= N")
    physics_timestep_us: int = Field(default=1000, ge=100, description="MuJoCo timestep, us")
    hall: HallConfig = Field(default_factory=HallConfig, description="hall layout")
    work_cell: WorkCellConfig = Field(default_factory=WorkCellConfig, description="the work cells (every loop's)")
    agvs: AgvConfig = Field(default_factory=AgvConfig,
                            description="AGVs, moving radios (need hall.inf_layout)")
    camera: CameraConfig = Field(default_factory=CameraConfig, description="cameras")
    robot: RobotConfig = Field(default_factory=RobotConfig, description="robot controllers")
    edge: EdgeConfig = Field(default_factory=EdgeConfig, description="Edge application")
    policy: PolicyConfig = Field(default_factory=PolicyConfig, description="co-design policy")
    netsim: NetsimConfig = Field(default_factory=NetsimConfig, description="network simulator")
    nodes: Nodes = Field(default_factory=Nodes, description="compute node profiles")
    watchdog: WatchdogConfig = Field(default_factory=WatchdogConfig, description="failure detection")

    @model_validator(mode="after")
    def _time_contract(self) -> Scenario:
        if self.detailed_loops > self.loops:
            raise ValueError(f"detailed_loops ({self.detailed_loops}) must be <= loops ({self.loops})")
        w = self.window_us
        for field, value in (
            ("camera.readout_latency_us", self.camera.readout_latency_us),
            ("robot.state_latency_us", self.robot.state_latency_us),
            ("robot.actuation_latency_us", self.robot.actuation_latency_us),
            ("netsim.slot_us", self.netsim.slot_us),
        ):
            if value < w:
                raise ValueError(
                    f"{field} = {value} us is below window_us = {w} us: every message between "
                    f"federates must arrive at or after the end of the window it was sent in; "
                    f"raise {field} or lower window_us"
                )
        if self.netsim.slot_us % w:
            raise ValueError(f"window_us ({w}) must divide netsim.slot_us ({self.netsim.slot_us})")
        if self.duration_us < w:
            raise ValueError(f"duration_s = {self.duration_s:g} s is shorter than one window "
                             f"(window_us = {w} us): nothing would be simulated")
        if self.runtime != "docker" and (wall := [name for name, node in self.nodes if node.timing == "wall"]):
            raise ValueError(f"nodes.{wall[0]}.timing = wall measures jobs in the node's CPU-limited "
                             f"container, which only runtime docker gives (runtime is {self.runtime}): "
                             "use timing cpu or model, or runtime docker")
        if (self.policy.name != "none" and 0 < self.detailed_loops < self.loops
                and self.edge.policy_period_ms * 1000 <= 2 * w):
            raise ValueError(
                f"edge.policy_period_ms = {self.edge.policy_period_ms} ms must exceed two windows "
                f"(window_us = {w} us): the detailed and the abstract loops' federates share each "
                f"Edge's counts of its frames a window before every period ends")
        if w % self.physics_timestep_us:
            raise ValueError(
                f"physics_timestep_us ({self.physics_timestep_us}) must divide window_us ({w})"
            )
        self._hall_into_nr()
        self._cells_in_hall()
        self._cells_apart()
        if self.hall.inf_layout is not None and self.netsim.model != "nr":
            raise ValueError(
                f"hall.inf_layout needs netsim.model = nr (the simple model has one cell), got "
                f"{self.netsim.model}")
        self._reuse_fits()
        if self.robot.control_period_us % self.physics_timestep_us:
            raise ValueError("robot.control_period_us must be a multiple of physics_timestep_us")
        return self

    def _reuse_fits(self) -> None:
        """With reuse 3 each gNB's cell has a third of the carrier: it must hold a PRB, and a
        configured-grant occasion (with no occasion that fits, its UEs would send nothing)."""
        layout, nr = self.hall.inf_layout, self.netsim.nr
        if layout is None or layout.reuse == 1:
            return
        per_cell = nr.n_prb // layout.reuse
        if per_cell < 1:
            raise ValueError(f"netsim.nr.n_prb = {nr.n_prb} leaves no PRB per cell with "
                             f"hall.inf_layout.reuse = {layout.reuse}: at least {layout.reuse} PRBs")
        if nr.ul_access == "configured_grant" and nr.cg_prb > per_cell:
            raise ValueError(f"netsim.nr.cg_prb = {nr.cg_prb} exceeds the {per_cell} PRBs of a cell "
                             f"(netsim.nr.n_prb = {nr.n_prb} over hall.inf_layout.reuse = {layout.reuse}): "
                             f"at most {per_cell}, or reuse 1")

    @model_validator(mode="after")
    def _agvs_in_hall(self) -> Scenario:
        agvs, hall = self.agvs, self.hall
        if agvs.count and hall.inf_layout is None:
            raise ValueError(
                f"agvs.count = {agvs.count} needs several gNBs to hand over between: set "
                f"hall.inf_layout (or agvs.count = 0)")
        for i, (x, y) in enumerate(agvs.waypoints_m or ()):
            if not (0 <= x <= hall.length_m and 0 <= y <= hall.width_m):
                raise ValueError(
                    f"agvs.waypoints_m[{i}] = ({x:g}, {y:g}) m lies outside the hall floor "
                    f"(0..{hall.length_m:g} x 0..{hall.width_m:g} m): every waypoint must lie on it")
        return self

    @model_validator(mode="after")
    def _partitions_fit(self) -> Scenario:
        n = self.partitions
        if n == 1:
            return self
        layout = self.hall.inf_layout
        if layout is None:
            raise ValueError(f"partitions = {n} splits netsim by gNB: set hall.inf_layout (several "
                             f"gNBs) or partitions = 1")
        gnbs = len(layout.gnb_positions_m) if layout.gnb_positions_m is not None else layout.gnb_count
        if n > gnbs:
            raise ValueError(f"partitions = {n} is above the {gnbs} gNBs of hall.inf_layout: at "
                             f"most one partition a gNB (1..{gnbs})")
        interruption_ms = self.netsim.handover.interruption_ms
        if self.agvs.count and round(interruption_ms * 1000) < 1:
            raise ValueError(f"partitions = {n} with agvs.count = {self.agvs.count} needs "
                             f"netsim.handover.interruption_ms of at least 0.001 (it is "
                             f"{interruption_ms:g}): a handover's held packets reach another "
                             f"partition's gNB a slot later")
        return self

    def _cells_in_hall(self) -> None:
        """Every loop's work cell, and so its camera and robot modems, must stand inside the hall."""
        def outside(n: int) -> tuple[str, tuple[float, float, float]] | None:
            h = self.hall
            for ue, (x, y, z) in self.ue_positions_m(n).items():
                if not (0 <= x <= h.length_m and 0 <= y <= h.width_m and 0 <= z <= h.height_m):
                    return ue, (x, y, z)
            return None

        if (bad := outside(self.loops)) is None:
            return
        # The work cells fill a fixed order: fewer fit if more do, so the most that fit are
        # bisected (a search down from loops costs loops^2, seconds at a thousand).
        fits, too_many = 0, self.loops
        while too_many - fits > 1:
            mid = (fits + too_many) // 2
            fits, too_many = (mid, too_many) if outside(mid) is None else (fits, mid)
        ue, pos = bad
        raise ValueError(
            f"loops = {self.loops} work cells do not fit in the hall ({self.hall.length_m:g} x "
            f"{self.hall.width_m:g} m): {ue} would stand at ({pos[0]:g}, {pos[1]:g}) m; at most "
            f"{fits} fit with hall.work_cells_per_row = {self.hall.work_cells_per_row} and "
            f"hall.work_cell_pitch_m = {tuple(self.hall.work_cell_pitch_m)}: lower loops, or enlarge "
            f"hall.length_m / hall.width_m (and hall.work_cells_per_row, hall.gnb_position_m) to hold them")

    def _cells_apart(self) -> None:
        """No two work cells nearer than their footprint along both x and y; around several gNBs
        (``work_cell_fill = gnbs``) one gNB's grid must not reach into its neighbour's either: no
        two work cells closer than the pitch allows."""
        h = self.hall
        px, py = h.work_cell_pitch_m
        cells = h.work_cell_origins(self.loops)
        foot = WORK_CELL_FOOTPRINT_M - 1e-6
        by_x = sorted(range(len(cells)), key=lambda k: cells[k][0])
        for a, i in enumerate(by_x):
            for j in by_x[a + 1:]:
                if cells[j][0] - cells[i][0] >= foot:
                    break  # sorted by x: the rest are farther along it
                if abs(cells[j][1] - cells[i][1]) < foot:
                    raise ValueError(
                        f"work cells {min(i, j)} and {max(i, j)} at ({cells[i][0]:g}, {cells[i][1]:g}) and "
                        f"({cells[j][0]:g}, {cells[j][1]:g}) m overlap: work cells stand at least "
                        f"{WORK_CELL_FOOTPRINT_M:g} m apart along x or y (the floor one takes: belt, arm "
                        f"and platform); raise hall.work_cell_pitch_m = {(px, py)} or change "
                        f"hall.work_cells_per_row = {h.work_cells_per_row}")
        if h.work_cell_fill != "gnbs":
            return
        gnbs = len(h.gnb_positions())
        for i, (xi, yi) in enumerate(cells):
            for j in range(i + 1, len(cells)):
                if (j - i) % gnbs == 0:
                    continue  # one gNB's grid: a pitch apart by construction
                xj, yj = cells[j]
                if abs(xi - xj) < px - 1e-6 and abs(yi - yj) < py - 1e-6:
                    raise ValueError(
                        f"loops = {self.loops} work cells around {gnbs} gNBs overlap with "
                        f"hall.work_cell_fill = gnbs: work cell {i} (gNB {i % gnbs}) at ({xi:g}, "
                        f"{yi:g}) m and work cell {j} (gNB {j % gnbs}) at ({xj:g}, {yj:g}) m are "
                        f"closer than hall.work_cell_pitch_m = {(px, py)}: lower loops, or shrink "
                        f"each gNB's grid (fewer hall.work_cells_per_row along x, a smaller pitch), "
                        f"or take work_cell_fill = centre")

    def _hall_into_nr(self) -> None:
        """The NR channel model uses the hall of the scenario; a different one is a mistake."""
        nr = self.netsim.nr
        hall = {"hall_length_m": self.hall.length_m, "hall_width_m": self.hall.width_m,
                "hall_height_m": self.hall.height_m}
        for field, value in hall.items():
            if field in nr.model_fields_set and getattr(nr, field) != value:
                raise ValueError(
                    f"netsim.nr.{field} = {getattr(nr, field)} differs from the hall ({value}): "
                    f"set the hall size in `hall` only"
                )
        if any(getattr(nr, f) != v for f, v in hall.items()):
            self.netsim.nr = nr.model_copy(update=hall)

    # Derived quantities, integers in microseconds.
    @property
    def duration_us(self) -> int:
        return int(round(self.duration_s * 1_000_000))

    @property
    def frame_period_us(self) -> int:
        return int(round(1_000_000 / self.camera.fps))

    def ue_positions_m(self, loops: int | None = None) -> dict[str, tuple[float, float, float]]:
        """Radio endpoints (camera-i, robot-i) and their positions in the hall, metres (of the
        scenario's loops, or of ``loops``)."""
        h = self.hall.ue_height_m
        out: dict[str, tuple[float, float, float]] = {}
        for i, (x, y) in enumerate(self.hall.work_cell_origins(self.loops if loops is None else loops)):
            out[f"camera-{i}"] = (x - 0.1, y, h)
            out[f"robot-{i}"] = (x, y + 0.6, h)
        return out


class ScenarioError(ValueError):
    """A scenario that cannot be loaded; ``errors`` lists (field, message) pairs."""

    def __init__(self, errors: list[tuple[str, str]]) -> None:
        self.errors = errors
        super().__init__("; ".join(f"{f}: {m}" for f, m in errors))

    def format(self) -> str:
        return "\n".join(f"  {field}: {msg}" for field, msg in self.errors)


def _allowed_fields(parent: tuple[Any, ...]) -> list[str]:
    """Field names of the section at ``parent`` (a pydantic error location)."""
    model: Any = Scenario
    for part in parent:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        ann = getattr(field, "annotation", None)
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return []
        model = ann
    return sorted(model.model_fields)


def _format_validation(exc: ValidationError) -> list[tuple[str, str]]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(scenario)"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            allowed = _allowed_fields(err["loc"][:-1])
            msg = f"unknown field; allowed here: {', '.join(allowed)}" if allowed else "unknown field"
        elif err["loc"] and "input" in err and err["type"] != "missing" and not (
                err["type"] == "value_error" and isinstance(err["input"], dict)):
            # A section's own check names its values; the whole section given says nothing more.
            msg = f"{msg} (given: {_given(err['input'])})"
        out.append((loc, msg))
    return out


# An override is a dotted field and a short YAML value; anything longer is refused unread.
MAX_OVERRIDE_CHARS = 4096


class _NoAliasLoader(yaml.SafeLoader):
    """Safe YAML without anchors and aliases: a few bytes of aliases expand into gigabytes
    wherever the value is walked (validated, printed), so a value from a user has none."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.events.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "aliases (*name) are not allowed",
                                              self.peek_event().start_mark)
        return super().compose_node(parent, index)


def parse_value(raw: str, field: str) -> Any:
    """The YAML value ``raw`` given for ``field`` (no aliases), or a ScenarioError naming it."""
    try:
        return yaml.load(raw, Loader=_NoAliasLoader)  # noqa: S506 - a SafeLoader without aliases
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ScenarioError([(field, f"not a YAML value ({problem}): {raw[:40]!r}")]) from None
    except RecursionError:  # brackets nested hundreds deep
        raise ScenarioError([(field, f"not a YAML value (nested too deep): {raw[:40]!r}")]) from None


def _given(value: Any) -> str:
    """A short repr of a user's value, built without walking all of it."""
    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxdict, short.maxstring, short.maxother = 2, 4, 4, 40, 40
    return short.repr(value)[:60]


# Fields renamed since scenarios were first written (radio cell and work cell named apart): an
# old name still loads, once with a warning naming the new one, in files, inline scenarios,
# overrides and sweep specs.
RENAMED = {"cell": "work_cell", "hall.cell_pitch_m": "hall.work_cell_pitch_m",
           "hall.cells_per_row": "hall.work_cells_per_row"}


def current_path(path: str) -> str:
    """``path`` (dotted) under its current name; a FutureWarning when it was an old one."""
    for old, new in RENAMED.items():
        if path == old or path.startswith(old + "."):
            warnings.warn(f"scenario field {old!r} is now {new!r}: rename it (the old name will stop "
                          "loading)", FutureWarning, stacklevel=3)
            return new + path[len(old):]
    return path


def _current_fields(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with every renamed field under its current name; ScenarioError when a field is
    given under both names."""
    for old, new in RENAMED.items():
        *parents, leaf = old.split(".")
        node: Any = data
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            continue
        new_leaf = new.split(".")[-1]
        if new_leaf in node:
            raise ScenarioError([(old, f"given twice, as {old!r} and as its new name {new!r}: keep {new!r}")])
        current_path(old)
        node[new_leaf] = node.pop(leaf)
    return data


def _apply_override(data: dict[str, Any], assignment: str) -> None:
    if len(assignment) > MAX_OVERRIDE_CHARS:
        raise ScenarioError([(assignment[:40] + "...", f"an override is at most {MAX_OVERRIDE_CHARS} "
                                                       f"characters, got {len(assignment)}")])
    if "=" not in assignment:
        raise ScenarioError([(assignment, "override must look like field.path=value")])
    path, raw = assignment.split("=", 1)
    path = current_path(path.strip())
    value = parse_value(raw, path) if raw != "" else ""
    node = data
    default: Any = Scenario().model_dump(mode="json")
    parts = path.strip().split(".")
    for part in parts[:-1]:
        default = default.get(part) if isinstance(default, dict) else None
        if node.get(part) is None:
            # A section absent from the file (or an optional one left out, None) starts from its
            # defaults, so that overriding one field of it keeps the others.
            node[part] = copy.deepcopy(default) if isinstance(default, dict) else {}
        child = node[part]
        if not isinstance(child, dict):
            raise ScenarioError([(path, f"{part} is not a section")])
        node = child
    node[parts[-1]] = value


def parse_scenario(data: Any, overrides: list[str] | None = None) -> Scenario:
    """Validate a scenario mapping (plus ``field.path=value`` overrides) or raise ScenarioError."""
    if not isinstance(data, dict):
        raise ScenarioError([("(scenario)", f"expected a mapping of fields, got {type(data).__name__}")])
    data = _current_fields(copy.deepcopy(data))
    for assignment in overrides or []:
        _apply_override(data, assignment)
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(_format_validation(exc)) from None


def shipped_names(directory: Path) -> list[str]:
    """The names of the YAML files in ``directory`` (shipped scenarios or sweep specs): the only
    names a request may use, so that a name from a request never becomes a path."""
    return sorted(p.stem for p in directory.glob("*.yaml"))


def load_scenario(path: str | Path, overrides: list[str] | None = None) -> Scenario:
    """Load a YAML scenario file, apply overrides, validate."""
    p = Path(path)
    if not p.is_file():
        raise ScenarioError([("file", f"{p} does not exist")])
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise ScenarioError([("file", f"{p} is not valid YAML: {exc}")]) from None
    return parse_scenario(data, overrides)


def dump_scenario(scenario: Scenario) -> str:
    """The resolved scenario as YAML (every field, defaults included)."""
    return yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False)
