"""LiDAR models the simulated sensor driver can be: beam layouts and datasheet ranges.

Directions are unit vectors in the sensor frame (x forward, y left, z up), shaped
(rows, cols, 3) like the organised cloud the driver publishes.

Ouster OS0 / OS1 (`os0-128`, `os1-64-2048`, ...: family, rows 32/64/128, optional columns
512/1024/2048, default 1024). A spinning sensor: `rows` beams spread evenly over the vertical
field of view centred on the horizon (OS0 90°, OS1 45°; row 0 is the highest beam), fired
together at `cols` azimuths per turn (column j at 2π·j/cols, counter-clockwise from +x). The
same directions every frame. Ranges as in seed 000's Table I: OS0 0.3–50 m, OS1 0.3–100 m.

Livox Mid-360 (`mid360`): 360° azimuth × −7°…52° elevation, 200,000 points/s, so 20,000
points per 10 Hz frame, laid out as (4, 5000): row = one of four beams, column = firing order
within the frame. Model (documented, not Livox's proprietary pattern): a head spinning at
10 rev/s carries four beams, a quarter turn apart; each beam nods up and down across the
whole elevation range along a triangle wave (even dwell at every elevation) at
40 + (√5 − 1)/2 nods per revolution. The ratio is irrational, so the nods drift by the golden
ratio of a cycle every turn and no two frames sample the same directions; within about
1 s they fill the field of view (tests/test_lidar_models.py: ≥ 90 % of the 1° × 1° cells).
Each frame covers roughly 70 % of the cells, in slanted sweeps about 1° apart. Rays that
return nothing are NaN in the cloud like any other sensor's. Ranges 0.1–40 m (40 m is the
datasheet figure at 10 % reflectivity). A different frame rate keeps 50,000 firings per
beam per second, so the frame has 50,000 / rate columns.
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numpy as np

DEFAULT_MOUNT = (0.0, 0.0, 0.4)  # m: the LiDAR above the UAV's centre (body frame), unless a driver's parameters say otherwise
MID360_BEAMS = 4
MID360_FIRINGS_PER_BEAM_S = 50_000  # 4 beams: 200,000 points/s
MID360_SPIN_HZ = 10.0
MID360_NODS_PER_TURN = 40.0 + (math.sqrt(5.0) - 1.0) / 2.0
MID360_ELEVATION_DEG = (-7.0, 52.0)

_OUSTER = re.compile(r"^(os0|os1)-(32|64|128)(?:-(512|1024|2048))?$")
_OUSTER_FAMILY = {  # vertical field of view (deg), min range, max range (m)
    "os0": (90.0, 0.3, 50.0),
    "os1": (45.0, 0.3, 100.0),
}
MODEL_NAMES = ("os0-32", "os0-64", "os0-128", "os1-32", "os1-64", "os1-128", "mid360")


@dataclass(frozen=True)
class LidarModel:
    name: str
    pattern: str  # "spinning" or "mid360"
    rows: int
    cols: int
    elevation_min_deg: float
    elevation_max_deg: float
    min_range: float
    max_range: float

    @property
    def repeats(self) -> bool:
        """Whether every frame fires the same directions."""
        return self.pattern == "spinning"

    def directions(self, frame: int) -> np.ndarray:
        """(rows, cols, 3) float64 read-only sensor-frame unit beams of frame `frame`
        (the n-th frame since mission time 0)."""
        if self.pattern == "spinning":
            return _spinning(self.rows, self.cols, self.elevation_min_deg, self.elevation_max_deg)
        return mid360_directions(frame, self.cols)


@dataclass(frozen=True)
class BeamSpacing:
    """How far apart the beams of one frame lie, rad: between rows (elevation) and between
    columns (azimuth step). Across the line of sight, two columns at elevation e lie cos(e) times
    the azimuth step apart; taking the step itself errs on the cautious side, by at most 1/cos(45°)
    in an OS0's top and bottom rows."""
    vertical: float
    horizontal: float


def beam_spacing(name: str, rows: int, cols: int) -> BeamSpacing | None:
    """How far apart the beams of a `rows` × `cols` frame of model `name` lie (None for a model
    this module does not know). A spinning sensor's rows are its field of view over rows − 1 and
    its columns a turn over cols; the Mid-360's frame scatters its firings over the whole field
    of view, so each stands for an equal patch of it: the square root of the azimuth × elevation
    rectangle (rad², 6 % more than its solid angle) over the firings, both ways."""
    try:
        model = lidar_model(name)
    except ValueError:
        return None
    if rows < 1 or cols < 1:
        return None
    field = math.radians(model.elevation_max_deg - model.elevation_min_deg)
    if model.pattern == "spinning":
        return BeamSpacing(field / max(rows - 1, 1), 2.0 * math.pi / cols)
    patch = math.sqrt(2.0 * math.pi * field / (rows * cols))
    return BeamSpacing(patch, patch)


def lidar_model(name: str, rate_hz: float = 10.0) -> LidarModel:
    """The model called `name` (see the module docstring); ValueError names the choices."""
    key = name.strip().lower()
    match = _OUSTER.match(key)
    if match:
        family, rows, cols = match.group(1), int(match.group(2)), int(match.group(3) or 1024)
        vfov, min_range, max_range = _OUSTER_FAMILY[family]
        return LidarModel(key, "spinning", rows, cols, -vfov / 2, vfov / 2, min_range, max_range)
    if key == "mid360":
        if not rate_hz > 0:
            raise ValueError(f"mid360: rate_hz must be > 0, got {rate_hz}")
        cols = max(1, int(round(MID360_FIRINGS_PER_BEAM_S / rate_hz)))
        return LidarModel(key, "mid360", MID360_BEAMS, cols, *MID360_ELEVATION_DEG, 0.1, 40.0)
    raise ValueError(f"unknown LiDAR model {name!r}: choose one of {', '.join(MODEL_NAMES)} "
                     "(Ouster names take an optional column count: os0-128-2048, os1-64-512)")


def beam_directions(rows: int, cols: int, vfov_deg: float, vertical_center_deg: float = 0.0) -> np.ndarray:
    """(rows, cols, 3) unit beams of a spinning sensor. Row 0 is the highest beam, rows spread
    evenly over the vertical field of view (ends included); column j points at azimuth
    2π·j/cols, counter-clockwise from +x."""
    half = vfov_deg / 2.0
    elevation = np.radians(np.linspace(vertical_center_deg + half, vertical_center_deg - half, rows))
    azimuth = 2.0 * np.pi * np.arange(cols) / cols
    return _unit(elevation[:, None], azimuth[None, :])


@functools.lru_cache(maxsize=8)
def _spinning(rows: int, cols: int, el_min: float, el_max: float) -> np.ndarray:
    directions = beam_directions(rows, cols, el_max - el_min, (el_max + el_min) / 2)
    directions.flags.writeable = False
    return directions


def mid360_directions(frame: int, cols: int = MID360_FIRINGS_PER_BEAM_S // 10) -> np.ndarray:
    """(4, cols, 3) beams of Mid-360 frame `frame`: firing j of the frame is beam firing
    number frame·cols + j since mission time 0."""
    firing = frame * cols + np.arange(cols, dtype=np.float64)
    t = firing / MID360_FIRINGS_PER_BEAM_S  # s
    beam = np.arange(MID360_BEAMS)[:, None]
    azimuth = 2.0 * np.pi * (MID360_SPIN_HZ * t[None, :] + beam / MID360_BEAMS)
    nod = np.mod(MID360_NODS_PER_TURN * MID360_SPIN_HZ * t, 1.0)[None, :]  # cycles
    triangle = 2.0 * np.abs(2.0 * nod - 1.0) - 1.0  # -1 … 1, even dwell
    low, high = MID360_ELEVATION_DEG
    elevation = np.radians((low + high) / 2 + (high - low) / 2 * triangle)
    return _unit(np.broadcast_to(elevation, azimuth.shape), azimuth)


def _unit(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    el, az = np.broadcast_arrays(elevation, azimuth)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
