"""The tracker's per-point pass, compiled (numba, `cache=True`; deterministic).

Every cloud update of seed 000's Alg. 2 (line 36) selects, for each track, the returns within its
uncertainty radius of its predicted position. With an OS0-128 scan (131,072 rays) and ten tracks,
numpy's broadcast distances cost about 1 ms per track and a (N, T) temporary; one compiled pass
over the points tests every track at once and writes the selections track by track (CSR).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def points_near(points, centres, radii):
    """For (N, 3) points and T balls (centres (T, 3), radii (T,)): (indices, starts) such that
    points[indices[starts[t]:starts[t + 1]]] are the points within radii[t] of centres[t], in
    the points' order. A point may appear under several tracks."""
    n, tracks = points.shape[0], centres.shape[0]
    limits = radii * radii
    low = centres - radii.reshape(-1, 1)
    high = centres + radii.reshape(-1, 1)
    counts = np.zeros(tracks + 1, dtype=np.int64)
    hits = np.zeros(n, dtype=np.int64)  # per point, how many balls hold it (first pass)
    if tracks == 0:
        return np.zeros(0, dtype=np.int64), counts
    # Most returns (the ground, walls far from any track) fail one test against the box of all balls.
    all_low = np.array([low[:, 0].min(), low[:, 1].min(), low[:, 2].min()])
    all_high = np.array([high[:, 0].max(), high[:, 1].max(), high[:, 2].max()])
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (all_low[2] <= z <= all_high[2] and all_low[0] <= x <= all_high[0] and all_low[1] <= y <= all_high[1]):
            continue
        for t in range(tracks):
            if low[t, 0] <= x <= high[t, 0] and low[t, 1] <= y <= high[t, 1] and low[t, 2] <= z <= high[t, 2]:
                dx, dy, dz = x - centres[t, 0], y - centres[t, 1], z - centres[t, 2]
                if dx * dx + dy * dy + dz * dz <= limits[t]:
                    counts[t + 1] += 1
                    hits[i] += 1
    starts = np.cumsum(counts)  # counts[0] is 0: starts[t] is where track t's points begin
    indices = np.empty(starts[-1], dtype=np.int64)
    fill = starts[:-1].copy()
    for i in range(n):
        if hits[i] == 0:
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for t in range(tracks):
            dx, dy, dz = x - centres[t, 0], y - centres[t, 1], z - centres[t, 2]
            if dx * dx + dy * dy + dz * dz <= limits[t]:
                indices[fill[t]] = i
                fill[t] += 1
    return indices, starts
