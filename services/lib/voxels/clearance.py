"""How far points are from occupied voxels, and the inflated map a path search runs on (numba,
`cache=True`).

An occupied voxel says an obstacle reaches somewhere into its cube, so every distance here is to
the cube — the nearest point of its box — never to its centre: a lower bound on the distance to
whatever is in it. With 0.5 m voxels the centre would overstate it by up to 0.43 m.

- `inflation_offsets` / `add_counts`: the inflated map as a count per voxel of the occupied
  voxels whose box lies within a radius of its centre, kept up to date voxel by voxel as the map
  changes (a few per scan), so a search never has to inflate the whole map.
- `box_clearance`, `first_within`, `nearest_box`: the exact distance from points to the nearest
  occupied box within a reach, the first point of a polyline closer than a distance, the way away
  from the nearest box; optionally leaving out the voxels inside a vertical cylinder (what a
  balloon's attack may pass over: its pole and itself). One search (`_nearest_box`) does all three.

Grids are flat C-order arrays over `shape`, as in services/lib/voxels/grid.py.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


def inflation_offsets(radius: float, voxel_size: float) -> np.ndarray:
    """(K, 3) int64 offsets d whose voxel's box lies closer than `radius` to the centre of voxel
    (0, 0, 0): voxel_size · |max(|d| − ½, 0)| < radius."""
    cells = int(math.ceil(radius / voxel_size + 0.5))
    axis = np.arange(-cells, cells + 1)
    d = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    gap = np.maximum(np.abs(d) - 0.5, 0.0) * voxel_size
    return d[np.sqrt((gap * gap).sum(axis=1)) < radius].astype(np.int64)


@njit(cache=True)
def add_counts(counts, flats, offsets, shape, sign):
    """counts[v] += sign for every voxel v within `offsets` of each voxel of `flats` (inside the grid)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for f in flats:
        i = f // (ny * nz)
        j = (f // nz) % ny
        k = f % nz
        for o in range(offsets.shape[0]):
            a = i + offsets[o, 0]
            b = j + offsets[o, 1]
            c = k + offsets[o, 2]
            if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz:
                counts[(a * ny + b) * nz + c] += sign


@njit(cache=True, inline="always")
def _nearest_box(px, py, pz, occupied, shape, corner, voxel_size, limit, exempt, stop):
    """(d², dx, dy, dz): the squared distance from the point (in voxel units of the grid: px = (x −
    corner) / voxel_size) to the nearest occupied voxel's box closer than `limit` (m), and the offset
    from that box's nearest point to the point (m); (limit², 0, 0, 0) when there is none. `exempt` =
    (x, y, radius, top): voxels whose centre is within `radius` of (x, y) and below `top` do not
    count (radius <= 0: none). `stop`: return at the first box closer than the limit."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    cells = int(math.ceil(limit / voxel_size)) + 1
    best, bx, by, bz = limit * limit, 0.0, 0.0, 0.0
    if not (-cells <= px < nx + cells and -cells <= py < ny + cells and -cells <= pz < nz + cells):
        return best, bx, by, bz
    r2 = exempt[2] * exempt[2]
    vx, vy, vz = int(math.floor(px)), int(math.floor(py)), int(math.floor(pz))
    for a in range(max(vx - cells, 0), min(vx + cells + 1, nx)):
        dx = (px - min(max(px, a), a + 1.0)) * voxel_size
        if dx * dx >= best:
            continue
        cx = corner[0] + (a + 0.5) * voxel_size - exempt[0]
        for b in range(max(vy - cells, 0), min(vy + cells + 1, ny)):
            dy = (py - min(max(py, b), b + 1.0)) * voxel_size
            if dx * dx + dy * dy >= best:
                continue
            cy = corner[1] + (b + 0.5) * voxel_size - exempt[1]
            in_column = exempt[2] > 0.0 and cx * cx + cy * cy <= r2
            base = (a * ny + b) * nz
            for c in range(max(vz - cells, 0), min(vz + cells + 1, nz)):
                if occupied[base + c] == 0:
                    continue
                if in_column and corner[2] + (c + 0.5) * voxel_size <= exempt[3]:
                    continue
                dz = (pz - min(max(pz, c), c + 1.0)) * voxel_size
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best:
                    best, bx, by, bz = d2, dx, dy, dz
                    if stop:
                        return best, bx, by, bz
    return best, bx, by, bz


@njit(cache=True)
def box_clearance(points, occupied, shape, corner, voxel_size, reach, exempt):
    """(N,) distance from each point to the nearest box of an occupied voxel (occupied: uint8 flat,
    non-zero = occupied), `reach` where none lies within reach (and for a non-finite point: 0);
    `exempt` as in _nearest_box."""
    out = np.empty(points.shape[0])
    for n in range(points.shape[0]):
        px = (points[n, 0] - corner[0]) / voxel_size
        py = (points[n, 1] - corner[1]) / voxel_size
        pz = (points[n, 2] - corner[2]) / voxel_size
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            out[n] = 0.0
            continue
        best, _, _, _ = _nearest_box(px, py, pz, occupied, shape, corner, voxel_size, reach, exempt, False)
        out[n] = math.sqrt(best)
    return out


@njit(cache=True)
def first_within(points, check, occupied, shape, corner, voxel_size, need, exempt):
    """Index of the first point (among those `check` marks) with an occupied box closer than `need`
    (`exempt` as in _nearest_box), or -1. A non-finite point counts as one. Cheaper than
    box_clearance: it looks only within `need` and stops at the first box."""
    for n in range(points.shape[0]):
        if not check[n]:
            continue
        px = (points[n, 0] - corner[0]) / voxel_size
        py = (points[n, 1] - corner[1]) / voxel_size
        pz = (points[n, 2] - corner[2]) / voxel_size
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            return n
        best, _, _, _ = _nearest_box(px, py, pz, occupied, shape, corner, voxel_size, need, exempt, True)
        if best < need * need:
            return n
    return -1


@njit(cache=True)
def nearest_box(point, occupied, shape, corner, voxel_size, reach):
    """(distance, away (3,)) from `point` to the nearest occupied voxel's box within `reach`, and
    the unit vector from that box's nearest point to `point` (zero when none is within reach, or
    the point is inside a box)."""
    away = np.zeros(3)
    px = (point[0] - corner[0]) / voxel_size
    py = (point[1] - corner[1]) / voxel_size
    pz = (point[2] - corner[2]) / voxel_size
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
        return reach, away
    best, dx, dy, dz = _nearest_box(px, py, pz, occupied, shape, corner, voxel_size, reach, _NONE, False)
    distance = math.sqrt(best)
    if 1e-9 < distance and best < reach * reach:
        away[0], away[1], away[2] = dx / distance, dy / distance, dz / distance
    return distance, away


_NONE = np.zeros(4)  # no exemption
