"""Object Detect and the Balloon Color Picker (seed 004 §4.1, §4.3): circular hue statistics,
correct pooling against eq. 4.7-4.8, thresholds (eq. 4.9-4.10), the LUT, distances on renders."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from schemas.messages import Appearance, TargetTruth
from services.camera.core import Camera, CameraParams, camera_rotation
from services.lib.geometry import quaternion
from services.lib.world.primitives import pack, primitives_from_obstacles
from services.object_detect.colors import (
    HUE_UNITS,
    ColorFile,
    ColorFileError,
    ColorStats,
    Lut,
    Thresholds,
    circular_mean_sigma,
    parse_color_file,
    seed_pooled,
    to_space,
)
from services.object_detect.core import CameraView, ObjectDetectParams, detect, find_blobs


def hsv_pixels(hues_half_degrees, s=200, v=180) -> np.ndarray:
    """sRGB pixels whose OpenCV hue is the given value (half degrees), at one saturation and value."""
    hsv = np.array([[h, s, v] for h in hues_half_degrees], dtype=np.uint8).reshape(-1, 1, 3)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).reshape(-1, 3)


def test_circular_hue_statistics_around_zero():
    hues = np.array([175.0, 178.0, 179.0, 1.0, 2.0, 5.0])  # half degrees: both sides of 0°/360°
    angles = hues * 2 * math.pi / HUE_UNITS
    mean, sigma = circular_mean_sigma(np.sin(angles).mean(), np.cos(angles).mean())
    assert min(mean, HUE_UNITS - mean) < 0.5  # at 0, not at 90 (the linear mean)
    assert 2.0 < sigma < 5.0  # a few half degrees, not ~90
    mean, sigma = circular_mean_sigma(0.0, 1.0)
    assert mean == 0.0 and sigma == 0.0
    mean, _ = circular_mean_sigma(1.0, 0.0)  # 90° = 45 half degrees
    assert mean == pytest.approx(45.0)


def test_stats_of_pixels_give_the_hue_across_zero():
    stats = ColorStats()
    stats.add(hsv_pixels([176, 178, 179, 0, 1, 3]))
    mean, sigma = stats.mean_sigma("hsv")
    assert min(mean[0], HUE_UNITS - mean[0]) < 1.0 and sigma[0] < 4.0
    assert mean[1] == pytest.approx(200, abs=3) and mean[2] == pytest.approx(180, abs=3)


def test_pooled_statistics_are_those_of_all_pixels_and_eq_4_7_4_8_are_not():
    rng = np.random.default_rng(4)
    first = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    second = np.clip(rng.normal(90, 10, (400, 3)), 0, 255).astype(np.uint8)
    pooled = ColorStats()
    pooled.add(first)
    pooled.add(second)
    at_once = ColorStats()
    at_once.add(np.vstack([first, second]))
    for space in ("hsv", "lab"):
        assert np.allclose(pooled.mean_sigma(space)[0], at_once.mean_sigma(space)[0])
        assert np.allclose(pooled.mean_sigma(space)[1], at_once.mean_sigma(space)[1])
    lab_first, lab_second = to_space(first, "lab")[:, 0].astype(float), to_space(second, "lab")[:, 0].astype(float)
    everything = np.concatenate([lab_first, lab_second])
    assert pooled.mean_sigma("lab")[0][0] == pytest.approx(everything.mean())
    assert pooled.mean_sigma("lab")[1][0] == pytest.approx(everything.std(ddof=1))
    seed_mean, seed_sigma = seed_pooled(lab_first.mean(), lab_first.std(ddof=1), lab_second.mean(),
                                        lab_second.std(ddof=1), 2)
    assert abs(seed_mean - everything.mean()) > 5  # the printed accumulation ignores the sizes ...
    assert abs(seed_sigma - everything.std(ddof=1)) > 20  # ... and adds means to variances


def test_thresholds_are_eq_4_9_and_4_10_and_the_hue_interval_wraps():
    t = Thresholds.from_stats("lab", np.array([100.0, 150.0, 130.0]), np.array([2.0, 4.0, 1.0]), [2.0, 1.5, 3.0])
    assert t.lower == (96.0, 144.0, 127.0) and t.upper == (104.0, 156.0, 133.0)
    t = Thresholds.from_stats("hsv", np.array([1.0, 200.0, 250.0]), np.array([2.0, 30.0, 10.0]), 2.0)
    assert t.lower[0] == pytest.approx(177.0) and t.upper[0] == pytest.approx(5.0)  # wraps across 0
    assert t.upper[1] == 255.0 and t.upper[2] == 255.0  # clipped to the 8-bit range
    values = np.array([[178, 220, 240], [3, 220, 240], [10, 220, 240], [178, 100, 240]], dtype=np.uint8)
    assert t.mask(values).tolist() == [True, True, False, False]


def test_a_lut_round_trips_through_its_file_text():
    rng = np.random.default_rng(2)
    values = to_space(np.clip(rng.normal((30, 160, 40), 12, (500, 3)), 0, 255).astype(np.uint8), "hsv").reshape(-1, 3)
    lut = Lut.from_pixels("hsv", values, (20.0, 255.0))
    # cells with a single pixel are left out (min_count 2): most, not all, of the picked pixels are in
    assert lut.mask.sum() > 10 and lut.lookup(values[values[:, 2] >= 20]).mean() > 0.9
    colors = ColorFile("green", 0.6, "lut", Thresholds("hsv", (0, 0, 0), (179, 255, 255)), lut, len(values))
    import tomllib
    back = parse_color_file(tomllib.loads(colors.to_toml()), "round trip")
    assert back.method == "lut" and np.array_equal(back.lut.mask, lut.mask) and back.lut.third == lut.third
    image = np.clip(rng.normal((30, 160, 40), 12, (20, 30, 3)), 0, 255).astype(np.uint8)
    assert np.array_equal(back.segment(image), colors.segment(image))


@pytest.mark.parametrize("text, complaint", [
    ("diameter = 0.6\n", "missing field 'thresholds'"),
    ('diameter = -1\n[thresholds]\nlower = [0,0,0]\nupper = [1,1,1]\n', "diameter must be positive"),
    ('diameter = 0.6\n[thresholds]\nspace = "rgb"\nlower = [0,0,0]\nupper = [1,1,1]\n', "thresholds.space"),
    ('diameter = 0.6\nmethod = "lut"\n[thresholds]\nlower = [0,0,0]\nupper = [1,1,1]\n[lut]\nmask = "AAAA"\n',
     "a LUT mask holds"),
    ('diameter = 0.6\n[thresholds]\nlower = [0,0]\nupper = [1,1,1]\n', "three finite numbers"),
])
def test_a_malformed_colour_file_is_one_clear_error(text, complaint):
    import tomllib
    with pytest.raises(ColorFileError, match=complaint) as info:
        parse_color_file(tomllib.loads(text), "bad.toml")
    assert "\n" not in str(info.value) and str(info.value).startswith("bad.toml: ")


def render_balloon(distance: float, bearing: float = 0.0, height: float = 4.0, noise: bool = False):
    params = CameraParams(pitch=0.0, **({} if noise else dict(color_noise=0.0, depth_noise=0.0, depth_dropout=0.0)))
    cam = Camera(params, np.random.default_rng(0))
    centre = np.array([distance * math.cos(bearing), distance * math.sin(bearing), height])
    balloon = TargetTruth(id="b", kind="balloon", position=tuple(centre), velocity=(0, 0, 0), radius=0.3,
                          color=(200, 30, 30))
    world = pack(primitives_from_obstacles([]).with_targets([balloon]))
    position, rotation = np.array([0.0, 0.0, 4.0]), camera_rotation(0.0, 0.0)
    frame = cam.render(world, Appearance(), position, rotation, np.ones(3), np.random.default_rng(0))
    k = cam.intrinsics
    view = CameraView(k, position, quaternion(rotation))
    return frame, view, centre


RED = ColorFile("red", 0.6, "thresholds", Thresholds("hsv", (170.0, 120.0, 40.0), (8.0, 255.0, 255.0)))


@pytest.mark.parametrize("distance", [5.0, 8.0, 12.0, 16.0, 20.0])
def test_the_distance_from_the_known_diameter_is_within_5_percent(distance):
    frame, view, centre = render_balloon(distance, bearing=0.1)
    found = detect(frame.rgb, None, view, RED, ObjectDetectParams())  # no depth: the size alone
    assert len(found.positions) == 1
    true_range = np.linalg.norm(centre - view.position)
    assert found.ranges_from_size[0] == pytest.approx(true_range, rel=0.05)
    assert np.linalg.norm(found.positions[0] - centre) < 0.05 * true_range


def test_depth_sharpens_the_position_where_there_is_depth():
    frame, view, centre = render_balloon(7.0, bearing=-0.2, noise=True)
    found = detect(frame.rgb, frame.depth_mm, view, RED, ObjectDetectParams())
    assert len(found.positions) == 1 and not math.isnan(found.ranges_from_depth[0])
    assert np.linalg.norm(found.positions[0] - centre) < 0.1
    along = found.covariances[0]
    assert np.all(np.linalg.eigvalsh(along) > 0)


def test_a_balloon_that_lost_its_shaded_side_reads_its_range_from_its_full_width():
    """benchmarks/camera.py: far balloons whose segmentation lost up to a quarter of their pixels on
    one side read 10-17 % long from their area alone; the width across keeps the balloon's size."""
    frame, view, centre = render_balloon(16.0, bearing=0.1)
    rgb = frame.rgb.copy()
    mask = RED.segment(rgb)
    rows, cols = np.nonzero(mask)
    shaded = rows > rows.min() + 0.7 * (rows.max() - rows.min())  # its lower 30 % lost to shade
    rgb[rows[shaded], cols[shaded]] = (40, 40, 40)
    found = detect(rgb, None, view, RED, ObjectDetectParams())
    true_range = np.linalg.norm(centre - view.position)
    assert len(found.positions) == 1 and found.ranges_from_size[0] == pytest.approx(true_range, rel=0.05)


def test_a_balloon_cut_by_the_images_edge_is_dropped_without_depth_and_kept_with_it():
    frame, view, centre = render_balloon(6.0, bearing=0.0)
    rgb, depth = frame.rgb.copy(), frame.depth_mm.copy()
    mask = RED.segment(rgb)
    cols = np.nonzero(mask)[1]
    cut = int(cols.min() + 0.25 * (cols.max() - cols.min()))  # the image now ends a quarter into the balloon
    [blob] = find_blobs(RED.segment(np.ascontiguousarray(rgb[:, cut:])), ObjectDetectParams())
    assert blob.clipped  # round enough to be a blob: the edge alone is what drops it below
    found = detect(np.ascontiguousarray(rgb[:, cut:]), None, view, RED, ObjectDetectParams())
    assert len(found.positions) == 0  # its size says only that it is nearer
    shifted = CameraView(dataclasses.replace(view.intrinsics, width=view.intrinsics.width - cut, cx=view.intrinsics.cx - cut),
                         view.position, view.orientation)
    found = detect(np.ascontiguousarray(rgb[:, cut:]), np.ascontiguousarray(depth[:, cut:]), shifted, RED,
                   ObjectDetectParams())
    assert len(found.positions) == 1 and np.linalg.norm(found.positions[0] - centre) < 0.3


def test_bad_frames_are_refused_with_one_clear_error():
    frame, view, _ = render_balloon(7.0)
    with pytest.raises(ValueError, match="uint8"):
        detect(frame.rgb.astype(np.float32), None, view, RED, ObjectDetectParams())
    with pytest.raises(ValueError, match="does not match"):
        detect(frame.rgb, frame.depth_mm[:10], view, RED, ObjectDetectParams())


def test_picking_a_colour_from_a_frame_finds_the_balloon_the_wrong_colour_does_not(tmp_path):
    """The balloon turned green (as at the competition): the built-in red finds nothing; `falconry
    colors pick` on a frame, one region inside the balloon, makes a colour file that finds it."""
    import subprocess
    import sys

    from services.object_detect.colors import load_color_file
    from services.object_detect.node import color_file_path

    params = CameraParams(pitch=0.0)
    cam = Camera(params, np.random.default_rng(3))
    centre = np.array([9.0, 0.8, 4.2])
    balloon = TargetTruth(id="b", kind="balloon", position=tuple(centre), velocity=(0, 0, 0), radius=0.3,
                          color=(40, 170, 60))
    world = pack(primitives_from_obstacles([]).with_targets([balloon]))
    position, rotation = np.array([0.0, 0.0, 4.0]), camera_rotation(0.0, 0.0)
    frame = cam.render(world, Appearance(), position, rotation, np.ones(3), np.random.default_rng(3))
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    k = cam.intrinsics
    u, v = k.project((rotation.T @ (centre - position))[None])[0]
    out = tmp_path / "green.toml"
    result = subprocess.run([sys.executable, "-m", "services.tools.launcher", "colors", "pick", str(image), "--roi",
                             f"{int(u) - 5},{int(v) - 5},10,10", "--out", str(out)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    view = CameraView(k, position, quaternion(rotation))
    red = load_color_file(color_file_path("red"))
    assert len(detect(frame.rgb, frame.depth_mm, view, red, ObjectDetectParams()).positions) == 0
    found = detect(frame.rgb, frame.depth_mm, view, load_color_file(out), ObjectDetectParams())
    assert len(found.positions) == 1 and np.linalg.norm(found.positions[0] - centre) < 0.2


@pytest.mark.parametrize("space", ["hsv", "lab"])
def test_an_image_converts_as_its_pixels_do_one_by_one(space):
    """to_space converts an image as it is (OpenCV's row-wise path), pixels in a column otherwise."""
    image = np.random.default_rng(4).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    assert np.array_equal(to_space(image, space), to_space(image.reshape(-1, 3), space).reshape(image.shape))


@pytest.mark.parametrize("space", ["hsv", "lab"])
def test_an_images_mask_by_opencv_is_the_same_bits_as_the_per_channel_rule(space):
    """ColorFile.segment masks whole images with cv2.inRange; Thresholds.mask is the rule (eq.
    4.9-4.10) written out per channel. Fractional, wrapping and out-of-range bounds included."""
    rng = np.random.default_rng(11)
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    values = to_space(image, space)
    for _ in range(200):
        lower = rng.uniform(-20, 260, 3)
        upper = lower + rng.uniform(-30, 120, 3)
        if space == "hsv" and rng.random() < 0.4:
            lower[0], upper[0] = rng.uniform(150, 179.9), rng.uniform(0, 20)  # across 0
        t = Thresholds(space, tuple(lower), tuple(upper))
        assert np.array_equal(t.mask_image(values), t.mask(values)), (lower, upper)
    t = Thresholds(space, (0, 0, 0), (255, 255, 255))
    assert t.mask_image(values).all() and t.mask_image(values).dtype == bool


def test_blobs_are_found_where_they_are_whatever_box_they_share_with_the_rest():
    """find_blobs labels only the box around what is left after the opening: positions, sizes and
    the cut at the edge are the whole image's."""
    mask = np.zeros((90, 160), dtype=bool)
    yy, xx = np.mgrid[:90, :160]
    for cx, cy, r in ((30.0, 40.0, 6.0), (120.5, 70.0, 9.0), (3.0, 10.0, 5.0), (156.0, 84.0, 4.0)):
        mask |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    blobs = find_blobs(mask, ObjectDetectParams(min_pixels=5))
    opened = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, _, stats, centroids = cv2.connectedComponentsWithStats(opened, connectivity=8)
    assert len(blobs) == count - 1 == 4
    for blob, stat, centroid in zip(blobs, stats[1:], centroids[1:]):
        assert blob.pixels == stat[cv2.CC_STAT_AREA] and blob.u == pytest.approx(centroid[0], abs=1e-9)
        assert blob.v == pytest.approx(centroid[1], abs=1e-9)
    assert [b.clipped for b in blobs] == [True, False, False, True]
    assert find_blobs(np.zeros((90, 160), dtype=bool), ObjectDetectParams()) == []
    rng = np.random.default_rng(3)  # boxes starting on odd rows and columns, blobs sharing rows: the same order
    for _ in range(60):
        mask = np.zeros((90, 160), dtype=bool)
        for _ in range(rng.integers(1, 6)):
            cx, cy, r = rng.uniform(0, 160), rng.uniform(0, 90), rng.uniform(2, 9)
            mask |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        opened = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        _, _, stats, centroids = cv2.connectedComponentsWithStats(opened, connectivity=8)
        whole = [(int(a), round(u, 9), round(v, 9)) for a, (u, v) in zip(stats[1:, cv2.CC_STAT_AREA], centroids[1:])]
        found = [(b.pixels, round(b.u, 9), round(b.v, 9)) for b in find_blobs(mask, ObjectDetectParams(min_pixels=1,
                                                                                                        min_fill=0,
                                                                                                        max_aspect=1e9))]
        assert found == whole
