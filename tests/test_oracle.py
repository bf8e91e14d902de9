"""Oracle detector: detections from the points that really hit a target, pairing by stamp."""
from __future__ import annotations

import numpy as np
import pytest

from schemas.messages import Obstacle, TargetTruth
from services.lib.lidar.models import lidar_model
from schemas.voxels import BACKGROUND, FLYING
from services.oracle.core import MAX_PENDING, OracleParams, ScanPairs, detect, label, scan_rng
from services.lib.voxels.grid import GridGeometry
from services.lib.world.primitives import primitives_from_obstacles
from services.sensor_driver.core import scan

NAN = np.nan


def synthetic_scan():
    """A 2 × 4 scan: target 1 hit three times, target 2 once, one NaN row flagged target 3."""
    points = np.array([
        [[1, 0, 0], [1.2, 0.1, 0], [1.1, -0.1, 0.3], [5, 5, 0]],
        [[9, 9, 9], [NAN, NAN, NAN], [NAN, NAN, NAN], [0, 0, -1]],
    ], dtype=np.float32)
    hits = np.array([[1, 1, 1, 0], [2, 3, 3, -1]], dtype=np.int32)
    return points, hits


def test_centroid_count_and_extent_without_noise():
    points, hits = synthetic_scan()
    found = detect(points, hits, OracleParams(min_points=2, sigma=0.0), scan_rng(0, "uav1"))
    assert found.targets.tolist() == [1]  # target 2 returned one point, target 3 none that are real
    assert np.allclose(found.positions[0], [1.1, 0.0, 0.1], atol=1e-6)
    assert found.point_counts.tolist() == [3] and found.point_counts.dtype == np.int32
    assert np.allclose(found.extents, [0.3]) and found.extents.dtype == np.float32  # z 0 … 0.3
    assert np.array_equal(found.covariances, np.zeros((1, 3, 3)))
    single = detect(points, hits, OracleParams(min_points=1, sigma=0.0), scan_rng(0, "uav1"))
    assert single.targets.tolist() == [1, 2] and single.point_counts.tolist() == [3, 1]
    assert np.allclose(single.positions[1], [9, 9, 9]) and single.extents[1] == 0.0


def test_label_sets_are_a_perfect_classifiers_for_the_mapper():
    """Returns on a target make a flying object's voxel (weight inf), the rest background voxels
    weighted by their returns; no return and a return outside the map make none."""
    points, hits = synthetic_scan()
    geometry = GridGeometry((-1.0, -1.0, -1.0), (20, 20, 20), 0.5)  # x, y, z in [-1, 9): (9, 9, 9) is outside
    slot = np.full(geometry.size, -1, np.int32)
    labels = label(points, hits, geometry, slot)
    assert len(labels.points) == 6 and labels.point_labels.tolist() == [FLYING] * 3 + [BACKGROUND, FLYING, BACKGROUND]
    by_voxel = {tuple(v): (int(k), float(w)) for v, k, w in zip(labels.voxels, labels.voxel_labels, labels.voxel_weights)}
    assert by_voxel == {(4, 2, 2): (FLYING, np.inf), (4, 1, 2): (FLYING, np.inf), (12, 12, 2): (BACKGROUND, 1.0),
                        (2, 2, 0): (BACKGROUND, 1.0)}
    assert np.all(slot == -1)  # the scratch is left as found
    with pytest.raises(ValueError):
        label(points, hits[:, :2], geometry, slot)


def test_noise_is_gaussian_seeded_by_stamp_and_uav():
    points, hits = synthetic_scan()
    params = OracleParams(sigma=0.1)
    a = detect(points, hits, params, scan_rng(100_000_000, "uav1"))
    again = detect(points, hits, params, scan_rng(100_000_000, "uav1"))
    other_uav = detect(points, hits, params, scan_rng(100_000_000, "uav2"))
    other_scan = detect(points, hits, params, scan_rng(200_000_000, "uav1"))
    assert np.array_equal(a.positions, again.positions)
    assert not np.array_equal(a.positions, other_uav.positions)
    assert not np.array_equal(a.positions, other_scan.positions)
    assert np.allclose(a.covariances[0], 0.01 * np.eye(3))
    errors = np.concatenate([detect(points, hits, params, scan_rng(s, "uav1")).positions - [1.1, 0.0, 0.1]
                             for s in range(2000)])
    assert abs(errors.mean()) < 0.01 and abs(errors.std() - 0.1) < 0.005


def test_empty_and_mismatched_scans():
    none = detect(np.full((2, 3, 3), np.nan, np.float32), np.full((2, 3), -1, np.int32), OracleParams(),
                  scan_rng(0, "uav1"))
    assert none.positions.shape == (0, 3) and none.covariances.shape == (0, 3, 3)
    assert none.point_counts.shape == (0,) and none.extents.shape == (0,)
    with pytest.raises(ValueError, match="same rays"):
        detect(np.zeros((2, 3, 3), np.float32), np.zeros((3, 2), np.int32), OracleParams(), scan_rng(0, "uav1"))


def test_visibility_and_occlusion_come_from_the_real_scan():
    sensor = np.array([0.0, 0.0, 5.0])
    balloons = [TargetTruth(id="seen", kind="balloon", position=(12.0, 0.0, 5.0), velocity=(0, 0, 0), radius=0.3),
                TargetTruth(id="hidden", kind="balloon", position=(0.0, 14.0, 5.0), velocity=(0, 0, 0), radius=0.3),
                TargetTruth(id="far", kind="balloon", position=(-80.0, 0.0, 5.0), velocity=(0, 0, 0), radius=0.3)]
    wall = Obstacle(kind="box", center=(0.0, 8.0, 5.0), size=(4.0, 0.5, 10.0))  # between the sensor and "hidden"
    world = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0)), wall]).with_targets(balloons)
    model = lidar_model("os0-128")
    result = scan(sensor, 0.0, model.directions(0), world, np.random.default_rng(1), max_range=model.max_range)
    found = detect(result.points, result.hits, OracleParams(), scan_rng(0, "uav1"))
    assert found.targets.tolist() == [1]  # hidden behind the wall; beyond the 50 m range
    # The centroid of the visible cap sits between the centre and the near surface, plus noise.
    assert np.linalg.norm(found.positions[0] - [12.0, 0.0, 5.0]) < 0.3 + 0.5
    assert found.point_counts[0] >= 10


def test_scan_pairs_match_by_stamp_in_either_order():
    pairs = ScanPairs()
    assert pairs.add(100, cloud="c100") is None
    assert pairs.add(200, truth="t200") is None
    assert pairs.add(100, truth="t100") == ("c100", "t100")
    assert pairs.add(200, cloud="c200") == ("c200", "t200")
    assert pairs.add(150, cloud="late") is None and pairs.dropped == 1  # older than a finished pair
    assert pairs.add(300, cloud="c300") is None
    assert pairs.add(400, cloud="c400") is None
    assert pairs.add(400, truth="t400") == ("c400", "t400")  # 300 never got its truth: dropped
    assert not pairs.clouds and not pairs.truths and pairs.dropped == 2
    for stamp in range(1000, 1000 + MAX_PENDING + 5):
        pairs.add(stamp, cloud=stamp)
    assert len(pairs.clouds) == MAX_PENDING  # a missing stream does not grow memory
