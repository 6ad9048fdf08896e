"""Camera sensor model and compression, the Edge estimators (learned and classical) and the
tracker, on frames rendered by our scene."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from domain import work_cell as g
from domain.codec import (
    decode_depth_delta_zlib,
    decode_frame,
    encode_depth_delta_zlib,
    encode_frame,
    slot_after,
    split_packets,
)
from domain.estimator import ClassicalEstimator, make_estimator
from domain.pose_net import DEFAULT_MODEL, LearnedEstimator, top_face_depth
from domain.sensor import (
    MAX_SHADOW_PX,
    SensorModel,
    decimate_depth,
    sense,
    sensor_depth_mm,
    sensor_for,
)
from domain.tracker import Tracker
from domain.work_cell import CameraIntrinsics
from domain.world import World
from fabric.seeding import rng
from scenario.schema import parse_scenario
from training.perception.dataset import generate, load_split
from training.perception.evaluate import evaluate

ROOT = Path(__file__).parents[2]


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray, list[dict]]:
    sc = parse_scenario({"loops": 1})
    world = World(sc)
    world.spawn(0, y_offset_m=0.02)
    world.advance_to(1_200_000)
    rgb, depth = world.render(0, sc.camera.width_px, sc.camera.height_px)
    assert depth is not None
    return rgb, sensor_depth_mm(depth, 0.0, rng(0, "t")), world.objects(0)


@pytest.fixture(scope="module")
def sensed(rendered: tuple) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The rendered frame as the default camera delivers it to the Edge (sensor + codec)."""
    rgb, depth, truth = rendered
    cam = parse_scenario({}).camera
    rgb_s, depth_s = sense(sensor_for(cam), rgb, depth, rng(0, "sensor"))
    data = encode_frame(rgb_s, depth_s, cam.jpeg_quality, cam.depth_codec, cam.depth_decimation)
    rgb2, depth2 = decode_frame(data)
    return rgb2, depth2, truth


def test_delta_depth_codec_keeps_the_whole_uint16_range_exact() -> None:
    full = np.random.default_rng(2).integers(0, 65536, (50, 50)).astype(np.uint16)
    for depth in (np.array([[0, 40000, 0], [0, 0, 65535]], np.uint16), full):
        h, w = depth.shape
        assert np.array_equal(decode_depth_delta_zlib(encode_depth_delta_zlib(depth), h, w), depth)


def intrinsics() -> CameraIntrinsics:
    cam = parse_scenario({}).camera
    return CameraIntrinsics(cam.width_px, cam.height_px, cam.fovy_deg)


@pytest.mark.parametrize("codec", ["delta-zlib", "png"])
def test_codec_round_trip_keeps_depth_exact(rendered: tuple, codec: str) -> None:
    rgb, depth, _ = rendered
    depth = SensorModel(intrinsics().f_px).depth(depth, rng(0, "codec"))  # noisy, with invalid pixels
    data = encode_frame(rgb, depth, 85, codec, 1)
    rgb2, depth2 = decode_frame(data)
    assert np.array_equal(depth2, depth)
    assert np.abs(rgb2.astype(int) - rgb.astype(int)).mean() < 3
    with pytest.raises(ValueError, match="not a compressed"):
        decode_frame(data[:-10])
    # Decimated depth comes back at the colour resolution, each block's value repeated.
    small = decimate_depth(depth, 4)
    _, depth4 = decode_frame(encode_frame(rgb, depth, 85, codec, 4))
    assert depth4.shape == depth.shape and np.array_equal(depth4[::4, ::4], small)


def test_decimation_is_the_median_or_mean_of_valid_pixels() -> None:
    d = np.array([[0, 0, 5, 7], [0, 0, 9, 0], [1, 2, 3, 4], [5, 6, 7, 8]], np.uint16)
    assert decimate_depth(d, 2).tolist() == [[0, 7], [2, 4]]
    assert decimate_depth(d, 4).tolist() == [[5]]  # mean of the 11 valid pixels, 5.18


def test_sensor_noise_grows_with_distance_squared_and_invalidates_the_left_band() -> None:
    sm = SensorModel(f_px=324.7, white_fraction=1.0)  # per-pixel noise only: easy to measure
    r = rng(0, "sensor-test")
    sds = []
    for z_mm in (800, 1600):
        flat = np.full((90, 160), z_mm, np.uint16)
        out = sm.depth(flat, r).astype(float)
        band = int(np.ceil(324.7 * 0.05 / (z_mm / 1000)))
        assert (out[:, :band - 1] == 0).all() and (out[:, band + 1:] > 0).all()
        sds.append(out[:, band + 1:].std())
    assert 3.0 < sds[1] / sds[0] < 5.0  # twice the distance, four times the noise
    assert abs(sds[0] - 0.8**2 * 0.08 / (324.7 * 0.05) * 1000) < 0.5


def test_colour_noise_is_shot_and_read_noise_per_pixel(rendered: tuple) -> None:
    """The looked-up sd per level gives, to the bit, the formula taken pixel by pixel."""
    rgb, _, _ = rendered
    sm = SensorModel(f_px=324.7)
    x = rgb.astype(np.float32)
    noise = rng(0, "colour").standard_normal(x.shape, dtype=np.float32)
    expected = np.clip(np.rint(x + noise * np.sqrt(sm.rgb_read_dn**2 + sm.rgb_gain_dn * x)), 0, 255)
    assert np.array_equal(sm.rgb(rgb, rng(0, "colour")), expected.astype(np.uint8))


def test_occlusion_shadow_is_the_scan_over_every_shift(rendered: tuple) -> None:
    """Rows scanned only as far as their disparity range reaches find every hidden pixel that a
    scan of every shift finds (for the pixels with a disparity: the others are invalid)."""
    _, depth, _ = rendered
    sm = SensorModel(f_px=324.7)
    disp = np.where(depth > 0, 324.7 * 0.05 / np.maximum(depth / 1000.0, 1e-3), 0.0).astype(np.float32)
    disp[100:140, 300:330] += 20.0  # a near surface: a wide shadow on its left
    scan = np.zeros(disp.shape, bool)
    for k in range(1, min(MAX_SHADOW_PX, int(np.ceil(disp.max()))) + 1):
        scan[:, :-k] |= disp[:, k:] - k > disp[:, :-k] + 0.5
    shadow = sm._shadow(disp)
    assert shadow[110, 290] and np.array_equal(shadow[disp > 0], scan[disp > 0])


def test_noise_free_depth_is_the_same_without_a_stream() -> None:
    depth_m = rng(0, "depth").uniform(0.2, 2.5, (36, 64)).astype(np.float32)
    assert np.array_equal(sensor_depth_mm(depth_m, 0.0, None), sensor_depth_mm(depth_m, 0.0, rng(0, "noise")))
    with pytest.raises(ValueError, match="needs a random stream"):
        sensor_depth_mm(depth_m, 1.0, None)


def test_default_camera_frame_is_about_35_kilobytes(rendered: tuple) -> None:
    rgb, depth, _ = rendered
    cam = parse_scenario({}).camera
    rgb_s, depth_s = sense(sensor_for(cam), rgb, depth, rng(0, "size"))
    size = len(encode_frame(rgb_s, depth_s, cam.jpeg_quality, cam.depth_codec, cam.depth_decimation))
    assert 25_000 < size < 45_000


def test_packetisation_respects_mtu_and_slots() -> None:
    sizes = split_packets(10_000, 1500)
    assert max(sizes) == 1500 and sum(s - 40 for s in sizes) == 10_000
    assert slot_after(0, 1000) == 1000 and slot_after(999, 1000) == 1000 and slot_after(1000, 1000) == 2000


def test_classical_estimator_finds_the_part_within_millimetres(sensed: tuple) -> None:
    rgb, depth, truth = sensed
    dets = ClassicalEstimator(intrinsics(), 0.06).detect(rgb, depth)
    assert len(dets) == 1
    assert np.linalg.norm(dets[0].p - np.asarray(truth[0]["p"])) < 0.01


def _part_under_cup(lift_m: float, size_m: float = 0.06) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A frame (rgb, depth in mm) of an orange part under the grey suction cup, seen from straight
    above at the image centre, with the face's true distance (m) and the focal length (px). On the
    belt (``lift_m`` 0) the cup hovers 5 cm over the middle of the face with the wrist reaching
    in from one side; lifted ``lift_m`` (m) in the cup, the cup's body stands on the face."""
    k = intrinsics()
    rgb = np.full((k.height, k.width, 3), 60, np.uint8)
    depth = np.full((k.height, k.width), round(g.CAMERA_HEIGHT_ABOVE_BELT * 1000), np.uint16)
    face_m = g.CAMERA_HEIGHT_ABOVE_BELT - size_m - lift_m
    u, v = k.width // 2, k.height // 2
    half = round(size_m / 2 * k.f_px / face_m)
    rgb[v - half:v + half + 1, u - half:u + half + 1] = (242, 115, 13)
    depth[v - half:v + half + 1, u - half:u + half + 1] = round(face_m * 1000)
    yy, xx = np.mgrid[:k.height, :k.width]
    if lift_m == 0:  # the hovering cup and the wrist: 15 % of the face left in view
        cover = ((xx - u) ** 2 + (yy - v) ** 2 <= (0.9 * half) ** 2) | ((np.abs(yy - v) <= 0.9 * half) & (xx >= u))
    else:
        cover = (xx - u) ** 2 + (yy - v) ** 2 <= (0.6 * half) ** 2
    rgb[cover] = 150
    depth[cover] = round((face_m - 0.05) * 1000)
    return rgb, depth, face_m, k.f_px


def test_top_face_depth_of_a_peak_off_the_image_is_none() -> None:
    rgb, depth = np.zeros((360, 640, 3), np.uint8), np.full((360, 640), 1000, np.uint16)
    for u, v in [(652.0, 180.0), (-12.0, 180.0), (320.0, 372.0), (320.0, -20.0)]:
        assert top_face_depth(rgb, depth, u, v, 0.06, 325.0) is None, (u, v)


def test_top_face_depth_is_the_part_not_the_cup_over_it() -> None:
    # Resting on the belt under the hovering cup: the ring of the face around the cup is the part.
    rgb, depth, face_m, f_px = _part_under_cup(0.0)
    u, v = depth.shape[1] / 2, depth.shape[0] / 2
    assert top_face_depth(rgb, depth, u, v, 0.06, f_px) == pytest.approx(face_m, abs=0.002)
    # Lifted in the cup: the face around the cup, above the belt's resting height.
    rgb, depth, face_m, f_px = _part_under_cup(0.05)
    assert top_face_depth(rgb, depth, u, v, 0.06, f_px) == pytest.approx(face_m, abs=0.002)
    # Most of the rim blended with the cup's depth: too little of the face to tell, no height.
    rgb, depth, face_m, f_px = _part_under_cup(0.0)
    rim = np.argwhere((depth == round(face_m * 1000)).ravel()).ravel()
    depth.ravel()[rim[: len(rim) * 3 // 5]] = round((face_m - 0.03) * 1000)
    assert top_face_depth(rgb, depth, u, v, 0.06, f_px) is None


def test_learned_estimator_on_held_out_frames_keeps_its_recorded_accuracy(tmp_path: Path) -> None:
    """Frames rendered now from the test split's seeds (never trained on, wider light, size and
    tilt ranges than training): the learned estimator finds nearly every part in view, with a
    median error within 2x of the one recorded in the model card on the full test split."""
    index = generate("test", episodes=2, out_dir=tmp_path, seconds=6.0, workers=1)
    frames, labels = load_split(tmp_path, "test")
    assert index["frames"] == len(frames) > 40
    result = evaluate(lambda k, size: LearnedEstimator(k, size), frames, labels)
    recorded = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())["test_metrics"]["learned"]
    assert result["parts_in_view"] >= 40
    assert result["detection_rate"] >= 0.95, result
    assert result["error_median_mm"] <= 2 * recorded["error_median_mm"], result
    assert result["false_positives_per_frame"] <= 0.1, result


def test_learned_model_is_small_and_recorded() -> None:
    assert DEFAULT_MODEL.stat().st_size < 1_000_000
    assert DEFAULT_MODEL.with_suffix(".json").is_file()


def test_factory_picks_the_estimator_by_name_and_falls_back_without_a_model(tmp_path: Path) -> None:
    k = intrinsics()
    est, why = make_estimator("learned", k, 0.06)
    assert est.name == "learned" and why is None
    est, why = make_estimator("classical", k, 0.06)
    assert est.name == "classical" and why is None
    est, why = make_estimator("learned", k, 0.06, tmp_path / "missing.onnx")
    assert est.name == "classical" and why is not None and "not found" in why
    with pytest.raises(ValueError, match="unknown estimator"):
        make_estimator("magic", k, 0.06)


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


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("torch") is None or importlib.util.find_spec("onnx") is None,
                    reason="training needs torch and onnx (pip install torch onnx)")
def test_quick_training_renders_trains_and_exports() -> None:
    """The training path end to end on a tiny budget (about a minute); needs torch + onnx."""
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "train_perception.py"), "--quick", "--threads", "1"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "epoch 2/2" in proc.stdout and "wrote " in proc.stdout
