"""Scan trajectories (seed 004 §5.3, Alg. 2-3): a boustrophedon over the working area's
inner rectangle, shrunk by an offset so GPS drift does not carry the vehicle into the net.

Deviations from the seed, on purpose: the rectangle is the largest axis-aligned one inside
the (possibly non-convex) polygon rather than a hand-drawn one, the lines run along its
long side (fewer turns), and Alg. 3's corner slow-down (v/c_f) is applied to the short
cross legs and to the rounded corners, which the time parameterisation keeps inside the
rectangle (an arc stays within the corner it rounds).
"""
from __future__ import annotations

import numpy as np

from schemas.messages import ConstraintProfile
from services.lib.geometry import as_polygon, point_in_polygon
from services.planner.timing import DT, Path, fly

MAX_LINES = 10_000  # the most sweep lines planned: 10 km of area at 1 m spacing
RESUME_OFF_LINE = 1.0  # m: a vehicle this close to its first line, heading along it, resumes it where it is
RESUME_HEADING = np.cos(np.radians(30.0))  # ... heading within 30° of the line

_EPS = 1e-9


def _edges_cross_cells(polygon: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(C,) whether any polygon edge passes through the open cell [low, high] (C, 2).
    Slab clipping; an edge lying on a cell's border does not count."""
    a = polygon[None, :, :]
    d = (np.roll(polygon, -1, axis=0) - polygon)[None, :, :]
    lo, hi = low[:, None, :], high[:, None, :]
    moving = np.abs(d) > _EPS
    safe = np.where(moving, d, 1.0)
    t_a, t_b = (lo - a) / safe, (hi - a) / safe
    parallel_inside = (a > lo) & (a < hi)
    enter = np.where(moving, np.minimum(t_a, t_b), np.where(parallel_inside, -np.inf, np.inf))
    leave = np.where(moving, np.maximum(t_a, t_b), np.where(parallel_inside, np.inf, -np.inf))
    first = np.maximum(enter.max(axis=2), 0.0)
    last = np.minimum(leave.min(axis=2), 1.0)
    return np.any(last - first > _EPS, axis=1)


def inner_rectangle(area: np.ndarray, resolution: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """(low (2,), high (2,)) of the largest-area axis-aligned rectangle inside the simple
    polygon `area` (K, 2). Candidate sides are the vertex coordinates: exact for rectilinear
    polygons. Otherwise `resolution` evenly spaced coordinates per axis are added and only
    cells no edge passes through count, so the result lies inside and is within about one
    grid step of the best."""
    poly = as_polygon(area)
    step = np.roll(poly, -1, axis=0) - poly
    rectilinear = bool(np.all(np.min(np.abs(step), axis=1) <= _EPS))
    axes = []
    for k in range(2):
        candidates = poly[:, k]
        if not rectilinear:
            candidates = np.concatenate([candidates, np.linspace(poly[:, k].min(), poly[:, k].max(), resolution + 1)])
        axes.append(np.unique(candidates))
    xs, ys = axes
    gx, gy = np.meshgrid(0.5 * (xs[:-1] + xs[1:]), 0.5 * (ys[:-1] + ys[1:]))  # (ny, nx) cell centres
    inside = point_in_polygon(np.column_stack([gx.ravel(), gy.ravel()]), poly)
    if not rectilinear:
        lx, ly = np.meshgrid(xs[:-1], ys[:-1])
        hx, hy = np.meshgrid(xs[1:], ys[1:])
        low = np.column_stack([lx.ravel(), ly.ravel()])
        high = np.column_stack([hx.ravel(), hy.ravel()])
        inside &= ~_edges_cross_cells(poly, low, high)
    inside = inside.reshape(gx.shape)
    widths, heights = np.diff(xs), np.diff(ys)
    best, box = 0.0, None
    columns = np.arange(len(widths))
    for bottom in range(len(heights)):
        # Columns free from `bottom` up to each top row, then the widest free run per row.
        free = np.logical_and.accumulate(inside[bottom:], axis=0)
        filled = np.cumsum(free * widths, axis=1)
        run = filled - np.maximum.accumulate(np.where(free, 0.0, filled), axis=1)
        area_of = run * np.cumsum(heights[bottom:])[:, None]
        row, end = np.unravel_index(int(np.argmax(area_of)), area_of.shape)
        if area_of[row, end] > best:
            begin = np.max(np.where(~free[row, : end + 1], columns[: end + 1], -1)) + 1
            best, box = area_of[row, end], (begin, end, bottom, bottom + row)
    if box is None:  # degenerate polygon: collapse to its vertex mean
        centre = poly.mean(axis=0)
        return centre, centre.copy()
    begin, end, bottom, top = box
    return np.array([xs[begin], ys[bottom]]), np.array([xs[end + 1], ys[top + 1]])


def scan_rectangle(area: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the area's inner rectangle shrunk by `offset` (collapsed to its middle
    along an axis where it is narrower than 2·offset)."""
    low, high = inner_rectangle(area)
    low, high = low + offset, high - offset
    middle = 0.5 * (low + high)
    narrow = high < low
    return np.where(narrow, middle, low), np.where(narrow, middle, high)


def lawnmower_waypoints(area: np.ndarray, height: float, spacing: float, offset: float,
                        start: np.ndarray, heading: float | None = None) -> np.ndarray:
    """Boustrophedon corners (2·lines, 3) over the scan rectangle: lines along its long side,
    `spacing` apart, as few as keep every point within spacing/2 of one (centred across the
    short side), from the corner nearest `start` — or, when the vehicle is on its first line and
    `heading` along it, from where it is, the way it was going (a sweep interrupted by a stop
    manoeuvre resumes instead of flying back to the line's start)."""
    return _sweep_corners(*scan_rectangle(area, offset), height, spacing, start, heading)


def _sweep_corners(low: np.ndarray, high: np.ndarray, height: float, spacing: float, start: np.ndarray,
                   heading: float | None = None) -> np.ndarray:
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    size = high - low
    along = 0 if size[0] >= size[1] else 1
    across = 1 - along
    lines = size[across] / spacing
    if not lines <= MAX_LINES:  # NaN and inf included
        raise ValueError(f"a sweep of {lines:.3g} lines {spacing:g} m apart: more than the {MAX_LINES} planned")
    lines = max(int(np.ceil(lines - 1e-9)), 1)
    first = low[across] + 0.5 * (size[across] - (lines - 1) * spacing)
    across_at = first + spacing * np.arange(lines)
    start = np.asarray(start, dtype=np.float64).reshape(3)
    # Alg. 3: from the vehicle's position to the furthest side. Lines behind the one nearest to
    # the vehicle are left for the next sweep, which starts from the far side and comes back:
    # a re-planned scan (after every target) therefore never restarts from an old corner.
    if high[across] - start[across] < start[across] - low[across]:
        across_at = across_at[::-1]
        ahead = across_at <= start[across] + 0.5 * spacing
    else:
        ahead = across_at >= start[across] - 0.5 * spacing
    ahead[-1] = True
    across_at = across_at[np.argmax(ahead):]
    lines = len(across_at)
    begin, end = low[along], high[along]
    if abs(start[along] - end) < abs(start[along] - begin):
        begin, end = end, begin
    resume = _resume_direction(start, heading, along, across_at[0] - start[across], low, high, spacing)
    if resume:
        begin, end = (low[along], high[along]) if resume > 0 else (high[along], low[along])
    forward = np.arange(lines) % 2 == 0
    corners = np.empty((2 * lines, 3))
    corners[0::2, along] = np.where(forward, begin, end)
    corners[1::2, along] = np.where(forward, end, begin)
    corners[:, across] = np.repeat(across_at, 2)
    corners[:, 2] = height
    if resume:
        corners[0, along] = start[along]  # the first line from where the vehicle is
    return corners


def _resume_direction(start: np.ndarray, heading: float | None, along: int, off_line: float, low: np.ndarray,
                      high: np.ndarray, spacing: float) -> int:
    """+1 or -1: resume the first line from `start` in that direction along it; 0: do not."""
    if heading is None or abs(off_line) > RESUME_OFF_LINE or not low[along] <= start[along] <= high[along]:
        return 0
    direction = (np.cos(heading), np.sin(heading))[along]
    if abs(direction) < RESUME_HEADING:
        return 0
    sign = 1 if direction > 0 else -1
    ahead = high[along] - start[along] if sign > 0 else start[along] - low[along]
    return sign if ahead >= spacing / 2 else 0


def lawnmower_line(area: np.ndarray, height: float, spacing: float, offset: float, profile: ConstraintProfile,
                   start: np.ndarray, start_heading: float | None = None, corner_factor: float = 2.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sweep's polyline from `start` (M, 3) with its speed caps at each vertex (M,) and on each
    leg (M - 1,): see `lawnmower`."""
    area = as_polygon(area)
    start = np.asarray(start, dtype=np.float64).reshape(3)
    low, high = scan_rectangle(area, offset)
    corners = _sweep_corners(low, high, height, spacing, start, start_heading)
    slow = profile.max_speed / max(corner_factor, 1.0)
    outside = bool(np.any(start[:2] < low - 1e-6) or np.any(start[:2] > high + 1e-6))
    corner_speeds = np.full(len(corners) + 1, slow)
    corner_speeds[1] = 0.0 if outside else slow
    segment_speeds = np.full(len(corners), np.inf)
    segment_speeds[2::2] = slow  # the cross legs between the long lines
    return np.vstack([start, corners]), corner_speeds, segment_speeds


def lawnmower(area: np.ndarray, height: float, spacing: float, offset: float = 2.0,
              profile: ConstraintProfile | None = None, start: np.ndarray | None = None, dt: float = DT,
              start_heading: float | None = None, *, corner_factor: float = 2.0,
              start_velocity: np.ndarray | None = None) -> Path:
    """Transfer in a straight line from `start` to the scan rectangle's corner nearest to it,
    at scan height, then sweep: long legs at max_speed, cross legs and every sweep corner at
    max_speed/corner_factor (keywords after `start_heading` only; the positional order is the
    one node.py already uses).
    Coming from outside the rectangle the transfer stops at the first corner, so the rounded
    corner cannot cut outside; from inside it flows straight into the sweep."""
    profile = profile if profile is not None else ConstraintProfile()
    area = as_polygon(area)
    if start is None:
        start = np.array([area[0, 0], area[0, 1], height])
    waypoints, corner_speeds, segment_speeds = lawnmower_line(area, height, spacing, offset, profile, start,
                                                              start_heading, corner_factor)
    return fly(waypoints, profile, dt, corner_speeds=corner_speeds, segment_speeds=segment_speeds,
               start_velocity=start_velocity, start_heading=start_heading)
