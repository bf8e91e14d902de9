"""Geometry shared by the services: plane polygons (arena, working areas, scan areas), rotations and
the checks on a measurement's covariance.

Pure numpy (no scipy: see services/lib/runtime/warmup.py). Polygons are (K, 2) vertex arrays, simple
(possibly non-convex), without a repeated closing vertex (one is tolerated and dropped).
"""
from __future__ import annotations

import math

import numpy as np

GRAVITY = 9.80665  # m/s², standard gravity: the world frame is z up, gravity along −z


def heading_quaternion(heading: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a level body turned `heading` rad about the world's z (up) axis."""
    return (math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2))


def heading_quaternions(headings) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) of level bodies turned `headings` rad about z."""
    half = np.asarray(headings, dtype=np.float64).reshape(-1) / 2
    return np.stack([np.cos(half), np.zeros_like(half), np.zeros_like(half), np.sin(half)], axis=1)


def wrap_angle(angle):
    """Angles, rad, wrapped to [−π, π) (a scalar stays a numpy scalar)."""
    return (np.asarray(angle, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def yaw_of(quaternion_wxyz):
    """The heading (rad, about world z) of a (w, x, y, z) quaternion, ZYX Euler yaw: a float for
    one quaternion, (N,) for (N, 4)."""
    q = np.asarray(quaternion_wxyz, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return float(yaw) if yaw.ndim == 0 else yaw


def yaw_rotation(heading: float) -> np.ndarray:
    """The 3×3 rotation by `heading` about z (world z up)."""
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotate_yaw(vectors: np.ndarray, heading) -> np.ndarray:
    """(..., 3) vectors turned by `heading` rad about z (a level body's frame to the world's; the
    negative heading turns world vectors into the body frame). `heading` is a scalar or broadcasts
    against the vectors' leading axes, one angle per vector."""
    c, s = np.cos(heading), np.sin(heading)
    x, y = vectors[..., 0], vectors[..., 1]
    return np.stack([c * x - s * y, s * x + c * y, vectors[..., 2]], axis=-1)


def rotation_matrix(orientation_wxyz) -> np.ndarray:
    """(3, 3) rotation of a quaternion given as (w, x, y, z), the order of schemas' Pose; normalised
    first (a message's quaternion is only approximately unit); all NaN for a zero quaternion."""
    q = np.asarray(orientation_wxyz, dtype=np.float64).reshape(4)
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero quaternion gives NaN: the caller refuses it
        w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z), w >= 0, of a (3, 3) rotation matrix (Shepperd's method: the largest of the four
    squared components first, so no division by a small number)."""
    m = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = (trace, m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    sign = -1.0 if q[0] < 0 else 1.0
    return tuple(float(sign * v) for v in q)  # type: ignore[return-value]


def as_polygon(polygon: np.ndarray) -> np.ndarray:
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if len(poly) > 1 and np.array_equal(poly[0], poly[-1]):
        poly = poly[:-1]
    if len(poly) < 3:
        raise ValueError(f"a polygon needs at least 3 vertices, got {len(poly)}")
    return poly


def signed_area(polygon: np.ndarray) -> float:
    """Shoelace area: positive when the vertices run counter-clockwise."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def polygon_area(polygon: np.ndarray) -> float:
    return abs(signed_area(polygon))


def counter_clockwise(polygon: np.ndarray) -> np.ndarray:
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    return poly[::-1].copy() if signed_area(poly) < 0 else poly


def point_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray | bool:
    """Even-odd rule for (N, 2) points (a bool array) or one (2,) point (a bool).
    Points exactly on an edge may fall either way."""
    poly = as_polygon(polygon)
    pts = np.asarray(points, dtype=np.float64)
    single = pts.ndim == 1
    pts = pts.reshape(-1, 2)
    ax, ay = poly[:, 0], poly[:, 1]
    bx, by = np.roll(ax, -1), np.roll(ay, -1)
    px, py = pts[:, :1], pts[:, 1:]  # (N, 1) against (K,) edges
    straddles = (ay > py) != (by > py)
    dy = np.where(by != ay, by - ay, 1.0)  # non-straddling edges are masked out below
    x_cross = ax + (py - ay) * (bx - ax) / dy
    inside = np.count_nonzero(straddles & (px < x_cross), axis=1) % 2 == 1
    return bool(inside[0]) if single else inside


def nearest_on_edges(points: np.ndarray, polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) nearest points of the polygon's outline to (N, 2) points, and (N,) their distances."""
    poly = as_polygon(polygon)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    a, b = poly, np.roll(poly, -1, axis=0)
    edge = b - a
    length2 = np.maximum(np.sum(edge * edge, axis=1), 1e-18)
    along = np.clip(np.einsum("nkd,kd->nk", pts[:, None, :] - a[None], edge) / length2, 0.0, 1.0)
    nearest = a[None] + along[..., None] * edge[None]  # (N, K, 2)
    gaps = np.linalg.norm(pts[:, None, :] - nearest, axis=2)
    best = np.argmin(gaps, axis=1)
    rows = np.arange(len(pts))
    return nearest[rows, best], gaps[rows, best]


def distance_to_edges(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) distance of (N, 2) points to the polygon's outline (inside or out)."""
    return nearest_on_edges(points, polygon)[1]


def deepest_point(polygon: np.ndarray, step: float = 1.0) -> tuple[float, float]:
    """The grid point inside the polygon furthest from its edges (a safe spot for a default start)."""
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + step, step), np.arange(lo[1], hi[1] + step, step))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    grid = grid[point_in_polygon(grid, polygon)]
    if len(grid) == 0:
        centre = polygon.mean(axis=0)
        return float(centre[0]), float(centre[1])
    a, b = polygon, np.roll(polygon, -1, axis=0)
    ab = b - a
    t = np.clip(((grid[:, None, :] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    nearest = a + t[..., None] * ab
    clearance = np.linalg.norm(grid[:, None, :] - nearest, axis=-1).min(axis=1)
    best = grid[int(np.argmax(clearance))]
    return float(best[0]), float(best[1])


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _segments_touch(p1, p2, q1, q2, eps: float = 1e-9) -> bool:
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > eps and d2 < -eps) or (d1 < -eps and d2 > eps)) and (
        (d3 > eps and d4 < -eps) or (d3 < -eps and d4 > eps)
    ):
        return True

    def on_segment(a, b, c, d) -> bool:  # c collinear with a-b: is it within the segment's box?
        return abs(d) <= eps and min(a[0], b[0]) - eps <= c[0] <= max(a[0], b[0]) + eps and \
            min(a[1], b[1]) - eps <= c[1] <= max(a[1], b[1]) + eps

    return on_segment(q1, q2, p1, d1) or on_segment(q1, q2, p2, d2) or \
        on_segment(p1, p2, q1, d3) or on_segment(p1, p2, q2, d4)


def polygon_self_intersection(polygon: np.ndarray) -> tuple[int, int] | None:
    """Indices (i, j) of two edges that cross or overlap (edge i runs from point i to i+1), or None."""
    n = len(polygon)
    for i in range(n):
        a, b = polygon[i], polygon[(i + 1) % n]
        for j in range(i + 1, n):
            c, d = polygon[j], polygon[(j + 1) % n]
            if j == i + 1 or (i == 0 and j == n - 1):
                # Neighbours share a vertex; they only overlap when they fold back on each other.
                e1, e2 = b - a, d - c
                if abs(e1[0] * e2[1] - e1[1] * e2[0]) <= 1e-9 and float(np.dot(e1, e2)) < 0:
                    return i, j
                continue
            if _segments_touch(a, b, c, d):
                return i, j
    return None


def pairwise_gaps(points: np.ndarray) -> np.ndarray:
    """(N, N) distances between (N, 3) points, infinite on the diagonal (no point is its own neighbour)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    gaps = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    np.fill_diagonal(gaps, np.inf)
    return gaps


def is_covariance(matrix: np.ndarray) -> bool:
    """Finite, symmetric and positive semi-definite: what a detection's covariance must be to weigh it."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all() or not np.allclose(m, m.T):
        return False
    eigenvalues = np.linalg.eigvalsh(m)
    return bool(np.isfinite(eigenvalues).all() and eigenvalues.min() >= -1e-9 * max(1.0, abs(eigenvalues).max()))


def with_variance_floor(covariance: np.ndarray | None, floor: float) -> np.ndarray:
    """A measurement noise R: the (3, 3) covariance with each variance raised to at least `floor`
    (stays positive semi-definite: only the diagonal grows); floor · I when there is none."""
    if covariance is None:
        return floor * np.eye(3)
    cov = np.asarray(covariance, dtype=np.float64)
    return cov + np.diag(np.maximum(floor - np.diag(cov), 0.0))
