"""The simulated RGB-D camera (seed 004 §2.3): geometry against the analytic projection, shading,
gains, depth noise and dropouts."""
from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.messages import Appearance, Obstacle, TargetTruth
from services.camera.core import Camera, CameraParams, Gains, camera_rotation
from services.lib.pinhole import Intrinsics
from services.lib.world.primitives import pack, primitives_from_obstacles

QUIET = dict(color_noise=0.0, depth_noise=0.0, depth_dropout=0.0, exposure_drift=0.0, white_balance_drift=0.0)
SKY = Appearance(sky=(10, 20, 250), ambient=1.0)


def world_with(balloon_at, radius=0.3, color=(200, 30, 30), ground=True):
    obstacles = [Obstacle(kind="plane", center=(0.0, 0.0, 0.0), color=(90, 90, 90))] if ground else []
    balloon = TargetTruth(id="b", kind="balloon", position=tuple(balloon_at), velocity=(0, 0, 0), radius=radius,
                          color=color)
    return pack(primitives_from_obstacles(obstacles).with_targets([balloon]))


def render(world, params=None, position=(0.0, 0.0, 5.0), heading=0.0, appearance=SKY, seed=0):
    cam = Camera(params or CameraParams(**QUIET), np.random.default_rng(seed))
    rotation = camera_rotation(heading, cam.params.pitch)
    return cam, cam.render(world, appearance, np.asarray(position, float), rotation, np.ones(3),
                           np.random.default_rng(seed))


@pytest.mark.parametrize("distance, off_axis", [(5.0, 0.0), (12.0, 0.15), (20.0, -0.1)])
def test_a_spheres_footprint_is_its_analytic_projection_within_a_pixel(distance, off_axis):
    """The pixels that see the sphere are the pixels whose centre rays meet it: the silhouette of
    a sphere through a pinhole is a cone of half-angle asin(r/d) about the line to its centre."""
    params = CameraParams(pitch=0.0, **QUIET)
    centre = np.array([distance, off_axis * distance, 5.0 + 0.05 * distance])
    cam, frame = render(world_with(centre, ground=False), params)
    seen = frame.hits >= 0
    rays = cam.rays.reshape(params.height, params.width, 3)
    line = centre - np.array([0.0, 0.0, 5.0])
    cos_half = math.cos(math.asin(0.3 / np.linalg.norm(line)))
    inside = rays @ (line / np.linalg.norm(line)) >= cos_half
    assert seen.sum() > 20
    assert np.array_equal(seen, inside)  # the caster's footprint is the exact one, pixel centre by pixel centre
    k = cam.intrinsics
    u, v = k.project(line[None])[0]
    ys, xs = np.nonzero(seen)
    assert abs(xs.mean() + 0.5 - u) < 1.0 and abs(ys.mean() + 0.5 - v) < 1.0  # centred where it projects
    radius_px = k.fx * math.tan(math.asin(0.3 / np.linalg.norm(line)))
    assert abs(math.sqrt(seen.sum() / math.pi) - radius_px) < 1.0


def test_intrinsics_are_the_d435_colour_field_of_view():
    k = Intrinsics.from_fov(640, 360, 69.4, 42.5)
    rays = Intrinsics.pixel_rays(k).reshape(360, 640, 3)
    assert math.degrees(2 * math.atan2(rays[180, 0, 1], rays[180, 0, 0])) == pytest.approx(69.4 * 639 / 640, abs=0.2)
    assert k.fx == pytest.approx(k.fy, rel=0.01)  # square pixels
    assert np.allclose(np.linalg.norm(rays, axis=-1), 1.0)


def test_shading_follows_the_sun_and_the_sky_has_its_colour():
    look = Appearance(sky=(10, 20, 250), sun_elevation=90.0, ambient=0.3)
    params = CameraParams(pitch=0.0, **QUIET)
    _, frame = render(world_with((6.0, 0.0, 5.0), radius=1.0, color=(200, 200, 200), ground=False), params,
                      appearance=look)
    sphere = frame.rgb[frame.hits >= 0].astype(int)
    assert (frame.rgb[frame.hits < 0] == (10, 20, 250)).all()
    top = frame.rgb[:180][frame.hits[:180] >= 0].astype(int).mean()
    bottom = frame.rgb[180:][frame.hits[180:] >= 0].astype(int).mean()
    assert top > bottom + 25  # lit from above
    assert sphere.min() > 0  # the ambient share lights the side away from the sun


def test_depth_is_along_the_optical_axis_with_noise_growing_with_range_squared_and_dropouts():
    params = CameraParams(pitch=-90.0, color_noise=0.0, depth_noise=0.004, depth_dropout=0.05, exposure_drift=0.0,
                          white_balance_drift=0.0, depth_max=20.0)
    errors = {}
    for height in (2.0, 8.0):
        world = pack(primitives_from_obstacles([Obstacle(kind="plane", center=(0, 0, 0))]))
        cam, frame = render(world, params, position=(0.0, 0.0, height))
        depth = frame.depth_mm.astype(float) / 1000.0
        camera_height = height  # render() places the camera itself, no mount
        valid = depth > 0
        assert 0.03 < 1 - valid.mean() < 0.07  # the dropouts
        errors[height] = np.std(depth[valid] - camera_height)
        assert abs(np.mean(depth[valid]) - camera_height) < 0.01  # z along the axis: the same over the image
    ratio = errors[8.0] / errors[2.0]
    assert ratio == pytest.approx((8.0 / 2.0) ** 2, rel=0.15)


def test_exposure_and_white_balance_drift_within_their_bounds():
    gains, rng, params = Gains(), np.random.default_rng(1), CameraParams(exposure_drift=0.05, white_balance_drift=0.02)
    seen = []
    for _ in range(2000):
        gains.step(rng, params)
        seen.append((gains.exposure, gains.red, gains.blue))
    seen = np.array(seen)
    assert np.abs(seen[:, 0]).max() <= params.exposure_limit + 1e-12
    assert np.abs(seen[:, 1:]).max() <= params.white_balance_limit + 1e-12
    assert seen[:, 0].std() > 0.05  # it does wander


@pytest.mark.parametrize("bad", [dict(width=4), dict(rate_hz=0), dict(phase=1.0), dict(mount=[0, 0]),
                                 dict(depth_dropout=1.0), dict(horizontal_fov=175.0), dict(jpeg_quality=0)])
def test_bad_camera_parameters_are_refused(bad):
    with pytest.raises(ValueError):
        CameraParams(**bad)


def test_a_tiled_frame_sees_what_the_caster_sees_through_every_pixel():
    """The renderer tests each pixel only against its tile's list of primitives (render.py): a list
    too short would lose what the pixel sees. The LiDAR's caster, which tests every primitive,
    must see the same primitive at the same range through every pixel, from poses inside bounding
    spheres, beside them and far away, with primitives filling several tiles and grazing others."""
    from services.lib.world.raycast import cast_kernel

    rng = np.random.default_rng(5)
    obstacles = [Obstacle(kind="plane", center=(0.0, 0.0, 0.0), color=(90, 90, 90))]
    for k in range(25):
        kind = ["box", "cylinder", "sphere", "cone"][k % 4]
        centre = (*rng.uniform(-25, 25, 2), 0.0 if kind != "sphere" else rng.uniform(1, 8))
        obstacles.append(Obstacle(kind=kind, center=tuple(centre), size=tuple(rng.uniform(0.3, 4.0, 3)),
                                  radius=float(rng.uniform(0.2, 2.0)), height=float(rng.uniform(1, 10))))
    obstacles.append(Obstacle(kind="sphere", center=(3.0, 4.0, 6.0), radius=-1.5))  # the caster squares radii
    world = pack(primitives_from_obstacles(obstacles))
    cam = Camera(CameraParams(width=200, height=120, **QUIET), rng)
    for k in range(30):
        position = world.bounds[1 + k % (len(world) - 1), :3] if k % 5 == 0 else np.array(
            [*rng.uniform(-30, 30, 2), rng.uniform(0.5, 15)])
        rotation = camera_rotation(rng.uniform(-math.pi, math.pi), rng.uniform(-60, 30))
        frame = cam.render(world, SKY, position, rotation, np.ones(3), rng)
        ranges, hits = np.empty(len(cam.rays)), np.empty(len(cam.rays), dtype=np.int64)
        cast_kernel(position, np.ascontiguousarray(cam.rays @ rotation.T), world.kinds, world.params, world.bounds,
                    ranges, hits)
        assert np.array_equal(frame.hits.ravel(), hits), k


def test_tiles_cover_every_pixel_once_and_their_cones_hold_their_rays():
    from services.camera.render import Tiles

    k = Intrinsics.from_fov(100, 37, 69.4, 42.5)  # tiles cut at both edges
    rays = k.pixel_rays()
    tiles = Tiles.of(rays, 100, 37, size=16)
    assert np.array_equal(np.sort(tiles.order), np.arange(100 * 37)) and tiles.start[-1] == 100 * 37
    assert len(tiles.axes) == 7 * 3
    for t in range(len(tiles.axes)):
        members = rays[tiles.order[tiles.start[t]:tiles.start[t + 1]]]
        assert (members @ tiles.axes[t] >= tiles.cos_half[t] - 1e-12).all()


def test_tiles_seeing_only_the_ground_give_the_bits_of_the_general_path():
    """A tile whose only candidate is a plane takes a short path (render.py). A second copy of the
    ground, listed after it, sends every tile through the general path instead; the nearer-hit rule
    keeps the first copy, so the frames must be the same bits: colour with noise and gains, depth
    with noise and dropouts, and the primitive each pixel sees (the balloons' indices one further
    on), from above the ground and below it."""
    rng = np.random.default_rng(11)
    ground = Obstacle(kind="plane", center=(0.0, 0.0, 0.6), color=(90, 120, 60))  # not at 0: its height counts
    balloons = [TargetTruth(id=f"b{k}", kind="balloon", position=(*rng.uniform(-20, 20, 2), rng.uniform(1, 6)),
                            velocity=(0, 0, 0), radius=0.4, color=(200, 30, 30)) for k in range(6)]
    once = pack(primitives_from_obstacles([ground]).with_targets(balloons))
    twice = pack(primitives_from_obstacles([ground, ground]).with_targets(balloons))
    params = CameraParams(width=160, height=96)  # noise, drifts and dropouts on
    look = Appearance(sun_elevation=35.0, sun_azimuth=120.0, ambient=0.3)
    for k, height in enumerate((5.0, 1.3, 14.0, -2.0)):
        position = np.array([*rng.uniform(-10, 10, 2), height])
        rotation = camera_rotation(rng.uniform(-math.pi, math.pi), rng.uniform(-10, 10))  # the horizon in view
        gains = rng.uniform(0.8, 1.2, 3)
        short, general = (Camera(params, np.random.default_rng(k)).render(world, look, position, rotation, gains,
                                                                          np.random.default_rng(k))
                          for world in (once, twice))
        assert np.array_equal(short.rgb, general.rgb) and np.array_equal(short.depth_mm, general.depth_mm), k
        assert not (general.hits == 1).any(), k  # the copy is never the nearer hit
        assert np.array_equal(short.hits, np.where(general.hits > 1, general.hits - 1, general.hits)), k
        sky = (short.hits == -1).sum()
        assert 0 < sky < short.hits.size, (k, sky)
