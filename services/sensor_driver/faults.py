"""LiDAR faults the sensor driver acts on (scheduled by the simulator on falconry/sim/faults).

`lidar_silent` publishes nothing, `lidar_nan` an all-NaN cloud, `lidar_garbage` random points
within max range around the sensor; neither of the last two hit anything real, so the truth
says -1 for every ray. Pure: the node feeds the commands and asks what is in force.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.sensor_driver.core import Scan

LIDAR_FAULTS = ("lidar_silent", "lidar_nan", "lidar_garbage")


@dataclass
class LidarFaults:
    windows: list[tuple[int, str, int | None]] = field(default_factory=list)  # (start ns, kind, end ns or None)

    def add(self, kind: str, start_ns: int, duration_s: float) -> None:
        """A fault from `start_ns` for `duration_s` seconds of mission time (0: until the end)."""
        if kind not in LIDAR_FAULTS:
            raise ValueError(f"not a LiDAR fault: {kind!r}")
        end = start_ns + int(round(duration_s * 1e9)) if duration_s > 0 else None
        self.windows.append((int(start_ns), kind, end))

    def active(self, now_ns: int) -> str | None:
        """The most recently started fault in force at `now_ns`, or None."""
        live = [(start, i, kind) for i, (start, kind, end) in enumerate(self.windows)
                if start <= now_ns and (end is None or now_ns < end)]
        return max(live)[2] if live else None


def faulty_scan(good: Scan, kind: str, origin: np.ndarray, max_range: float, rng: np.random.Generator) -> Scan:
    """What the driver publishes during a LiDAR fault (`lidar_silent` publishes nothing):
    `lidar_nan` every point NaN, `lidar_garbage` every point random within max_range around the
    sensor. Neither hit anything real, so the truth says -1 everywhere."""
    shape = good.hits.shape
    none = np.full(shape, -1, dtype=np.int32)
    if kind == "lidar_nan":
        points = np.full((*shape, 3), np.nan, dtype=np.float32)
    elif kind == "lidar_garbage":
        offsets = rng.uniform(-max_range, max_range, (*shape, 3))
        points = (np.asarray(origin, dtype=float) + offsets).astype(np.float32)
    else:
        raise ValueError(f"no scan to publish for fault {kind!r}")
    intensity = None if good.intensity is None else np.full(shape, np.nan, dtype=np.float32)
    return Scan(points, none, intensity)
