"""The classifier's per-point passes, compiled (numba, `cache=True`; deterministic): a scan's valid
returns onto a grid (downsampling), per-cluster statistics and grouping points by cluster (the voxel
label sets of eq. 16–18 are services/lib/voxels/labels.py). Each is one pass over the points; `slot`
arrays (int32 over a grid, all -1) are scratch that every pass leaves as it found it.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from services.lib.voxels.labels import point_cell

INF = math.inf


@njit(cache=True)
def downsample(points, corner, edge, shape, slot):
    """The scan's returns (N, 3) float32 (NaN: none) onto a grid of `edge` cells.

    Returns (valid returns (M, 3) float64, cell of each (M,), cell centroids (C, 3), points per
    cell (C,), invalid count): a return with an infinite coordinate is invalid and dropped; a
    return outside the grid is a cell of its own."""
    n = points.shape[0]
    valid = np.empty((n, 3), dtype=np.float64)
    m, invalid = 0, 0
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if math.isnan(x) or math.isnan(y) or math.isnan(z):
            continue
        if math.isinf(x) or math.isinf(y) or math.isinf(z):
            invalid += 1
            continue
        valid[m, 0], valid[m, 1], valid[m, 2] = x, y, z
        m += 1
    valid = valid[:m]
    cell_of = np.empty(m, dtype=np.int64)
    sums = np.zeros((m, 3), dtype=np.float64)
    counts = np.zeros(m, dtype=np.int64)
    flats = np.empty(m, dtype=np.int64)
    cells = 0
    for i in range(m):
        flat = point_cell(valid[i, 0], valid[i, 1], valid[i, 2], corner, edge, shape)
        c = slot[flat] if flat >= 0 else -1
        if c < 0:
            c = cells
            cells += 1
            flats[c] = flat
            if flat >= 0:
                slot[flat] = c
        cell_of[i] = c
        sums[c, 0] += valid[i, 0]
        sums[c, 1] += valid[i, 1]
        sums[c, 2] += valid[i, 2]
        counts[c] += 1
    for c in range(cells):
        if flats[c] >= 0:
            slot[flats[c]] = -1
        sums[c, 0] /= counts[c]
        sums[c, 1] /= counts[c]
        sums[c, 2] /= counts[c]
    return valid, cell_of, sums[:cells], counts[:cells], invalid


@njit(cache=True)
def cluster_stats(points, cluster, clusters, sensor):
    """Per cluster: returns in it, lowest and highest corner of its box, farthest range from `sensor`."""
    sizes = np.zeros(clusters, dtype=np.int64)
    low = np.full((clusters, 3), INF)
    high = np.full((clusters, 3), -INF)
    far = np.zeros(clusters)
    for i in range(points.shape[0]):
        c = cluster[i]
        sizes[c] += 1
        for a in range(3):
            v = points[i, a]
            if v < low[c, a]:
                low[c, a] = v
            if v > high[c, a]:
                high[c, a] = v
        dx, dy, dz = points[i, 0] - sensor[0], points[i, 1] - sensor[1], points[i, 2] - sensor[2]
        r = math.sqrt(dx * dx + dy * dy + dz * dz)
        if r > far[c]:
            far[c] = r
    return sizes, low, high, far


@njit(cache=True)
def group_by(cluster, clusters):
    """Point indices ordered by cluster (stable), and where each cluster's run starts (counting sort)."""
    starts = np.zeros(clusters + 1, dtype=np.int64)
    for c in cluster:
        starts[c + 1] += 1
    for c in range(clusters):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    order = np.empty(len(cluster), dtype=np.int64)
    for i in range(len(cluster)):
        order[fill[cluster[i]]] = i
        fill[cluster[i]] += 1
    return order, starts
