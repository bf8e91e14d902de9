"""The compiled voxel-map algorithms of seed 000 (numba, `cache=True`; deterministic).

- `accumulate_ray_lengths` / `cast_scan`: exact 3D grid traversal (Amanatides & Woo, 1987) of every
  ray, adding the length of the ray inside each voxel it crosses to that voxel's weight (eq. 20–22).
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

INF = math.inf


@njit(cache=True)
def accumulate_ray_lengths(origin, ends, corner, voxel_size, shape, weights):
    """For each segment origin → ends[i] (world frame, metres), add the length (m) of the segment
    inside every voxel it crosses to `weights` (float32, flat over `shape`), clipped to the grid.
    The voxels crossed are those whose weight grew (the caller zeroes them afterwards)."""
    per_voxel = 1.0 / voxel_size
    sx = (origin[0] - corner[0]) * per_voxel
    sy = (origin[1] - corner[1]) * per_voxel
    sz = (origin[2] - corner[2]) * per_voxel
    for i in range(ends.shape[0]):
        dx, dy, dz = ends[i, 0] - origin[0], ends[i, 1] - origin[1], ends[i, 2] - origin[2]
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        if distance > 0.0 and distance < INF:
            scale = 1.0 / distance
            _walk(sx, sy, sz, dx * scale, dy * scale, dz * scale, distance * per_voxel, shape, voxel_size, weights)


@njit(cache=True, error_model="numpy")
def cast_scan(origin, rotation, points, beams, masked, max_distance, corner, voxel_size, shape, weights):
    """`accumulate_ray_lengths` for the rays of an organised scan, their ends found on the way
    (eq. 20): a return at most `max_distance` away ends its ray, a farther one or none at all (NaN)
    ends it at `max_distance` along the ray (when it returned nothing, along its beam: `beams[i]`,
    sensor frame, turned by `rotation`). Rays `masked` (the carrier's body) are skipped.
    points (N, 3) float32, beams (N, 3)."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    r = rotation
    per_voxel = 1.0 / voxel_size
    sx, sy, sz = (ox - corner[0]) * per_voxel, (oy - corner[1]) * per_voxel, (oz - corner[2]) * per_voxel
    for i in range(points.shape[0]):
        if masked[i]:
            continue
        dx, dy, dz = points[i, 0] - ox, points[i, 1] - oy, points[i, 2] - oz
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        if distance > 0.0 and distance < INF:  # a return (NaN fails both tests)
            reach = min(distance, max_distance)
        else:
            bx, by, bz = beams[i, 0], beams[i, 1], beams[i, 2]
            if not (abs(bx) < INF and abs(by) < INF and abs(bz) < INF):
                continue
            dx = r[0, 0] * bx + r[0, 1] * by + r[0, 2] * bz
            dy = r[1, 0] * bx + r[1, 1] * by + r[1, 2] * bz
            dz = r[2, 0] * bx + r[2, 1] * by + r[2, 2] * bz
            distance = math.sqrt(dx * dx + dy * dy + dz * dz)
            if not distance > 0.0:
                continue
            reach = max_distance
        scale = 1.0 / distance
        _walk(sx, sy, sz, dx * scale, dy * scale, dz * scale, reach * per_voxel, shape, voxel_size, weights)


@njit(cache=True, error_model="numpy")
def _walk(sx, sy, sz, ux, uy, uz, length, shape, voxel_size, weights):
    """Amanatides–Woo along one segment: from s (grid coordinates, voxel edges) in the unit
    direction u for `length` voxel edges, adding the length inside each voxel (m) to `weights`.
    The hot loop of the mapper: one comparison chain picks the next boundary, a countdown per axis
    replaces the bounds tests. A reciprocal per axis replaces the divisions of the set-up (a third
    of the time of a scan's rays went into it)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    inv_x = 1.0 / ux if ux != 0.0 else INF
    inv_y = 1.0 / uy if uy != 0.0 else INF
    inv_z = 1.0 / uz if uz != 0.0 else INF
    t0, t1 = 0.0, length
    t0, t1 = _clip(sx, ux, inv_x, nx, t0, t1)
    t0, t1 = _clip(sy, uy, inv_y, ny, t0, t1)
    t0, t1 = _clip(sz, uz, inv_z, nz, t0, t1)
    if not t0 < t1:
        return
    ix = _start(sx + ux * t0, nx)
    iy = _start(sy + uy * t0, ny)
    iz = _start(sz + uz * t0, nz)
    step_x, next_x, delta_x = _axis(sx, ux, inv_x, ix)
    step_y, next_y, delta_y = _axis(sy, uy, inv_y, iy)
    step_z, next_z, delta_z = _axis(sz, uz, inv_z, iz)
    left_x = _left(step_x, ix, nx)  # voxels before the grid's edge along each axis
    left_y = _left(step_y, iy, ny)
    left_z = _left(step_z, iz, nz)
    jump_x, jump_y, jump_z = step_x * ny * nz, step_y * nz, step_z
    flat = (ix * ny + iy) * nz + iz
    t = t0
    while True:
        on_x = next_x <= next_y and next_x <= next_z
        on_y = (not on_x) and next_y <= next_z
        t_next = next_x if on_x else (next_y if on_y else next_z)
        weights[flat] += (min(t_next, t1) - t) * voxel_size
        if t_next >= t1:
            break
        t = t_next
        if on_x:
            if left_x == 0:
                break
            left_x -= 1
            flat += jump_x
            next_x += delta_x
        elif on_y:
            if left_y == 0:
                break
            left_y -= 1
            flat += jump_y
            next_y += delta_y
        else:
            if left_z == 0:
                break
            left_z -= 1
            flat += jump_z
            next_z += delta_z


@njit(cache=True)
def _left(step, i, n):
    if step > 0:
        return n - 1 - i
    if step < 0:
        return i
    return 1 << 40


@njit(cache=True)
def _clip(s, u, inv_u, n, t0, t1):
    """Narrow [t0, t1] to where s + u·t lies within [0, n] (slab test); inv_u = 1/u."""
    if u == 0.0:
        if s < 0.0 or s >= n:
            return 1.0, 0.0  # parallel and outside: empty
        return t0, t1
    a, b = -s * inv_u, (n - s) * inv_u
    return max(t0, min(a, b)), min(t1, max(a, b))


@njit(cache=True)
def _start(p, n):
    i = int(math.floor(p))
    return min(max(i, 0), n - 1)  # a start exactly on the far face belongs to the last voxel


@njit(cache=True)
def _axis(s, u, inv_u, i):
    """(step, parameter of the first boundary crossed, parameter between boundaries) along one axis,
    in the same units as the ray's length (voxel edges); inv_u = 1/u."""
    if u > 0.0:
        return 1, (i + 1 - s) * inv_u, inv_u
    if u < 0.0:
        return -1, (i - s) * inv_u, -inv_u
    return 0, INF, INF


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
            continue  # no voxel within reach; and a far point's int() overflowed into out-of-bounds reads
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
    neighbouring cells. Each pair of neighbouring cells is looked at once; when both cells are
    already connected inside, one link between them settles the pair (so a dense surface costs
    about one distance per cell pair, not one per point pair)."""
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    parent = np.arange(n)
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        keys[i] = _cell_key(int(math.floor(points[i, 0] / radius)), int(math.floor(points[i, 1] / radius)),
                            int(math.floor(points[i, 2] / radius)))
    order = np.argsort(keys, kind="mergesort")
    sorted_keys = keys[order]
    starts = [0]
    for k in range(1, n):
        if sorted_keys[k] != sorted_keys[k - 1]:
            starts.append(k)
    cells = len(starts)
    begin = np.array(starts, dtype=np.int64)
    end = np.empty(cells, dtype=np.int64)
    end[:-1] = begin[1:]
    end[-1] = n
    cell_keys = sorted_keys[begin]
    limit = radius * radius
    whole = np.zeros(cells, dtype=np.bool_)  # every point of the cell already in one cluster
    for c in range(cells):
        for a in range(begin[c], end[c]):
            for b in range(a + 1, end[c]):
                if _close(points, order[a], order[b], limit):
                    _union(parent, order[a], order[b])
        root = _find(parent, order[begin[c]])
        whole[c] = True
        for a in range(begin[c] + 1, end[c]):
            if _find(parent, order[a]) != root:
                whole[c] = False
                break
    for c in range(cells):
        key = cell_keys[c]
        for offset in range(13):  # the 13 neighbours "after" this cell: each pair once
            ox, oy, oz = _forward(offset)
            other = np.searchsorted(cell_keys, key + ox * _KX + oy * _KY + oz)
            if other >= cells or cell_keys[other] != key + ox * _KX + oy * _KY + oz:
                continue
            if whole[c] and whole[other]:
                if _find(parent, order[begin[c]]) == _find(parent, order[begin[other]]):
                    continue
                linked = False
                for a in range(begin[c], end[c]):
                    for b in range(begin[other], end[other]):
                        if _close(points, order[a], order[b], limit):
                            _union(parent, order[a], order[b])
                            linked = True
                            break
                    if linked:
                        break
            else:
                for a in range(begin[c], end[c]):
                    for b in range(begin[other], end[other]):
                        if _find(parent, order[a]) != _find(parent, order[b]) and _close(points, order[a], order[b], limit):
                            _union(parent, order[a], order[b])
    labels = np.full(n, -1, dtype=np.int64)
    root_label = np.full(n, -1, dtype=np.int64)
    count = 0
    for i in range(n):
        r = _find(parent, i)
        if root_label[r] < 0:
            root_label[r] = count
            count += 1
        labels[i] = root_label[r]
    return labels, count


_KY = 1 << 21
_KX = 1 << 42


@njit(cache=True)
def _cell_key(cx, cy, cz):
    """One int64 per cell, ordered like (cx, cy, cz); a neighbour's key is the key plus its offset."""
    half = 1 << 20
    return (cx + half) * _KX + (cy + half) * _KY + (cz + half)


@njit(cache=True)
def _forward(k):
    """The k-th of the 13 neighbour offsets that come after (0, 0, 0) in (x, y, z) order."""
    index = k + 14  # offsets -1..1 enumerated 0..26, (0, 0, 0) is 13
    return index // 9 - 1, (index // 3) % 3 - 1, index % 3 - 1


@njit(cache=True)
def _close(points, i, j, limit):
    dx = points[i, 0] - points[j, 0]
    dy = points[i, 1] - points[j, 1]
    dz = points[i, 2] - points[j, 2]
    return dx * dx + dy * dy + dz * dz <= limit


@njit(cache=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        parent[i], i = root, parent[i]
    return root


@njit(cache=True)
def _union(parent, i, j):
    a, b = _find(parent, i), _find(parent, j)
    if a != b:
        parent[max(a, b)] = min(a, b)
