"""Path search over the inflated voxel map: A* on the map's own grid, then string pulling.

The map is a voxel grid already, so the search runs on it: the 26-neighbourhood of the voxels
between a start and a goal (their box, widened by `margin` and cut to the flight band), a voxel
blocked when an occupied box lies closer than the search radius to its centre (freespace.py).
Costs are flight times up to a constant: a metre up or down costs `vertical_weight` metres across
(the profile's speed over its vertical speed), so the search goes over a low building only when
that is quicker than going round it. The heuristic is the same metric to the goal (admissible
and consistent), weighted by `EPSILON` (weighted A*: a path at most that much longer than the
best on the grid, found expanding far fewer voxels); string pulling then straightens it.

Why not a library: scikit-image's MCP is Dijkstra without a heuristic, 79 ms on a 120 x 80 x 30
voxel box for a 20 m detour round a building where this A* takes about a millisecond; OMPL's
sampling planners draw random paths, stop on wall time (a lockstep run must repeat byte for
byte) and would call a Python validity check for every state (its 2.0.1 Python bindings also
refused a Python checker with std::bad_cast).

Pure (numpy and numba); `route` is what the planner calls.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from services.planner.freespace import FreeSpace

EPSILON = 1.5  # heuristic weight
MAX_EXPANSIONS = 400_000  # voxels expanded before a search gives up
FREE_SEARCH_STEPS = 12  # voxels around a blocked start or goal searched for the nearest free one


@njit(cache=True)
def _push(heap_f, heap_i, size, f, i):
    k = size
    heap_f[k] = f
    heap_i[k] = i
    while k > 0:
        parent = (k - 1) // 2
        if heap_f[parent] < heap_f[k] or (heap_f[parent] == heap_f[k] and heap_i[parent] <= heap_i[k]):
            break
        heap_f[parent], heap_f[k] = heap_f[k], heap_f[parent]
        heap_i[parent], heap_i[k] = heap_i[k], heap_i[parent]
        k = parent
    return size + 1


@njit(cache=True)
def _pop(heap_f, heap_i, size):
    f, i = heap_f[0], heap_i[0]
    size -= 1
    heap_f[0], heap_i[0] = heap_f[size], heap_i[size]
    k = 0
    while True:
        left, right, low = 2 * k + 1, 2 * k + 2, k
        if left < size and (heap_f[left] < heap_f[low] or (heap_f[left] == heap_f[low] and heap_i[left] < heap_i[low])):
            low = left
        if right < size and (heap_f[right] < heap_f[low] or (heap_f[right] == heap_f[low] and heap_i[right] < heap_i[low])):
            low = right
        if low == k:
            break
        heap_f[low], heap_f[k] = heap_f[k], heap_f[low]
        heap_i[low], heap_i[k] = heap_i[k], heap_i[low]
        k = low
    return f, i, size


@njit(cache=True)
def astar(blocked, start, goal, vertical_weight, epsilon, max_expansions):
    """Cells (M, 3) of a path from `start` to `goal` (int64 (3,) cells of `blocked`, a (nx, ny, nz)
    uint8 grid, 1 = blocked) through the 26-neighbourhood; empty when there is none (or the search
    expanded `max_expansions` voxels). Ties are broken by the voxel's index: deterministic."""
    nx, ny, nz = blocked.shape
    total = nx * ny * nz
    flat = blocked.reshape(total)
    s = (start[0] * ny + start[1]) * nz + start[2]
    t = (goal[0] * ny + goal[1]) * nz + goal[2]
    if flat[s] or flat[t]:
        return np.zeros((0, 3), dtype=np.int64)
    cost = np.full(total, np.inf)
    parent = np.full(total, -1, dtype=np.int64)
    closed = np.zeros(total, dtype=np.uint8)
    heap_f = np.empty(1024)
    heap_i = np.empty(1024, dtype=np.int64)
    steps = np.empty((26, 3), dtype=np.int64)
    lengths = np.empty(26)
    n = 0
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                if dx == 0 and dy == 0 and dz == 0:
                    continue
                steps[n, 0], steps[n, 1], steps[n, 2] = dx, dy, dz
                lengths[n] = math.sqrt(dx * dx + dy * dy + (vertical_weight * dz) ** 2)
                n += 1
    gx, gy, gz = goal[0], goal[1], goal[2]
    cost[s] = 0.0
    size = _push(heap_f, heap_i, 0, 0.0, s)
    expanded = 0
    found = False
    while size > 0:
        _, v, size = _pop(heap_f, heap_i, size)
        if closed[v]:
            continue
        if v == t:
            found = True
            break
        closed[v] = 1
        expanded += 1
        if expanded > max_expansions:
            break
        vx = v // (ny * nz)
        vy = (v // nz) % ny
        vz = v % nz
        for k in range(26):
            ax, ay, az = vx + steps[k, 0], vy + steps[k, 1], vz + steps[k, 2]
            if ax < 0 or ay < 0 or az < 0 or ax >= nx or ay >= ny or az >= nz:
                continue
            w = (ax * ny + ay) * nz + az
            if flat[w] or closed[w]:
                continue
            c = cost[v] + lengths[k]
            if c < cost[w]:
                cost[w] = c
                parent[w] = v
                h = math.sqrt((gx - ax) ** 2 + (gy - ay) ** 2 + (vertical_weight * (gz - az)) ** 2)
                if size == heap_f.shape[0]:  # lazy deletion leaves stale entries: grow
                    heap_f = np.concatenate((heap_f, np.empty(size)))
                    heap_i = np.concatenate((heap_i, np.empty(size, dtype=np.int64)))
                size = _push(heap_f, heap_i, size, c + epsilon * h, w)
    if not found:
        return np.zeros((0, 3), dtype=np.int64)
    count = 1
    v = t
    while v != s:
        v = parent[v]
        count += 1
    cells = np.empty((count, 3), dtype=np.int64)
    v = t
    for m in range(count - 1, -1, -1):
        cells[m, 0] = v // (ny * nz)
        cells[m, 1] = (v // nz) % ny
        cells[m, 2] = v % nz
        if m > 0:
            v = parent[v]
    return cells


@njit(cache=True)
def nearest_free(blocked, cell, max_steps):
    """The free cell nearest (breadth first through the 6-neighbourhood, then by distance) to
    `cell`, within `max_steps` steps; (-1, -1, -1) when there is none."""
    nx, ny, nz = blocked.shape
    best = np.array([-1, -1, -1], dtype=np.int64)
    best_d = np.inf
    for radius in range(max_steps + 1):
        for dx in range(-radius, radius + 1):
            for dy in range(-radius, radius + 1):
                for dz in range(-radius, radius + 1):
                    if max(abs(dx), abs(dy), abs(dz)) != radius:
                        continue
                    a, b, c = cell[0] + dx, cell[1] + dy, cell[2] + dz
                    if a < 0 or b < 0 or c < 0 or a >= nx or b >= ny or c >= nz or blocked[a, b, c]:
                        continue
                    d = dx * dx + dy * dy + dz * dz
                    if d < best_d:
                        best_d = d
                        best[0], best[1], best[2] = a, b, c
        if best_d < np.inf and math.sqrt(best_d) <= radius:
            break
    return best


@dataclass(frozen=True)
class Route:
    """A polyline the body can fly along with the asked clearance."""

    points: np.ndarray  # (M, 3), from the start
    searched: bool  # not the straight line: a search found it
    reached: bool  # it ends at the goal (False: at the free point nearest to it)


@dataclass(frozen=True)
class Band:
    """Where a search may go: z between low and high (world), x and y within the box (world)."""

    low: float
    high: float
    box_low: tuple[float, float] = (-math.inf, -math.inf)
    box_high: tuple[float, float] = (math.inf, math.inf)


def route(space: FreeSpace, start: np.ndarray, goal: np.ndarray, need: float, band: Band,
          vertical_weight: float = 2.5, margin: float = 15.0, exempt: np.ndarray | None = None) -> Route | None:
    """A polyline from `start` to `goal` keeping `need` m from every occupied box: the straight line
    when it does, else the searched one (string-pulled), ending at the free voxel nearest the goal
    when the goal itself is too close to something. None: no way within the searched box."""
    start, goal = np.asarray(start, dtype=np.float64).reshape(3), np.asarray(goal, dtype=np.float64).reshape(3)
    if space.path_conflict(np.stack([start, goal]), need, exempt) is None:
        return Route(np.stack([start, goal]), searched=False, reached=True)
    if not space.known:
        return None
    g = space.geometry
    low_point = np.minimum(start, goal) - margin
    high_point = np.maximum(start, goal) + margin
    low_point[:2] = np.maximum(low_point[:2], band.box_low)
    high_point[:2] = np.minimum(high_point[:2], band.box_high)
    low_point[2], high_point[2] = band.low, band.high
    low = np.clip(g.voxel_of(low_point)[0], 0, np.asarray(g.shape) - 1)
    high = np.clip(g.voxel_of(high_point)[0] + 1, 1, np.asarray(g.shape))
    if np.any(high <= low):
        return None
    blocked = space.blocked(low, high)
    ends = []
    for point in (start, goal):
        cell = np.clip(g.voxel_of(point)[0] - low, 0, high - low - 1)
        if blocked[tuple(cell)]:
            cell = nearest_free(blocked, cell, FREE_SEARCH_STEPS)
            if cell[0] < 0:
                return None
        ends.append(cell)
    cells = astar(blocked, ends[0], ends[1], float(vertical_weight), EPSILON, MAX_EXPANSIONS)
    if not len(cells):
        return None
    centres = g.centres(cells + low)
    reached = not blocked[tuple(np.clip(g.voxel_of(goal)[0] - low, 0, high - low - 1))]
    points = np.vstack([start, centres, goal]) if reached else np.vstack([start, centres])
    return Route(pull_string(space, points, need, exempt), searched=True, reached=bool(reached))


def pull_string(space: FreeSpace, points: np.ndarray, need: float, exempt: np.ndarray | None = None) -> np.ndarray:
    """The polyline with every vertex dropped that a straight segment keeping `need` can skip
    (greedy from the start: the farthest visible vertex next). The ends stay."""
    kept = [0]
    anchor = 0
    last = len(points) - 1
    while anchor < last:
        nxt = anchor + 1
        for j in range(last, anchor + 1, -1):  # farthest first: few long checks on open ground
            if space.path_conflict(points[[anchor, j]], need, exempt) is None:
                nxt = j
                break
        kept.append(nxt)
        anchor = nxt
    return points[kept]
