"""Classifier core (seed 000 sec. III-B, IV-A): clusters, rules A / B / unknown on constructed maps,
label sets with weights, detections with centroid, covariance and confidence, bad input."""
from __future__ import annotations

import msgspec
import numpy as np
import pytest

from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.classifier import kernels as classifier_kernels
from services.classifier.core import ClassifierCore, ClassifierParams, SensorPose, warm_up
from services.lib.voxels import kernels as voxel_kernels
from tests.tools.compiled import in_fresh_interpreter, newly_compiled

ORIGIN, SHAPE, VOXEL = (0.0, 0.0, 0.0), (80, 60, 30), 0.5  # 40 × 30 × 15 m
PARAMS = ClassifierParams(map_origin=ORIGIN, map_shape=SHAPE)
SENSOR = SensorPose(np.array([5.0, 15.0, 5.0]), np.eye(3))
BALL_CENTRE = np.array([15.0, 15.0, 6.0])


def ball(centre=BALL_CENTRE, radius=0.3, count=60, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    return np.asarray(centre) + radius * directions / np.linalg.norm(directions, axis=1, keepdims=True)


def classifier(free=(), occupied=(), params=PARAMS) -> ClassifierCore:
    """A classifier whose map replica has confident free boxes and tentatively occupied voxels."""
    core = ClassifierCore(params)
    indices, values = [], []
    for low, high in free:
        ijk = np.stack(np.meshgrid(*[np.arange(int(a / VOXEL), int(b / VOXEL)) for a, b in zip(low, high)],
                                   indexing="ij"), axis=-1).reshape(-1, 3)
        indices.append(np.ravel_multi_index(tuple(ijk.T), SHAPE))
        values.append(np.full(len(ijk), -1000.0))
    for point in occupied:
        ijk = np.floor(np.asarray(point) / VOXEL).astype(int)
        indices.append([np.ravel_multi_index(tuple(ijk), SHAPE)])
        values.append([-100.0])
    core.apply_map(True, ORIGIN, SHAPE, VOXEL, -740.0, np.concatenate(indices or [[]]).astype(np.int64),
                   np.concatenate(values or [[]]).astype(np.float32))
    return core


FREE_AROUND_BALL = [((11.0, 11.0, 2.0), (19.0, 19.0, 10.0))]


def test_a_ball_walled_off_by_free_space_is_a_flying_object():
    eq_19 = ClassifierParams(map_origin=ORIGIN, map_shape=SHAPE, surface_bias=0.0)
    scan = classifier(free=FREE_AROUND_BALL, params=eq_19).classify(ball(), SENSOR)
    assert (scan.point_labels == FLYING).all()
    assert len(scan.positions) == 1
    assert np.allclose(scan.positions[0], ball().mean(axis=0))  # eq. 19: the centroid of its returns
    assert scan.point_counts.tolist() == [60] and 0.5 < scan.extents[0] <= 0.6


def facing_hemisphere(radius=0.325, count=400, seed=1) -> np.ndarray:
    """Returns of parallel rays from -x on a sphere at BALL_CENTRE: uniform over its projected disc."""
    rng = np.random.default_rng(seed)
    rho, angle = radius * np.sqrt(rng.uniform(0, 1, count)), rng.uniform(0, 2 * np.pi, count)
    y, z = rho * np.cos(angle), rho * np.sin(angle)
    return BALL_CENTRE + np.column_stack([-np.sqrt(radius ** 2 - rho ** 2), y, z])


def test_the_one_sided_sampling_bias_is_taken_out_of_the_centre_estimate():
    sensor = SensorPose(np.array([5.0, 15.0, 6.0]), np.eye(3))
    plain = ClassifierParams(map_origin=ORIGIN, map_shape=SHAPE, surface_bias=0.0)
    for params, largest_error in ((plain, None), (PARAMS, 0.03)):
        (position,) = classifier(free=FREE_AROUND_BALL, params=params).classify(facing_hemisphere(), sensor).positions
        error = position - BALL_CENTRE
        if largest_error is None:  # eq. 19: 2a/3 in front of the centre, towards the sensor
            assert error[0] == pytest.approx(-2 / 3 * 0.325, abs=0.02) and abs(error[1:]).max() < 0.03
        else:
            assert np.linalg.norm(error) < largest_error
    with pytest.raises(ValueError, match="surface_bias"):
        ClassifierParams(surface_bias=1.5)


def test_the_same_ball_in_unknown_space_is_unknown_rule_b_needs_the_map():
    scan = classifier().classify(ball(), SENSOR)
    assert (scan.point_labels == UNKNOWN).all() and len(scan.positions) == 0


def test_a_gap_in_the_free_space_leading_to_the_search_cube_keeps_it_unknown():
    gapped = [((11.0, 11.0, 2.0), (15.0, 19.0, 10.0)), ((15.5, 11.0, 2.0), (19.0, 19.0, 10.0)),
              ((15.0, 11.0, 2.0), (15.5, 14.5, 10.0)), ((15.0, 15.5, 2.0), (15.5, 19.0, 10.0))]  # a tunnel at y 15
    assert (classifier(free=gapped).classify(ball(), SENSOR).point_labels == UNKNOWN).all()


def test_rule_a_a_point_within_d_close_of_a_tentative_voxel_makes_the_cluster_background():
    near = classifier(free=FREE_AROUND_BALL, occupied=[BALL_CENTRE + [1.4, 0, 0]]).classify(ball(), SENSOR)
    assert (near.point_labels == BACKGROUND).all() and len(near.positions) == 0
    # 2.5 m away is beyond d_close; reachable through non-free space it would still stop rule B,
    # but here it sits inside the free box, walled off from the ball
    far = classifier(free=FREE_AROUND_BALL, occupied=[BALL_CENTRE + [2.5, 0, 0]]).classify(ball(), SENSOR)
    assert (far.point_labels == BACKGROUND).sum() == 0


def test_a_cluster_too_big_to_be_a_target_is_background_even_on_an_empty_map():
    xs, zs = np.meshgrid(np.arange(20.0, 25.0, 0.2), np.arange(1.0, 6.0, 0.2))
    wall = np.stack([xs.ravel(), np.full(xs.size, 10.0), zs.ravel()], axis=1)
    scan = classifier().classify(np.vstack([wall, ball()]), SENSOR)
    assert (scan.point_labels[:len(wall)] == BACKGROUND).all()
    assert (scan.point_labels[len(wall):] == UNKNOWN).all()  # the ball is 5 m away: its own cluster


def test_too_few_returns_or_too_far_stays_unknown():
    core = classifier(free=FREE_AROUND_BALL)
    assert core.classify(ball(count=1), SENSOR).point_labels.tolist() == [UNKNOWN]
    far_sensor = SensorPose(np.array([-60.0, 15.0, 6.0]), np.eye(3))
    assert (core.classify(ball(), far_sensor).point_labels == UNKNOWN).all()


def test_clustering_distance_is_1_5_m():
    """Eq. 13–15 on (nearly) undownsampled returns: two balls whose surfaces are 1.3 m apart are one
    cluster, 1.7 m apart two."""
    fine = msgspec.structs.replace(PARAMS, downsample=0.05)  # 5 cm cells: 1 in 20 of the gaps tested
    core = ClassifierCore(fine)
    core.map = classifier(free=[((11.0, 11.0, 2.0), (21.0, 19.0, 10.0))]).map
    near, touching = ball(BALL_CENTRE, count=400), ball(BALL_CENTRE + [1.9, 0, 0], count=400, seed=1)
    assert len(core.classify(np.vstack([near, touching]), SENSOR).positions) == 1
    apart = ball(BALL_CENTRE + [2.3, 0, 0], count=400, seed=1)
    assert len(core.classify(np.vstack([near, apart]), SENSOR).positions) == 2


def test_label_sets_count_returns_per_voxel_with_infinite_weight_for_flying_objects():
    core = classifier(free=FREE_AROUND_BALL)
    xs, ys = np.meshgrid(np.arange(20.0, 26.0, 0.1), np.arange(20.0, 26.0, 0.1))
    ground = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.1)], axis=1)  # 6 × 6 m: background
    scan = core.classify(np.vstack([ground, ball()]), SENSOR)
    flying = scan.voxel_labels == FLYING
    assert np.isinf(scan.voxel_weights[flying]).all() and flying.any()
    background = scan.voxel_labels == BACKGROUND
    assert scan.voxel_weights[background].sum() == len(ground)  # eq. 16: n = returns in the voxel
    assert len(np.unique(scan.voxels, axis=0)) == len(scan.voxels)  # one class per voxel
    assert scan.voxels.dtype == np.int32 and scan.voxel_weights.dtype == np.float32


def test_a_voxel_with_returns_of_several_classes_takes_the_most_cautious():
    from services.lib.voxels.labels import label_sets
    slot = np.full(80 * 60 * 30, -1, np.int32)
    voxels, labels, weights, outside = label_sets(
        np.array([[1.1, 1.1, 1.1], [1.2, 1.2, 1.2], [1.3, 1.3, 1.3], [5.1, 1.1, 1.1], [5.2, 1.1, 1.1]]),
        np.array([BACKGROUND, FLYING, UNKNOWN, BACKGROUND, UNKNOWN], np.uint8), np.zeros(3), VOXEL,
        np.array(SHAPE), slot, BACKGROUND, FLYING, UNKNOWN)
    assert labels.tolist() == [FLYING, UNKNOWN] and np.isinf(weights[0]) and weights[1] == 1.0
    assert voxels.tolist() == [[2, 2, 2], [10, 2, 2]] and outside == 0 and (slot == -1).all()


def test_detection_covariance_and_confidence_follow_the_pose_uncertainty():
    core = classifier(free=FREE_AROUND_BALL)
    certain = core.classify(ball(), SENSOR)
    uncertain_pose = SensorPose(SENSOR.position, SENSOR.rotation, np.diag([0.2 ** 2] * 3 + [np.radians(2) ** 2] * 3))
    uncertain = core.classify(ball(), uncertain_pose)
    spread = np.cov(ball().T)
    assert np.allclose(certain.covariances[0], spread + 0.01 * np.eye(3), atol=1e-4)  # perfect pose, 2 cm ranges/√60
    extra = uncertain.covariances[0] - certain.covariances[0]
    assert np.all(np.linalg.eigvalsh(extra) > 0.03)  # at least the position noise, 0.04 m², on every axis
    assert 0.9 < certain.confidences[0] <= 1.0 and uncertain.confidences[0] < 0.6


def test_bad_input_is_dropped_and_counted():
    core = classifier(free=FREE_AROUND_BALL)
    points = np.vstack([ball(), [[np.inf, 1.0, 1.0], [np.nan, np.nan, np.nan], [1.0, -np.inf, 2.0]]])
    scan = core.classify(points, SENSOR)
    assert len(scan.points) == 60 and core.counters.invalid_points == 2
    assert len(core.classify(np.zeros((5, 2)), SENSOR).points) == 0  # not (…, 3)
    assert len(core.classify(ball(), SensorPose(np.array([np.nan, 0, 0]), np.eye(3))).points) == 0
    assert len(core.classify(ball(), SensorPose(SENSOR.position, np.full((3, 3), np.nan))).points) == 0
    assert len(core.classify(ball(), SensorPose(SENSOR.position, np.eye(3), np.full((6, 6), np.inf))).points) == 0
    assert core.counters.rejected_scans == 4
    outside = core.classify(ball(np.array([-30.0, 15.0, 6.0])), SENSOR)
    assert core.counters.points_outside_map == 60 and len(outside.voxels) == 0 and len(outside.positions) == 0
    organised = np.full((4, 16, 3), np.nan, np.float32)
    organised.reshape(-1, 3)[:60 // 2] = ball(count=30)
    assert len(core.classify(organised, SENSOR).points) == 30


@pytest.mark.parametrize("seed", [1, 2])
def test_result_is_deterministic(seed):
    rng = np.random.default_rng(seed)
    points = np.vstack([ball(seed=seed), rng.uniform((0, 0, 0), (40, 30, 1), (3000, 3))])
    first = classifier(free=FREE_AROUND_BALL).classify(points, SENSOR)
    second = classifier(free=FREE_AROUND_BALL).classify(points, SENSOR)
    for a, b in zip(vars(first).values(), vars(second).values()):
        assert np.array_equal(a, b)


def test_maps_it_could_not_hold_or_downsample_are_refused_before_anything_changes():
    """Found by tests/test_fuzz_messages.py: a snapshot of 4 billion voxels had the classifier killed for
    want of memory; one of 1 km voxels made every later scan fail on its downsampling grid."""
    core = classifier()
    for origin, shape, voxel in ((ORIGIN, (4189, 1630, 577), VOXEL), (ORIGIN, SHAPE, 1000.0),
                                 (ORIGIN, (0, 1, 1), VOXEL), ((np.nan, 0.0, 0.0), SHAPE, VOXEL)):
        with pytest.raises(ValueError):
            core.apply_map(True, origin, shape, voxel, -740.0, np.zeros(0, np.int64), np.zeros(0, np.float32))
    assert core.map.shape == SHAPE and core.map.voxel_size == VOXEL and core.map.snapshots == 1
    assert len(core.classify(ball(), SENSOR).points) == 60


def compiled_by_a_real_scan_after_warm_up() -> dict:
    """In a fresh interpreter (tests/tools/compiled.py): what warm_up labels, then the kernels a
    real scan (detections and p_hit included) still compiles or loads after it."""
    modules = (classifier_kernels, voxel_kernels)
    labelled = []
    warmed = newly_compiled(modules, lambda: labelled.append(warm_up(PARAMS)))
    pose = SensorPose(SENSOR.position, SENSOR.rotation, np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]))
    scans = []
    left = newly_compiled(modules, lambda: scans.append(classifier(free=FREE_AROUND_BALL).classify(
        np.concatenate([ball(), np.full((3, 3), np.nan)]).reshape(1, -1, 3), pose)))
    return {"labelled": labelled[0], "warmed": warmed, "left": left, "detections": len(scans[0].positions)}


def test_warm_up_leaves_no_kernel_for_a_real_scan_to_compile():
    """The node warms up before its liveliness token: a real scan must then find every kernel
    compiled for its types (a cold compile takes seconds)."""
    result = in_fresh_interpreter(compiled_by_a_real_scan_after_warm_up)
    assert result["labelled"] > 0 and result["warmed"] and result["detections"] == 1
    assert result["left"] == []
