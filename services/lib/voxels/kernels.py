"""The compiled voxel-map algorithms of seed 000 (numba, `cache=True`; deterministic); the ray
traversal of eq. 20–22 is in services/lib/voxels/traversal.py.

- `clusters_near_occupied`: rule A of sec. III-B, the cube search around every point.
- `enclosed_by_free`: rule B of sec. III-B, the BFS flood fill of Alg. 1 bounded by the search cube.
- `euclidean_clusters`: Euclidean clusters of points (eq. 13–15), by a cell grid and union-find.

Grids are flat C-order arrays over `shape`; states are the uint8 codes of schemas/voxels.py.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from schemas.voxels import STATE_FREE, STATE_TENTATIVE


@njit(cache=True)
def clusters_near_occupied(points, cluster, n_clusters, candidate, states, corner, voxel_size, shape, d_close):
    """Rule A: for each cluster marked `candidate`, whether any of its points lies closer than
    `d_close` to the centre of a voxel that is at least tentatively occupied (the cube search of
    sec. III-B: every voxel of the cube of edge 2·d_close around the point's voxel). A cluster
    stops being searched at its first hit."""
    near = np.zeros(n_clusters, dtype=np.bool_)
    nx, ny, nz = shape[0], shape[1], shape[2]
    reach = int(math.ceil(d_close / voxel_size))
    limit = d_close * d_close
    for i in range(points.shape[0]):
        c = cluster[i]
        if not candidate[c] or near[c]:
            continue
        px = (points[i, 0] - corner[0]) / voxel_size
        py = (points[i, 1] - corner[1]) / voxel_size
        pz = (points[i, 2] - corner[2]) / voxel_size
        if not (-reach <= px < nx + reach and -reach <= py < ny + reach and -reach <= pz < nz + reach):
            continue  # no voxel within reach; and a far point's int() would overflow into out-of-bounds reads
        vx, vy, vz = int(math.floor(px)), int(math.floor(py)), int(math.floor(pz))
        found = False
        for ax in range(max(vx - reach, 0), min(vx + reach + 1, nx)):
            ex = (ax + 0.5 - px) * voxel_size
            for ay in range(max(vy - reach, 0), min(vy + reach + 1, ny)):
                ey = (ay + 0.5 - py) * voxel_size
                base = (ax * ny + ay) * nz
                for az in range(max(vz - reach, 0), min(vz + reach + 1, nz)):
                    if states[base + az] >= STATE_TENTATIVE:
                        ez = (az + 0.5 - pz) * voxel_size
                        if ex * ex + ey * ey + ez * ez < limit:
                            found = True
                            break
                if found:
                    break
            if found:
                break
        near[c] = found
    return near


@njit(cache=True)
def enclosed_by_free(states, shape, seeds, low, high, visited, queue):
    """Rule B (Alg. 1): breadth-first flood fill from the cluster's voxels `seeds` through every
    voxel that is not confidently free. False as soon as it reaches a voxel at least tentatively
    occupied (a path to the background exists) or leaves the search cube [low, high) (too much
    unknown around it to tell); True when every path ends at confidently free voxels.
    `visited` (uint8, flat, all 0) is left as it was found; `queue` holds at least the cube."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    head = tail = 0
    enclosed = True
    for s in seeds:
        if states[s] >= STATE_TENTATIVE:
            enclosed = False
            break
        if visited[s] == 0:
            visited[s] = 1
            queue[tail] = s
            tail += 1
    while enclosed and head < tail:
        v = queue[head]
        head += 1
        ix = v // (ny * nz)
        iy = (v // nz) % ny
        iz = v % nz
        for k in range(6):
            jx, jy, jz = ix, iy, iz
            if k == 0:
                jx -= 1
            elif k == 1:
                jx += 1
            elif k == 2:
                jy -= 1
            elif k == 3:
                jy += 1
            elif k == 4:
                jz -= 1
            else:
                jz += 1
            if jx < low[0] or jy < low[1] or jz < low[2] or jx >= high[0] or jy >= high[1] or jz >= high[2] \
                    or jx < 0 or jy < 0 or jz < 0 or jx >= nx or jy >= ny or jz >= nz:
                enclosed = False  # the border of the search cube (or of the map) is reachable
                break
            w = (jx * ny + jy) * nz + jz
            if visited[w]:
                continue
            state = states[w]
            if state >= STATE_TENTATIVE:
                enclosed = False
                break
            if state == STATE_FREE:
                continue  # blocked: this way is walled off by confident free space
            visited[w] = 1
            queue[tail] = w
            tail += 1
    for q in range(tail):
        visited[queue[q]] = 0
    return enclosed


@njit(cache=True)
def euclidean_clusters(points, radius):
    """Labels 0..K-1 (in order of first appearance) and K for (N, 3) points such that two points
    closer than `radius` share a cluster and clusters are the transitive closure of that (eq. 13–15).

    Points are bucketed in cells of edge `radius`: partners lie in the same or one of the 26
    neighbouring cells, found through a hash table of the occupied cells. Each pair of neighbouring
    cells is looked at once; when both cells are already connected inside, one link between them
    settles the pair (so a dense surface costs about one distance per cell pair, not one per point
    pair). Hashing the cells and grouping the points by a counting sort costs less than sorting the
    cell keys and a binary search per neighbour (benchmarks/README.md, perception.py)."""
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    parent = np.arange(n)
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        keys[i] = _cell_key(int(math.floor(points[i, 0] / radius)), int(math.floor(points[i, 1] / radius)),
                            int(math.floor(points[i, 2] / radius)))
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    table = np.full(1 << bits, -1, dtype=np.int64)  # open addressing: cell index or -1
    cell_keys = np.empty(n, dtype=np.int64)
    cell_of = np.empty(n, dtype=np.int64)
    sizes = np.zeros(n + 1, dtype=np.int64)
    cells = 0
    for i in range(n):
        slot = _slot(table, cell_keys, keys[i], bits)
        if table[slot] < 0:
            table[slot] = cells
            cell_keys[cells] = keys[i]
            cells += 1
        cell_of[i] = table[slot]
        sizes[cell_of[i] + 1] += 1
    begin = np.cumsum(sizes[:cells + 1])  # the cell's points in `order`: begin[c] .. begin[c + 1]
    end = begin[1:]
    fill = begin[:-1].copy()
    order = np.empty(n, dtype=np.int64)  # points by cell, in point order within a cell
    for i in range(n):
        order[fill[cell_of[i]]] = i
        fill[cell_of[i]] += 1
    limit = radius * radius
    whole = np.zeros(cells, dtype=np.bool_)  # every point of the cell already in one cluster
    for c in range(cells):
        for a in range(begin[c], end[c]):
            for b in range(a + 1, end[c]):
                if _close(points, order[a], order[b], limit):
                    union_sets(parent, order[a], order[b])
        root = find_root(parent, order[begin[c]])
        whole[c] = True
        for a in range(begin[c] + 1, end[c]):
            if find_root(parent, order[a]) != root:
                whole[c] = False
                break
    for c in range(cells):
        key = cell_keys[c]
        for offset in range(13):  # the 13 neighbours "after" this cell: each pair once
            ox, oy, oz = _forward(offset)
            other = table[_slot(table, cell_keys, key + ox * _KX + oy * _KY + oz, bits)]
            if other < 0:
                continue
            if whole[c] and whole[other]:
                if find_root(parent, order[begin[c]]) == find_root(parent, order[begin[other]]):
                    continue
                linked = False
                for a in range(begin[c], end[c]):
                    for b in range(begin[other], end[other]):
                        if _close(points, order[a], order[b], limit):
                            union_sets(parent, order[a], order[b])
                            linked = True
                            break
                    if linked:
                        break
            else:
                for a in range(begin[c], end[c]):
                    for b in range(begin[other], end[other]):
                        if find_root(parent, order[a]) != find_root(parent, order[b]) and _close(points, order[a], order[b], limit):
                            union_sets(parent, order[a], order[b])
    labels = np.full(n, -1, dtype=np.int64)
    root_label = np.full(n, -1, dtype=np.int64)
    count = 0
    for i in range(n):
        r = find_root(parent, i)
        if root_label[r] < 0:
            root_label[r] = count
            count += 1
        labels[i] = root_label[r]
    return labels, count


_KY = 1 << 21
_KX = 1 << 42


@njit(cache=True, inline="always")
def _cell_key(cx, cy, cz):
    """One int64 per cell, ordered like (cx, cy, cz); a neighbour's key is the key plus its offset."""
    half = 1 << 20
    return (cx + half) * _KX + (cy + half) * _KY + (cz + half)


@njit(cache=True, inline="always")
def _slot(table, cell_keys, key, bits):
    """Where `key` sits in the open-addressing table, or the empty slot where it would go
    (Fibonacci hashing, linear probing; the table is at least twice the number of cells)."""
    mask = (1 << bits) - 1
    slot = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))
    while table[slot] >= 0 and cell_keys[table[slot]] != key:
        slot = (slot + 1) & mask
    return slot


@njit(cache=True, inline="always")
def _forward(k):
    """The k-th of the 13 neighbour offsets that come after (0, 0, 0) in (x, y, z) order."""
    index = k + 14  # offsets -1..1 enumerated 0..26, (0, 0, 0) is 13
    return index // 9 - 1, (index // 3) % 3 - 1, index % 3 - 1


@njit(cache=True, inline="always")
def _close(points, i, j, limit):
    dx = points[i, 0] - points[j, 0]
    dy = points[i, 1] - points[j, 1]
    dz = points[i, 2] - points[j, 2]
    return dx * dx + dy * dy + dz * dz <= limit


@njit(cache=True, inline="always")
def find_root(parent, i):
    """The root of i's set in a union-find forest (`parent`), compressing the path on the way."""
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        parent[i], i = root, parent[i]
    return root


@njit(cache=True, inline="always")
def union_sets(parent, i, j):
    """Join the sets of i and j; the smaller index becomes the root (the grouping is order-independent)."""
    a, b = find_root(parent, i), find_root(parent, j)
    if a != b:
        parent[max(a, b)] = min(a, b)
