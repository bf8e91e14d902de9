"""LiDAR models: Ouster layouts, and the Livox Mid-360 non-repetitive pattern's coverage."""
from __future__ import annotations

import numpy as np
import pytest

from services.lidar.models import MODEL_NAMES, lidar_model, mid360_directions


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
