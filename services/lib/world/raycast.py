"""The compiled ray caster: numba kernels over a packed primitive table.

Same geometry, same expressions in the same order as the numpy reference (numpy_caster.py),
one ray at a time: for each ray every primitive whose bounding sphere the ray can reach gets
its exact test (planes have no bound). `error_model="numpy"` keeps IEEE division (x/0 = ±inf,
0/0 = NaN) exactly as numpy computes it, and fastmath stays off so nothing is reordered.
Single-threaded on purpose: the machine has 2 cores for 3 UAVs' worth of services. The per-ray
helpers are inlined (numba `inline="always"`): called, each passed the primitive table as an
array and paid its set-up per primitive per ray, which was most of a scan (OS0-128 × 1024 on
mbzirc: 8.8 → 3.0 ms for the kernel, the same bits). The loop over the primitives, though, is
written out in each kernel (cast_kernel, scan_kernel, the camera's render_kernel) with the plane
tested before the bounding-sphere test: as an inlined helper returning (range, index) it made a
camera frame's cast 2-3.7× slower (3.3 against 7.1-12.2 ms on mbzirc, benchmarks/README.md), for
the same bits.

Packed table (`Packed`), one row per primitive, in the order planes, spheres, cylinders,
boxes, cones (the reference's order, so ties resolve alike):
  kinds  int64 (P,)     PLANE, SPHERE, CYLINDER, BOX, CONE
  params float64 (P, 6) plane: z; sphere: cx, cy, cz, r; cylinder: cx, cy, z0, r, h;
                        box: x_min, y_min, z_min, x_max, y_max, z_max; cone: cx, cy, z0, r, h, (r/h)²
  bounds float64 (P, 4) bounding sphere cx, cy, cz, radius (unused for planes)
  ids    int32 (P,)     0 static world, k >= 1 target k
  reflectivity float64 (P,)
  colors uint8 (P, 3)   sRGB, for the simulated camera (services/camera)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

PLANE, SPHERE, CYLINDER, BOX, CONE = 0, 1, 2, 3, 4
EPS = 1e-9  # as numpy_caster.EPS
INF = np.inf


@dataclass(frozen=True)
class Packed:
    kinds: np.ndarray
    params: np.ndarray
    bounds: np.ndarray
    ids: np.ndarray
    reflectivity: np.ndarray
    colors: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.kinds)


# ------------------------------------------------------------------ exact hits (scalars)
@njit(cache=True, error_model="numpy", inline="always")
def ahead(t):
    """A range along the ray, INF if it is behind the origin (or at it)."""
    return t if t > EPS else INF


@njit(cache=True, error_model="numpy", inline="always")
def _fmin(a, b):  # np.fmin: a NaN operand is skipped
    if a != a:
        return b
    if b != b:
        return a
    return a if a < b else b


@njit(cache=True, error_model="numpy", inline="always")
def _fmax(a, b):
    if a != a:
        return b
    if b != b:
        return a
    return a if a > b else b


@njit(cache=True, error_model="numpy", inline="always")
def _disk(ox, oy, oz, dx, dy, dz, cx, cy, z, r):
    t = ahead((z - oz) / dz)
    x = ox + t * dx - cx
    y = oy + t * dy - cy
    return t if x * x + y * y <= r * r else INF


@njit(cache=True, error_model="numpy", inline="always")
def _in_height(t, oz, dz, z0, h):
    z = oz + t * dz
    return t if (z >= z0) and (z <= z0 + h) else INF


@njit(cache=True, error_model="numpy", inline="always")
def hit_range(kind, table, q, ox, oy, oz, dx, dy, dz):
    """The exact range from o along unit d to primitive q of the packed table (kind its kind), INF if none."""
    if kind == PLANE:
        return ahead((table[q, 0] - oz) / dz)
    p = table[q]
    if kind == SPHERE:
        ocx, ocy, ocz = ox - p[0], oy - p[1], oz - p[2]
        b = dx * ocx + dy * ocy + dz * ocz
        c = (ocx * ocx + ocy * ocy + ocz * ocz) - p[3] * p[3]
        disc = b * b - c
        if not disc >= 0.0:
            return INF
        root = math.sqrt(disc)
        return min(ahead(-b - root), ahead(-b + root))
    if kind == CYLINDER:
        cx, cy, z0, r, h = p[0], p[1], p[2], p[3], p[4]
        px, py = ox - cx, oy - cy
        a = dx * dx + dy * dy
        b = px * dx + py * dy
        c = px * px + py * py - r * r
        root = math.sqrt(b * b - a * c) if b * b - a * c >= 0.0 else np.nan
        best = min(_in_height(ahead((-b - root) / a), oz, dz, z0, h), _in_height(ahead((-b + root) / a), oz, dz, z0, h))
        best = min(best, _disk(ox, oy, oz, dx, dy, dz, cx, cy, z0 + h, r))
        return min(best, _disk(ox, oy, oz, dx, dy, dz, cx, cy, z0, r))
    if kind == BOX:
        t_near = np.nan  # as fmax/fmin.reduce over the axes: NaNs skipped
        t_far = np.nan
        for k in range(3):
            o = ox if k == 0 else (oy if k == 1 else oz)
            d = dx if k == 0 else (dy if k == 1 else dz)
            t1 = (p[k] - o) / d
            t2 = (p[k + 3] - o) / d
            t_near = _fmax(t_near, _fmin(t1, t2))
            t_far = _fmin(t_far, _fmax(t1, t2))
        if (t_near <= t_far) and (t_far > EPS):
            return t_near if t_near > EPS else t_far
        return INF
    # CONE: (x-cx)² + (y-cy)² = (k·(apex_z - z))², k = r/h, for z in [z0, apex].
    cx, cy, z0, r, h, k2 = p[0], p[1], p[2], p[3], p[4], p[5]
    px, py, pz = ox - cx, oy - cy, (z0 + h) - oz
    a = dx * dx + dy * dy - k2 * dz * dz
    b = px * dx + py * dy + k2 * pz * dz
    c = px * px + py * py - k2 * pz * pz
    root = math.sqrt(b * b - a * c) if b * b - a * c >= 0.0 else np.nan
    best = min(_in_height(ahead((-b - root) / a), oz, dz, z0, h), _in_height(ahead((-b + root) / a), oz, dz, z0, h))
    if abs(a) < 1e-12:  # parallel to the side: the quadratic degenerates to 2bt + c = 0
        best = min(best, _in_height(ahead(-c / (2 * b)), oz, dz, z0, h))
    return min(best, _disk(ox, oy, oz, dx, dy, dz, cx, cy, z0, r))


@njit(cache=True, error_model="numpy")
def cull_setup(ox, oy, oz, kinds, bounds):
    """Per primitive: centre - origin and the least d·(centre - origin) of a ray that reaches
    its bounding sphere (-inf: every ray, for planes and when the origin is inside)."""
    cull = np.empty((len(kinds), 4))
    for q in range(len(kinds)):
        cx, cy, cz = bounds[q, 0] - ox, bounds[q, 1] - oy, bounds[q, 2] - oz
        dist2 = cx * cx + cy * cy + cz * cz
        radius2 = bounds[q, 3] * bounds[q, 3]
        cull[q, 0], cull[q, 1], cull[q, 2] = cx, cy, cz
        if kinds[q] == PLANE or dist2 <= radius2:
            cull[q, 3] = -INF
        else:
            cull[q, 3] = math.sqrt(dist2 - radius2) * (1.0 - 1e-12)
    return cull


@njit(cache=True, error_model="numpy")
def cast_kernel(origin, dirs, kinds, params, bounds, ranges, hit_index):
    """ranges[i], hit_index[i] for every unit direction dirs[i] (world frame) from `origin`."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    cull = cull_setup(ox, oy, oz, kinds, bounds)
    for i in range(len(dirs)):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best, best_p = INF, -1  # the nearest hit over every primitive: written out, see the module's note
        for q in range(len(kinds)):
            if kinds[q] == PLANE:
                t = ahead((params[q, 0] - oz) / dz)
            elif dx * cull[q, 0] + dy * cull[q, 1] + dz * cull[q, 2] < cull[q, 3]:
                continue  # the ray cannot reach its bounding sphere
            else:
                t = hit_range(kinds[q], params, q, ox, oy, oz, dx, dy, dz)
            if t < best:
                best, best_p = t, q
        ranges[i], hit_index[i] = best, best_p


# ------------------------------------------------------------------ a whole scan
@njit(cache=True, error_model="numpy", inline="always")
def outward_normal(kind, table, q, hx, hy, hz):
    """Unit outward normal at hit point h on primitive q of the packed table; the plane's points
    up. Caps and box faces are told apart by the nearest face."""
    if kind == PLANE:
        return 0.0, 0.0, 1.0
    p = table[q]
    if kind == SPHERE:
        nx, ny, nz = hx - p[0], hy - p[1], hz - p[2]
    elif kind == BOX:
        nx, ny, nz, gap = 0.0, 0.0, 0.0, INF
        for k in range(3):
            h = hx if k == 0 else (hy if k == 1 else hz)
            for side in range(2):
                g = abs(h - p[k + 3 * side])
                if g < gap:
                    gap = g
                    sign = 1.0 if side == 1 else -1.0
                    nx, ny, nz = (sign if k == 0 else 0.0), (sign if k == 1 else 0.0), (sign if k == 2 else 0.0)
    else:  # upright cylinder or cone: a cap, or the side
        cx, cy, z0, r, h = p[0], p[1], p[2], p[3], p[4]
        top = z0 + h
        rho = math.sqrt((hx - cx) ** 2 + (hy - cy) ** 2)
        if abs(hz - z0) < 1e-6:
            nx, ny, nz = 0.0, 0.0, -1.0
        elif kind == CYLINDER and abs(hz - top) < 1e-6:
            nx, ny, nz = 0.0, 0.0, 1.0
        elif kind == CYLINDER:
            nx, ny, nz = hx - cx, hy - cy, 0.0
        else:
            nx, ny, nz = hx - cx, hy - cy, rho * r / h
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if norm == 0.0:
        return 0.0, 0.0, 1.0
    return nx / norm, ny / norm, nz / norm


@njit(cache=True, error_model="numpy", inline="always")
def _normal_cos(kind, table, q, hx, hy, hz, dx, dy, dz):
    """|cos| of the incidence angle at hit point h on primitive q."""
    nx, ny, nz = outward_normal(kind, table, q, hx, hy, hz)
    return abs(nx * dx + ny * dy + nz * dz)


@njit(cache=True, error_model="numpy")
def scan_kernel(true_origin, true_rotation, believed_origin, believed_rotation, sensor_dirs, noise,
                kinds, params, bounds, ids, reflectivity, min_range, max_range, body, has_body,
                intensity_range, points, hits, intensity):
    """One scan. Rays leave from the sensor's true pose; points are placed from the believed
    pose (the pose error shows up in the cloud as it would on a real UAV). Writes float32
    points (N, 3) (NaN: no return), int32 hit ids (-1: no return) and float32 intensity."""
    ox, oy, oz = true_origin[0], true_origin[1], true_origin[2]
    cull = cull_setup(ox, oy, oz, kinds, bounds)
    R, B = true_rotation, believed_rotation
    for i in range(len(sensor_dirs)):
        sx, sy, sz = sensor_dirs[i, 0], sensor_dirs[i, 1], sensor_dirs[i, 2]
        dx = R[0, 0] * sx + R[0, 1] * sy + R[0, 2] * sz
        dy = R[1, 0] * sx + R[1, 1] * sy + R[1, 2] * sz
        dz = R[2, 0] * sx + R[2, 1] * sy + R[2, 2] * sz
        t, q = INF, -1  # the nearest hit over every primitive: written out, see the module's note
        for p in range(len(kinds)):
            if kinds[p] == PLANE:
                t_p = ahead((params[p, 0] - oz) / dz)
            elif dx * cull[p, 0] + dy * cull[p, 1] + dz * cull[p, 2] < cull[p, 3]:
                continue  # the ray cannot reach its bounding sphere
            else:
                t_p = hit_range(kinds[p], params, p, ox, oy, oz, dx, dy, dz)
            if t_p < t:
                t, q = t_p, p
        valid = (t >= min_range) and (t <= max_range)
        if valid and has_body and _hits_body(sx, sy, sz, t, body):
            valid = False
        if not valid:
            points[i, 0] = points[i, 1] = points[i, 2] = np.nan
            hits[i] = -1
            intensity[i] = np.nan
            continue
        measured = t + noise[i]
        bx = B[0, 0] * sx + B[0, 1] * sy + B[0, 2] * sz
        by = B[1, 0] * sx + B[1, 1] * sy + B[1, 2] * sz
        bz = B[2, 0] * sx + B[2, 1] * sy + B[2, 2] * sz
        points[i, 0] = believed_origin[0] + bx * measured
        points[i, 1] = believed_origin[1] + by * measured
        points[i, 2] = believed_origin[2] + bz * measured
        hits[i] = ids[q]
        if intensity_range > 0.0:
            cos = _normal_cos(kinds[q], params, q, ox + t * dx, oy + t * dy, oz + t * dz, dx, dy, dz)
            falloff = min(1.0, (intensity_range / t) ** 2)
            intensity[i] = reflectivity[q] * cos * falloff
        else:
            intensity[i] = np.nan


@njit(cache=True, error_model="numpy", inline="always")
def _hits_body(sx, sy, sz, t, body):
    """Whether the return at range t along sensor-frame direction s comes from the carrier:
    the ray enters the body box before t, or (sensor inside the box) t is within the box."""
    t_near, t_far = -INF, INF
    for k in range(3):
        s = sx if k == 0 else (sy if k == 1 else sz)
        lo, hi = body[k], body[k + 3]
        if s == 0.0:
            if lo > 0.0 or hi < 0.0:
                return False
            continue
        t1, t2 = lo / s, hi / s
        t_near = max(t_near, min(t1, t2))
        t_far = min(t_far, max(t1, t2))
    if t_near > t_far or t_far <= 0.0:
        return False
    if t_near > 0.0:  # a solid body in front of the sensor
        return t_near < t
    return t <= t_far  # the sensor sits inside the box: crop what lies within it
