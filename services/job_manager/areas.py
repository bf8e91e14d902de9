"""Polygon geometry for the job manager: area, point-in-polygon, and the split of the
arena into equal-area working areas, one per UAV (seed 004, §3.5.4).

Pure numpy. Polygons are (K, 2) vertex arrays, simple (possibly non-convex), without
a repeated closing vertex (one is tolerated and dropped).
"""
from __future__ import annotations

import numpy as np

from services.lib.geometry import as_polygon, counter_clockwise, polygon_area

_BISECTION_STEPS = 100


def clip_x(polygon: np.ndarray, cut: float, keep_left: bool = True) -> np.ndarray:
    """Sutherland–Hodgman clip against the half-plane x <= cut (or x >= cut).

    A non-convex polygon cut into several pieces comes back as one polygon whose pieces
    are joined by zero-width bridges along x = cut; its area is still exact. Returns an
    empty (0, 2) array when nothing is left."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if len(poly) == 0:
        return poly
    outside_by = poly[:, 0] - cut if keep_left else cut - poly[:, 0]
    inside = outside_by <= 0.0
    nxt = np.roll(poly, -1, axis=0)
    outside_next = np.roll(outside_by, -1)
    inside_next = np.roll(inside, -1)
    crosses = inside != inside_next
    denom = np.where(crosses, outside_by - outside_next, 1.0)
    t = np.where(crosses, outside_by / denom, 0.0)
    crossing = poly + t[:, None] * (nxt - poly)
    crossing[crosses, 0] = cut  # exactly on the line, whatever the rounding
    # Per edge p→q the algorithm emits [crossing if it crosses] then [q if q is inside].
    candidates = np.stack([crossing, nxt], axis=1)  # (K, 2 slots, 2)
    emit = np.stack([crosses, inside_next], axis=1)
    return _drop_repeats(candidates[emit])


def _drop_repeats(poly: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    if len(poly) < 2:
        return poly
    step = np.abs(poly - np.roll(poly, 1, axis=0)).max(axis=1)
    keep = step > tol
    if not keep.any():
        return poly[:1]
    return poly[keep]


def _left_area(poly: np.ndarray, cut: float) -> float:
    return polygon_area(clip_x(poly, cut, keep_left=True))


def equal_area_cuts(polygon: np.ndarray, parts: int) -> np.ndarray:
    """The parts−1 vertical lines x = c that split the polygon into equal areas, found by
    bisection on the (monotone) area left of the line."""
    poly = as_polygon(polygon)
    if parts < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    total = polygon_area(poly)
    x_min, x_max = float(poly[:, 0].min()), float(poly[:, 0].max())
    tol = 1e-10 * max(x_max - x_min, 1.0)
    cuts = np.empty(parts - 1)
    lo_start = x_min
    for k in range(1, parts):
        target = total * k / parts
        lo, hi = lo_start, x_max  # cuts increase with k, so the previous one bounds this one
        for _ in range(_BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            if _left_area(poly, mid) < target:
                lo = mid
            else:
                hi = mid
            if hi - lo <= tol:
                break
        cuts[k - 1] = 0.5 * (lo + hi)
        lo_start = cuts[k - 1]
    return cuts


def split_area(polygon: np.ndarray, parts: int) -> list[np.ndarray]:
    """Split a simple polygon into `parts` pieces of equal area by vertical cuts,
    ordered by x (west to east), each counter-clockwise."""
    poly = as_polygon(polygon)
    cuts = equal_area_cuts(poly, parts)
    pieces = []
    remainder = poly
    for cut in cuts:
        pieces.append(counter_clockwise(clip_x(remainder, cut, keep_left=True)))
        remainder = clip_x(remainder, cut, keep_left=False)
    pieces.append(counter_clockwise(remainder))
    return pieces


def grown_part(before: np.ndarray, after: np.ndarray, min_area: float = 1.0) -> np.ndarray | None:
    """The largest piece of the working area `after` beyond the x-range of `before` (working areas
    are x-strips of one arena: split_area), or None when it did not grow by at least `min_area` m²:
    the part a UAV took over from a fallen partner."""
    before, after = as_polygon(before), as_polygon(after)
    low, high = float(before[:, 0].min()), float(before[:, 0].max())
    pieces = [clip_x(after, low, keep_left=True), clip_x(after, high, keep_left=False)]
    pieces = [counter_clockwise(piece) for piece in pieces if len(piece) >= 3 and polygon_area(piece) >= min_area]
    return max(pieces, key=polygon_area) if pieces else None
