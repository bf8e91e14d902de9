"""Mapper core (first version): label assignments, sampled free-space rays, deltas, snapshots."""
from __future__ import annotations

import numpy as np

from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.mapper.core import MapperCore, MapperParams

SMALL = MapperParams(origin=(0.0, 0.0, 0.0), shape=(40, 20, 20))  # 20 x 10 x 10 m


def voxel_of(core: MapperCore, point) -> tuple[int, int, int]:
    return tuple(np.floor((np.asarray(point) - core.origin) / core.voxel_size).astype(int))


def flat_of(core: MapperCore, voxels) -> np.ndarray:
    return np.ravel_multi_index(tuple(np.asarray(voxels).T), core.shape)


def test_default_area_fits_120_by_100_by_25_m():
    p = MapperParams()
    size = np.asarray(p.shape) * p.voxel_size
    assert np.all(size >= (120.0, 100.0, 25.0))
    assert MapperCore().grid.dtype == np.float32 and np.all(MapperCore(SMALL).grid == -740.0)


def test_background_labels_set_occupied():
    core = MapperCore(SMALL)
    voxels = np.array([[4, 4, 0], [5, 4, 0], [6, 4, 0]], dtype=np.int32)
    indices, values = core.apply_labels((0.0, 0.0, 5.0), np.zeros((0, 3)), voxels, np.zeros(3, np.uint8))
    assert np.all(core.grid[4:7, 4, 0] == 0.0)
    assert indices.tolist() == sorted(flat_of(core, voxels).tolist())
    assert np.all(values == 0.0)
    # Voxels outside the map are dropped, not wrapped.
    outside = np.array([[-1, 0, 0], [40, 0, 0]], dtype=np.int32)
    indices, _ = core.apply_labels((0.0, 0.0, 5.0), np.zeros((0, 3)), outside, np.zeros(2, np.uint8))
    assert len(indices) == 0


def test_ray_marks_traversed_voxels_free_but_not_the_end_voxel():
    core = MapperCore(SMALL)
    sensor = np.array([1.25, 5.25, 5.25])  # voxel centres: the ray runs along x through voxels 2..17
    end = np.array([8.75, 5.25, 5.25])
    end_voxel = voxel_of(core, end)
    core.apply_labels(sensor, end[None], np.array([end_voxel], np.int32), np.array([UNKNOWN], np.uint8))
    row = core.grid[:, 10, 10]
    assert np.all(row[2:17] == -1000.0)
    assert row[17] == -740.0  # the end voxel holds a point: not free
    assert row[1] == -740.0 and row[18] == -740.0
    assert np.count_nonzero(core.grid == -1000.0) == 15


def test_ray_is_cut_at_the_raycast_max_distance():
    core = MapperCore(MapperParams(origin=(0.0, 0.0, 0.0), shape=(80, 4, 4), raycast_max_distance=20.0))
    sensor = np.array([0.25, 1.25, 1.25])
    end = np.array([35.25, 1.25, 1.25])
    core.apply_labels(sensor, end[None], np.zeros((0, 3), np.int32), np.zeros(0, np.uint8))
    free = np.flatnonzero(core.grid[:, 2, 2] == -1000.0)
    assert free.min() == 0 and free.max() == 40  # 0.25 m + 20 m lies in voxel 40


def test_rays_do_not_clear_confident_occupied_voxels():
    core = MapperCore(SMALL)
    wall = (10, 10, 10)
    core.apply_labels((0, 0, 0), np.zeros((0, 3)), np.array([wall], np.int32), np.array([BACKGROUND], np.uint8))
    sensor, end = np.array([1.25, 5.25, 5.25]), np.array([8.75, 5.25, 5.25])
    indices, _ = core.apply_labels(sensor, end[None], np.zeros((0, 3), np.int32), np.zeros(0, np.uint8))
    assert core.grid[wall] == 0.0
    assert flat_of(core, [wall])[0] not in indices


def test_delta_contains_exactly_the_changed_voxels():
    core = MapperCore(SMALL)
    sensor = np.array([1.25, 5.25, 5.25])
    points = np.array([[8.75, 5.25, 5.25], [1.25, 5.25, 1.25]])
    voxels = np.array([voxel_of(core, pt) for pt in points], np.int32)
    labels = np.array([BACKGROUND, FLYING], np.uint8)
    before = core.grid.copy()
    indices, values = core.apply_labels(sensor, points, voxels, labels)
    changed = np.flatnonzero(core.grid.reshape(-1) != before.reshape(-1))
    assert indices.tolist() == changed.tolist()
    assert np.array_equal(values, core.grid.reshape(-1)[changed])
    # The flying object's voxel takes g_unk = -740 (unchanged from the initial value, so not in the delta).
    assert flat_of(core, voxels[1:])[0] not in indices
    # Replaying the same scan changes nothing.
    again, _ = core.apply_labels(sensor, points, voxels, labels)
    assert len(again) == 0


def test_flying_voxel_previously_free_becomes_unknown():
    core = MapperCore(SMALL)
    sensor, end = np.array([1.25, 5.25, 5.25]), np.array([8.75, 5.25, 5.25])
    core.apply_labels(sensor, end[None], np.zeros((0, 3), np.int32), np.zeros(0, np.uint8))
    target = (8, 10, 10)
    assert core.grid[target] == -1000.0
    no_points = np.zeros((0, 3))
    indices, values = core.apply_labels(sensor, no_points, np.array([target], np.int32), np.array([FLYING], np.uint8))
    assert core.grid[target] == -740.0 and values.tolist() == [-740.0]


def test_snapshot_lists_the_non_default_voxels():
    core = MapperCore(SMALL)
    assert len(core.snapshot()[0]) == 0
    sensor = np.array([1.25, 5.25, 5.25])
    points = np.array([[8.75, 5.25, 5.25]])
    core.apply_labels(sensor, points, np.array([voxel_of(core, points[0])], np.int32), np.array([BACKGROUND], np.uint8))
    indices, values = core.snapshot()
    expected = np.flatnonzero(core.grid.reshape(-1) != -740.0)
    assert indices.tolist() == expected.tolist() and len(indices) == 16
    assert indices.dtype == np.int64 and values.dtype == np.float32
    rebuilt = np.full(core.grid.size, -740.0, np.float32)
    rebuilt[indices] = values
    assert np.array_equal(rebuilt.reshape(core.shape), core.grid)


def test_many_rays_at_once():
    core = MapperCore()
    rng = np.random.default_rng(3)
    sensor = np.array([50.0, 40.0, 5.0])
    points = sensor + rng.uniform(-15.0, 15.0, (1000, 3))
    points[:, 2] = np.clip(points[:, 2], 0.1, 20.0)
    free = core.traversed_voxels(sensor, points)
    assert len(free) > 1000
    # Batching changes nothing: the set is the union of the rays taken one at a time.
    expected = set()
    for point in points[:50]:
        expected |= set(core.traversed_voxels(sensor, point[None]).tolist())
    assert expected == set(core.traversed_voxels(sensor, points[:50]).tolist())
    assert np.all(np.diff(free) > 0)
    centres = (np.stack(np.unravel_index(free, core.shape), axis=1) + 0.5) * core.voxel_size + core.origin
    assert np.linalg.norm(centres - sensor, axis=1).max() < 15.0 * 3**0.5 + core.voxel_size
