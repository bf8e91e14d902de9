"""An a-priori map (seed 000 sec. III-E): voxels known to be occupied before the flight, pinned.

From the world model's static obstacles (the simulation's stand-in for a surveyed site) or from a
file (`.npz` with `indices`, `values` and the grid's `origin`, `shape`, `voxel_size`). A voxel is
occupied when its cube meets an obstacle: its centre lies inside the solid, or a point of the
solid's surface sampled at a fraction of the voxel lies in it (so a 5 cm pole marks its column).
Pure numpy.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from schemas.messages import Obstacle
from services.lib.voxels.grid import GridGeometry

SURFACE_STEP = 0.25  # surface samples per voxel edge (4 per edge)


def obstacle_voxels(obstacles: list[Obstacle], grid: GridGeometry) -> np.ndarray:
    """Sorted flat indices of the voxels the obstacles occupy (a plane: its layer of voxels)."""
    flats = [_voxels_of(o, grid) for o in obstacles]
    flats = [f for f in flats if len(f)]
    return np.unique(np.concatenate(flats)) if flats else np.zeros(0, dtype=np.int64)


def _voxels_of(o: Obstacle, grid: GridGeometry) -> np.ndarray:
    step = grid.voxel_size * SURFACE_STEP
    low = grid.corner
    c = np.asarray(o.center, dtype=np.float64)
    if o.kind == "plane":  # the whole layer of voxels at its height
        layer = int(np.floor((c[2] - low[2]) / grid.voxel_size))
        if not 0 <= layer < grid.shape[2]:
            return np.zeros(0, dtype=np.int64)
        i, j = np.meshgrid(np.arange(grid.shape[0]), np.arange(grid.shape[1]), indexing="ij")
        return np.ravel_multi_index((i.ravel(), j.ravel(), np.full(i.size, layer)), grid.shape)
    if o.kind == "box":
        half = np.asarray(o.size, dtype=np.float64) / 2
        axes = [_range(c[a] - half[a], c[a] + half[a], step, ends=True) for a in range(3)]
        samples = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    elif o.kind in ("cylinder", "cone"):
        samples = _upright(c, o.radius, o.height, step, cone=o.kind == "cone")
    elif o.kind == "sphere":
        samples = _ball(c, o.radius, step)
    else:
        raise ValueError(f"no voxelisation for obstacle kind {o.kind!r}")
    voxels = grid.voxel_of(samples)
    return np.unique(grid.flat(voxels[grid.inside(voxels)]))


def _range(a: float, b: float, step: float, ends: bool = False) -> np.ndarray:
    n = max(int(np.ceil((b - a) / step)), 1)
    return np.linspace(a, b, n + 1) if ends else np.arange(a, b, step)


def _upright(base: np.ndarray, radius: float, height: float, step: float, cone: bool) -> np.ndarray:
    """Samples filling a vertical cylinder or cone (apex up) standing on `base`."""
    zs = _range(0.0, height, step, ends=True)
    rs = _range(0.0, radius, step, ends=True) if radius > 0 else np.zeros(1)
    out = []
    for z in zs:
        top = radius * (1.0 - z / height) if cone and height > 0 else radius
        for r in rs[rs <= top + 1e-9]:
            count = max(int(np.ceil(2 * np.pi * r / step)), 1)
            a = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
            out.append(np.stack([base[0] + r * np.cos(a), base[1] + r * np.sin(a), np.full(count, base[2] + z)], 1))
    return np.vstack(out)


def _ball(centre: np.ndarray, radius: float, step: float) -> np.ndarray:
    axis = _range(-radius, radius, step, ends=True)
    cube = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    return centre + cube[np.linalg.norm(cube, axis=1) <= radius + 1e-9]


def load_map_file(path: str | Path, grid: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(flat indices, values) of an a-priori map file made for this grid; ValueError says what is wrong."""
    try:
        with np.load(path) as data:
            indices, values = np.asarray(data["indices"], np.int64), np.asarray(data["values"], np.float32)
            theirs = GridGeometry(tuple(data["origin"].tolist()), tuple(int(s) for s in data["shape"]),
                                  float(data["voxel_size"]))
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"a-priori map {path}: {exc}") from None
    if not theirs.same_as(grid):
        raise ValueError(f"a-priori map {path} is for another grid ({theirs}), the mapper's is {grid}")
    if indices.shape != values.shape or (len(indices) and (indices.min() < 0 or indices.max() >= grid.size)):
        raise ValueError(f"a-priori map {path}: indices and values must match and lie inside the grid")
    return indices, values


def save_map_file(path: str | Path, grid: GridGeometry, indices: np.ndarray, values: np.ndarray) -> None:
    np.savez_compressed(path, indices=np.asarray(indices, np.int64), values=np.asarray(values, np.float32),
                        origin=np.asarray(grid.origin), shape=np.asarray(grid.shape), voxel_size=grid.voxel_size)
