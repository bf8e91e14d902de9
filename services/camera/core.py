"""Simulated RGB-D camera after seed 004 §2.3 (Intel RealSense D435): a pinhole colour camera
looking forward from the carrier, and the depth image aligned with it.

Geometry: the D435 colour camera's field of view, 69.4° × 42.5°, at a resolution of choice
(default 640 × 360: a 0.6 m balloon 20 m away is 14 pixels across), square pixels, the principal
point at the image centre; mounted `mount` from the carrier's reference point, its optical axis
`pitch` degrees above the horizon (negative: down) when the carrier is level, turned with the
carrier's heading. The camera frame: x the optical axis, y left, z up (the LiDAR's convention).

Image: the world the LiDAR sees (services/sensor_driver: the same primitives and caster), each
surface its sRGB colour lit by the scenario's sun and ambient light (render.py); then the
camera's exposure and white balance, which drift as bounded random walks from frame to frame
(an auto-exposure that never quite settles), and sensor noise of `color_noise` levels (σ).

Depth: the distance along the optical axis where the pixel's ray hits, as a D435 measures it
aligned to the colour image: noise σ = depth_noise · z² (the stereo error grows with the square
of the range: σ_z = z² · subpixel / (focal · baseline) = z² · 0.08 / (444 px · 0.05 m) ≈
0.0036 z² for the D435's 848-pixel depth at its 0.08 subpixel accuracy; 0.004 by default), none
closer than depth_min or beyond depth_max, and `depth_dropout` of the pixels missing at random.

Pure: numpy in, numpy out; the caller owns the random generator and the drifting gains.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from statistics import NormalDist

import msgspec
import numpy as np

from schemas.messages import Appearance
from services.camera.render import Tiles, encode_table, noise_table, render_kernel, srgb_to_linear, tile_candidates
from services.lib.geometry import yaw_rotation
from services.lib.pinhole import Intrinsics
from services.lib.world.primitives import Packed

D435_HORIZONTAL_FOV = 69.4  # degrees, colour camera
D435_VERTICAL_FOV = 42.5
NOISE_TABLE_SIZE = 1 << 21  # entries of each noise table: several frames' worth before it repeats


class CameraParams(msgspec.Struct, forbid_unknown_fields=True):
    width: int = 640  # pixels
    height: int = 360
    rate_hz: float = 10.0  # frames per second of mission time
    # Where in the frame period the frames fall (0-1): 0.5 puts them between the 10 Hz LiDAR scans,
    # so a lockstep tick does not carry both (the fleet's busiest ticks stay as they were).
    phase: float = 0.5
    horizontal_fov: float = D435_HORIZONTAL_FOV  # degrees
    vertical_fov: float = D435_VERTICAL_FOV
    pitch: float = -10.0  # degrees above the horizon of the optical axis when level (negative: down)
    mount: list[float] = msgspec.field(default_factory=lambda: [0.15, 0.0, 0.15])  # m, x fwd, y left, z up
    color_noise: float = 2.0  # σ of the sensor noise, sRGB levels
    exposure_drift: float = 0.01  # σ of the log exposure gain's step per frame
    exposure_limit: float = 0.2  # the log exposure gain stays within ± this
    white_balance_drift: float = 0.004  # σ of the red and blue gains' log step per frame
    white_balance_limit: float = 0.08
    depth: bool = True  # publish the aligned depth image
    depth_min: float = 0.3  # m
    depth_max: float = 10.0  # m
    depth_noise: float = 0.004  # σ = depth_noise · z², m
    depth_dropout: float = 0.02  # share of pixels without depth
    preview_hz: float = 1.0  # compressed frames for the ground (recordings, snapshots); 0 = none
    jpeg_quality: int = 90

    def __post_init__(self) -> None:
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ValueError(f"width and height must lie in 16..4096 pixels, got {self.width} × {self.height}")
        for name in ("rate_hz", "horizontal_fov", "vertical_fov", "depth_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if not (self.horizontal_fov < 170 and self.vertical_fov < 170):
            raise ValueError("a pinhole camera's field of view must stay below 170°")
        if not 0.0 <= self.phase < 1.0:
            raise ValueError(f"phase must lie in [0, 1), got {self.phase}")
        if len(self.mount) != 3 or not all(math.isfinite(v) for v in self.mount):
            raise ValueError(f"mount must be [x, y, z] in metres, got {self.mount}")
        for name in ("color_noise", "exposure_drift", "exposure_limit", "white_balance_drift",
                     "white_balance_limit", "depth_min", "depth_noise", "preview_hz"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        if not 0.0 <= self.depth_dropout < 1.0:
            raise ValueError(f"depth_dropout must lie in [0, 1), got {self.depth_dropout}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must lie in 1..100, got {self.jpeg_quality}")


def camera_rotation(heading: float, pitch_deg: float) -> np.ndarray:
    """Camera frame → world: yawed by the heading, the optical axis pitch_deg above the horizon."""
    a = math.radians(-pitch_deg)  # about +y (left): a positive angle turns the optical axis down
    tilt = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    return yaw_rotation(heading) @ tilt


@dataclass
class Gains:
    """The camera's drifting exposure and white balance (log gains; green is the reference)."""

    exposure: float = 0.0
    red: float = 0.0
    blue: float = 0.0

    def step(self, rng: np.random.Generator, params: CameraParams) -> None:
        e, r, b = rng.normal(0.0, 1.0, 3)
        self.exposure = _bounded(self.exposure + params.exposure_drift * e, params.exposure_limit)
        self.red = _bounded(self.red + params.white_balance_drift * r, params.white_balance_limit)
        self.blue = _bounded(self.blue + params.white_balance_drift * b, params.white_balance_limit)

    def factors(self) -> np.ndarray:
        return np.exp(np.array([self.exposure + self.red, self.exposure, self.exposure + self.blue]))


def sane_appearance(look: Appearance) -> Appearance:
    """The world model's appearance with what a renderer cannot use replaced: colours clipped to
    0-255, a non-finite sun by the default one, the ambient share clipped to [0, 1]."""
    default = Appearance()
    finite = all(math.isfinite(v) for v in (look.sun_elevation, look.sun_azimuth))
    ambient = look.ambient if math.isfinite(look.ambient) else default.ambient
    return Appearance(sky=clip_color(look.sky), ground=clip_color(look.ground), obstacle=clip_color(look.obstacle),
                      sun_elevation=look.sun_elevation if finite else default.sun_elevation,
                      sun_azimuth=look.sun_azimuth if finite else default.sun_azimuth,
                      ambient=min(max(ambient, 0.0), 1.0))


def clip_color(color) -> tuple[int, int, int]:
    c = np.clip(np.asarray(color, dtype=np.float64).reshape(3), 0, 255)
    return tuple(int(v) for v in c)  # type: ignore[return-value]


def _bounded(value: float, limit: float) -> float:
    """Reflected at ±limit, so the walk stays inside without sticking to the edge."""
    if limit <= 0:
        return 0.0
    while abs(value) > limit:
        value = math.copysign(2 * limit, value) - value
    return value


@dataclass(frozen=True)
class Frame:
    rgb: np.ndarray  # uint8 (height, width, 3)
    depth_mm: np.ndarray  # uint16 (height, width), 0: none
    hits: np.ndarray  # int64 (height, width): packed primitive index, -1 sky (truth; evaluation only)
    rotation: np.ndarray  # camera frame → world
    position: np.ndarray  # camera centre, world


class Camera:
    """A camera's fixed parts (rays, tables, noise) and its render call."""

    def __init__(self, params: CameraParams, rng: np.random.Generator) -> None:
        self.params = params
        self.intrinsics = Intrinsics.from_fov(params.width, params.height, params.horizontal_fov, params.vertical_fov)
        self.rays = self.intrinsics.pixel_rays()
        self.tiles = Tiles.of(self.rays, params.width, params.height)
        self.tile_rays = np.ascontiguousarray(self.rays[self.tiles.order])
        self.encode = encode_table()
        self.color_noise = noise_table(rng, NOISE_TABLE_SIZE, params.color_noise, np.int16)
        self.depth_noise = noise_table(rng, NOISE_TABLE_SIZE // 2, 1.0, np.float32)
        self.dropout = NormalDist().inv_cdf(1.0 - params.depth_dropout / 2) if params.depth_dropout > 0 else math.inf

    def pose(self, carrier_position, heading: float) -> tuple[np.ndarray, np.ndarray]:
        """(camera centre, camera → world rotation) on a level carrier at this pose."""
        position = np.asarray(carrier_position, dtype=np.float64) + yaw_rotation(heading) @ np.asarray(self.params.mount)
        return position, camera_rotation(heading, self.params.pitch)

    def render(self, world: Packed, appearance: Appearance, position: np.ndarray, rotation: np.ndarray,
               gains: np.ndarray, rng: np.random.Generator) -> Frame:
        """One frame of `world` (its `colors` set) from the camera pose; `gains` (3,) multiply the
        linear light per channel (exposure × white balance)."""
        p = self.params
        n = len(self.rays)
        rgb = np.empty((n, 3), dtype=np.uint8)
        depth = np.empty(n, dtype=np.uint16)
        hits = np.empty(n, dtype=np.int64)
        colors = world.colors if world.colors is not None else np.full((len(world), 3), 128, np.uint8)
        look = sane_appearance(appearance)
        elevation, azimuth = math.radians(look.sun_elevation), math.radians(look.sun_azimuth)
        sun = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                        math.sin(elevation)])
        offsets = rng.integers(0, NOISE_TABLE_SIZE, 2)
        position = np.asarray(position, dtype=np.float64)
        rotation = np.ascontiguousarray(rotation, dtype=np.float64)
        tiles = self.tiles
        candidates = np.empty((len(tiles.axes), len(world)), dtype=np.int64)
        counts = np.empty(len(tiles.axes), dtype=np.int64)
        tile_candidates(position, rotation, tiles.axes, tiles.cos_half, tiles.sin_half, world.kinds, world.bounds,
                        candidates, counts)
        render_kernel(position, rotation, self.tile_rays, tiles.order, tiles.start, candidates, counts,
                      world.kinds, world.params, world.bounds, srgb_to_linear(colors), srgb_to_linear(look.sky),
                      sun, float(look.ambient), np.asarray(gains, dtype=np.float64), self.encode,
                      self.color_noise, int(offsets[0]), self.depth_noise, int(offsets[1]), float(p.depth_noise),
                      float(p.depth_min), float(p.depth_max), float(self.dropout), rgb, depth, hits)
        shape = (p.height, p.width)
        return Frame(rgb.reshape(*shape, 3), depth.reshape(shape), hits.reshape(shape), np.asarray(rotation),
                     np.asarray(position))


CAMERA_FAULTS = ("camera_frozen", "camera_saturated")  # what the camera node acts on (falconry/sim/faults)


def frozen_or_saturated(frame: Frame, kind: str, last: Frame | None) -> Frame:
    """What the camera gives during a fault: its previous frame again, or a white one (depth kept)."""
    if kind == "camera_frozen" and last is not None:
        return last
    if kind == "camera_saturated":
        return replace(frame, rgb=np.full_like(frame.rgb, 255))
    return frame
