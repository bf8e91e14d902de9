"""The mapper's compiled passes (numba, `cache=True`; deterministic):

- `apply_ray_lengths`: the ray lengths gathered around the sensor applied to the map in one pass
  (eq. 12 with n = n_int, towards g_free), skipping voxels that hold a point of the scan and pinned
  (±∞) ones, collecting the voxels whose state (eq. 7) changed. Numerically the same as
  `core.exponential_update` voxel by voxel.
- `first_occurrences`: one label-set update per voxel.
- `weakly_held_voxels`: the groups of the separate-cluster reset (eq. 23).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from schemas import voxels
from services.lib.voxels.kernels import find_root, union_sets

THRESHOLDS = np.array([voxels.UNCERTAIN, voxels.TENTATIVE_OCCUPIED, voxels.CONFIDENT_OCCUPIED], dtype=np.float32)


@njit(cache=True, inline="always")
def _state(value, thresholds):
    state = 0
    for k in range(3):
        if value >= thresholds[k]:
            state = k + 1
    return state


@njit(cache=True)
def apply_ray_lengths(grid, window, window_low, window_shape, grid_shape, holds_point, target, thresholds, changed):
    """For every voxel of `window` (ray lengths over the box of the map starting at voxel
    `window_low`) that a ray crossed: move the map voxel towards `target` by its summed ray length
    (eq. 12), unless `holds_point` marks it (flat map index) or it is pinned; zero the window as it
    goes. Writes the flat map indices whose state changed to `changed` (room for the whole window)
    and returns how many. One pass in the map's own order: every row of the window along z is a
    contiguous run of the map."""
    wx, wy, wz = window_shape[0], window_shape[1], window_shape[2]
    gy, gz = grid_shape[1], grid_shape[2]
    at_target = np.float32(target)
    n_changed = 0
    for ix in range(wx):
        for iy in range(wy):
            window_row = (ix * wy + iy) * wz
            grid_row = ((ix + window_low[0]) * gy + iy + window_low[1]) * gz + window_low[2]
            for iz in range(wz):
                n = window[window_row + iz]
                if n == 0.0:
                    continue
                window[window_row + iz] = 0.0
                flat = grid_row + iz
                old = grid[flat]
                if holds_point[flat] or old == at_target or not (old > -math.inf and old < math.inf):
                    continue  # a point's voxel takes the point's update; a voxel at the target stays there
                keep = 2.0 ** (-float(n))
                new = np.float32(keep * float(old) + (1.0 - keep) * target)
                grid[flat] = new
                if _state(new, thresholds) != _state(old, thresholds):
                    changed[n_changed] = flat
                    n_changed += 1
    return n_changed


@njit(cache=True)
def first_occurrences(flat, seen):
    """Positions in `flat` of the first occurrence of each of its values, in order; `seen` (bool,
    indexed by the values) is scratch, left all False. One pass instead of a sort (np.unique)."""
    keep = np.empty(len(flat), dtype=np.int64)
    count = 0
    for i in range(len(flat)):
        if not seen[flat[i]]:
            seen[flat[i]] = True
            keep[count] = i
            count += 1
    for k in range(count):
        seen[flat[keep[k]]] = False
    return keep[:count]


@njit(cache=True)
def weakly_held_voxels(grid, low, high, grid_shape, tentative, confident, forward, min_confident, slot, out):
    """Eq. 23's groups: the voxels of the box [low, high) at least `tentative` are grouped by
    adjacency (`forward`: the neighbour offsets (K, 3) after (0, 0, 0) in C order, half of a
    symmetric neighbourhood); writes to `out` the flat map indices of the voxels of every group
    with fewer than `min_confident` voxels at least `confident`, and returns how many. `slot`
    (int64, at least the box's size, all -1) is scratch, left as it was found.

    Union-find over the occupied voxels only: a box around the sensor holds ~440,000 voxels and a
    few thousand occupied ones (scipy.ndimage.label over the whole box took 6 ms)."""
    bx, by, bz = high[0] - low[0], high[1] - low[1], high[2] - low[2]
    gy, gz = grid_shape[1], grid_shape[2]
    occupied = np.empty(bx * by * bz, dtype=np.int64)  # box-relative flat index of each occupied voxel
    n = 0
    for ix in range(bx):
        for iy in range(by):
            row = ((ix + low[0]) * gy + iy + low[1]) * gz + low[2]
            for iz in range(bz):
                if grid[row + iz] >= tentative:
                    local = (ix * by + iy) * bz + iz
                    slot[local] = n
                    occupied[n] = local
                    n += 1
    parent = np.arange(n)
    for k in range(n):
        local = occupied[k]
        ix, iy, iz = local // (by * bz), (local // bz) % by, local % bz
        for f in range(forward.shape[0]):
            jx, jy, jz = ix + forward[f, 0], iy + forward[f, 1], iz + forward[f, 2]
            if 0 <= jx < bx and 0 <= jy < by and 0 <= jz < bz:
                other = slot[(jx * by + jy) * bz + jz]
                if other >= 0:
                    union_sets(parent, k, other)
    held = np.zeros(n, dtype=np.int64)  # confident voxels per group root
    for k in range(n):
        if _grid_value(grid, occupied[k], low, by, bz, gy, gz) >= confident:
            held[find_root(parent, k)] += 1
    count = 0
    for k in range(n):
        if held[find_root(parent, k)] < min_confident:
            local = occupied[k]
            out[count] = ((local // (by * bz) + low[0]) * gy + (local // bz) % by + low[1]) * gz + local % bz + low[2]
            count += 1
        slot[occupied[k]] = -1
    return count


@njit(cache=True, inline="always")
def _grid_value(grid, local, low, by, bz, gy, gz):
    return grid[((local // (by * bz) + low[0]) * gy + (local // bz) % by + low[1]) * gz + local % bz + low[2]]
