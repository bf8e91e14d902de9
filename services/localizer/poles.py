"""Pole features of an organised scan: the axes of free-standing upright round things (tree trunks,
poles, masts) as infinite lines, beside seed 003's planes and edges (features.py).

Why, beyond the seed: Grape's planes and edges need built structure. An outdoor arena like the
MBZIRC field has a floor, a building seen from one end only, and trees and poles elsewhere; there
the floor is every scan's only plane, and x, y and yaw are left to the IMU, which drifts metres in
ten seconds. LOAM rejects a round object's silhouette as an edge because it moves with the
viewpoint; its axis does not, and it is an infinite line: the landmark kind the graph already holds.

Per row (one beam): the returns are cut into runs at range steps (a free-standing object stands in
front of what is behind it, or of the sky). A run whose both ends step back by at least
`pole_min_step` (or into no return) is free-standing; of those:
- a narrow one (chord at most `pole_thin_width`: a pole of a few centimetres shows as one to three
  returns) gives its returns' mean as the axis point, off by at most the pole's radius;
- a wider one of at least five returns is fitted with a circle in the horizontal plane (Kåsa's
  algebraic fit), kept when the radius is at most `pole_max_radius`, the fit's RMSE at most
  `pole_max_fit_rmse` and the centre lies beyond the returns (the surface bulges toward the
  sensor, as a trunk's does and a hollow's does not): the circle's centre is the axis point.
Across rows, axis points within `pole_match` horizontally join one pole; a pole with points on at
least `pole_min_rows` rows spanning at least `pole_min_height` is a line through them (principal
axis), ranked by the points' RMSE from it. A flying drone (a thin disc a few rows tall) and a
balloon (a sphere, whose slices also centre on a vertical axis) span less than a metre.

The sensor is taken to be near level (a few degrees of tilt): the circles are fitted in the sensor's
x-y plane. Runs do not wrap across the first and last columns: an object on the seam is cut in two
and its narrower part may be missed in that scan.

Pure: numpy in, numpy out; the pass over the grid is compiled (numba, `cache=True`).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_SLICE_FIELDS = 5  # x, y, z of the axis point, the row, the fit's RMSE


@njit(cache=True)
def _circle(xs, ys):
    """Kåsa's fit: (centre x, centre y, radius, RMSE of the radial residuals); radius −1 when degenerate."""
    n = xs.size
    mx, my = xs.mean(), ys.mean()
    u, v = xs - mx, ys - my
    suu, svv, suv = (u * u).sum(), (v * v).sum(), (u * v).sum()
    suuu, svvv, suvv, svuu = (u * u * u).sum(), (v * v * v).sum(), (u * v * v).sum(), (v * u * u).sum()
    det = suu * svv - suv * suv
    if abs(det) < 1e-12:
        return 0.0, 0.0, -1.0, 0.0
    bu, bv = 0.5 * (suuu + suvv), 0.5 * (svvv + svuu)
    uc = (bu * svv - bv * suv) / det
    vc = (bv * suu - bu * suv) / det
    radius = math.sqrt(uc * uc + vc * vc + (suu + svv) / n)
    cx, cy = uc + mx, vc + my
    residual = 0.0
    for k in range(n):
        d = math.sqrt((xs[k] - cx) ** 2 + (ys[k] - cy) ** 2) - radius
        residual += d * d
    return cx, cy, radius, math.sqrt(residual / n)


@njit(cache=True)
def pole_slices(points, min_step, thin_width, max_radius, max_fit_rmse):
    """(K, 5) axis points of free-standing round runs, one per run: x, y, z, row, fit RMSE (0 for a
    thin run)."""
    rows, cols = points.shape[0], points.shape[1]
    out = np.empty((rows * cols // 2 + 1, _SLICE_FIELDS))
    count = 0
    for r in range(rows):
        c = 0
        while c < cols:
            if not np.isfinite(points[r, c, 0]):
                c += 1
                continue
            start = c
            previous = math.sqrt(points[r, c, 0] ** 2 + points[r, c, 1] ** 2 + points[r, c, 2] ** 2)
            c += 1
            while c < cols and np.isfinite(points[r, c, 0]):
                rng = math.sqrt(points[r, c, 0] ** 2 + points[r, c, 1] ** 2 + points[r, c, 2] ** 2)
                if abs(rng - previous) >= min_step:
                    break
                previous = rng
                c += 1
            end = c  # the run is [start, end)
            first = math.sqrt(points[r, start, 0] ** 2 + points[r, start, 1] ** 2 + points[r, start, 2] ** 2)
            # stands in front of both neighbours (or of no return); never at the grid's edge
            if start == 0 or end == cols:
                continue
            left_ok = not np.isfinite(points[r, start - 1, 0]) or \
                math.sqrt(points[r, start - 1, 0] ** 2 + points[r, start - 1, 1] ** 2 + points[r, start - 1, 2] ** 2) \
                >= first + min_step
            right_ok = not np.isfinite(points[r, end, 0]) or \
                math.sqrt(points[r, end, 0] ** 2 + points[r, end, 1] ** 2 + points[r, end, 2] ** 2) >= previous + min_step
            if not (left_ok and right_ok):
                continue
            xs = points[r, start:end, 0].copy()
            ys = points[r, start:end, 1].copy()
            zs = points[r, start:end, 2]
            chord = math.sqrt((xs[-1] - xs[0]) ** 2 + (ys[-1] - ys[0]) ** 2)
            if chord <= thin_width:
                out[count, 0], out[count, 1], out[count, 2] = xs.mean(), ys.mean(), zs.mean()
                out[count, 3], out[count, 4] = r, 0.0
                count += 1
            elif end - start >= 5:
                cx, cy, radius, rmse = _circle(xs, ys)
                if 0.0 < radius <= max_radius and rmse <= max_fit_rmse and \
                        cx * cx + cy * cy > xs.mean() ** 2 + ys.mean() ** 2:
                    out[count, 0], out[count, 1], out[count, 2] = cx, cy, zs.mean()
                    out[count, 3], out[count, 4] = r, rmse
                    count += 1
    return out[:count]


def group_poles(slices: np.ndarray, match: float, min_rows: int, min_height: float
                ) -> list[tuple[np.ndarray, np.ndarray, float, int]]:
    """Axis points joined across rows into poles: (centre (3,), direction (3,) unit with z ≥ 0,
    RMSE of the points from the line, rows) per pole, the points within `match` of a pole's running
    mean joining it (nearest first)."""
    groups: list[list[int]] = []
    means: list[np.ndarray] = []
    for k in np.argsort(slices[:, 3], kind="stable"):  # row by row
        xy = slices[k, :2]
        if means:
            gaps = np.linalg.norm(np.array(means) - xy, axis=1)
            g = int(np.argmin(gaps))
            if gaps[g] <= match:
                groups[g].append(int(k))
                means[g] = slices[groups[g], :2].mean(axis=0)
                continue
        groups.append([int(k)])
        means.append(xy.copy())
    poles = []
    for members in groups:
        rows = np.unique(slices[members, 3])
        axis_points = slices[members, :3]
        if len(rows) < min_rows or np.ptp(axis_points[:, 2]) < min_height:
            continue
        centre = axis_points.mean(axis=0)
        _, _, vt = np.linalg.svd(axis_points - centre, full_matrices=False)
        direction = vt[0] if vt[0][2] >= 0 else -vt[0]
        offsets = axis_points - centre
        across = offsets - np.outer(offsets @ direction, direction)
        rmse = float(np.sqrt((across ** 2).sum(axis=1).mean()))
        poles.append((centre, direction, rmse, len(rows)))
    return poles
