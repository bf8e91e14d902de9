"""Mapper core: the occupancy voxel map G(v) (seed 000, sec. III-A and III-C).

FIRST VERSION (walking skeleton). Every label set is applied as hard assignments:
- voxels with background points: G = g_occ (0, "occupied point");
- voxels with flying-object points: G = g_unk (eq. 17, n = infinity);
- voxels that a ray from the sensor to a point passes through (the point's own voxel
  excluded, up to the ray-cast max distance), that hold no point of this scan and are not
  confident occupied: G = g_free (-1000).
The ray traversal samples every ray each half voxel and takes the unique voxels (the
voxel a ray merely clips at a corner can be missed). Later issues deepen this to the seed's method: the
exponential update with weights (eq. 8-12, 16-18), exact per-voxel ray lengths n_int
(eq. 20-22, rays without return included), separate-cluster reset (eq. 23) and a-priori
initialisation from the world model (sec. III-E).

Pure: numpy in, numpy out.
"""
from __future__ import annotations

import msgspec
import numpy as np

from schemas.voxels import BACKGROUND, FLYING


class MapperParams(msgspec.Struct, forbid_unknown_fields=True):
    voxel_size: float = 0.5  # m
    # Operation area 120 x 100 x 26 m: x in [-10, 110), y in [-10, 90), z in [-1, 25).
    origin: tuple[float, float, float] = (-10.0, -10.0, -1.0)
    shape: tuple[int, int, int] = (240, 200, 52)
    unknown_value: float = -740.0  # g_unk, also every voxel's initial value
    occupied_value: float = 0.0  # g_occ
    free_value: float = -1000.0  # g_free
    confident_occupied: float = -0.1  # G_conf: rays never clear such voxels
    raycast_max_distance: float = 20.0  # m, d_max
    snapshot_period: float = 1.0  # s of mission time between snapshots


class MapperCore:
    def __init__(self, params: MapperParams | None = None) -> None:
        self.params = params or MapperParams()
        p = self.params
        self.origin = np.asarray(p.origin, dtype=np.float64)
        self.shape = tuple(int(s) for s in p.shape)
        self.voxel_size = float(p.voxel_size)
        self.grid = np.full(self.shape, p.unknown_value, dtype=np.float32)
        self._flat = self.grid.reshape(-1)  # a view: writes land in grid
        self._marks = np.zeros(self.grid.size, dtype=bool)  # scratch, always left all False

    # ------------------------------------------------------------- queries
    def flat_index(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of the (M, 3) voxels inside the map, and which rows were inside."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        inside = np.all((voxels >= 0) & (voxels < np.asarray(self.shape)), axis=1)
        return np.ravel_multi_index(tuple(voxels[inside].T), self.shape), inside

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """Every voxel that differs from the initial value: (int64 flat indices, float32 values)."""
        indices = np.flatnonzero(self._flat != np.float32(self.params.unknown_value))
        return indices.astype(np.int64), self._flat[indices].copy()

    def traversed_voxels(self, sensor_origin, points: np.ndarray) -> np.ndarray:
        """Sorted flat indices of in-map voxels the rays sensor -> point pass through,
        each ray's end voxel excluded and every ray cut at the ray-cast max distance.

        Samples every half voxel along each ray. The loop runs over sample steps (about
        2 * d_max / voxel of them), each step handling every ray still long enough at once,
        so the work is the number of samples with no (rays x samples) temporaries."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        start = (np.asarray(sensor_origin, dtype=np.float64) - self.origin) / self.voxel_size  # voxel units
        ends = (points - self.origin) / self.voxel_size
        offsets = ends - start
        lengths = np.linalg.norm(offsets, axis=1)
        keep = lengths > 1e-9
        if not keep.any():
            return np.zeros(0, dtype=np.int64)
        ends, offsets, lengths = ends[keep], offsets[keep], lengths[keep]
        reach = np.minimum(lengths, self.params.raycast_max_distance / self.voxel_size)
        longest_first = np.argsort(-reach, kind="stable")
        reach = reach[longest_first]
        directions = (offsets / lengths[:, None])[longest_first]
        size_y, size_z = self.shape[1], self.shape[2]
        end_voxels = np.floor(ends[longest_first]).astype(np.int64)
        end_inside = np.all((end_voxels >= 0) & (end_voxels < np.asarray(self.shape)), axis=1)
        end_flat = (end_voxels[:, 0] * size_y + end_voxels[:, 1]) * size_z + end_voxels[:, 2]
        end_flat[~end_inside] = -1

        # One contiguous float32 array per axis: several times faster than (rays, 3) rows.
        axes = [np.ascontiguousarray(directions[:, a], dtype=np.float32) for a in range(3)]
        steps = np.arange(0.0, reach[0], 0.5)
        active = np.searchsorted(-reach, -steps, side="left")  # rays with reach > step
        for step, count in zip(steps, active):
            x, y, z = (np.floor(np.float32(start[a]) + axes[a][:count] * np.float32(step)).astype(np.int32)
                       for a in range(3))
            # Negative indices wrap to huge unsigned values, so one compare per axis checks both ends.
            inside = ((x.view(np.uint32) < self.shape[0]) & (y.view(np.uint32) < size_y)
                      & (z.view(np.uint32) < size_z))
            flat = (x.astype(np.int64) * size_y + y) * size_z + z
            self._marks[flat[inside & (flat != end_flat[:count])]] = True
        traversed = np.flatnonzero(self._marks)
        self._marks[traversed] = False
        return traversed

    # ------------------------------------------------------------- update
    def apply_labels(self, sensor_origin, points: np.ndarray, voxels: np.ndarray,
                     voxel_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply one LabelSet; returns the delta: (sorted int64 flat indices, float32 new values)
        of exactly the voxels whose value changed."""
        p = self.params
        labelled, inside = self.flat_index(voxels)
        labels = np.asarray(voxel_labels).reshape(-1)[inside]
        background = labelled[labels == BACKGROUND]
        flying = labelled[labels == FLYING]

        rayed = self.traversed_voxels(sensor_origin, points)
        # Voxels holding a point of this scan take the point's update, not the ray's (eq. 9).
        self._marks[labelled] = True
        rayed = rayed[~self._marks[rayed]]
        self._marks[labelled] = False
        rayed = rayed[self._flat[rayed] < p.confident_occupied]

        touched = np.unique(np.concatenate([rayed, flying, background]))
        before = self._flat[touched].copy()
        self._flat[rayed] = p.free_value
        self._flat[flying] = p.unknown_value
        self._flat[background] = p.occupied_value
        changed = touched[self._flat[touched] != before]
        return changed.astype(np.int64), self._flat[changed].copy()
