"""The mapper's free-space update, compiled (numba, `cache=True`): the ray lengths gathered around
the sensor applied to the map in one pass (eq. 12 with n = n_int, towards g_free), skipping
voxels that hold a point of the scan and pinned (±∞) ones, collecting the voxels whose state
(eq. 7) changed. Numerically the same as `core.exponential_update` voxel by voxel.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from schemas import voxels

THRESHOLDS = np.array([voxels.UNCERTAIN, voxels.TENTATIVE_OCCUPIED, voxels.CONFIDENT_OCCUPIED], dtype=np.float32)


@njit(cache=True)
def _state(value, thresholds):
    state = 0
    for k in range(3):
        if value >= thresholds[k]:
            state = k + 1
    return state


@njit(cache=True)
def apply_ray_lengths(grid, window, touched, count, window_low, window_shape, grid_shape, holds_point,
                      target, thresholds, changed):
    """For the first `count` window voxels in `touched`: move the map voxel towards `target` by
    its summed ray length (eq. 12), unless `holds_point` marks it (flat map index) or it is pinned;
    zero its window weight. Writes the flat map indices whose state changed to `changed` (which may
    be `touched` itself: it is written behind the reading) and returns how many; the number of
    voxels the rays moved is the second result."""
    wy, wz = window_shape[1], window_shape[2]
    gy, gz = grid_shape[1], grid_shape[2]
    n_changed = 0
    n_rayed = 0
    for k in range(count):
        local = touched[k]
        n = window[local]
        window[local] = 0.0
        ix = local // (wy * wz) + window_low[0]
        iy = (local // wz) % wy + window_low[1]
        iz = local % wz + window_low[2]
        flat = (ix * gy + iy) * gz + iz
        if holds_point[flat]:
            continue
        old = grid[flat]
        if not (old > -math.inf and old < math.inf):
            continue
        n_rayed += 1
        keep = 2.0 ** (-float(n))
        new = np.float32(keep * float(old) + (1.0 - keep) * target)
        grid[flat] = new
        if _state(new, thresholds) != _state(old, thresholds):
            changed[n_changed] = flat
            n_changed += 1
    return n_changed, n_rayed
