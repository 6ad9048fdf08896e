"""Camera compression and the Edge estimator/tracker on frames rendered by our scene."""

from __future__ import annotations

import numpy as np
import pytest

from services.camera.codec import decode_frame, encode_frame, slot_after, split_packets
from services.common.scenario import parse_scenario
from services.common.seeding import rng
from services.edge.estimator import ClassicalEstimator
from services.edge.tracker import Tracker
from services.physics.cell_geometry import CameraIntrinsics
from services.physics.federate import sensor_depth_mm
from services.physics.world import World


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray, list[dict]]:
    sc = parse_scenario({"loops": 1})
    world = World(sc)
    world.spawn(0, y_offset_m=0.02)
    world.advance_to(1_200_000)
    rgb, depth = world.render(0, sc.camera.width_px, sc.camera.height_px)
    assert depth is not None
    return rgb, sensor_depth_mm(depth, 0.0, rng(0, "t")), world.objects(0)


def test_codec_round_trip_keeps_depth_exact(rendered: tuple) -> None:
    rgb, depth, _ = rendered
    data = encode_frame(rgb, depth, 85)
    rgb2, depth2 = decode_frame(data)
    assert np.array_equal(depth2, depth)
    assert np.abs(rgb2.astype(int) - rgb.astype(int)).mean() < 3
    assert len(data) < rgb.nbytes // 5
    with pytest.raises(ValueError, match="not a compressed"):
        decode_frame(data[:-10])


def test_packetisation_respects_mtu_and_slots() -> None:
    sizes = split_packets(10_000, 1500)
    assert max(sizes) == 1500 and sum(s - 40 for s in sizes) == 10_000
    assert slot_after(0, 1000) == 1000 and slot_after(999, 1000) == 1000 and slot_after(1000, 1000) == 2000


def test_classical_estimator_finds_the_part_within_millimetres(rendered: tuple) -> None:
    rgb, depth, truth = rendered
    sc = parse_scenario({})
    est = ClassicalEstimator(CameraIntrinsics(sc.camera.width_px, sc.camera.height_px, sc.camera.fovy_deg),
                             sc.cell.object_size_m)
    rgb2, depth2 = decode_frame(encode_frame(rgb, depth, 85))
    dets = est.detect(rgb2, depth2)
    assert len(dets) == 1
    assert np.linalg.norm(dets[0].p - np.asarray(truth[0]["p"])) < 0.01


def test_tracker_estimates_belt_velocity() -> None:
    tr = Tracker()
    noise = rng(0, "tracker-test")
    for k in range(30):
        t = k * 33_333
        p = np.array([-0.5 + 0.2 * t / 1e6, 0.01, 0.78]) + noise.normal(0, 0.003, 3)
        tr.update(t, [p])
    (track,) = tr.tracks.values()
    assert abs(track.x[3] - 0.2) < 0.03 and abs(track.x[4]) < 0.03
    assert track.t_us == 29 * 33_333
