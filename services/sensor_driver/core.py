"""Simulated LiDAR: whole scans of the simulated world (services/lib/world) with noise, body mask
and truth.

A scan casts a sensor model's beams (services/lib/lidar/models.py: Ouster OS0/OS1, Livox Mid-360)
with the compiled caster, keeps the id of what every ray hit (for evaluation and the oracle
detector, never in the cloud), and adds sensor pose noise, a body mask and an optional intensity.
Ideal in time: every ray of a frame is cast at the frame's stamp (no motion distortion), and the
carrier has no roll or pitch.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import msgspec
import numpy as np

from schemas.messages import Obstacle, TargetTruth, WorldModel
from services.lib.geometry import yaw_rotation
from services.lib.lidar.models import DEFAULT_MOUNT, LidarModel, lidar_model
from services.lib.world.primitives import Packed, Primitives, pack, read_only
from services.lib.world.raycast import scan_kernel

INTENSITY_FULL_RANGE = 5.0  # m: intensity falls as 1/r² beyond this
DEFAULT_BODY_BOX = (-0.4, -0.4, -0.4, 0.4, 0.4, 0.4)
FALLBACK_MODEL = "os0-32-512"  # when neither the parameters nor the scenario name one


class SensorDriverParams(msgspec.Struct, forbid_unknown_fields=True):
    # LiDAR model (services/lib/lidar/models.py): os0-/os1- 32/64/128 [-512/-1024/-2048], mid360. "" = the one the
    # scenario names for this UAV (falconry/sim/world `sensors`), FALLBACK_MODEL if it names none.
    model: str = ""
    rate_hz: float = 10.0  # frames per second of mission time
    min_range: float = 0.0  # m; 0 = the model's datasheet value
    max_range: float = 0.0  # m; 0 = the model's datasheet value
    range_noise: float = 0.02  # m, standard deviation of every range
    position_noise: float = 0.0  # m, σ per axis of where a scan is really taken from (per scan)
    attitude_noise: float = 0.0  # rad, σ of the sensor's true roll, pitch and yaw (per scan)
    # Carrier body in the sensor frame (x fwd, y left, z up): x_min, y_min, z_min, x_max, y_max, z_max.
    # A box in front of the sensor (e.g. the frame below it) blocks rays; a box around the sensor
    # crops returns inside it. Either way those rays return nothing. [] = no body.
    body_box: list[float] = msgspec.field(default_factory=lambda: list(DEFAULT_BODY_BOX))
    # Where the sensor sits on the carrier (x fwd, y left, z up), m from the carrier's reference
    # point, which rests on the ground when landed: on top of the frame, not in the grass.
    mount: list[float] = msgspec.field(default_factory=lambda: list(DEFAULT_MOUNT))
    intensity: bool = False  # publish a per-point intensity (reflectivity · |cos incidence| / range²)
    # Check every scan (services/lib/lidar/sanity.py); a failing one is flagged and its points skipped downstream
    sanity_checks: bool = True
    max_return_share: float = 0.98  # of unblocked beams returning: above it the sky is missing (> 1 indoors)

    def __post_init__(self) -> None:  # msgspec reports these as validation errors naming the table
        if self.model:
            lidar_model(self.model, self.rate_hz if self.rate_hz > 0 else 10.0)
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        for name in ("min_range", "max_range", "range_noise", "position_noise", "attitude_noise"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if len(self.mount) != 3 or not all(np.isfinite(self.mount)):
            raise ValueError(f"mount must be [x, y, z] in metres, got {self.mount}")
        box = self.body_box
        if len(box) not in (0, 6) or (len(box) == 6 and not all(box[k] < box[k + 3] for k in range(3))):
            raise ValueError(f"body_box must be [] or [x_min, y_min, z_min, x_max, y_max, z_max] "
                             f"with min < max, got {box}")


# ------------------------------------------------------------------ scanning
@dataclass
class Scan:
    points: np.ndarray  # float32 (rows, cols, 3) world frame, NaN: no return
    hits: np.ndarray  # int32 (rows, cols): -1 no return, 0 static world, k >= 1 target k
    intensity: np.ndarray | None  # float32 (rows, cols) in [0, 1], NaN: no return


def reregistered(points: np.ndarray, origin: np.ndarray, heading: float, believed_origin: np.ndarray,
                 believed_heading: float) -> np.ndarray:
    """A scan cast from (origin, heading) as the vehicle would register it from where it believes the
    sensor is: each point keeps its place relative to the sensor, which moves to the belief
    (float32, NaN stays NaN). A UAV flying without GNSS registers its scans by its localizer's
    estimate; the perception behind it then works in the estimate's frame, as onboard."""
    turn = yaw_rotation(believed_heading) @ yaw_rotation(heading).T
    relative = np.asarray(points, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    moved = relative @ turn.T + np.asarray(believed_origin, dtype=np.float64)
    return moved.astype(np.float32)


def small_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw)·Ry(pitch)·Rx(roll)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return yaw_rotation(yaw) @ ry @ rx


def scan(origin: np.ndarray, heading: float, directions: np.ndarray, world: Primitives | Packed,
         rng: np.random.Generator, min_range: float = 0.3, max_range: float = 50.0,
         range_noise: float = 0.01, position_noise: float = 0.0, attitude_noise: float = 0.0,
         body_box: Sequence[float] | None = DEFAULT_BODY_BOX, intensity: bool = False) -> Scan:
    """One organised scan from the believed pose (`origin`, yawed by `heading`) of sensor-frame
    beams `directions` (rows, cols, 3).

    The rays really leave from the believed pose moved by gaussian position / attitude noise
    (one draw per scan), and the points are placed from the believed pose, as a real driver
    would. A ray returns nothing when its true range is outside [min_range, max_range] or
    when it meets the carrier (`body_box`, sensor frame; see SensorDriverParams). Range noise
    is one draw per ray whether it hits or not, so the RNG stream stays in step."""
    shape = directions.shape[:-1]
    packed = world if isinstance(world, Packed) else pack(world)
    sensor_dirs = read_only(np.asarray(directions, dtype=float).reshape(-1, 3))
    pose_draw = rng.normal(0.0, 1.0, 6)
    noise = rng.normal(0.0, range_noise, len(sensor_dirs)) if range_noise > 0 else np.zeros(len(sensor_dirs))
    believed_origin = np.asarray(origin, dtype=float)
    believed = yaw_rotation(heading)
    true_origin = believed_origin + position_noise * pose_draw[:3]
    true_rotation = believed @ small_rotation(*(attitude_noise * pose_draw[3:]))
    body = np.asarray(body_box if body_box is not None else (), dtype=float)
    if len(body) not in (0, 6):
        raise ValueError(f"body_box needs 6 numbers (x_min, y_min, z_min, x_max, y_max, z_max), got {len(body)}")
    n = len(sensor_dirs)
    points = np.empty((n, 3), dtype=np.float32)
    hits = np.empty(n, dtype=np.int32)
    brightness = np.empty(n, dtype=np.float32)
    scan_kernel(true_origin, true_rotation, believed_origin, believed, sensor_dirs, noise,
                packed.kinds, packed.params, packed.bounds, packed.ids, packed.reflectivity,
                float(min_range), float(max_range), body if len(body) else np.zeros(6), len(body) == 6,
                INTENSITY_FULL_RANGE if intensity else 0.0, points, hits, brightness)
    return Scan(points.reshape(*shape, 3), hits.reshape(shape),
                brightness.reshape(shape) if intensity else None)


def scan_ranges(params: SensorDriverParams, model: LidarModel) -> tuple[float, float]:
    """(min, max) range of the returns a scan keeps: the parameters' where set, else the model's."""
    return params.min_range or model.min_range, params.max_range or model.max_range


def model_scan(params: SensorDriverParams, model: LidarModel, origin: np.ndarray, heading: float,
               world: Primitives, rng: np.random.Generator, frame: int = 0):
    """One scan of `world` by `model` with the driver's parameters (`scan`)."""
    min_range, max_range = scan_ranges(params, model)
    return scan(origin, heading, model.directions(frame), world, rng, min_range=min_range, max_range=max_range,
                range_noise=params.range_noise, position_noise=params.position_noise,
                attitude_noise=params.attitude_noise, body_box=params.body_box, intensity=params.intensity)
