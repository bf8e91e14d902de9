"""Where voxels are: the map's geometry and its index arithmetic (pure numpy).

A map is a dense grid of `shape` voxels of edge `voxel_size`, voxel (0, 0, 0)'s minimum corner at
`origin`; voxel (i, j, k) covers origin + [i, i+1) × [j, j+1) × [k, k+1) voxel edges. Flat indices
are C order over `shape`, as in VoxelMap messages.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridGeometry:
    origin: tuple[float, float, float]
    shape: tuple[int, int, int]
    voxel_size: float

    def __post_init__(self) -> None:
        if len(self.shape) != 3 or min(self.shape) <= 0:
            raise ValueError(f"a voxel grid needs three positive dimensions, got {self.shape}")
        if not 0 < self.voxel_size < np.inf:
            raise ValueError(f"voxel size must be positive and finite, got {self.voxel_size}")
        if not np.all(np.isfinite(self.origin)):
            raise ValueError(f"a voxel grid needs a finite origin, got {self.origin}")

    @property
    def size(self) -> int:
        return math.prod(self.shape)  # Python ints: numpy's product of three huge dimensions wraps around

    @property
    def corner(self) -> np.ndarray:
        return np.asarray(self.origin, dtype=np.float64)

    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) int64 voxel indices of (N, 3) points (outside the grid too: check with `inside`)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.floor((p - self.corner) / self.voxel_size).astype(np.int64)

    def inside(self, voxels: np.ndarray) -> np.ndarray:
        v = np.asarray(voxels).reshape(-1, 3)
        return np.all((v >= 0) & (v < np.asarray(self.shape)), axis=1)

    def flat(self, voxels: np.ndarray) -> np.ndarray:
        """Flat indices of (N, 3) voxels that are inside the grid."""
        v = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        return np.ravel_multi_index(tuple(v.T), self.shape)

    def unflat(self, flat: np.ndarray) -> np.ndarray:
        return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), self.shape), axis=1)

    def centres(self, voxels: np.ndarray) -> np.ndarray:
        return self.corner + (np.asarray(voxels, dtype=np.float64).reshape(-1, 3) + 0.5) * self.voxel_size

    def window(self, centre: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) voxel bounds, high exclusive, of the box of half-width `reach` (m) around the
        point `centre`, cut to the grid; empty along an axis where high <= low."""
        middle = (np.asarray(centre, dtype=np.float64).reshape(3) - self.corner) / self.voxel_size
        cells = reach / self.voxel_size
        shape = np.asarray(self.shape)
        low = np.clip(np.floor(middle - cells).astype(np.int64), 0, shape)
        high = np.clip(np.ceil(middle + cells).astype(np.int64) + 1, 0, shape)
        return low, high

    def same_as(self, other: "GridGeometry") -> bool:
        return (tuple(self.shape) == tuple(other.shape) and float(self.voxel_size) == float(other.voxel_size)
                and np.array_equal(self.corner, other.corner))
