"""Mapper core: the occupancy voxel map G(v) of seed 000 (sec. III-A, III-C, III-D, III-E).

One scan updates the map in three ways:
- the classifier's label sets (eq. 16–18): background voxels towards g_occ with weight n_bg (points
  in the voxel), unknown voxels towards g_unk with n_unk, flying-object voxels set to g_unk
  (n = ∞, so a false detection never biases the map towards free);
- ray casting (eq. 20–22): every ray of the scan that the carrier's body does not block, from the
  sensor to its return or to d_max (rays without a return too, along their beam), traversed
  exactly; each voxel it crosses moves towards g_free with weight n_int = the ray length inside it
  (m), except voxels that hold a point of this scan (they take their point's update, eq. 9);
- every `separation_period`, the separate-cluster reset (sec. III-D, eq. 23): voxels at least
  tentatively occupied are grouped by d_sep around the sensor; groups with fewer than
  n_conf,min confidently occupied voxels (what a drone that took off leaves beside a wall) are
  updated with g_free, n = 1.
Every update is the exponential filter of eq. 12, G ← 2⁻ⁿ G + (1 − 2⁻ⁿ) g, with real n. Voxels the
a-priori map pins (sec. III-E) hold ±∞ and never change.

What the map publishes is class-quantised: a delta lists the voxels whose state (eq. 7) changed,
which is all a classifier needs; values drift between state changes without a message.

Where the seed is vague: the ray weight is in metres, as the text says ("the length of r within
every intersected voxel"), so with 0.5 m voxels one ray through a voxel weighs up to 0.87; the
separate-cluster grouping uses voxel adjacency within d_sep (up to the 26-neighbourhood), and
only around the sensor (within d_max + d_search), where the scan can have changed anything.

Pure: numpy in, numpy out (plus the compiled kernels of services/lib/voxels).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from schemas import voxels
from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.lib.lidar.rays import ScanRays
from services.lib.voxels.grid import GridGeometry
from services.lib.voxels.traversal import cast_scan
from services.mapper.update import THRESHOLDS, apply_ray_lengths, first_occurrences, weakly_held_voxels


class MapperParams(msgspec.Struct, forbid_unknown_fields=True):
    voxel_size: float = 0.5  # m
    # Operation area 120 x 100 x 26 m: x in [-10, 110), y in [-10, 90), z in [-1, 25).
    origin: tuple[float, float, float] = (-10.0, -10.0, -1.0)
    shape: tuple[int, int, int] = (240, 200, 52)
    unknown_value: float = -740.0  # g_unk, also every voxel's initial value
    occupied_value: float = 0.0  # g_occ
    free_value: float = -1000.0  # g_free
    raycast_max_distance: float = 20.0  # m, d_max
    separation_distance: float = 0.8  # m, d_sep
    separation_min_confident: int = 24  # n_conf,min
    separation_period: float = 0.5  # s of mission time between separate-cluster resets
    separation_reach: float = 23.0  # m around the sensor that the reset looks at (d_max + d_search)
    snapshot_period: float = 5.0  # s of mission time between snapshots
    # The a-priori map (sec. III-E): "world": the world model's static obstacles pinned occupied,
    # the simulation's stand-in for the surveyed site of the seed's experiments (nothing is pinned
    # where no world model is published); "": learn everything; or an .npz file
    # (services/lib/voxels/apriori.py)
    apriori: str = "world"

    def __post_init__(self) -> None:
        if not self.voxel_size > 0 or min(self.shape) <= 0:
            raise ValueError("voxel_size and every dimension of shape must be positive")
        if not self.free_value < self.unknown_value < self.occupied_value:
            raise ValueError("the update values must satisfy free_value < unknown_value < occupied_value")
        for name in ("raycast_max_distance", "separation_distance", "separation_reach"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.apriori not in ("", "world") and not Path(self.apriori).is_file():
            raise ValueError(f"apriori must be '', 'world' or an existing .npz map file, not {self.apriori!r}")


@dataclass(frozen=True)
class MapDelta:
    indices: np.ndarray  # int32 flat indices of the voxels whose state changed, sorted
    values: np.ndarray  # float32 their values now


@dataclass
class MapperCounters:
    scans: int = 0
    rays: int = 0
    voxels_outside: int = 0  # label voxels outside the map, dropped
    rejected_label_sets: int = 0  # label sets with impossible contents, not applied
    rejected_rays: int = 0  # scans whose rays could not be cast (sensor pose not finite, fields of other lengths)
    resets: int = 0  # voxels reset by the separate-cluster rule


def exponential_update(values: np.ndarray, weights: np.ndarray, target: float | np.ndarray) -> np.ndarray:
    """Eq. 12: n applications of eq. 8 at once, n real (one target for all, or one per voxel);
    n = ∞ sets the target; ±∞ values (pinned) stay."""
    g = np.asarray(values, dtype=np.float64)
    keep = 2.0 ** -np.asarray(weights, dtype=np.float64)
    with np.errstate(invalid="ignore"):  # 0 · ±∞ of a pinned voxel: replaced by its pinned value below
        out = keep * g + (1.0 - keep) * np.asarray(target, dtype=np.float64)
    return np.where(np.isfinite(g), out, g).astype(np.float32)


class MapperCore:
    def __init__(self, params: MapperParams | None = None) -> None:
        self.params = params or MapperParams()
        p = self.params
        self.geometry = GridGeometry(tuple(p.origin), tuple(int(s) for s in p.shape), float(p.voxel_size))
        self.origin = self.geometry.corner
        self.shape = self.geometry.shape
        self.voxel_size = self.geometry.voxel_size
        self.grid = np.full(self.shape, p.unknown_value, dtype=np.float32)
        self._flat = self.grid.reshape(-1)  # a view: writes land in grid
        self._window = np.zeros(0, dtype=np.float32)  # ray lengths around the sensor: scratch, left all 0
        self._changed = np.zeros(0, dtype=np.int64)  # scratch: the voxels the rays moved to another state
        self._marks = np.zeros(self.geometry.size, dtype=bool)  # scratch, always left all False
        self._box_slot = np.zeros(0, dtype=np.int64)  # separate-cluster reset scratch, left all -1
        self._weak = np.zeros(0, dtype=np.int64)  # separate-cluster reset scratch
        self._forward = _forward_neighbours(p.separation_distance / p.voxel_size)
        self._next_separation: int | None = None
        self.counters = MapperCounters()

    # ------------------------------------------------------------- a priori
    def pin(self, indices: np.ndarray, values: np.ndarray | float = np.inf) -> MapDelta:
        """Set voxels to given values (±∞ pins them: occupied or free for good, sec. III-E)."""
        flat = np.asarray(indices, dtype=np.int64).reshape(-1)
        flat = flat[(flat >= 0) & (flat < self.geometry.size)]
        before = voxels.map_states(self._flat[flat])
        self._flat[flat] = np.broadcast_to(np.asarray(values, dtype=np.float32), flat.shape)
        return self._delta(flat[voxels.map_states(self._flat[flat]) != before])

    # ------------------------------------------------------------- queries
    def snapshot(self) -> MapDelta:
        """Every voxel that differs from the initial value."""
        indices = np.flatnonzero(self._flat != np.float32(self.params.unknown_value))
        return MapDelta(indices.astype(np.int32), self._flat[indices].copy())

    def states(self) -> np.ndarray:
        return voxels.map_states(self._flat)

    # ------------------------------------------------------------- update
    def integrate(self, stamp: int, rays: ScanRays, label_voxels: np.ndarray, voxel_labels: np.ndarray,
                  voxel_weights: np.ndarray) -> MapDelta:
        """One scan: the label sets (voxel indices relative to the map origin, labels, weights n),
        then the scan's rays, then, when due, the separate-cluster reset. Returns the voxels whose
        state changed."""
        p = self.params
        self.counters.scans += 1
        labelled, labels, weights = self._label_sets(label_voxels, voxel_labels, voxel_weights)
        self._marks[labelled] = True  # voxels holding a point of this scan take the point's update (eq. 9)
        changed_by_rays = self._cast(rays)
        self._marks[labelled] = False
        before = voxels.map_states(self._flat[labelled])
        targets = np.where(labels == BACKGROUND, p.occupied_value, p.unknown_value)
        self._flat[labelled] = exponential_update(self._flat[labelled], weights, targets)
        changed = [changed_by_rays, labelled[voxels.map_states(self._flat[labelled]) != before]]
        if self._separation_due(stamp):
            changed.append(self._separate(np.asarray(rays.origin, dtype=np.float64)))
        return self._delta(np.concatenate(changed))

    def _cast(self, rays: ScanRays) -> np.ndarray:
        """Ray casting: every voxel the scan's rays cross moves towards free by its summed ray length,
        except voxels marked in `_marks`; returns the flat indices whose state changed. The rays are
        traversed in a window of the grid around the sensor (every ray ends within d_max of it), a
        grid small enough to stay in the processor's cache."""
        nothing = np.zeros(0, dtype=np.int64)
        origin = np.asarray(rays.origin, dtype=np.float64).reshape(3)
        pts = np.asarray(rays.points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            self.counters.rejected_rays += 1
            return nothing
        pts = np.ascontiguousarray(pts)
        beams = np.full(pts.shape, np.nan) if rays.beams is None else \
            np.ascontiguousarray(np.asarray(rays.beams, dtype=np.float64).reshape(-1, 3))
        blocked = np.zeros(len(pts), dtype=bool) if rays.masked is None else \
            np.asarray(rays.masked, dtype=bool).reshape(-1)
        rotation = np.ascontiguousarray(np.asarray(rays.rotation, dtype=np.float64).reshape(3, 3))
        if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(rotation))) or len(beams) != len(pts) \
                or len(blocked) != len(pts):
            self.counters.rejected_rays += 1
            return nothing
        self.counters.rays += int(np.count_nonzero(~blocked))
        # one voxel of margin: a ray ending exactly d_max away may touch the voxel beyond
        low, high = self.geometry.window(origin, self.params.raycast_max_distance + self.voxel_size)
        window = high - low
        if np.any(window <= 0):
            return nothing
        size = int(np.prod(window))
        if len(self._window) < size:
            self._window = np.zeros(size, dtype=np.float32)
        cast_scan(origin, rotation, pts, beams, blocked, self.params.raycast_max_distance,
                  self.origin + low * self.voxel_size, self.voxel_size, window, self._window)
        if len(self._changed) < size:
            self._changed = np.zeros(size, dtype=np.int64)
        n_changed = apply_ray_lengths(self._flat, self._window, low, window, np.asarray(self.shape), self._marks,
                                      self.params.free_value, THRESHOLDS, self._changed)
        return self._changed[:n_changed].copy()

    def _label_sets(self, label_voxels, voxel_labels, voxel_weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(flat indices, labels, weights) of the label sets inside the map; a set with impossible
        contents (lengths, label codes, weights) is refused whole: the map is never corrupted."""
        v = np.asarray(label_voxels).reshape(-1, 3)
        labels = np.asarray(voxel_labels).reshape(-1)
        weights = np.asarray(voxel_weights, dtype=np.float64).reshape(-1)
        sane = (len(v) == len(labels) == len(weights) and np.isin(labels, (BACKGROUND, FLYING, UNKNOWN)).all()
                and not np.isnan(weights).any() and (weights >= 0).all())
        if not sane:
            self.counters.rejected_label_sets += 1
            return np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0)
        inside = self.geometry.inside(v)
        self.counters.voxels_outside += int(np.count_nonzero(~inside))
        flat = self.geometry.flat(v[inside])
        labels, weights = labels[inside], weights[inside]
        weights = np.where(labels == FLYING, np.inf, weights)  # eq. 17: n_det = ∞
        first = first_occurrences(flat, self._marks)  # one update per voxel (the classifier sends one)
        return flat[first], labels[first], weights[first]

    def _separation_due(self, stamp: int) -> bool:
        """Every `separation_period` of mission time, the first one a period after the first scan."""
        period = int(self.params.separation_period * 1e9)
        if self._next_separation is None:
            self._next_separation = stamp + period
            return False
        if stamp < self._next_separation:
            return False
        self._next_separation = stamp + period
        return True

    def _separate(self, origin: np.ndarray) -> np.ndarray:
        """Eq. 23 around the sensor: groups of at least tentatively occupied voxels with fewer than
        n_conf,min confident ones are moved towards free. Returns the voxels whose state changed."""
        p = self.params
        if not np.all(np.isfinite(origin)):
            return np.zeros(0, dtype=np.int64)
        low, high = self.geometry.window(origin, p.separation_reach)
        if np.any(high <= low):
            return np.zeros(0, dtype=np.int64)
        size = int(np.prod(high - low))
        if len(self._box_slot) < size:
            self._box_slot = np.full(size, -1, dtype=np.int64)
            self._weak = np.zeros(size, dtype=np.int64)
        count = weakly_held_voxels(self._flat, low, high, np.asarray(self.shape), np.float32(voxels.TENTATIVE_OCCUPIED),
                                   np.float32(voxels.CONFIDENT_OCCUPIED), self._forward, p.separation_min_confident,
                                   self._box_slot, self._weak)
        flat = self._weak[:count]
        flat = flat[np.isfinite(self._flat[flat])]  # pinned voxels stay
        before = voxels.map_states(self._flat[flat])
        self._flat[flat] = exponential_update(self._flat[flat], np.ones(len(flat)), p.free_value)
        self.counters.resets += len(flat)
        return flat[voxels.map_states(self._flat[flat]) != before]

    def _delta(self, changed: np.ndarray) -> MapDelta:
        changed = np.unique(changed)
        return MapDelta(changed.astype(np.int32), self._flat[changed].copy())


def warm_up(params: MapperParams) -> int:
    """Integrate two small synthetic scans on a throwaway core, a separation period apart, so that
    the update's compiled kernels (numba, cached on disk after a machine's first run) are ready
    before the first real scan (see classifier/core.py, `warm_up`, for why). Rays with and without
    returns from the map's centre, label sets of both kinds; the second scan is due for the
    separate-cluster reset. Returns the voxels the scans changed."""
    core = MapperCore(params)
    geometry = core.geometry
    centre = np.asarray(geometry.corner) + 0.5 * np.asarray(geometry.shape) * geometry.voxel_size
    beams = np.random.default_rng(0).normal(size=(64, 3))
    beams /= np.linalg.norm(beams, axis=1, keepdims=True)
    points = (centre + 4.0 * beams).astype(np.float32)
    points[::8] = np.nan  # no return
    voxels_of_points = np.floor((points[1:3] - geometry.corner) / geometry.voxel_size).astype(np.int32)
    changed = 0
    for stamp in (0, int(params.separation_period * 1e9) + 1):
        delta = core.integrate(stamp, ScanRays(centre, np.eye(3), points, beams, None), voxels_of_points,
                               np.array([BACKGROUND, UNKNOWN], dtype=np.uint8), np.ones(2, dtype=np.float32))
        changed += len(delta.indices)
    return changed


def _forward_neighbours(reach_voxels: float) -> np.ndarray:
    """(K, 3) offsets of the neighbours whose centres are within `reach_voxels` voxel edges (at
    least the 6 face neighbours, at most the 26 of the 3×3×3 cube), those after (0, 0, 0) in C
    order: each adjacent pair of voxels is looked at once."""
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    near = np.linalg.norm(offsets, axis=-1) <= max(reach_voxels, 1.0) + 1e-9
    after = np.arange(len(offsets)) > 13  # (0, 0, 0) is the 14th of the 27
    return np.ascontiguousarray(offsets[near & after], dtype=np.int64)
