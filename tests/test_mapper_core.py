"""Mapper core (seed 000 sec. III-A, C, D, E): the exponential update, label sets, exact ray
casting with per-voxel lengths, class-quantised deltas, the separate-cluster reset, pinned voxels
and bad input."""
from __future__ import annotations

import numpy as np
import pytest

from schemas import voxels
from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.lib.lidar.rays import ScanRays
from services.lib.voxels import traversal
from services.mapper import update as mapper_kernels
from services.mapper.core import MapperCore, MapperParams, exponential_update, warm_up
from tests.tools.compiled import in_fresh_interpreter, newly_compiled

SMALL = MapperParams(origin=(0.0, 0.0, 0.0), shape=(40, 20, 20), separation_period=1e9)  # 20 × 10 × 10 m
NO_LABELS = (np.zeros((0, 3), np.int32), np.zeros(0, np.uint8), np.zeros(0, np.float32))


def rays(origin, points, beams=None, masked=None) -> ScanRays:
    """Rays from `origin` ending at `points` (a return: the ray ends there, or at d_max if farther)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    return ScanRays(np.asarray(origin, dtype=np.float64), np.eye(3), pts, beams, masked)


def voxel_of(core: MapperCore, point) -> tuple[int, int, int]:
    return tuple(np.floor((np.asarray(point) - core.origin) / core.voxel_size).astype(int))


def labels(*rows):
    """Label sets from (voxel, label, weight) rows."""
    return (np.array([r[0] for r in rows], np.int32).reshape(-1, 3), np.array([r[1] for r in rows], np.uint8),
            np.array([r[2] for r in rows], np.float32))


def test_default_area_fits_120_by_100_by_25_m():
    p = MapperParams()
    size = np.asarray(p.shape) * p.voxel_size
    assert np.all(size >= (120.0, 100.0, 25.0))
    assert MapperCore().grid.dtype == np.float32 and np.all(MapperCore(SMALL).grid == -740.0)


@pytest.mark.parametrize("g", [0.0, -740.0, -1000.0])
@pytest.mark.parametrize("start", [-740.0, -3.0, -999.0])
def test_eq_12_is_n_applications_of_eq_8(g, start):
    value = np.float64(start)
    for n in range(1, 7):
        value = (value + g) / 2.0  # eq. 8
        assert exponential_update(np.array([start]), np.array([float(n)]), g)[0] == pytest.approx(value, rel=1e-6)
    # real n lies between its integer neighbours; n = inf sets the target; 0 leaves it; pinned stays
    half = exponential_update(np.array([start]), np.array([2.5]), g)[0]
    assert min(exponential_update(np.array([start]), np.array([2.0]), g)[0],
               exponential_update(np.array([start]), np.array([3.0]), g)[0]) <= half + 1e-3
    assert exponential_update(np.array([start]), np.array([np.inf]), g)[0] == g
    assert exponential_update(np.array([start]), np.array([0.0]), g)[0] == np.float32(start)
    assert exponential_update(np.array([np.inf, -np.inf]), np.array([5.0, 5.0]), g).tolist() == [np.inf, -np.inf]


def test_label_sets_move_voxels_by_their_weights():
    core = MapperCore(SMALL)
    sensor = (5.0, 5.0, 5.0)
    core.integrate(0, rays(sensor, np.zeros((0, 3))), *labels(((4, 4, 0), BACKGROUND, 3.0), ((6, 4, 0), UNKNOWN, 2.0),
                                                         ((8, 4, 0), FLYING, 1.0)))
    assert core.grid[4, 4, 0] == pytest.approx(-740.0 / 8)  # 2^-3 · -740 + (1 - 2^-3) · 0
    assert core.grid[6, 4, 0] == -740.0  # towards g_unk, which it already is
    core.grid[8, 4, 1] = -1000.0
    delta = core.integrate(1, rays(sensor, np.zeros((0, 3))), *labels(((8, 4, 1), FLYING, 1.0)))
    assert core.grid[8, 4, 1] == -740.0  # n_det = ∞: set to g_unk at once, whatever the weight said
    assert delta.indices.tolist() == [np.ravel_multi_index((8, 4, 1), core.shape)]  # free -> uncertain


def test_ray_lengths_are_the_free_weights_and_point_voxels_are_not_cleared():
    core = MapperCore(SMALL)
    sensor = np.array([1.25, 5.25, 5.25])  # voxel centres: the ray runs along x through voxels 2..17
    end = np.array([8.75, 5.25, 5.25])
    end_voxel = voxel_of(core, end)
    core.integrate(0, rays(sensor, end[None]), *labels((end_voxel, UNKNOWN, 1.0)))
    row = core.grid[:, 10, 10]
    crossing = exponential_update(np.array([-740.0]), np.array([0.5]), -1000.0)[0]  # 0.5 m inside each voxel
    start = exponential_update(np.array([-740.0]), np.array([0.25]), -1000.0)[0]  # the sensor's own half voxel
    assert row[2] == pytest.approx(start) and np.allclose(row[3:17], crossing)
    assert row[17] == -740.0  # the end voxel holds the point: not cleared
    assert row[1] == -740.0 and row[18] == -740.0
    assert np.count_nonzero(core.grid != -740.0) == 15


def test_rays_are_cut_at_d_max_and_rays_without_return_reach_it():
    params = MapperParams(origin=(0.0, 0.0, 0.0), shape=(80, 4, 4), raycast_max_distance=20.0, separation_period=1e9)
    sensor = np.array([0.25, 1.25, 1.25])
    far_return = rays(sensor, [sensor + [35.0, 0.0, 0.0]])
    no_return = rays(sensor, [[np.nan] * 3], beams=np.array([[1.0, 0.0, 0.0]]))  # eq. 20: cast along its beam
    for scan in (far_return, no_return):
        core = MapperCore(params)
        core.integrate(0, scan, *NO_LABELS)
        changed = np.flatnonzero(core.grid[:, 2, 2] != -740.0)
        assert changed.min() == 0 and changed.max() == 40  # 0.25 m + 20 m lies in voxel 40
    core = MapperCore(params)
    core.integrate(0, rays(sensor, [[np.nan] * 3]), *NO_LABELS)  # no return and no known beam: no ray
    assert (core.grid == -740.0).all()


def test_masked_rays_are_skipped_and_beams_turn_with_the_sensor():
    core = MapperCore(SMALL)
    sensor = np.array([5.25, 5.25, 5.25])
    beams = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    heading = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90°: sensor x is world y
    scan = ScanRays(sensor, heading, np.full((2, 3), np.nan, np.float32), beams, np.array([True, False]))
    core.integrate(0, scan, *NO_LABELS)
    changed = np.argwhere(core.grid != -740.0)
    assert set(changed[:, 0]) == {10} and set(changed[:, 2]) == {10}  # along world +y only, nothing below
    assert changed[:, 1].min() == 10 and changed[:, 1].max() == 19


def test_deltas_list_state_changes_only():
    core = MapperCore(SMALL)
    sensor = np.array([1.25, 5.25, 5.25])
    first = core.integrate(0, rays(sensor, np.array([[8.75, 5.25, 5.25]])), *NO_LABELS)
    assert len(first.indices) == 16 and np.all(first.values < voxels.UNCERTAIN)  # unknown -> free at once
    second = core.integrate(1, rays(sensor, np.array([[8.75, 5.25, 5.25]])), *NO_LABELS)
    assert len(second.indices) == 0  # values moved further towards free, no state changed
    assert first.indices.dtype == np.int32 and first.values.dtype == np.float32
    snapshot = core.snapshot()
    assert len(snapshot.indices) == 16


def test_pinned_voxels_never_change():
    core = MapperCore(SMALL)
    wall = np.ravel_multi_index(([10, 10], [10, 11], [10, 10]), core.shape)
    core.pin(wall[:1], np.inf)
    core.pin(wall[1:], -np.inf)
    sensor = np.array([1.25, 5.25, 5.25])
    for step in range(3):
        core.integrate(step, rays(sensor, np.array([[9.75, 5.25, 5.25], [9.75, 5.75, 5.25]])),
                       *labels(((10, 10, 10), UNKNOWN, 5.0), ((10, 11, 10), BACKGROUND, 5.0)))
    assert core.grid[10, 10, 10] == np.inf and core.grid[10, 11, 10] == -np.inf
    assert voxels.map_states(core.grid[10, 10:12, 10]).tolist() == [voxels.STATE_OCCUPIED, voxels.STATE_FREE]


def test_separate_cluster_reset_frees_what_a_drone_left_beside_a_wall():
    """Fig. 4: a drone standing against a wall was mapped as background with it; once it has left,
    its voxels form a small occupied cluster apart from the wall (eq. 23)."""
    p = MapperParams(origin=(0.0, 0.0, 0.0), shape=(40, 20, 20), separation_period=0.0, separation_min_confident=24)
    core = MapperCore(p)
    wall = [(x, 15, z) for x in range(5, 15) for z in range(0, 8)]  # 80 confident voxels
    drone = [(9, 12, 4), (10, 12, 4), (9, 12, 5)]  # 3 voxels, 1.5 m from the wall: a cluster of its own
    touching = [(12, 14, 3)]  # next to the wall: part of the wall's cluster
    for v in wall + drone + touching:
        core.grid[v] = 0.0
    sensor = np.array([10.0, 2.0, 5.0])
    assert len(core.integrate(0, rays(sensor, np.zeros((0, 3))), *NO_LABELS).indices) == 0  # the first scan: not yet
    delta = core.integrate(1, rays(sensor, np.zeros((0, 3))), *NO_LABELS)
    assert all(core.grid[v] < voxels.TENTATIVE_OCCUPIED for v in drone)  # 2^-1·0 + ½·-1000 = -500: uncertain
    assert all(core.grid[v] == 0.0 for v in wall + touching)
    assert set(delta.indices.tolist()) == {np.ravel_multi_index(v, core.shape) for v in drone}
    assert core.counters.resets == 3


@pytest.mark.parametrize("seed, d_sep", [(0, 0.8), (1, 0.8), (2, 0.45), (3, 0.9)])
def test_the_reset_groups_voxels_as_connected_component_labelling_does(seed, d_sep):
    """The compiled grouping of eq. 23 against scipy.ndimage.label on random maps: the same voxels
    reset, for 6-, 18- and 26-neighbourhoods (d_sep of 0.45, 0.8 and 0.9 m over 0.5 m voxels)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    p = MapperParams(origin=(0.0, 0.0, 0.0), shape=(40, 30, 20), separation_period=0.0, separation_min_confident=3,
                     separation_distance=d_sep, separation_reach=6.0)
    core = MapperCore(p)
    core.grid[...] = rng.choice([-1000.0, -500.0, -200.0, 0.0, np.inf], size=core.shape, p=[0.8, 0.12, 0.05, 0.025, 0.005])
    before = core.grid.copy()
    sensor = np.array([10.2, 7.7, 5.1])
    low, high = core.geometry.window(sensor, p.separation_reach)
    box = before[low[0]:high[0], low[1]:high[1], low[2]:high[2]]
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1)
    structure = np.linalg.norm(offsets, axis=-1) <= max(d_sep / p.voxel_size, 1.0) + 1e-9
    groups, count = ndimage.label(box >= np.float32(voxels.TENTATIVE_OCCUPIED), structure=structure)
    confident = np.bincount(groups[box >= np.float32(voxels.CONFIDENT_OCCUPIED)], minlength=count + 1)
    weak = confident < p.separation_min_confident
    weak[0] = False
    expected = np.zeros(core.shape, bool)
    expected[low[0]:high[0], low[1]:high[1], low[2]:high[2]] = weak[groups]
    expected &= np.isfinite(before)
    core.integrate(0, rays(sensor, np.zeros((0, 3))), *NO_LABELS)
    core.integrate(1, rays(sensor, np.zeros((0, 3))), *NO_LABELS)
    reset = core.grid != before
    assert 0 < expected.sum() < (box >= np.float32(voxels.TENTATIVE_OCCUPIED)).sum()  # a case that tells
    assert np.array_equal(reset, expected)
    assert core.counters.resets == expected.sum()


def test_bad_label_sets_are_refused_whole_and_the_map_is_never_corrupted():
    core = MapperCore(SMALL)
    before = core.grid.copy()
    sensor = (5.0, 5.0, 5.0)
    for bad in (labels(((4, 4, 0), 7, 1.0)),  # no such label
                labels(((4, 4, 0), BACKGROUND, np.nan)),  # NaN weight
                labels(((4, 4, 0), BACKGROUND, -2.0)),  # negative weight
                (np.zeros((2, 3), np.int32), np.zeros(1, np.uint8), np.ones(2, np.float32))):  # lengths differ
        core.integrate(0, rays(sensor, np.zeros((0, 3))), *bad)
    assert core.counters.rejected_label_sets == 4 and np.array_equal(core.grid, before)
    core.integrate(0, rays(sensor, np.zeros((0, 3))), *labels(((-1, 0, 0), BACKGROUND, 1.0), ((40, 0, 0), BACKGROUND, 1.0)))
    assert core.counters.voxels_outside == 2 and np.array_equal(core.grid, before)
    # rays: NaN or infinite ends are dropped, a NaN sensor position casts nothing
    core.integrate(0, rays(sensor, np.array([[np.nan, 1, 1], [np.inf, 1, 1]])), *NO_LABELS)
    core.integrate(0, rays((np.nan, 0.0, 0.0), np.array([[9.0, 5.0, 5.0]])), *NO_LABELS)
    assert np.array_equal(core.grid, before)
    # points that are not (N, 3), a rotation that is not finite: refused and counted
    core.integrate(0, ScanRays(np.array(sensor), np.eye(3), np.ones((4, 2), np.float32), None, None), *NO_LABELS)
    core.integrate(0, ScanRays(np.array(sensor), np.full((3, 3), np.nan), np.ones((4, 3), np.float32), None, None),
                   *NO_LABELS)
    assert core.counters.rejected_rays == 3 and np.array_equal(core.grid, before)
    assert np.isfinite(core.grid).all()


def test_many_rays_are_deterministic():
    rng = np.random.default_rng(11)
    sensor = np.array([10.0, 5.0, 5.0])
    ends = sensor + rng.normal(0, 6.0, (5000, 3))
    results = []
    for _ in range(2):
        core = MapperCore(SMALL)
        core.integrate(0, rays(sensor, ends), *NO_LABELS)
        results.append(core.grid.copy())
    assert np.array_equal(results[0], results[1])


def compiled_by_real_scans_after_warm_up() -> dict:
    """In a fresh interpreter (tests/tools/compiled.py): what warm_up changed, then the kernels
    real scans (beams, masked rays, label sets, the separate-cluster reset) still compile or load."""
    modules = (mapper_kernels, traversal)
    changed = []
    warmed = newly_compiled(modules, lambda: changed.append(warm_up(SMALL)))
    core = MapperCore(MapperParams(origin=(0.0, 0.0, 0.0), shape=(40, 20, 20), separation_period=0.0))
    beams = np.tile([[1.0, 0.0, 0.0]], (3, 1))
    scan = rays([2.0, 5.0, 5.0], [[8.0, 5.0, 5.0], [np.nan] * 3, [6.0, 5.0, 5.0]], beams, np.array([False, False, True]))

    def two_scans():
        for stamp in (0, 1):
            core.integrate(stamp, scan, *labels(((16, 10, 10), BACKGROUND, 2.0), ((12, 10, 10), FLYING, 1.0)))
    left = newly_compiled(modules, two_scans)
    return {"changed": changed[0], "warmed": warmed, "left": left, "resets_due": core.counters.scans}


def test_warm_up_leaves_no_kernel_for_a_real_scan_to_compile():
    """The node warms up before its liveliness token: real scans must then find every kernel
    compiled for their types (a cold compile takes seconds)."""
    result = in_fresh_interpreter(compiled_by_real_scans_after_warm_up)
    assert result["changed"] > 0 and result["warmed"] and result["resets_due"] == 2
    assert result["left"] == []
