"""The numpy ray caster: the reference the numba caster (raycast.py) is checked against.

`raycast.py` computes the same expressions in the same order, ray by ray, and the tests hold the
two to agree; `benchmarks/lidar.py` compares their speed. Its bounding spheres (`sphere_bounds`,
`upright_bounds`, `box_bounds`) are also those of the packed table (primitives.pack), so both
casters skip the same primitives. Every function takes float64 arrays; see primitives.py for the
row layouts.
"""
from __future__ import annotations

import numpy as np

from services.lib.geometry import rotate_yaw

EPS = 1e-9  # hits closer than this along the ray are the surface the ray starts on


def cast(origin: np.ndarray, directions: np.ndarray, primitives) -> tuple[np.ndarray, np.ndarray]:
    """(range, id) along each unit direction (N, 3) from `origin` to the nearest surface:
    range inf and id -1 where nothing is hit; ids as in `primitives` (0 static, k >= 1 target k)."""
    o = np.asarray(origin, dtype=float)
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    best_id = np.full(len(d), -1, dtype=np.int32)

    def keep(idx: np.ndarray, t: np.ndarray, ident: int) -> None:
        closer = t < best[idx]
        best[idx[closer]] = t[closer]
        best_id[idx[closer]] = ident

    everything = np.arange(len(d))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for z in primitives.planes:
            keep(everything, _hit_plane(o, d, z), 0)
        kinds = (
            (primitives.spheres, primitives.sphere_ids, _hit_sphere, sphere_bounds),
            (primitives.cylinders, primitives.cylinder_ids, _hit_cylinder, upright_bounds),
            (primitives.boxes, np.zeros(len(primitives.boxes), np.int32), _hit_box, box_bounds),
            (primitives.cones, np.zeros(len(primitives.cones), np.int32), _hit_cone, upright_bounds),
        )
        for rows, ids, hit, bounds in kinds:
            for row, ident in zip(rows, ids):
                centre, radius = bounds(row)
                idx = _rays_near(o, d, centre, radius)
                if len(idx):
                    keep(idx, hit(o, d[idx], row), int(ident))
    return best, best_id


def _rays_near(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays that can reach the bounding sphere: the exact test runs on these only."""
    oc = centre - o
    dist2 = _norm2(oc)
    if dist2 <= radius * radius:
        return np.arange(len(d))
    along = _dot(d, oc)
    return np.flatnonzero((along > 0) & (dist2 - along * along <= radius * radius))


# Bounding spheres, a hair larger than the primitive so rounding never culls a true hit.
def sphere_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    return row[:3], float(row[3]) * (1 + 1e-9) + 1e-9


def upright_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    cx, cy, z0, r, h = row
    return np.array([cx, cy, z0 + h / 2]), float(np.hypot(r, h / 2)) * (1 + 1e-9) + 1e-9


def box_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    return (row[:3] + row[3:]) / 2, float(np.linalg.norm(row[3:] - row[:3])) / 2 * (1 + 1e-9) + 1e-9


def _norm2(v: np.ndarray) -> float:
    """v·v written out, in the order the numba caster adds it up."""
    return float(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _dot(d: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise d·v written out: BLAS may round differently by batch size, this does not."""
    return d[:, 0] * v[0] + d[:, 1] * v[1] + d[:, 2] * v[2]


def _positive(t: np.ndarray) -> np.ndarray:
    """Hit distances in front of the origin; everything else (behind, NaN) becomes inf."""
    return np.where(t > EPS, t, np.inf)


def _hit_plane(o: np.ndarray, d: np.ndarray, z: float) -> np.ndarray:
    return _positive((z - o[2]) / d[:, 2])


def _hit_sphere(o: np.ndarray, d: np.ndarray, row: np.ndarray) -> np.ndarray:
    oc = o - row[:3]
    b = _dot(d, oc)
    c = _norm2(oc) - row[3] * row[3]
    disc = b * b - c
    root = np.sqrt(disc)  # NaN where the line misses: _positive turns it into inf
    near, far = _positive(-b - root), _positive(-b + root)
    return np.minimum(near, far)


def _disk(o: np.ndarray, d: np.ndarray, cx: float, cy: float, z: float, r: float) -> np.ndarray:
    t = _positive((z - o[2]) / d[:, 2])
    x = o[0] + t * d[:, 0] - cx
    y = o[1] + t * d[:, 1] - cy
    return np.where(x * x + y * y <= r * r, t, np.inf)


def _hit_cylinder(o: np.ndarray, d: np.ndarray, row: np.ndarray) -> np.ndarray:
    cx, cy, z0, r, h = row
    ox, oy = o[0] - cx, o[1] - cy
    a = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    b = ox * d[:, 0] + oy * d[:, 1]
    c = ox * ox + oy * oy - r * r
    root = np.sqrt(b * b - a * c)
    best = np.full(len(d), np.inf)
    for t in (_positive((-b - root) / a), _positive((-b + root) / a)):
        z = o[2] + t * d[:, 2]
        np.minimum(best, np.where((z >= z0) & (z <= z0 + h), t, np.inf), out=best)
    np.minimum(best, _disk(o, d, cx, cy, z0 + h, r), out=best)
    np.minimum(best, _disk(o, d, cx, cy, z0, r), out=best)
    return best


def _hit_box(o: np.ndarray, d: np.ndarray, row: np.ndarray) -> np.ndarray:
    # Slabs; a zero direction component gives ±inf (or NaN on the face, which fmin/fmax skip).
    t1 = (row[:3] - o) / d
    t2 = (row[3:] - o) / d
    t_near = np.fmax.reduce(np.fmin(t1, t2), axis=1)
    t_far = np.fmin.reduce(np.fmax(t1, t2), axis=1)
    hit = (t_near <= t_far) & (t_far > EPS)
    return np.where(hit, np.where(t_near > EPS, t_near, t_far), np.inf)


def _hit_cone(o: np.ndarray, d: np.ndarray, row: np.ndarray) -> np.ndarray:
    # Lateral surface: (x-cx)² + (y-cy)² = (k·(apex_z - z))², k = r/h, for z in [z0, apex].
    cx, cy, z0, r, h = row
    k2 = (r / h) * (r / h)
    ox, oy, oz = o[0] - cx, o[1] - cy, (z0 + h) - o[2]  # oz: apex height above the origin
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dy * dy - k2 * dz * dz
    b = ox * dx + oy * dy + k2 * oz * dz
    c = ox * ox + oy * oy - k2 * oz * oz
    root = np.sqrt(b * b - a * c)
    best = np.full(len(d), np.inf)
    parallel = np.abs(a) < 1e-12  # ray parallel to the side: the quadratic degenerates to 2bt + c = 0
    linear = np.where(parallel, _positive(-c / (2 * b)), np.inf)
    for t in (_positive((-b - root) / a), _positive((-b + root) / a), linear):
        z = o[2] + t * dz
        np.minimum(best, np.where((z >= z0) & (z <= z0 + h), t, np.inf), out=best)
    np.minimum(best, _disk(o, d, cx, cy, z0, r), out=best)
    return best


def scan(origin: np.ndarray, heading: float, directions: np.ndarray, primitives,
         rng: np.random.Generator, min_range: float = 0.3, max_range: float = 50.0,
         range_noise: float = 0.01, body_radius: float = 0.4) -> np.ndarray:
    """The walking skeleton's whole scan in numpy (the benchmark's "before"): float32
    (rows, cols, 3) world points, NaN where no return."""
    shape = directions.shape[:-1]
    world_dirs = rotate_yaw(directions, heading).reshape(-1, 3)
    ranges, _ = cast(origin, world_dirs, primitives)
    noise = rng.normal(0.0, range_noise, ranges.shape) if range_noise > 0 else np.zeros(ranges.shape)
    valid = (ranges >= max(min_range, body_radius)) & (ranges <= max_range)
    measured = np.where(valid, ranges + noise, 0.0)
    points = np.asarray(origin, dtype=float) + world_dirs * measured[:, None]
    points[~valid] = np.nan
    return points.astype(np.float32).reshape(*shape, 3)
