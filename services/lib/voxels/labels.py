"""The voxel label sets of seed 000 eq. 16–18 (numba, `cache=True`; deterministic): which map voxels
a scan's labelled returns fall in, each with one class and its update weight n, as the mapper takes
them. One home for the classifier and for the oracle that stands in for it. `slot` is an int32
scratch array over the map's voxels, all -1, that every call leaves as it found it.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

INF = math.inf


@njit(cache=True, inline="always")
def point_cell(px, py, pz, corner, edge, shape):
    """Flat index of the grid cell holding a point, -1 outside the grid."""
    x, y, z = (px - corner[0]) / edge, (py - corner[1]) / edge, (pz - corner[2]) / edge
    if not (0.0 <= x < shape[0] and 0.0 <= y < shape[1] and 0.0 <= z < shape[2]):
        return -1  # tested before int(), which a far point would overflow (undefined in compiled code)
    return (int(x) * shape[1] + int(y)) * shape[2] + int(z)


@njit(cache=True)
def label_sets(points, labels, corner, edge, shape, slot, background, flying, unknown):
    """Eq. 16–18: the map voxels holding returns, each with one class and its update weight n.
    A voxel with returns of several classes takes the most cautious (flying object over unknown over
    background): weight ∞ for a flying object, else the number of returns of its class.
    Returns (voxel indices (V, 3) int32 in first-seen order, labels (V,) uint8, weights (V,)
    float32, returns outside the map)."""
    n = points.shape[0]
    flats = np.empty(n, dtype=np.int64)
    counts = np.zeros((n, 3), dtype=np.int64)  # background, unknown, flying
    voxels = 0
    outside = 0
    for i in range(n):
        flat = point_cell(points[i, 0], points[i, 1], points[i, 2], corner, edge, shape)
        if flat < 0:
            outside += 1
            continue
        v = slot[flat]
        if v < 0:
            v = voxels
            voxels += 1
            slot[flat] = v
            flats[v] = flat
        label = labels[i]
        counts[v, 0 if label == background else (2 if label == flying else 1)] += 1
    ijk = np.empty((voxels, 3), dtype=np.int32)
    out_labels = np.empty(voxels, dtype=np.uint8)
    weights = np.empty(voxels, dtype=np.float32)
    for v in range(voxels):
        flat = flats[v]
        slot[flat] = -1
        ijk[v, 0] = flat // (shape[1] * shape[2])
        ijk[v, 1] = (flat // shape[2]) % shape[1]
        ijk[v, 2] = flat % shape[2]
        if counts[v, 2] > 0:
            out_labels[v], weights[v] = flying, INF
        elif counts[v, 1] > 0:
            out_labels[v], weights[v] = unknown, counts[v, 1]
        else:
            out_labels[v], weights[v] = background, counts[v, 0]
    return ijk, out_labels, weights, outside
