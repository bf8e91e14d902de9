"""A copy of a mapper's occupancy map G(v), kept up to date from VoxelMap messages.

Held by every service that reads the map (classifier, viewer). Pure numpy.
"""
from __future__ import annotations

import numpy as np


class MapReplica:
    """G(v) as the last VoxelMap messages left it: a snapshot replaces everything (and may change
    the geometry), a delta overwrites the voxels it lists."""

    def __init__(self, origin, shape, voxel_size: float, default_value: float) -> None:
        self._reset(origin, shape, voxel_size, default_value)
        self.snapshots = 0

    def _reset(self, origin, shape, voxel_size: float, default_value: float) -> None:
        self.origin = np.asarray(origin, dtype=np.float64)
        self.shape = tuple(int(s) for s in shape)
        self.voxel_size = float(voxel_size)
        self.default_value = float(default_value)
        self.grid = np.full(self.shape, self.default_value, dtype=np.float32)

    def same_geometry(self, origin, shape, voxel_size: float) -> bool:
        return (
            tuple(int(s) for s in shape) == self.shape
            and float(voxel_size) == self.voxel_size
            and np.array_equal(np.asarray(origin, dtype=np.float64), self.origin)
        )

    def apply(self, snapshot: bool, origin, shape, voxel_size: float, default_value: float,
              indices: np.ndarray, values: np.ndarray) -> bool:
        """Apply one VoxelMap; False when a delta does not fit our geometry (wait for a snapshot)."""
        if snapshot:
            if self.same_geometry(origin, shape, voxel_size) and default_value == self.default_value:
                self.grid.fill(self.default_value)
            else:
                self._reset(origin, shape, voxel_size, default_value)
            self.snapshots += 1
        elif not self.same_geometry(origin, shape, voxel_size):
            return False
        indices = np.asarray(indices, dtype=np.int64)
        inside = (indices >= 0) & (indices < self.grid.size)
        self.grid.reshape(-1)[indices[inside]] = np.asarray(values, dtype=np.float32)[inside]
        return True

    def occupied_near(self, voxels: np.ndarray, reach: int, threshold: float) -> np.ndarray:
        """For each (M, 3) voxel index: is any voxel within `reach` (Chebyshev) at G >= threshold?"""
        if len(voxels) == 0:
            return np.zeros(0, dtype=bool)
        steps = np.arange(-reach, reach + 1)
        offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
        near = voxels[:, None, :] + offsets[None, :, :]  # (M, K, 3)
        inside = np.all((near >= 0) & (near < np.asarray(self.shape)), axis=-1)
        flat = np.ravel_multi_index(tuple(np.where(inside[..., None], near, 0).transpose(2, 0, 1)), self.shape)
        hit = (self.grid.reshape(-1)[flat] >= threshold) & inside
        return hit.any(axis=1)
