"""Simulated LiDAR: exact ray-primitive hits (the compiled caster, checked against the numpy
reference), scan shape, masking, hit ids, pose noise, intensity, faults and determinism."""
from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.messages import Obstacle, TargetTruth
from services.lib.lidar.models import beam_directions
from services.lib.world import numpy_caster as reference
from services.lib.world import primitives
from services.lib.world.primitives import Primitives, cast, cast_with_ids, primitives_from_obstacles, target_spheres
from services.sensor_driver.core import scan
from services.sensor_driver.faults import faulty_scan, lidar_faults

MM = 1e-3


def unit(*v) -> np.ndarray:
    v = np.asarray(v, dtype=float).reshape(-1, 3)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def hit_points(origin, directions, primitives) -> np.ndarray:
    """World hit points; rows of misses are NaN."""
    ranges = cast(np.asarray(origin, float), directions, primitives)
    points = np.asarray(origin) + directions * np.nan_to_num(ranges, posinf=0.0)[:, None]
    return np.where(np.isfinite(ranges)[:, None], points, np.nan)


def test_ray_plane():
    d = unit([1, 0, -1], [0, 2, -1], [1, 0, 0], [0, 0, 1])
    r = cast(np.array([0.0, 0.0, 5.0]), d, Primitives(planes=np.array([0.5])))
    assert abs(r[0] - 4.5 * math.sqrt(2)) < MM and abs(r[1] - 4.5 * math.sqrt(5)) < MM
    assert np.isinf(r[2]) and np.isinf(r[3])


def test_ray_sphere():
    prims = Primitives(spheres=np.array([[10.0, 0.0, 2.0, 0.3]]))
    d = unit([1, 0, 0.2], [1, 0.02, 0.2], [1, 0.2, 0.2], [-1, 0, 0])
    r = cast(np.zeros(3), d, prims)
    along = math.sqrt(104)  # straight at the centre: the near surface is 0.3 m before it
    assert abs(r[0] - (along - 0.3)) < MM
    # Off-centre ray: analytic near root of |o + t d - c|² = r².
    dd = d[1]
    b = dd @ np.array([10.0, 0.0, 2.0])
    expected = b - math.sqrt(b * b - (104 - 0.09))
    assert abs(r[1] - expected) < MM
    assert np.isinf(r[2]) and np.isinf(r[3])
    # From inside the sphere the ray hits the far side.
    inside = cast(np.array([10.0, 0.0, 2.0]), unit([0, 0, 1]), prims)
    assert abs(inside[0] - 0.3) < MM


def test_ray_box():
    prims = Primitives(boxes=np.array([[5.0, -1.0, 0.0, 7.0, 1.0, 3.0]]))  # x 5..7, y -1..1, z 0..3
    front = hit_points([0.0, 0.0, 1.0], unit([1, 0, 0], [1, 0.1, 0.3]), prims)
    assert np.allclose(front, [[5.0, 0.0, 1.0], [5.0, 0.5, 2.5]], atol=MM)
    roof = hit_points([6.0, 0.0, 5.0], unit([0.1, 0, -1]), prims)
    assert np.allclose(roof, [[6.2, 0.0, 3.0]], atol=MM)
    side = hit_points([6.0, -5.0, 1.0], unit([0, 1, 0]), prims)
    assert np.allclose(side, [[6.0, -1.0, 1.0]], atol=MM)
    misses = unit([1, 0.5, 0], [0, 1, 0], [1, 0, 0.8], [-1, 0, 0])  # beside, beside, over the top, away
    assert np.isinf(cast(np.array([0.0, 0.0, 1.0]), misses, prims)).all()


def test_ray_cylinder():
    prims = Primitives(cylinders=np.array([[10.0, 0.0, 0.0, 0.5, 4.0]]))  # pole at x=10, r 0.5, 0..4 m
    origin = [0.0, 0.0, 2.0]
    d = unit([1, 0, 0], [10, 0.3, 0], [1, 0, 0.5], [1, 0, 0.21])
    p = hit_points(origin, d, prims)
    assert np.allclose(p[0], [9.5, 0.0, 2.0], atol=MM)
    y = 0.03  # along y = 0.03 x: x² - 20x + 100 + (0.03x)² = 0.25, nearer root
    a, b, c = 1 + y * y, -20.0, 99.75
    x = (-b - math.sqrt(b * b - 4 * a * c)) / (2 * a)
    assert np.allclose(p[1], [x, y * x, 2.0], atol=MM)
    assert np.isinf(cast(np.array(origin), d[2:3], prims)).all()  # passes over the top (z = 6.75 at x = 9.5)
    assert np.allclose(p[3], [9.5, 0.0, 2.0 + 0.21 * 9.5], atol=MM)
    top = hit_points([10.2, 0.0, 9.0], unit([0, 0, -1]), prims)  # straight down onto the cap
    assert np.allclose(top[0], [10.2, 0.0, 4.0], atol=MM)


def test_ray_cone():
    prims = Primitives(cones=np.array([[10.0, 0.0, 0.0, 2.0, 8.0]]))  # radius 2 at z 0, apex at z 8
    p = hit_points([0.0, 0.0, 4.0], unit([1, 0, 0]), prims)  # at z 4 the radius is 1
    assert np.allclose(p[0], [9.0, 0.0, 4.0], atol=MM)
    apex = hit_points([10.0, 0.0, 12.0], unit([0, 0, -1]), prims)
    assert np.allclose(apex[0], [10.0, 0.0, 8.0], atol=MM)
    assert np.isinf(cast(np.array([0.0, 0.0, 7.0]), unit([1, 0.2, 0]), prims)).all()


def test_culling_matches_brute_force():
    obstacles = [Obstacle(kind="plane", center=(0, 0, 0)),
                 Obstacle(kind="box", center=(5, 5, 2), size=(3, 2, 4)),
                 Obstacle(kind="cylinder", center=(-4, 3, 0), radius=0.6, height=5),
                 Obstacle(kind="cone", center=(0, -6, 0), radius=2, height=6),
                 Obstacle(kind="sphere", center=(-3, -3, 4), radius=0.3)]
    prims = primitives_from_obstacles(obstacles)
    rng = np.random.default_rng(0)
    d = unit(*rng.normal(size=(20000, 3)))
    origin = np.array([0.5, 0.2, 3.0])
    brute = np.full(len(d), np.inf)
    with np.errstate(all="ignore"):
        brute = np.minimum(brute, reference._hit_plane(origin, d, 0.0))
        brute = np.minimum(brute, reference._hit_box(origin, d, prims.boxes[0]))
        brute = np.minimum(brute, reference._hit_cylinder(origin, d, prims.cylinders[0]))
        brute = np.minimum(brute, reference._hit_cone(origin, d, prims.cones[0]))
        brute = np.minimum(brute, reference._hit_sphere(origin, d, prims.spheres[0]))
    assert np.array_equal(cast(origin, d, prims), brute)
    assert np.isfinite(brute).sum() > 10000


def test_beam_directions():
    d = beam_directions(32, 512, 90.0)
    assert d.shape == (32, 512, 3)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    elevation = np.degrees(np.arcsin(d[:, 0, 2]))
    assert abs(elevation[0] - 45) < 1e-9 and abs(elevation[-1] + 45) < 1e-9 and np.all(np.diff(elevation) < 0)
    assert np.allclose(d[:, 0, 1], 0.0) and np.all(d[:, 0, 0] > 0)  # column 0 looks along +x
    assert np.allclose(d[:, 128, 0], 0.0) and np.all(d[:, 128, 1] > 0)  # a quarter turn later: +y


def test_scan_of_ground_from_5m():
    directions = beam_directions(32, 512, 90.0)
    prims = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))])
    origin = np.array([3.0, 4.0, 5.0])
    unlimited = scan(origin, 0.7, directions, prims, np.random.default_rng(1), max_range=1e9).points
    assert unlimited.shape == (32, 512, 3) and unlimited.dtype == np.float32
    pointing_up = directions[..., 2] >= 0
    assert np.array_equal(np.isnan(unlimited).any(axis=-1), pointing_up)
    assert np.array_equal(np.isnan(unlimited).all(axis=-1), pointing_up)  # no partial NaN points
    assert pointing_up[:16].all() and not pointing_up[16:].any()  # the upper half of the rows
    hits = unlimited[~pointing_up]
    assert np.abs(hits[:, 2]).max() < 0.06  # on the ground up to range noise (sigma 1 cm)
    # With the 50 m limit the shallow downward beams lose their far returns as well.
    limited = scan(origin, 0.7, directions, prims, np.random.default_rng(1)).points
    expected = pointing_up | (5.0 / np.maximum(-directions[..., 2], 1e-12) > 50.0)
    assert np.array_equal(np.isnan(limited).any(axis=-1), expected)
    assert expected.sum() > pointing_up.sum()


def test_scan_rotates_with_heading_and_masks_body():
    directions = beam_directions(8, 64, 60.0)
    wall = primitives_from_obstacles([Obstacle(kind="box", center=(0, 10, 0), size=(40, 1, 40))])
    points = scan(np.zeros(3), math.pi / 2, directions, wall, np.random.default_rng(0), range_noise=0.0).points
    # Column 0 points along the heading (+y), straight at the wall face at y = 9.5.
    assert np.allclose(points[4, 0, 1], 9.5, atol=MM)
    # A return inside the carrier's body box (default ±0.4 m around the sensor) is dropped.
    near = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, -0.18))])  # 0.36 m at -30°
    points = scan(np.zeros(3), 0.0, directions, near, np.random.default_rng(0), range_noise=0.0).points
    assert np.isnan(points[-1, :, :]).all()


def test_scan_is_seeded_and_targets_are_spheres():
    targets = [TargetTruth(id="b", kind="balloon", position=(8.0, 0.0, 5.0), velocity=(0, 0, 0), radius=0.3),
               TargetTruth(id="x", kind="balloon", position=(0.0, 8.0, 5.0), velocity=(0, 0, 0), radius=0.3,
                           destroyed=True)]
    spheres = target_spheres(targets)
    assert spheres.shape == (1, 4)
    prims = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))]).with_spheres(spheres)
    directions = beam_directions(32, 512, 90.0)
    a = scan(np.array([0.0, 0.0, 5.0]), 0.0, directions, prims, np.random.default_rng([1, 0, 7])).points
    b = scan(np.array([0.0, 0.0, 5.0]), 0.0, directions, prims, np.random.default_rng([1, 0, 7])).points
    assert np.array_equal(a, b, equal_nan=True)
    on_balloon = np.linalg.norm(a - np.array([8.0, 0.0, 5.0], np.float32), axis=-1) < 0.35
    assert on_balloon.sum() >= 2


# ------------------------------------------------------------------ issue 3: compiled caster, truth, noise
def random_world(rng: np.random.Generator) -> Primitives:
    boxes = [Obstacle(kind="box", center=tuple(rng.uniform(-8, 8, 3)), size=tuple(rng.uniform(0.5, 4, 3)))
             for _ in range(4)]
    upright = [Obstacle(kind=kind, center=(*rng.uniform(-8, 8, 2), rng.uniform(-1, 1)),
                        radius=rng.uniform(0.2, 2), height=rng.uniform(1, 6))
               for kind in ("cylinder", "cone", "cylinder", "cone")]
    prims = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, -1.5))] + boxes + upright)
    targets = [TargetTruth(id=f"t{k}", kind=kind, position=tuple(rng.uniform(-6, 6, 3)), velocity=(0, 0, 0),
                           radius=0.3 + 0.1 * k) for k, kind in enumerate(("balloon", "drone", "balloon", "drone"))]
    return prims.with_targets(targets)


def test_compiled_caster_matches_the_numpy_reference_bit_for_bit():
    rng = np.random.default_rng(5)
    for trial in range(4):
        world = random_world(rng)
        d = unit(*rng.normal(size=(20000, 3)))
        d[:300, rng.integers(0, 3)] = 0.0  # axis-parallel rays: the 0/0 and ±inf branches
        d[:300] /= np.linalg.norm(d[:300], axis=1, keepdims=True)
        origin = rng.uniform(-3, 3, 3)
        ranges, ids = cast_with_ids(origin, d, world)
        expected_ranges, expected_ids = reference.cast(origin, d, world)
        assert np.array_equal(ranges, expected_ranges)
        assert np.array_equal(ids, expected_ids)
        assert len(np.unique(ids)) >= 4  # misses, static world and some targets were all exercised


def test_hit_ids_name_the_target_and_match_the_returns():
    targets = [TargetTruth(id="b1", kind="balloon", position=(8.0, 0.0, 5.0), velocity=(0, 0, 0), radius=0.3),
               TargetTruth(id="gone", kind="balloon", position=(0.0, 8.0, 5.0), velocity=(0, 0, 0), radius=0.3,
                           destroyed=True),
               TargetTruth(id="d1", kind="drone", position=(0.0, -8.0, 5.0), velocity=(1, 0, 0), radius=0.325)]
    world = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))]).with_targets(targets)
    directions = beam_directions(64, 1024, 45.0)
    result = scan(np.array([0.0, 0.0, 5.0]), 0.0, directions, world, np.random.default_rng(3))
    assert result.hits.shape == (64, 1024) and result.hits.dtype == np.int32
    assert np.array_equal(result.hits == -1, np.isnan(result.points).any(axis=-1))
    assert set(np.unique(result.hits)) == {-1, 0, 1, 3}  # target 2 is destroyed: never hit
    for k, centre in ((1, (8.0, 0.0, 5.0)), (3, (0.0, -8.0, 5.0))):
        on = result.points[result.hits == k]
        assert len(on) >= 2 and np.linalg.norm(on - np.array(centre, np.float32), axis=1).max() < 0.5
    drone = result.points[result.hits == 3]
    assert np.abs(drone[:, 2] - 5.0).max() < primitives.DRONE_BODY_HEIGHT / 2 + 0.1  # a flat body, not a ball
    assert (result.points[result.hits == 0][:, 2] < 0.1).all()  # the rest is ground


def test_position_noise_moves_the_rays_not_the_published_pose():
    ground = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))])
    directions = beam_directions(16, 64, 90.0)
    origin = np.array([0.0, 0.0, 5.0])
    kwargs = dict(range_noise=0.0, max_range=1e9, body_box=None)
    exact = scan(origin, 0.3, directions, ground, np.random.default_rng(9), **kwargs).points
    assert np.nanmax(np.abs(exact[..., 2])) < 1e-5
    moved = scan(origin, 0.3, directions, ground, np.random.default_rng(9), position_noise=0.5, **kwargs).points
    offset = 0.5 * np.random.default_rng(9).normal(0.0, 1.0, 6)[:3]  # the scan's first draws
    # Rays left from origin + offset, points are placed from origin: the ground appears at -dz.
    assert np.allclose(moved[..., 2][np.isfinite(moved[..., 2])], -offset[2], atol=1e-5)
    tilted = scan(origin, 0.3, directions, ground, np.random.default_rng(9), attitude_noise=0.02, **kwargs).points
    err = np.abs(tilted[..., 2])
    assert np.nanmax(err) > 0.05 and np.nanmin(err) < 0.1  # a tilted ground, worse far away


def test_body_box_below_the_sensor_blocks_the_steep_rays():
    ground = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))])
    directions = beam_directions(91, 8, 90.0)  # rows every 1°: +45 … -45
    elevation = 45.0 - np.arange(91)
    frame = (-0.3, -0.3, -0.3, 0.3, 0.3, -0.1)  # the carrier 10 cm below the optical centre
    points = scan(np.array([0.0, 0.0, 5.0]), 0.0, directions, ground, np.random.default_rng(0),
                  range_noise=0.0, max_range=1e9, body_box=frame).points
    blocked = np.isnan(points[..., 0])
    assert blocked[elevation < -19.0].all()  # through the top face (atan(0.1/0.3) = 18.4° at the edge)
    assert not blocked[(elevation < -1.0) & (elevation > -13.0)].any()  # past the frame, onto the ground
    # The same box without the ground: blocked rays are blocked, not just out of range.
    nothing = scan(np.array([0.0, 0.0, 5.0]), 0.0, directions, Primitives(), np.random.default_rng(0),
                   body_box=frame)
    assert (nothing.hits == -1).all()


def test_intensity_falls_with_range_and_incidence():
    wall = primitives_from_obstacles([Obstacle(kind="box", center=(0, 0, 0), size=(1, 40, 40))])  # face x = -0.5
    directions = unit([1, 0, 0], [1, 1, 0], [1, 0, 0]).reshape(1, 3, 3)
    near = scan(np.array([-3.5, 0.0, 0.0]), 0.0, directions, wall, np.random.default_rng(0), intensity=True)
    far = scan(np.array([-10.5, 0.0, 0.0]), 0.0, directions, wall, np.random.default_rng(0), intensity=True)
    static = primitives.REFLECTIVITY["static"]
    assert near.intensity.dtype == np.float32
    assert abs(near.intensity[0, 0] - static) < 1e-6  # head-on within the full-signal range
    assert abs(near.intensity[0, 1] - static * math.cos(math.pi / 4)) < 1e-6  # 45°, 4.2 m away
    assert abs(far.intensity[0, 0] - static * (5.0 / 10.0) ** 2) < 1e-6
    assert scan(np.zeros(3), 0.0, directions, wall, np.random.default_rng(0)).intensity is None


def test_faulty_scans_hide_the_world():
    world = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))])
    beams = beam_directions(8, 32, 90.0)
    origin = np.array([0.0, 0.0, 5.0])
    good = scan(origin, 0.0, beams, world, np.random.default_rng(0))
    nan = faulty_scan(good, "lidar_nan", origin, beams, 0.3, 50.0, np.random.default_rng(0))
    assert np.isnan(nan.points).all() and (nan.hits == -1).all()
    garbage = faulty_scan(good, "lidar_garbage", origin, beams, 0.3, 50.0, np.random.default_rng(0))
    assert np.isfinite(garbage.points).all() and (garbage.hits == -1).all()
    assert garbage.points.shape == good.points.shape
    offsets = garbage.points.astype(float) - origin
    ranges = np.linalg.norm(offsets, axis=-1)
    assert ranges.min() >= 0.3 - 1e-4 and ranges.max() <= 50.0 + 1e-3 and ranges.std() > 5  # random ranges ...
    assert np.allclose(offsets / ranges[..., None], beams, atol=1e-5)  # ... along the real beams


def test_mid360_scan_sees_a_balloon_with_a_few_points():
    from services.lib.lidar.models import lidar_model

    model = lidar_model("mid360")
    balloon = [TargetTruth(id="b", kind="balloon", position=(15.0, 0.0, 8.0), velocity=(0, 0, 0), radius=0.3)]
    world = primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))]).with_targets(balloon)
    counts = [int((scan(np.array([0.0, 0.0, 5.0]), 0.0, model.directions(f), world, np.random.default_rng(f),
                        min_range=model.min_range, max_range=model.max_range).hits == 1).sum()) for f in range(10)]
    assert sum(counts) > 0 and min(counts) < max(counts)  # sparse and changing from frame to frame


def test_fault_windows_follow_mission_time():
    faults = lidar_faults()
    faults.add("lidar_silent", 5_000_000_000, 2.0)
    faults.add("lidar_nan", 6_000_000_000, 0.0)  # until the end
    assert faults.active(4_999_999_999) is None
    assert faults.active(5_000_000_000) == "lidar_silent"
    assert faults.active(6_500_000_000) == "lidar_nan"  # the later one wins while both are on
    assert faults.active(60_000_000_000) == "lidar_nan"
    with pytest.raises(ValueError, match="odometry_jump"):
        faults.add("odometry_jump", 0, 1.0)
