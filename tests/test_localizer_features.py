"""The localizer's feature extraction and association (seed 003 sec. 2.1) on synthetic organised
scans of known geometry: an analytic ray caster against a ground plane and two perpendicular walls
meeting in a vertical corner, with 1 cm range noise and 2 % dropouts."""
from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from services.lib.lidar.models import beam_directions
from services.localizer import features as feature_kernels
from services.localizer import graph, poles
from services.localizer.association import AssociationParams, FeatureMap, associate, transform_features
from services.localizer.core import LocalizerParams, warm_up
from services.localizer.features import EdgeFeature, FeatureParams, Features, PlaneFeature, extract_features, sector_of
from tests.tools.compiled import in_fresh_interpreter, newly_compiled

SENSOR_HEIGHT = 2.0  # m above the ground
WALL_TOP = 1.5  # m above the sensor: the sky (no return) above
CORNER_RANGE = 5.0
CORNER_AZIMUTH = math.radians(10.3)  # between two columns, as a real corner would be
UP = np.array([0.0, 0.0, 1.0])


def horizontal(azimuth: float) -> np.ndarray:
    return np.array([math.cos(azimuth), math.sin(azimuth), 0.0])


CORNER = CORNER_RANGE * horizontal(CORNER_AZIMUTH)
# The walls run from the corner back past the sensor on either side, 45° off the line of sight:
# the sensor looks straight into the corner.
WALL_RUNS = (horizontal(CORNER_AZIMUTH + math.radians(135)), horizontal(CORNER_AZIMUTH - math.radians(135)))


def wall_normal(run: np.ndarray) -> np.ndarray:
    normal = np.cross(UP, run)
    return normal if normal @ CORNER < 0 else -normal  # toward the sensor, as extraction orients them


TRUE_PLANES = [(UP, SENSOR_HEIGHT)] + [(wall_normal(run), -float(wall_normal(run) @ CORNER)) for run in WALL_RUNS]
GROUND_CORNER = CORNER - SENSOR_HEIGHT * UP
TRUE_EDGES = [(CORNER, UP)] + [(GROUND_CORNER, run) for run in WALL_RUNS]  # the corner, the walls' feet


def cast_scan(rows=128, cols=1024, vfov_deg=90.0, noise=0.01, dropout=0.02, seed=0, tilt=np.eye(3)) -> np.ndarray:
    """(rows, cols, 3) sensor-frame returns of an OS0-like sensor (beam_directions) turned by `tilt`
    (sensor to world) in the scene above: nearest hit along each ray, Gaussian range noise, random
    dropouts and no return from the sky or beyond 40 m, as NaN."""
    beams = beam_directions(rows, cols, vfov_deg)
    rays = beams @ tilt.T
    hits = np.full(rays.shape[:2], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = -SENSOR_HEIGHT / rays[..., 2]
        hits = np.where(ground > 0, ground, hits)
        for run in WALL_RUNS:
            normal = wall_normal(run)
            t = (normal @ CORNER) / (rays @ normal)
            points = rays * t[..., None]
            on_wall = (t > 0) & ((points - CORNER) @ run >= 0) & (points[..., 2] <= WALL_TOP)
            hits = np.where(on_wall & (t < hits), t, hits)
    rng = np.random.default_rng(seed)
    ranges = hits + rng.normal(0.0, noise, hits.shape)
    ranges[(ranges > 40.0) | (rng.random(hits.shape) < dropout)] = np.nan
    return beams * ranges[..., None]


def degrees_between(a: np.ndarray, b: np.ndarray, signed: bool = True) -> float:
    cosine = float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, cosine if signed else abs(cosine))))


def distance_to_line(point: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> float:
    offset = point - origin
    return float(np.linalg.norm(offset - (offset @ direction) * direction))


def nearest_true_edge(edge: EdgeFeature, truth=TRUE_EDGES, rotate=np.eye(3)) -> tuple[float, float]:
    """(angle in degrees, distance in m) to the true edge it is nearest in direction and place."""
    errors = [(degrees_between(edge.direction, rotate @ direction, signed=False),
               distance_to_line(edge.centre, rotate @ origin, rotate @ direction)) for origin, direction in truth]
    return min(errors, key=lambda error: error[0] + 100.0 * error[1])


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    return cast_scan()


SEED_SELECTION = FeatureParams(per_sector=1, min_angle_between_deg=0.0, poles_per_sector=0)  # seed 003: the best of each per sector


@pytest.fixture(scope="module")
def features(scan) -> Features:
    return extract_features(scan, SEED_SELECTION)


def test_planes_lie_on_the_true_surfaces(features):
    assert len(features.planes) == 4  # the ground is in every sector
    for plane in features.planes:
        normal, offset = max(TRUE_PLANES, key=lambda truth: truth[0] @ plane.normal)
        assert degrees_between(plane.normal, normal) < 1.0
        assert abs(plane.offset - offset) < 0.02
        assert abs(plane.normal @ plane.centre + plane.offset) < 1e-9  # the centre is on the plane
        assert plane.rmse < 0.02 and plane.point_count >= FeatureParams().plane_min_points


def test_the_corner_is_the_forward_edge_and_every_edge_is_a_true_one(features):
    [forward] = [edge for edge in features.edges if edge.sector == 0]
    assert degrees_between(forward.direction, UP, signed=False) < 1.0
    assert distance_to_line(forward.centre, CORNER, UP) < 0.02
    assert forward.direction[2] > 0  # reported with its largest component positive
    for edge in features.edges:
        angle, distance = nearest_true_edge(edge)
        assert angle < 1.0 and distance < 0.02


def test_at_most_one_plane_and_one_edge_per_sector(features):
    for kind in (features.planes, features.edges):
        sectors = [feature.sector for feature in kind]
        assert len(sectors) == len(set(sectors))
        for feature in kind:
            assert sector_of(feature.centre[None], 4)[0] == feature.sector


def test_sectors_are_counted_counter_clockwise_from_forward():
    directions = np.array([horizontal(math.radians(a)) for a in (0, 44, 46, 90, 180, 270, 316)])
    assert sector_of(directions, 4).tolist() == [0, 0, 1, 1, 2, 3, 0]
    assert sector_of(directions, 8).tolist() == [0, 1, 1, 2, 4, 6, 7]


def test_more_sectors_and_more_per_sector(scan):
    features = extract_features(scan, FeatureParams(sectors=8, per_sector=2, min_separation=1.0,
                                                    min_angle_between_deg=0.0, poles_per_sector=0))
    for kind in (features.planes, features.edges):
        for sector in range(8):
            members = [feature for feature in kind if feature.sector == sector]
            assert len(members) <= 2
            if len(members) == 2:
                assert np.linalg.norm(members[0].centre - members[1].centre) >= 1.0
    assert len(features.planes) > 8


def test_the_default_selection_keeps_a_wall_beside_the_floor(scan):
    """The floor is the smoothest surface in every sector: by RMSE alone (the seed) every plane is floor
    (the test above); a second plane of another orientation per sector adds the walls, which hold x and y."""
    features = extract_features(scan)
    for sector in range(4):
        normals = [plane.normal for plane in features.planes if plane.sector == sector]
        assert len(normals) <= 2
        if len(normals) == 2:
            assert degrees_between(normals[0], normals[1], signed=False) >= FeatureParams().min_angle_between_deg
    vertical = [plane for plane in features.planes if abs(plane.normal[2]) < 0.1]
    assert len(vertical) >= 2 and len(features.planes) > 4
    for plane in features.planes:
        normal, offset = max(TRUE_PLANES, key=lambda truth: truth[0] @ plane.normal)
        assert degrees_between(plane.normal, normal) < 1.0 and abs(plane.offset - offset) < 0.02


def test_a_tilted_sensor_follows_the_corner_across_columns():
    roll = math.radians(15.0)  # the corner leans across the columns in the sensor frame
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(roll), -math.sin(roll)], [0.0, math.sin(roll), math.cos(roll)]])
    features = extract_features(cast_scan(seed=3, tilt=tilt))
    to_sensor = tilt.T
    corner = [edge for edge in features.edges if nearest_true_edge(edge, TRUE_EDGES[:1], to_sensor)[1] < 0.02]
    assert corner, "the corner was not found"
    assert nearest_true_edge(corner[0], TRUE_EDGES[:1], to_sensor)[0] < 1.0


def test_a_scan_without_returns_gives_no_features():
    assert extract_features(np.full((128, 1024, 3), np.nan)) == Features((), ())
    assert extract_features(np.full((4, 8, 3), np.nan, dtype=np.float32)) == Features((), ())


def test_a_scan_of_the_wrong_shape_is_refused():
    with pytest.raises(ValueError, match="rows, columns, 3"):
        extract_features(np.zeros((100, 3)))


@pytest.mark.parametrize("bad", [{"sectors": 0}, {"per_sector": 0}, {"window": 0}, {"max_incidence_deg": 90.0},
                                 {"plane_max_rmse": 0.0}, {"edge_min_deviation": -0.1}, {"plane_min_points": 2},
                                 {"edge_search": -1}, {"plane_max_smoothness": math.nan}])
def test_bad_feature_params_are_refused_in_one_line(bad):
    with pytest.raises(msgspec.ValidationError) as refused:
        msgspec.convert(bad, FeatureParams)
    assert "\n" not in str(refused.value) and next(iter(bad)) in str(refused.value)


def test_unknown_and_bad_association_params_are_refused():
    with pytest.raises(msgspec.ValidationError, match="sectorz"):
        msgspec.convert({"sectorz": 4}, FeatureParams)
    with pytest.raises(msgspec.ValidationError, match="max_normal_angle_deg"):
        AssociationParams(max_normal_angle_deg=0.0)
    with pytest.raises(msgspec.ValidationError, match="neighbours"):
        AssociationParams(neighbours=0)


# ---------------------------------------------------------------------------------------------
# Association


def small_pose() -> tuple[np.ndarray, np.ndarray]:
    """About 1° of yaw and pitch and 5 cm: the error of a predicted pose."""
    yaw, pitch = math.radians(1.0), math.radians(0.7)
    rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    return rz @ ry, np.array([0.05, -0.03, 0.02])


def map_of(features: Features) -> tuple[FeatureMap, list[int]]:
    feature_map = FeatureMap()
    return feature_map, [feature_map.add(feature) for feature in (*features.planes, *features.edges)]


def test_transform_keeps_features_on_their_moved_surfaces(features):
    rotation, translation = small_pose()
    moved = transform_features(features, rotation, translation)
    for plane, before in zip(moved.planes, features.planes):
        point_on_plane = before.centre + np.cross(before.normal, [0.3, 0.2, 0.1])  # any point of the old plane
        assert abs(plane.normal @ (rotation @ point_on_plane + translation) + plane.offset) < 1e-9
        assert plane.sector == before.sector and plane.rmse == before.rmse
    for edge, before in zip(moved.edges, features.edges):
        assert np.allclose(edge.direction, rotation @ before.direction)
    with pytest.raises(ValueError, match="3 × 3"):
        transform_features(features, np.eye(2), translation)


def test_moved_features_associate_to_their_own_map_features(features):
    feature_map, ids = map_of(features)
    moved = transform_features(features, *small_pose())
    associations = associate(moved, feature_map)
    assert [a.map_id for a in associations] == ids
    assert all(a.angle < math.radians(1.5) for a in associations)  # the pose turns by 1.2°
    assert [a.feature for a in associations] == [*moved.planes, *moved.edges]


def test_a_plane_whose_normal_disagrees_is_left_unassociated_and_added_anew(features):
    feature_map, ids = map_of(features)
    moved = transform_features(features, *small_pose())
    wrong = moved.planes[1]
    axis = np.cross(wrong.normal, UP if abs(wrong.normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    angle = math.radians(30.0)  # Rodrigues: the normal turned 30° about an axis perpendicular to it
    turned = wrong.normal * math.cos(angle) + np.cross(axis, wrong.normal) * math.sin(angle)
    planes = list(moved.planes)
    planes[1] = PlaneFeature(wrong.centre, turned, float(-turned @ wrong.centre), wrong.rmse, wrong.point_count,
                             wrong.sector)
    mismatched = Features(tuple(planes), moved.edges)
    associations = associate(mismatched, feature_map)
    assert [a.map_id for a in associations] == [None if k == 1 else ids[k] for k in range(len(ids))]
    assert math.isnan(associations[1].angle)
    registered = feature_map.add_unassociated(associations)
    assert registered[1] == max(ids) + 1 and registered[:1] + registered[2:] == ids[:1] + ids[2:]
    assert len(feature_map) == len(ids) + 1 and feature_map.feature(registered[1]) is planes[1]
    again = associate(mismatched, feature_map)  # the tree was rebuilt with the new plane
    assert [a.map_id for a in again] == registered


def test_opposite_normals_are_different_planes_and_edges_ignore_sign(features):
    feature_map, ids = map_of(features)
    flipped_plane = features.planes[0]
    flipped_plane = PlaneFeature(flipped_plane.centre, -flipped_plane.normal, -flipped_plane.offset,
                                 flipped_plane.rmse, flipped_plane.point_count, flipped_plane.sector)
    edge = features.edges[0]
    flipped_edge = EdgeFeature(edge.centre, -edge.direction, edge.rmse, edge.point_count, edge.sector)
    associations = associate(Features((flipped_plane,), (flipped_edge,)), feature_map)
    assert associations[0].map_id is None  # the back face of a wall is another surface
    assert associations[1].map_id == ids[len(features.planes)]


def test_an_empty_map_associates_nothing(features):
    associations = associate(features, FeatureMap())
    assert len(associations) == len(features.planes) + len(features.edges)
    assert all(a.map_id is None for a in associations)
    assert associate(Features((), ()), FeatureMap(), AssociationParams()) == []


def compiled_by_a_real_scan_after_warm_up() -> dict:
    """In a fresh interpreter (tests/tools/compiled.py): what warm_up found, then the kernels a
    real scan's features and a line factor's linearisation still compile or load after it."""
    modules = (feature_kernels, poles, graph)
    found = []
    warmed = newly_compiled(modules, lambda: found.append(warm_up(LocalizerParams())))
    extracted = []
    direction = np.array([[0.0, 0.0, 1.0]])

    def real():
        extracted.append(extract_features(cast_scan()))
        graph.line_residuals(np.ones((1, 3)), direction, np.eye(3)[None], np.zeros((1, 3)), direction,
                             np.array([[1.0, 2.0, 0.0]]), graph.tangent_basis(direction))
    left = newly_compiled(modules, real)
    return {"found": found[0], "warmed": warmed, "left": left,
            "planes": len(extracted[0].planes), "edges": len(extracted[0].edges)}


def test_warm_up_leaves_no_kernel_for_a_real_scan_to_compile():
    """The localizer node warms up before its liveliness token (a cold compile takes seconds)."""
    result = in_fresh_interpreter(compiled_by_a_real_scan_after_warm_up)
    assert result["found"] >= 1 and result["warmed"] and result["planes"] and result["edges"]
    assert result["left"] == []
