"""Simulated rotating multi-beam LiDAR: beam pattern and a vectorised ray caster.

First version (walking skeleton): an ideal spinning sensor (every beam fired at the same
instant, no motion distortion) with gaussian range noise, cast against the world's static
primitives and the targets. A later issue deepens it with Ouster/Livox beam patterns,
intensity, dropouts, motion distortion and a numba-compiled caster (`cast` is written as a loop
over primitives with plain float64 arrays so it translates directly).

Primitives (`Primitives`, all float64 arrays, one row each):
  planes     (P,)   horizontal planes z = value (the ground)
  spheres    (S, 4) cx, cy, cz, r (balloons, intruder drones as spheres of their body radius)
  cylinders  (C, 5) cx, cy, z_base, r, h (vertical, capped: poles, tree trunks)
  boxes      (B, 6) x_min, y_min, z_min, x_max, y_max, z_max (axis-aligned: buildings)
  cones      (K, 5) cx, cy, z_base, r_base, h (vertical, apex up, base disk closed: trees)
Ranges are along unit directions, so a range is also the distance to the hit.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import Obstacle, TargetTruth

EPS = 1e-9  # hits closer than this along the ray are the surface the ray starts on


def _rows(n: int) -> np.ndarray:
    return np.zeros((0, n))


@dataclass
class Primitives:
    planes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    spheres: np.ndarray = field(default_factory=lambda: _rows(4))
    cylinders: np.ndarray = field(default_factory=lambda: _rows(5))
    boxes: np.ndarray = field(default_factory=lambda: _rows(6))
    cones: np.ndarray = field(default_factory=lambda: _rows(5))

    def with_spheres(self, spheres: np.ndarray) -> "Primitives":
        """These primitives plus more spheres (the moving targets of one scan)."""
        extra = np.asarray(spheres, dtype=float).reshape(-1, 4)
        return Primitives(self.planes, np.vstack([self.spheres, extra]), self.cylinders, self.boxes, self.cones)


def primitives_from_obstacles(obstacles: Iterable[Obstacle]) -> Primitives:
    planes, spheres, cylinders, boxes, cones = [], [], [], [], []
    for o in obstacles:
        cx, cy, cz = o.center
        if o.kind == "plane":
            planes.append(cz)
        elif o.kind == "sphere":
            spheres.append((cx, cy, cz, o.radius))
        elif o.kind == "cylinder":
            cylinders.append((cx, cy, cz, o.radius, o.height))
        elif o.kind == "cone":
            cones.append((cx, cy, cz, o.radius, o.height))
        elif o.kind == "box":
            half = np.asarray(o.size, dtype=float) / 2
            boxes.append((cx - half[0], cy - half[1], cz - half[2], cx + half[0], cy + half[1], cz + half[2]))
    return Primitives(
        np.asarray(planes, dtype=float),
        np.asarray(spheres, dtype=float).reshape(-1, 4),
        np.asarray(cylinders, dtype=float).reshape(-1, 5),
        np.asarray(boxes, dtype=float).reshape(-1, 6),
        np.asarray(cones, dtype=float).reshape(-1, 5),
    )


def target_spheres(targets: Iterable[TargetTruth]) -> np.ndarray:
    """(S, 4) spheres of the targets still standing."""
    rows = [(*t.position, t.radius) for t in targets if not t.destroyed]
    return np.asarray(rows, dtype=float).reshape(-1, 4)


def beam_directions(rows: int, cols: int, vfov_deg: float, vertical_center_deg: float = 0.0) -> np.ndarray:
    """(rows, cols, 3) unit beams in the sensor frame (x forward, z up). Row 0 is the highest beam,
    rows spread evenly over the vertical field of view (ends included); column j points at azimuth
    2π·j/cols, counter-clockwise from +x."""
    half = vfov_deg / 2.0
    elevation = np.radians(np.linspace(vertical_center_deg + half, vertical_center_deg - half, rows))
    azimuth = 2.0 * np.pi * np.arange(cols) / cols
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def rotate_yaw(directions: np.ndarray, heading: float) -> np.ndarray:
    c, s = np.cos(heading), np.sin(heading)
    x, y = directions[..., 0], directions[..., 1]
    return np.stack([c * x - s * y, s * x + c * y, directions[..., 2]], axis=-1)


# ------------------------------------------------------------------ ray casting
def cast(origin: np.ndarray, directions: np.ndarray, primitives: Primitives) -> np.ndarray:
    """Distance along each unit direction (N, 3) from `origin` to the nearest surface; inf if none."""
    o = np.asarray(origin, dtype=float)
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for z in primitives.planes:
            np.minimum(best, _hit_plane(o, d, z), out=best)
        kinds = (
            (primitives.spheres, _hit_sphere, _sphere_bounds),
            (primitives.cylinders, _hit_cylinder, _upright_bounds),
            (primitives.boxes, _hit_box, _box_bounds),
            (primitives.cones, _hit_cone, _upright_bounds),
        )
        for rows, hit, bounds in kinds:
            for row in rows:
                centre, radius = bounds(row)
                idx = _rays_near(o, d, centre, radius)
                if len(idx):
                    best[idx] = np.minimum(best[idx], hit(o, d[idx], row))
    return best


def _rays_near(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays that can reach the bounding sphere: the exact test runs on these only."""
    oc = centre - o
    dist2 = float(oc @ oc)
    if dist2 <= radius * radius:
        return np.arange(len(d))
    along = _dot(d, oc)
    return np.flatnonzero((along > 0) & (dist2 - along * along <= radius * radius))


def _sphere_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    return row[:3], float(row[3]) * (1 + 1e-9) + 1e-9


def _upright_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    cx, cy, z0, r, h = row
    return np.array([cx, cy, z0 + h / 2]), float(np.hypot(r, h / 2)) * (1 + 1e-9) + 1e-9


def _box_bounds(row: np.ndarray) -> tuple[np.ndarray, float]:
    return (row[:3] + row[3:]) / 2, float(np.linalg.norm(row[3:] - row[:3])) / 2 * (1 + 1e-9) + 1e-9


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
    c = float(oc @ oc) - row[3] ** 2
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
    a = d[:, 0] ** 2 + d[:, 1] ** 2
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
    k2 = (r / h) ** 2
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


# ------------------------------------------------------------------ scanning
def scan(origin: np.ndarray, heading: float, directions: np.ndarray, primitives: Primitives,
         rng: np.random.Generator, min_range: float = 0.3, max_range: float = 50.0,
         range_noise: float = 0.01, body_radius: float = 0.4) -> np.ndarray:
    """One organised scan: float32 (rows, cols, 3) world-frame points, NaN where no return.

    `directions` are the sensor-frame beams (rows, cols, 3), yawed by `heading`. Returns closer
    than `body_radius` would come from inside the carrier's own body and count as no return.
    The noise draw is one sample per beam whether it hits or not, so the RNG stream stays in step."""
    shape = directions.shape[:-1]
    world_dirs = rotate_yaw(directions, heading).reshape(-1, 3)
    ranges = cast(origin, world_dirs, primitives)
    noise = rng.normal(0.0, range_noise, ranges.shape) if range_noise > 0 else np.zeros(ranges.shape)
    valid = (ranges >= max(min_range, body_radius)) & (ranges <= max_range)
    measured = np.where(valid, ranges + noise, 0.0)
    points = np.asarray(origin, dtype=float) + world_dirs * measured[:, None]
    points[~valid] = np.nan
    return points.astype(np.float32).reshape(*shape, 3)
