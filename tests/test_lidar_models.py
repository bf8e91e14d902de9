"""LiDAR models: Ouster layouts, and the Livox Mid-360 non-repetitive pattern's coverage."""
from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.lidar.models import MODEL_NAMES, BeamSpacing, beam_spacing, lidar_model, mid360_directions
from services.lib.lidar.uncertainty import sampling_covariance


def elevation_azimuth_deg(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = directions.reshape(-1, 3)
    return np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1))), np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0


@pytest.mark.parametrize("name, rows, cols, fov, max_range", [
    ("os0-128", 128, 1024, 90.0, 50.0),
    ("os0-128-2048", 128, 2048, 90.0, 50.0),
    ("os1-128", 128, 1024, 45.0, 100.0),
    ("os0-64", 64, 1024, 90.0, 50.0),
    ("OS0-32-512", 32, 512, 90.0, 50.0),
    ("os1-32-2048", 32, 2048, 45.0, 100.0),
])
def test_ouster_layouts(name, rows, cols, fov, max_range):
    model = lidar_model(name)
    d = model.directions(0)
    assert d.shape == (rows, cols, 3) and model.repeats and model.max_range == max_range
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    elevation, azimuth = elevation_azimuth_deg(d)
    assert abs(elevation.max() - fov / 2) < 1e-9 and abs(elevation.min() + fov / 2) < 1e-9  # centred on the horizon
    steps = np.diff(elevation.reshape(rows, cols)[:, 0])
    assert np.allclose(steps, -fov / (rows - 1))  # row 0 highest, even spacing
    assert np.allclose(azimuth.reshape(rows, cols)[rows // 2], np.arange(cols) * 360.0 / cols)  # column j at 2πj/cols
    assert np.array_equal(model.directions(7), d)  # the same beams every frame


def test_every_listed_model_loads_and_bad_names_are_named():
    for name in MODEL_NAMES:
        assert lidar_model(name).directions(3).shape[-1] == 3
    with pytest.raises(ValueError, match="unknown LiDAR model 'os2-128'.*mid360"):
        lidar_model("os2-128")
    with pytest.raises(ValueError, match="os0-48"):
        lidar_model("os0-48")


def test_mid360_frame_shape_rate_and_field_of_view():
    model = lidar_model("mid360")
    assert (model.rows, model.cols, model.min_range, model.max_range) == (4, 5000, 0.1, 40.0)
    assert model.rows * model.cols * 10 == 200_000  # points per second at 10 Hz
    assert lidar_model("mid360", rate_hz=20.0).cols == 2500
    d = model.directions(12)
    assert d.shape == (4, 5000, 3) and not model.repeats
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    elevation, azimuth = elevation_azimuth_deg(d)
    assert elevation.min() >= -7.0 - 1e-9 and elevation.max() <= 52.0 + 1e-9
    assert elevation.min() < -6.5 and elevation.max() > 51.5
    assert np.histogram(azimuth, bins=36, range=(0, 360))[0].min() > 0  # all the way round every frame


def coverage(frames: range) -> float:
    """Fraction of the 1° × 1° cells of 360° × -7…52° that the frames' beams pass through."""
    seen = np.zeros((360, 59), dtype=bool)
    for frame in frames:
        elevation, azimuth = elevation_azimuth_deg(mid360_directions(frame))
        rows = np.clip(np.floor(elevation + 7.0).astype(int), 0, 58)
        seen[np.floor(azimuth).astype(int) % 360, rows] = True
    return float(seen.mean())


@pytest.mark.parametrize("first", [0, 1234])
def test_mid360_covers_its_field_of_view_within_one_second(first):
    one_frame = coverage(range(first, first + 1))
    one_second = coverage(range(first, first + 10))
    assert one_frame < 0.8  # a single frame leaves gaps ...
    assert one_second >= 0.90  # ... which the next frames fill: the pattern does not repeat


def test_mid360_consecutive_frames_differ():
    a, b = mid360_directions(40), mid360_directions(41)
    assert np.abs(a - b).max() > 0.5
    # Not a rotated copy either: the elevations fired at the same column differ.
    assert np.mean(np.abs(a[..., 2] - b[..., 2]) > 0.05) > 0.5
    assert np.array_equal(mid360_directions(40), a)  # and deterministic


def test_beam_spacing_is_the_angle_between_neighbouring_rows_and_columns_of_the_models_beams():
    for name, rows, cols in (("os0-32-512", 32, 512), ("os1-128", 128, 1024)):
        beams = lidar_model(name).directions(0)
        spacing = beam_spacing(name, rows, cols)
        between_rows = math.acos(float(np.clip(beams[0, 0] @ beams[1, 0], -1, 1)))
        between_cols = math.acos(float(np.clip(beams[rows // 2, 0] @ beams[rows // 2, 1], -1, 1)))
        assert spacing.vertical == pytest.approx(between_rows, rel=1e-9)
        assert spacing.horizontal == pytest.approx(between_cols, rel=1e-3)  # the middle row lies near the horizon
    # the Mid-360's 20,000 firings a frame each stand for an equal patch of 360° x 59°: about 1°
    mid = beam_spacing("mid360", 4, 5000)
    assert mid.vertical == mid.horizontal == pytest.approx(math.radians(math.sqrt(360 * 59 / 20000)), rel=1e-9)
    assert beam_spacing("velodyne-hdl32", 32, 2000) is None and beam_spacing("os0-32", 0, 512) is None


def test_a_far_target_between_beams_is_uncertain_across_the_line_of_sight_by_a_beam_gap():
    spacing = beam_spacing("os0-32-512", 32, 512)
    sensor, target = np.array([0.0, 0.0, 12.0]), np.array([20.0, 15.0, 12.0])  # 25 m off, level
    cov = sampling_covariance(target, sensor, spacing)
    sight = (target - sensor) / 25.0
    across = np.array([-sight[1], sight[0], 0.0])
    assert sight @ cov @ sight == pytest.approx(0.0, abs=1e-12)  # the range measures the surface
    assert cov[2, 2] == pytest.approx((25.0 * spacing.vertical) ** 2 / 12)  # rows 1.27 m apart: sigma 0.37 m
    assert across @ cov @ across == pytest.approx((25.0 * spacing.horizontal) ** 2 / 12)
    assert np.allclose(sampling_covariance(sensor + [0, 0, 5.0], sensor, BeamSpacing(0.1, 0.1)),
                       np.diag([0.25 / 12, 0.25 / 12, 0]))
    assert not sampling_covariance(sensor, sensor, BeamSpacing(0.1, 0.1)).any()
