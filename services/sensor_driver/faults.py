"""LiDAR faults the sensor driver acts on (scheduled by the simulator on falconry/sim/faults).

`lidar_silent` publishes nothing, `lidar_nan` an all-NaN cloud, `lidar_garbage` a return on
every beam at a random range (uniform within the sensor's range limits), as a sensor whose
timing went wrong would give; neither of the last two hit anything real, so the truth says -1
for every ray. Pure: the node feeds the commands (services/lib/runtime/sensor_faults.py) and asks what
is in force.
"""
from __future__ import annotations

import numpy as np

from services.lib.runtime.sensor_faults import SensorFaults
from services.sensor_driver.core import Scan

LIDAR_FAULTS = ("lidar_silent", "lidar_nan", "lidar_garbage")


def lidar_faults() -> SensorFaults:
    return SensorFaults(LIDAR_FAULTS)


def faulty_scan(good: Scan, kind: str, origin: np.ndarray, beams: np.ndarray, min_range: float,
                max_range: float, rng: np.random.Generator) -> Scan:
    """What the driver publishes during a LiDAR fault (`lidar_silent` publishes nothing).
    `beams` are the scan's world-frame unit directions (rows, cols, 3)."""
    shape = good.hits.shape
    if kind == "lidar_nan":
        points = np.full((*shape, 3), np.nan, dtype=np.float32)
    elif kind == "lidar_garbage":
        ranges = rng.uniform(min_range, max_range, shape)
        points = (np.asarray(origin, dtype=float) + np.asarray(beams).reshape(*shape, 3) * ranges[..., None])
        points = points.astype(np.float32)
    else:
        raise ValueError(f"no scan to publish for fault {kind!r}")
    intensity = None if good.intensity is None else np.full(shape, np.nan, dtype=np.float32)
    return Scan(points, np.full(shape, -1, dtype=np.int32), intensity)
