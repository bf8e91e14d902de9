"""What the UAV knows is occupied, as its planner asks about it (pure: numpy and the compiled
kernels of services/lib/voxels/clearance.py; the node hands in the map messages).

The source is the UAV's own mapper (falconry/<uav>/map): the mission's a-priori map (the world
model's static obstacles, which the mapper pins occupied) and everything its LiDAR has shown it
since. A voxel counts as occupied from the tentative state of eq. 7 up (schemas/voxels.py): one
scan's returns on a surface make it tentative, so an obstacle the survey lacks is avoided from the
first scans that show it, not after the many a confident state takes. The ground is left out —
the voxel layer holding the ground plane and everything below it — because the ground is not
something to keep a margin from: take-off and landing touch it, and the sweep height and the
pursuit floor keep flight above it. A box lower than one voxel (0.5 m) is left out with it.

Three questions:
- `clearance(points)`: the distance from each point to the nearest occupied voxel's box (m);
- `path_conflict(positions, need)`: the first point of a polyline (densified to SAMPLE_STEP) that
  is closer than `need` to an occupied box, as a fraction of the polyline's vertex index. A
  polyline that starts closer than `need` (the vehicle is there already) may leave: it conflicts
  only where it comes closer than it started, or where it is not clear ESCAPE_LENGTH along;
- `blocked(low, high)`: the search grid over a box of voxels — a voxel is blocked when an occupied
  box lies closer than `search_radius` to its centre, kept as a count per voxel that each map
  message updates where it changed (services/lib/voxels/clearance.py).
The arena's edge is a wall to the planner (`set_arena`): the voxel columns of a band
FENCE_BAND wide just outside the arena polygon count as occupied above the ground, as far out
as makes a plan that keeps the plan clearance from them keep about `keep_inside` (the planner's
fence_margin) inside the edge (`_set_fence`: the grid's 0.5 m steps make it 0.65-1.35 m for 1 m). Every part that asks about the map then keeps inside without a
rule of its own: routes go round a notch, a timed reference is clipped before the edge, the
pursuit's speed barrier slides along it, an attack's overshoot is shortened, and the guard brakes
before the body crosses it. Where the band falls off the map's grid (an arena reaching the grid's
edge) the edge is not known here; the planner still clamps what it aims at (Airspace.confine).

A point anywhere in a voxel that is not blocked is at least search_radius − half the voxel's
diagonal from every occupied box, so the search radius is the plans' `clearance` + half the map's
voxel diagonal (+ half a sample step, so that a check at the plans' clearance can trust a free
voxel without measuring), and a polyline through free voxel centres keeps that clearance along
its whole length (every point of a segment between neighbouring centres lies in the closed cube of
one of them).
"""
from __future__ import annotations

import math

import numpy as np

from schemas.voxels import STATE_TENTATIVE, STATE_UNKNOWN
from services.lib.geometry import distance_to_edges, point_in_polygon
from services.lib.voxels.clearance import add_counts, box_clearance, first_within, inflation_offsets, nearest_box
from services.lib.voxels.grid import GridGeometry
from services.lib.voxels.replica import MapReplica

SAMPLE_STEP = 0.2  # m between the points a polyline is checked at
NO_EXEMPTION = np.array([0.0, 0.0, 0.0, 0.0])
MAX_OFFSETS = 100_000  # voxels of the inflation kernel at most (0.5 m voxels and 2.2 m: about 300)
ESCAPE_LENGTH = 3.0  # m along which a polyline that starts too close must be clear again
ESCAPE_TOLERANCE = 0.05  # m it may come closer than it started (the box distance is not smooth)
FENCE_BAND = 1.0  # m: how wide the band of occupied columns that stands for the arena's edge is
NEIGHBOURS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)


def half_diagonal(voxel_size: float) -> float:
    return 0.5 * math.sqrt(3.0) * voxel_size


def densify(positions: np.ndarray, step: float = SAMPLE_STEP) -> tuple[np.ndarray, np.ndarray]:
    """Points along the polyline (N, 3) at most `step` apart (every vertex included), and each
    point's position as a fractional vertex index."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) < 2:
        return positions.copy(), np.zeros(len(positions))
    lengths = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    pieces = np.maximum(np.ceil(lengths / step).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(lengths)), pieces)
    within = np.arange(int(pieces.sum())) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    fraction = within / pieces[owner]
    points = positions[owner] + fraction[:, None] * (positions[owner + 1] - positions[owner])
    return (np.vstack([points, positions[-1:]]),
            np.concatenate([owner + fraction, [len(positions) - 1.0]]))


class FreeSpace:
    """The planner's copy of its UAV's map, with the occupancy and search grids derived from it.
    `clearance` is what plans keep from occupied boxes (the search radius follows from it and the
    map's voxel size). Until a map arrives nothing is known to be occupied."""

    def __init__(self, clearance: float, reach: float = 4.0) -> None:
        self.clearance_kept = float(clearance)
        self.search_radius = self.clearance_kept
        self.reach = float(reach)  # m: how far clearance is looked for (farther counts as `reach`)
        self.replica: MapReplica | None = None
        self.geometry: GridGeometry | None = None
        self.occupied = np.zeros(0, dtype=np.uint8)  # flat, 1 = occupied and above the ground
        self.counts = np.zeros(0, dtype=np.uint16)  # flat: occupied boxes within search_radius
        self.ground_z: float | None = None
        self.floor_layer = -1  # voxel layers up to this one hold the ground (left out)
        self.offsets = np.zeros((0, 3), dtype=np.int64)
        self.arena: np.ndarray | None = None  # (K, 2) the polygon plans stay inside; None: no edge
        self.keep_inside = 0.0  # m inside the arena's edge a plan keeping clearance_kept stays
        self.fence = np.zeros(0, dtype=bool)  # per voxel column (x, y): part of the arena's edge band

    @property
    def known(self) -> bool:
        return self.geometry is not None

    # ---------------------------------------------------------------- inputs
    def set_ground(self, ground_z: float) -> None:
        """The ground plane's height; the voxel layer holding it and those below are not obstacles."""
        if self.ground_z == ground_z:
            return
        self.ground_z = float(ground_z)
        if self.geometry is not None:
            self._set_floor()
            self._rebuild()

    def set_arena(self, arena: np.ndarray | None, keep_inside: float = 0.0) -> None:
        """The polygon (K, 2) plans keep `keep_inside` m inside of (None: no edge); see the module."""
        arena = None if arena is None or len(arena) < 3 else np.asarray(arena, dtype=np.float64).reshape(-1, 2)
        same = (arena is None and self.arena is None) or (
            arena is not None and self.arena is not None and np.array_equal(arena, self.arena))
        if same and float(keep_inside) == self.keep_inside:
            return
        self.arena, self.keep_inside = arena, float(keep_inside)
        if self.geometry is not None:
            self._set_fence()
            self._rebuild()

    def _set_fence(self) -> None:
        """The columns FENCE_BAND deep from clearance_kept (centre to centre) beyond every column a body
        centre may be in (its centre inside the arena, keep_inside or more from the edge): a plan
        keeping clearance_kept from their boxes stays within those columns, give or take the grid.
        Measured on mbzirc's outline over four grid offsets (0.5 m voxels, 1.7 m clearance, 1 m
        margin): the body stays 0.95-1.35 m inside a straight edge, 0.65 m or more at the notch's
        corners. A distance transform, not the distance to the edges: beyond a re-entrant corner the
        points that far from the edges form a square corner, and a body keeping its distance from its
        tip could pass the corner 0.3 m from the edge."""
        g = self.geometry
        nx, ny = g.shape[0], g.shape[1]
        self.fence = np.zeros(nx * ny, dtype=bool)
        if self.arena is None:
            return
        i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        centres = g.corner[:2] + (np.column_stack([i.ravel(), j.ravel()]) + 0.5) * g.voxel_size
        allowed = point_in_polygon(centres, self.arena) & (distance_to_edges(centres, self.arena) >= self.keep_inside)
        if not allowed.any():
            return
        from scipy.ndimage import distance_transform_edt  # imported here: see services/lib/runtime/warmup.py

        apart = distance_transform_edt(~allowed.reshape(nx, ny), sampling=g.voxel_size).ravel()
        self.fence = (apart >= self.clearance_kept) & (apart <= self.clearance_kept + FENCE_BAND)

    def apply_map(self, snapshot: bool, origin, shape, voxel_size: float, default_value: float,
                  indices: np.ndarray, values: np.ndarray) -> bool:
        """One VoxelMap message; False when a delta does not fit the map held (wait for a snapshot).
        ValueError, and nothing changed, for a map the planner cannot hold: indices and values of
        other lengths, a grid too large for a replica, or voxels so small that the search radius
        spans more than MAX_OFFSETS of them."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        values = np.asarray(values, dtype=np.float32).reshape(-1)
        if len(indices) != len(values):
            raise ValueError(f"a map message with {len(indices)} indices and {len(values)} values")
        if snapshot and (self.replica is None or not self.replica.same_geometry(origin, shape, voxel_size)
                         or float(default_value) != self.replica.default_value):
            radius, offsets = self._inflation(float(voxel_size))
            replica = MapReplica(origin, shape, voxel_size, default_value)
            replica.apply(True, origin, shape, voxel_size, default_value, indices, values)
            self.replica, self.geometry, self.offsets, self.search_radius = replica, replica.geometry, offsets, radius
            self.occupied = np.zeros(self.geometry.size, dtype=np.uint8)
            self.counts = np.zeros(self.geometry.size, dtype=np.uint16)
            self._set_floor()
            self._set_fence()
            self._rebuild()
            return True
        if self.replica is None or not self.replica.apply(snapshot, origin, shape, voxel_size, default_value,
                                                          indices, values):
            return False
        if snapshot:
            self._rebuild()
        else:
            self._update(np.unique(indices))  # a voxel listed twice is counted once
        return True

    def _inflation(self, voxel_size: float) -> tuple[float, np.ndarray]:
        """The search radius for this voxel size and its kernel's offsets."""
        if not 0.0 < voxel_size < math.inf:
            raise ValueError(f"a map of {voxel_size:.3g} m voxels")
        radius = self.clearance_kept + half_diagonal(voxel_size) + 0.5 * SAMPLE_STEP
        if 2.0 * radius / voxel_size + 2.0 > MAX_OFFSETS ** (1 / 3):
            raise ValueError(f"a map of {voxel_size:.3g} m voxels: the planner's search radius of "
                             f"{radius:.2f} m would span more than {MAX_OFFSETS} of them")
        return radius, inflation_offsets(radius, voxel_size)

    def _set_floor(self) -> None:
        g = self.geometry
        self.floor_layer = -1 if self.ground_z is None else \
            int(math.floor((self.ground_z - g.corner[2]) / g.voxel_size + 1e-6))

    def _occupancy(self, flats: np.ndarray) -> np.ndarray:
        depth = self.geometry.shape[2]
        layer = flats % depth
        occupied = (self.replica.states[flats] >= STATE_TENTATIVE) | self.fence[flats // depth]
        return (occupied & (layer > self.floor_layer)).astype(np.uint8)

    def _rebuild(self) -> None:
        every = np.arange(self.geometry.size, dtype=np.int64)
        self._update(every)

    def _update(self, flats: np.ndarray) -> None:
        flats = flats[(flats >= 0) & (flats < self.geometry.size)]
        now = self._occupancy(flats)
        changed = now != self.occupied[flats]
        if not changed.any():
            return
        gained, lost = flats[changed & (now == 1)], flats[changed & (now == 0)]
        self.occupied[flats[changed]] = now[changed]
        shape = np.asarray(self.geometry.shape, dtype=np.int64)
        add_counts(self.counts, lost, self.offsets, shape, -1)
        add_counts(self.counts, gained, self.offsets, shape, 1)

    # --------------------------------------------------------------- queries
    def clearance(self, points: np.ndarray, exempt: np.ndarray | None = None) -> np.ndarray:
        """(N,) m from each point to the nearest occupied box (`reach` when none is that near)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.geometry is None:
            return np.full(len(points), self.reach)
        g = self.geometry
        return box_clearance(points, self.occupied, np.asarray(g.shape, dtype=np.int64), g.corner, g.voxel_size,
                             self.reach, NO_EXEMPTION if exempt is None else np.asarray(exempt, dtype=np.float64))

    def nearest(self, point: np.ndarray, reach: float | None = None) -> tuple[float, np.ndarray]:
        """(distance, away): how far the point is from the nearest occupied box (`reach` at most, the
        space's own by default), and the unit vector pointing away from it (zero when none is within
        reach)."""
        reach = self.reach if reach is None else float(reach)
        if self.geometry is None:
            return reach, np.zeros(3)
        g = self.geometry
        return nearest_box(np.asarray(point, dtype=np.float64).reshape(3), self.occupied,
                           np.asarray(g.shape, dtype=np.int64), g.corner, g.voxel_size, reach)

    def _maybe_near(self, points: np.ndarray) -> np.ndarray:
        """(N,) True where a point's voxel is blocked or outside the grid: only those need the exact
        distance (any point of a free voxel is search_radius − HALF_DIAGONAL clear)."""
        g = self.geometry
        voxels = g.voxel_of(points)
        inside = g.inside(voxels)
        near = np.ones(len(points), dtype=bool)
        near[inside] = self.counts[g.flat(voxels[inside])] > 0
        return near

    def path_conflict(self, positions: np.ndarray, need: float, exempt: np.ndarray | None = None) -> float | None:
        """The first place along the polyline (N, 3) closer than `need` to an occupied box, as a
        fractional vertex index; None when it is clear all along. One that starts closer than
        `need` conflicts where it comes closer than it started, or is not clear ESCAPE_LENGTH on."""
        if self.geometry is None or len(positions) == 0:
            return None
        points, where = densify(positions)
        limit = need + 0.5 * SAMPLE_STEP
        start, conflict = self._escape(points, limit, exempt)
        if conflict is not None:
            return float(where[conflict])
        points, where = points[start:], where[start:]
        fast_ok = self.search_radius - half_diagonal(self.geometry.voxel_size) >= limit
        check = self._maybe_near(points) if fast_ok else np.ones(len(points), dtype=bool)
        if not check.any():
            return None
        g = self.geometry
        first = first_within(points, check, self.occupied, np.asarray(g.shape, dtype=np.int64), g.corner,
                             g.voxel_size, limit, NO_EXEMPTION if exempt is None else np.asarray(exempt, dtype=np.float64))
        return None if first < 0 else float(where[first])

    def _escape(self, points: np.ndarray, limit: float, exempt: np.ndarray | None) -> tuple[int, int | None]:
        """(index of the first point clear of `limit`, None) for a polyline that starts closer and
        leaves (0 when it starts clear); (_, index of the conflict) when it comes closer than it
        started before it is clear, or is still not clear ESCAPE_LENGTH along."""
        head = self.clearance(points[:1], exempt)[0]
        if head >= limit:
            return 0, None
        distances = self.clearance(points, exempt)
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        clear = np.flatnonzero(distances >= limit)
        end = int(clear[0]) if len(clear) else len(points)
        closer = np.flatnonzero(distances[:end] < head - ESCAPE_TOLERANCE)
        if len(closer):
            return end, int(closer[0])
        stuck = np.flatnonzero(along[:end] > ESCAPE_LENGTH)
        if len(stuck):
            return end, int(stuck[0])
        return end, None

    def path_clearance(self, positions: np.ndarray, exempt: np.ndarray | None = None) -> float:
        """The smallest clearance along the polyline (densified), `reach` at most."""
        if self.geometry is None or len(positions) == 0:
            return self.reach
        points, _ = densify(positions)
        return float(self.clearance(points, exempt).min())

    def unknown(self, points: np.ndarray) -> np.ndarray:
        """(N,) True where a point lies in a voxel never seen (eq. 7's uncertain state) or off the map."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.geometry is None:
            return np.zeros(len(points), dtype=bool)
        g = self.geometry
        voxels = g.voxel_of(points)
        inside = g.inside(voxels)
        out = np.ones(len(points), dtype=bool)
        out[inside] = self.replica.states[g.flat(voxels[inside])] == STATE_UNKNOWN
        return out

    def unseen(self, points: np.ndarray) -> np.ndarray:
        """(N,) True where a point lies in unseen space: its voxel never seen and at least half of its
        26 neighbours neither (off the map counts as unseen). A lone unknown voxel is not: the map
        keeps the voxels of a flying object at the unknown value (seed 000's g_unk), and a drone is
        not a region the LiDAR has failed to look into."""
        out = self.unknown(points)
        if self.geometry is None or not out.any():
            return out
        g = self.geometry
        voxels = g.voxel_of(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        rows = np.flatnonzero(out & g.inside(voxels))
        around = voxels[rows][:, None, :] + NEIGHBOURS[None]  # (R, 27, 3)
        inside = np.all((around >= 0) & (around < np.asarray(g.shape)), axis=2)
        flats = np.ravel_multi_index(tuple(np.clip(around, 0, np.asarray(g.shape) - 1).transpose(2, 0, 1)), g.shape)
        unknown = (self.replica.states[flats] == STATE_UNKNOWN) | ~inside  # off the map: never seen
        out[rows] = unknown.sum(axis=1) - 1 >= 0.5 * (len(NEIGHBOURS) - 1)
        return out

    def blocked(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """(nx, ny, nz) uint8 of the voxels low..high-1 (clipped to the grid by the caller):
        1 where an occupied box is closer than search_radius to the centre."""
        g = self.geometry
        counts = self.counts.reshape(g.shape)[low[0]:high[0], low[1]:high[1], low[2]:high[2]]
        return (counts > 0).astype(np.uint8)
