"""Exact ray traversal (seed 000 eq. 20–22): the per-ray reference against a brute-force sampler,
and the mapper's lane-parallel `cast_scan` against the reference on scans with every kind of ray."""
from __future__ import annotations

import numpy as np
import pytest

from services.lib.lidar.rays import ray_ends
from services.lib.voxels import traversal
from services.lib.voxels.traversal import accumulate_ray_lengths, cast_scan, cast_scan_per_ray

SHAPE = np.array([20, 16, 12])
CORNER = np.array([-1.0, -2.0, 0.5])
VOXEL = 0.5


def traverse(origin, ends):
    weights = np.zeros(int(SHAPE.prod()), np.float32)
    accumulate_ray_lengths(np.asarray(origin, float), np.asarray(ends, float).reshape(-1, 3), CORNER, VOXEL,
                           SHAPE, weights)
    return weights, np.flatnonzero(weights)


def sampled(origin, end, samples=200_000):
    """Brute force: the length of the segment in each voxel, by sampling it densely."""
    origin, end = np.asarray(origin, float), np.asarray(end, float)
    t = (np.arange(samples) + 0.5) / samples
    points = origin + t[:, None] * (end - origin)
    ijk = np.floor((points - CORNER) / VOXEL).astype(int)
    inside = np.all((ijk >= 0) & (ijk < SHAPE), axis=1)
    flat = np.ravel_multi_index(tuple(ijk[inside].T), tuple(SHAPE))
    return np.bincount(flat, minlength=int(SHAPE.prod())) * np.linalg.norm(end - origin) / samples


def cast_both(origin, points, beams, masked, max_distance, rotation=np.eye(3), shape=SHAPE):
    """The lanes' and the reference's weights for one scan."""
    args = (np.asarray(origin, float), np.ascontiguousarray(rotation, dtype=float),
            np.ascontiguousarray(points, dtype=np.float32), np.ascontiguousarray(beams, dtype=float),
            np.asarray(masked, bool), float(max_distance), CORNER, VOXEL, np.asarray(shape))
    lanes = np.zeros(int(np.prod(shape)))
    reference = np.zeros(int(np.prod(shape)))
    cast_scan(*args, lanes)
    cast_scan_per_ray(*args, reference)
    return lanes, reference


def random_scan(rng, origin, rays, max_range=12.0):
    beams = rng.normal(size=(rays, 3))
    beams /= np.linalg.norm(beams, axis=1, keepdims=True)
    points = np.asarray(origin) + beams * rng.uniform(0.2, max_range, rays)[:, None]
    return beams, points


@pytest.mark.parametrize("seed", range(6))
def test_traversal_lengths_sum_to_the_ray_and_match_a_brute_force_sampler(seed):
    rng = np.random.default_rng(seed)
    high = CORNER + SHAPE * VOXEL
    origin = rng.uniform(CORNER, high)
    end = rng.uniform(CORNER, high)
    weights, _ = traverse(origin, end)
    assert weights.sum() == pytest.approx(np.linalg.norm(end - origin), rel=1e-5)
    assert np.allclose(weights, sampled(origin, end), atol=2e-4)
    direction = (end - origin) / np.linalg.norm(end - origin)
    lanes, _ = cast_both(origin, end[None], direction[None], [False], 100.0)
    assert lanes.sum() == pytest.approx(np.linalg.norm(end - origin), rel=1e-5)
    assert np.allclose(lanes, sampled(origin, end), atol=2e-4)


def test_a_ray_leaving_the_grid_is_clipped_and_a_ray_outside_touches_nothing():
    origin = np.array([0.0, 0.0, 1.0])
    far = np.array([100.0, 0.0, 1.0])  # leaves through x = corner + 10 m
    weights, _ = traverse(origin, far)
    assert weights.sum() == pytest.approx(9.0 - 0.0, rel=1e-5)  # from x = 0 to x = 9 (= -1 + 20 × 0.5)
    assert np.allclose(weights, sampled(origin, far, 1_000_000), atol=1e-3)
    lanes, _ = cast_both(origin, far[None], [[1.0, 0.0, 0.0]], [False], 200.0)
    assert np.allclose(lanes, weights, atol=1e-5)
    weights, touched = traverse([50.0, 50.0, 50.0], [60.0, 50.0, 50.0])
    assert weights.sum() == 0.0 and len(touched) == 0
    lanes, _ = cast_both([50.0, 50.0, 50.0], [[60.0, 50.0, 50.0]], [[1.0, 0.0, 0.0]], [False], 20.0)
    assert not lanes.any()


def test_rays_along_grid_lines_and_through_corners():
    origin = CORNER + np.array([1.0, 1.0, 1.0])  # on a voxel corner
    ends = [origin + [3.0, 0, 0], origin + [2.0, 2.0, 2.0], origin + [0.0, 0.0, -0.7]]
    for end in ends:
        weights, _ = traverse(origin, end)
        assert weights.sum() == pytest.approx(np.linalg.norm(end - origin), rel=1e-5)
        assert np.allclose(weights, sampled(origin, end), atol=5e-4)
        lanes, _ = cast_both(origin, end[None], [[1.0, 0.0, 0.0]], [False], 20.0)
        assert lanes.sum() == pytest.approx(np.linalg.norm(end - origin), rel=1e-5)
        assert np.allclose(lanes, sampled(origin, end), atol=5e-4)


def test_accumulation_over_many_rays_is_the_sum_of_single_rays():
    rng = np.random.default_rng(7)
    origin = np.array([3.0, 1.0, 2.0])
    ends = origin + rng.normal(0, 3.0, (50, 3))
    together, _ = traverse(origin, ends)
    alone = sum(traverse(origin, e)[0].astype(np.float64) for e in ends)
    assert np.allclose(together, alone, atol=1e-4)


def test_casting_a_scan_equals_traversing_its_ray_ends():
    """cast_scan finds the ends of eq. 20 itself: the same lengths as ray_ends + accumulate_ray_lengths."""
    rng = np.random.default_rng(9)
    origin = np.array([3.0, 1.5, 3.0])
    beams, points = random_scan(rng, origin, 400)
    points[::7] = np.nan  # no return: cast along the beam to d_max
    masked = np.zeros(400, bool)
    masked[::11] = True
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the sensor yawed by 90°
    lanes, per_ray = cast_both(origin, points, beams @ turn, masked, 4.0, rotation=turn)  # sensor-frame beams
    reference, _ = traverse(origin, ray_ends(origin, points, beams, masked, 4.0))
    assert np.allclose(per_ray, reference, atol=1e-4)
    assert np.allclose(lanes, reference, atol=1e-4)


@pytest.mark.parametrize("seed, rays", [(1, 1), (2, 255), (3, 257), (4, 1000), (5, 3 * traversal.LANES)])
def test_the_lanes_give_the_reference_lengths_for_every_kind_of_ray(seed, rays):
    """Returns near and beyond d_max, no return (NaN, inf), masked rays, rays along the axes and
    along diagonals, zero and non-finite beams, a sensor inside the grid and outside it; a scan
    that does not fill its last block of lanes."""
    rng = np.random.default_rng(seed)
    for origin in (np.array([3.0, 1.5, 3.0]), CORNER + [0.0, 3.0, 2.0], CORNER + [-2.0, 3.3, 2.1]):
        beams, points = random_scan(rng, origin, rays)
        beams[::5] = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-0.6, 0.0, 0.8],
                      [0.5773502691896258] * 3][rng.integers(5)]
        points[::5] = origin + beams[::5] * rng.uniform(0.2, 12.0)
        points[1::9] = np.nan
        points[2::13] = np.inf
        beams[3::17] = 0.0
        beams[4::19] = np.nan
        masked = rng.random(rays) < 0.1
        lanes, reference = cast_both(origin, points, beams, masked, 6.0)
        assert np.allclose(lanes, reference, atol=1e-5, rtol=1e-5)
        assert lanes.sum() == pytest.approx(reference.sum(), rel=1e-6)


def test_the_lanes_give_the_same_bytes_every_time():
    rng = np.random.default_rng(11)
    origin = np.array([3.0, 1.5, 3.0])
    beams, points = random_scan(rng, origin, 2000)
    first, _ = cast_both(origin, points, beams, np.zeros(2000, bool), 8.0)
    second, _ = cast_both(origin, points, beams, np.zeros(2000, bool), 8.0)
    assert first.tobytes() == second.tobytes()


def test_a_grid_too_large_for_float32_indices_takes_the_per_ray_path():
    """Lanes hold voxel indices in float32, exact below 2^24: a larger window is cast ray by ray."""
    shape = np.array([257, 256, 256])  # 2^24 + 65536 voxels
    assert np.prod(shape) > traversal.MAX_LANE_VOXELS
    origin = CORNER + np.array([100.3, 100.2, 100.1])
    rng = np.random.default_rng(12)
    beams, points = random_scan(rng, origin, 50)
    weights = np.zeros(int(np.prod(shape)), np.float32)
    cast_scan(origin, np.eye(3), points.astype(np.float32), beams, np.zeros(50, bool), 30.0, CORNER, VOXEL, shape,
              weights)
    lengths = np.minimum(np.linalg.norm(points - origin, axis=1), 30.0)
    assert weights.sum(dtype=np.float64) == pytest.approx(lengths.sum(), rel=1e-5)
