"""A copy of a mapper's occupancy map G(v), kept up to date from VoxelMap messages.

Held by every service that reads the map (classifier, viewer). Beside the values it keeps every
voxel's state of eq. 7 (schemas/voxels.py), which is what the classification rules read and what
the mapper's deltas keep exact. Pure numpy.
"""
from __future__ import annotations

import numpy as np

from schemas import voxels
from services.lib.voxels.grid import GridGeometry


def geometry_of(origin, shape, voxel_size: float) -> GridGeometry:
    """The geometry a VoxelMap's fields describe (ValueError: none)."""
    return GridGeometry(tuple(float(v) for v in origin), tuple(int(s) for s in shape), float(voxel_size))


class MapReplica:
    """G(v) as the last VoxelMap messages left it: a snapshot replaces everything (and may change
    the geometry), a delta overwrites the voxels it lists."""

    # A map message asking for a larger grid is refused, never allocated (1 GiB per float32 layer): it
    # would make every replica of the map (classifier, viewer) run out of memory.
    MAX_VOXELS = 1 << 28

    def __init__(self, origin, shape, voxel_size: float, default_value: float) -> None:
        self._reset(origin, shape, voxel_size, default_value)
        self.snapshots = 0

    def _reset(self, origin, shape, voxel_size: float, default_value: float) -> None:
        # all or nothing: a geometry whose arrays cannot be allocated leaves the replica as it was
        geometry = geometry_of(origin, shape, voxel_size)
        if geometry.size > self.MAX_VOXELS:
            raise ValueError(f"a map of {geometry.shape} voxels is more than the {self.MAX_VOXELS} a replica holds")
        grid = np.full(geometry.shape, float(default_value), dtype=np.float32)
        states = np.full(geometry.size, voxels.map_states(np.float32(default_value)), dtype=np.uint8)
        self.geometry, self.grid, self.states = geometry, grid, states
        self.origin = self.geometry.corner
        self.shape = self.geometry.shape
        self.voxel_size = self.geometry.voxel_size
        self.default_value = float(default_value)

    def same_geometry(self, origin, shape, voxel_size: float) -> bool:
        return self.geometry.same_as(geometry_of(origin, shape, voxel_size))

    def apply(self, snapshot: bool, origin, shape, voxel_size: float, default_value: float,
              indices: np.ndarray, values: np.ndarray) -> bool:
        """Apply one VoxelMap; False when a delta does not fit our geometry (wait for a snapshot)."""
        if snapshot:
            if self.same_geometry(origin, shape, voxel_size) and default_value == self.default_value:
                self.grid.fill(self.default_value)
                self.states.fill(voxels.map_states(np.float32(self.default_value)))
            else:
                self._reset(origin, shape, voxel_size, default_value)
            self.snapshots += 1
        elif not self.same_geometry(origin, shape, voxel_size):
            return False
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        values = np.asarray(values, dtype=np.float32).reshape(-1)
        if len(indices) != len(values):
            raise ValueError(f"a map message with {len(indices)} indices and {len(values)} values")
        inside = (indices >= 0) & (indices < self.grid.size) & ~np.isnan(values)
        self.grid.reshape(-1)[indices[inside]] = values[inside]
        self.states[indices[inside]] = voxels.map_states(values[inside])
        return True
