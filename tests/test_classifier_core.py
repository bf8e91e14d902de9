"""Classifier core (first version): clustering and background / flying / unknown rules."""
from __future__ import annotations

import numpy as np
import pytest

from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.classifier.core import ClassifierCore, ClassifierParams, cluster_voxels
from services.mapper.core import MapperParams

SENSOR = (0.0, 0.0, 5.0)
BALL_CENTRE = np.array([8.0, 3.0, 6.0])


def ground_grid(half: float = 15.0, step: float = 0.5) -> np.ndarray:
    xs = np.arange(-half, half + 1e-9, step)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)


def ball(centre, radius: float = 0.3, count: int = 200) -> np.ndarray:
    """Evenly spread points on a sphere (Fibonacci lattice): their centroid is the centre."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * i / count)
    azimuth = np.pi * (1 + 5**0.5) * i
    unit = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)
    return np.asarray(centre) + radius * unit


def organised(*clouds: np.ndarray, width: int = 128, nan_every: int = 0) -> np.ndarray:
    """Pack clouds into an (H, W, 3) float32 scan padded with NaN (no return)."""
    pts = np.concatenate(clouds).astype(np.float32)
    if nan_every:
        pts = np.insert(pts, np.arange(0, len(pts), nan_every), np.nan, axis=0)
    height = -(-len(pts) // width)
    scan = np.full((height * width, 3), np.nan, dtype=np.float32)
    scan[: len(pts)] = pts
    return scan.reshape(height, width, 3)


def test_ball_above_ground_is_the_only_detection():
    core = ClassifierCore()
    ground = ground_grid()
    scan = core.classify(organised(ground, ball(BALL_CENTRE)), SENSOR)
    assert len(scan.positions) == 1
    assert np.linalg.norm(scan.positions[0] - BALL_CENTRE) < 0.1
    assert scan.point_counts[0] == 200
    assert 0.5 < scan.extents[0] < 0.65
    cov = scan.covariances[0]
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) >= 0.01 - 1e-9)
    on_ground = scan.points[:, 2] < 0.1
    assert on_ground.sum() == len(ground)
    assert np.all(scan.point_labels[on_ground] == BACKGROUND)
    assert np.all(scan.point_labels[~on_ground] == FLYING)
    # Voxel label sets: weights count points, labels follow the points'.
    assert scan.voxel_weights.sum() == len(scan.points)
    assert set(scan.voxel_labels.tolist()) == {BACKGROUND, FLYING}
    assert scan.voxels.dtype == np.int32


def test_voxels_are_relative_to_the_map_origin():
    core = ClassifierCore()
    scan = core.classify(np.array([[[0.1, 0.1, 0.1]]], dtype=np.float32), SENSOR)
    # origin (-10, -10, -1) at 0.5 m: x = 0.1 lies in voxel 20, z = 0.1 in voxel 2
    assert scan.voxels.tolist() == [[20, 20, 2]]


def test_pole_from_the_ground_is_background():
    core = ClassifierCore()
    pole = np.stack([np.full(51, 6.0), np.full(51, -4.0), np.linspace(0.0, 5.0, 51)], axis=1)
    scan = core.classify(organised(pole), SENSOR)
    assert len(scan.positions) == 0
    assert np.all(scan.point_labels == BACKGROUND)


def test_balloon_touching_its_pole_is_background_in_the_first_version():
    """Known first-version limit: a pole within 1.5 m joins the balloon's cluster, which then
    touches the ground. The flood-fill rule and cluster splitting of later issues address it."""
    core = ClassifierCore()
    pole = np.stack([np.full(41, 8.0), np.full(41, 3.0), np.linspace(0.0, 5.6, 41)], axis=1)
    scan = core.classify(organised(pole, ball(BALL_CENTRE)), SENSOR)
    assert len(scan.positions) == 0
    assert np.all(scan.point_labels == BACKGROUND)


def test_cluster_touching_a_map_occupied_voxel_is_background():
    core = ClassifierCore()
    origin = np.asarray(core.map.origin)
    shape = core.map.shape
    occupied = np.floor((BALL_CENTRE + [0.0, 0.0, 0.6] - origin) / 0.5).astype(int)  # just above the ball
    flat = np.ravel_multi_index(tuple(occupied), shape)
    assert core.apply_map(True, tuple(origin), shape, 0.5, -740.0, np.array([flat]), np.array([0.0], np.float32))
    scan = core.classify(organised(ball(BALL_CENTRE)), SENSOR)
    assert len(scan.positions) == 0
    assert np.all(scan.point_labels == BACKGROUND)
    # A delta freeing that voxel (G = -1000) makes the ball a flying object again.
    assert core.apply_map(False, tuple(origin), shape, 0.5, -740.0, np.array([flat]), np.array([-1000.0], np.float32))
    assert len(core.classify(organised(ball(BALL_CENTRE)), SENSOR).positions) == 1


def test_delta_for_another_geometry_is_ignored_and_snapshot_replaces():
    core = ClassifierCore()
    assert not core.apply_map(False, (0.0, 0.0, 0.0), (10, 10, 10), 0.5, -740.0, np.array([5]), np.array([0.0]))
    assert core.apply_map(True, (0.0, 0.0, 0.0), (10, 10, 10), 0.5, -740.0, np.array([5]), np.array([0.0]))
    assert core.map.shape == (10, 10, 10) and core.map.grid.reshape(-1)[5] == 0.0
    assert core.apply_map(True, (0.0, 0.0, 0.0), (10, 10, 10), 0.5, -740.0, np.array([7]), np.array([0.0]))
    assert core.map.grid.reshape(-1)[5] == -740.0  # a snapshot replaces, it does not add


def test_unknown_rules():
    core = ClassifierCore()
    low = ball((5.0, -5.0, 1.0), radius=0.2)  # lowest point 0.8 m: not ground, not high enough
    lone = np.array([[-5.0, 5.0, 8.0]])  # a single point
    far = ball((60.0, 0.0, 10.0))  # beyond 50 m
    scan = core.classify(organised(low, lone, far), SENSOR)
    assert len(scan.positions) == 0
    assert np.all(scan.point_labels == UNKNOWN)


def test_large_cluster_in_the_air_is_background():
    core = ClassifierCore()
    xs = np.arange(0.0, 4.01, 0.25)
    wire = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 7.0)], axis=1)  # 4 m long
    scan = core.classify(organised(wire), SENSOR)
    assert np.all(scan.point_labels == BACKGROUND)


def test_nan_points_are_ignored():
    core = ClassifierCore()
    clean = core.classify(organised(ground_grid(), ball(BALL_CENTRE)), SENSOR)
    noisy = core.classify(organised(ground_grid(), ball(BALL_CENTRE), nan_every=7), SENSOR)
    assert len(noisy.points) == len(clean.points)
    assert np.isfinite(noisy.points).all()
    assert np.allclose(noisy.positions, clean.positions)
    empty = core.classify(np.full((4, 8, 3), np.nan, np.float32), SENSOR)
    assert len(empty.points) == 0 and len(empty.positions) == 0


def test_clustering_distance_is_1_5_m():
    voxels = np.array([[0, 0, 0], [3, 0, 0], [7, 0, 0], [9, 2, 1]])  # gaps 1.5 m, 2.0 m, 1.5 m
    count, labels = cluster_voxels(voxels, 1.5 / 0.5)
    assert count == 2
    assert labels[0] == labels[1] != labels[2] == labels[3]


def test_two_balls_two_detections():
    core = ClassifierCore()
    other = BALL_CENTRE + [0.0, 3.0, 0.0]  # surfaces 2.4 m apart, more than the 1.5 m clustering distance
    scan = core.classify(organised(ball(BALL_CENTRE), ball(other)), SENSOR)
    assert len(scan.positions) == 2


def test_default_map_geometry_matches_the_mapper():
    c, m = ClassifierParams(), MapperParams()
    assert (c.map_origin, c.map_shape) == (m.origin, m.shape)
    assert (c.voxel_size, c.map_default) == (m.voxel_size, m.unknown_value)


@pytest.mark.parametrize("seed", [0, 1])
def test_result_is_deterministic(seed):
    rng = np.random.default_rng(seed)
    pts = np.concatenate([ground_grid(), ball(BALL_CENTRE) + rng.normal(0, 0.02, (200, 3))])
    a = ClassifierCore().classify(organised(pts), SENSOR)
    b = ClassifierCore().classify(organised(pts), SENSOR)
    assert np.array_equal(a.voxels, b.voxels) and np.array_equal(a.positions, b.positions)
