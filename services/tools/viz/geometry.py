"""Geometry the viewer needs to draw what the fleet believes: covariance ellipsoids, predicted
paths, decimated clouds, meshes for primitives rerun has no archetype for, and colours.

Pure numpy (scipy for rotations): numbers in, numbers out.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

Color = tuple[int, int, int, int]

# Colour stops of matplotlib's viridis, enough for a height ramp without importing matplotlib.
VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)
# Sand to rust: solid things, light at the ground so the map does not bury the scene in one dark slab.
TERRAIN = np.array([[214, 205, 180], [190, 170, 130], [170, 130, 90], [200, 105, 50], [170, 50, 30]], dtype=np.float64)


def covariance_ellipsoids(covariances: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Half-axes (N, 3) and orientations as quaternions (N, 4, x-y-z-w) of the `sigma`-level
    ellipsoids of (N, 3, 3) covariances. Negative eigenvalues (round-off) count as zero."""
    cov = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    if not len(cov):
        return np.zeros((0, 3)), np.zeros((0, 4))
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    values, vectors = np.linalg.eigh(cov)
    half = sigma * np.sqrt(np.clip(values, 0.0, None))
    flip = np.linalg.det(vectors) < 0  # eigh may return a reflection; a rotation needs det +1
    vectors[flip, :, 2] *= -1.0
    return half, Rotation.from_matrix(vectors).as_quat()


def wxyz_to_xyzw(quaternion) -> np.ndarray:
    w, x, y, z = (float(v) for v in quaternion)
    return np.array([x, y, z, w])


def thin_out(count: int, budget: int) -> np.ndarray:
    """Indices of at most `budget` of `count` items, evenly spread (deterministic)."""
    if count <= budget:
        return np.arange(count)
    return np.linspace(0, count - 1, budget).round().astype(np.int64)


def height_colors(z: np.ndarray, low: float, high: float, alpha: int = 255, ramp: np.ndarray = VIRIDIS) -> np.ndarray:
    """(N, 4) uint8 colours on a ramp (viridis unless given) from `low` to `high` metres."""
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    where = np.clip((z - low) / max(high - low, 1e-9), 0.0, 1.0) * (len(ramp) - 1)
    stops = np.arange(len(ramp))
    rgb = np.stack([np.interp(where, stops, ramp[:, c]) for c in range(3)], axis=1)
    return np.concatenate([rgb.round(), np.full((len(z), 1), alpha)], axis=1).astype(np.uint8)


def cone_mesh(base: np.ndarray, radius: float, height: float, sides: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (sides + 2, 3) and triangles (2 sides, 3) of a vertical cone standing on `base`."""
    angles = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    rim = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros(sides)], axis=1) + base
    apex = np.asarray(base, dtype=np.float64) + (0.0, 0.0, height)
    vertices = np.vstack([rim, apex, base])
    i = np.arange(sides)
    j = (i + 1) % sides
    sides_ = np.stack([i, j, np.full(sides, sides)], axis=1)
    bottom = np.stack([j, i, np.full(sides, sides + 1)], axis=1)
    return vertices, np.vstack([sides_, bottom]).astype(np.uint32)


def merge_meshes(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh from several (vertices, triangles) pairs."""
    vertices, triangles, offset = [], [], 0
    for v, t in parts:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32)
    return np.vstack(vertices), np.vstack(triangles).astype(np.uint32)


def rectangle_mesh(low: tuple[float, float], high: tuple[float, float], z: float) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal rectangle at height z (two triangles facing up)."""
    (x0, y0), (x1, y1) = low, high
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def closed_polygon(polygon, z: float) -> np.ndarray:
    """A (K+1, 3) line strip around a (K, 2) polygon at height z."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if not len(poly):
        return np.zeros((0, 3))
    ring = np.vstack([poly, poly[:1]])
    return np.hstack([ring, np.full((len(ring), 1), z)])
