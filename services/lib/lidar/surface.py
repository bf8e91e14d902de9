"""Where a target's centre lies behind the returns a LiDAR got from it: a LiDAR samples only the
side facing it, so the returns' centroid sits in front of the centre by the mean depth of the
visible surface (2a/3 for a sphere of radius a, πa/4 for an upright disc seen edge-on; seed 000,
sec. V-A bounds it by [0, a]). Shared by the classifier, which moves a detection by it, and the
tracker, which re-centres the returns it re-identifies a target by. Pure numpy."""
from __future__ import annotations

import numpy as np


def half_width_across(members: np.ndarray, centroid: np.ndarray, sensor: np.ndarray) -> float:
    """Half the cluster's extent across the line of sight from `sensor` to `centroid`: the larger
    of its extents along the two directions across that line. Few returns under-measure it (the
    outermost rays miss the rim); only range noise can add to it, by about a centimetre (intruder:
    up to 0.333 m for a 0.325 m drone). 0 for a single return."""
    line = _line_of_sight(centroid, sensor)
    if line is None or len(members) < 2:
        return 0.0
    across = np.cross(line, [0.0, 0.0, 1.0])
    if np.linalg.norm(across) < 1e-6:  # looking straight up or down
        across = np.array([1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    offsets = members - centroid
    return 0.5 * max(float(np.ptp(offsets @ across)), float(np.ptp(offsets @ np.cross(line, across))))


def surface_offset(centroid: np.ndarray, sensor: np.ndarray, bias: float, half_width: float) -> np.ndarray:
    """The shift from the returns' centroid to the target's centre estimate: `bias` × the target's
    half-width across the line of sight, away from the sensor (the module's words)."""
    line = _line_of_sight(centroid, sensor)
    return np.zeros(3) if line is None else bias * half_width * line


def _line_of_sight(centroid: np.ndarray, sensor: np.ndarray) -> np.ndarray | None:
    line = np.asarray(centroid, dtype=np.float64) - np.asarray(sensor, dtype=np.float64)
    distance = float(np.linalg.norm(line))
    return None if distance == 0.0 else line / distance
