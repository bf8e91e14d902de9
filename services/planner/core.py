"""Trajectory generation (seed 004, ch. 5) — FIRST VERSION.

Every trajectory is a polyline flown segment by segment, each with a trapezoidal (or,
when too short to reach cruise speed, triangular) speed profile that starts and ends at
rest, sampled every `dt` seconds as positions (N, 3) and headings (N,). Where the heading
changes at a corner the vehicle waits there and yaws at `max_heading_rate`, so every
sample respects the whole constraint profile: speed, vertical speed, acceleration and
heading rate.

Later issues deepen it: the lawnmower over the arena's inner rectangle clipped to the
polygon (§5.3, Alg. 2–3, pointInArena) with a corner slow-down factor instead of full
stops, approach with deadband and attack with overshoot and height offsets (§5.1–5.2),
interception of moving targets, and starting from the vehicle's current velocity.
"""
from __future__ import annotations

import numpy as np

from schemas.messages import ConstraintProfile

DT = 0.1
_EPS = 1e-9

Path = tuple[np.ndarray, np.ndarray]  # positions (N, 3), headings (N,)


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def _segments(waypoints: np.ndarray, profile: ConstraintProfile, start_heading: float | None) -> dict:
    """Per-segment timing of a waypoint list (zero-length segments dropped)."""
    wp = np.asarray(waypoints, dtype=np.float64).reshape(-1, 3)
    if len(wp) == 0:
        raise ValueError("a path needs at least one waypoint")
    steps = np.linalg.norm(np.diff(wp, axis=0), axis=1)
    wp = wp[np.concatenate([[True], steps > _EPS])]
    d = np.diff(wp, axis=0)
    length = np.linalg.norm(d, axis=1)
    unit = d / np.where(length > 0, length, 1.0)[:, None]
    # Speed along the segment is capped by the total and by the vertical limit.
    vertical = np.abs(unit[:, 2])
    v_limit = np.minimum(profile.max_speed,
                         np.where(vertical > _EPS, profile.max_vertical_speed / np.maximum(vertical, _EPS), np.inf))
    acc = profile.max_acceleration
    t_acc = np.minimum(v_limit / acc, np.sqrt(length / acc))
    v_peak = acc * t_acc
    t_cruise = (length - acc * t_acc**2) / np.where(v_peak > 0, v_peak, 1.0)
    t_move = 2.0 * t_acc + np.maximum(t_cruise, 0.0)

    # Heading along the horizontal direction of travel; vertical segments keep the previous one.
    horizontal = np.linalg.norm(unit[:, :2], axis=1) > 1e-6
    travel = np.arctan2(unit[:, 1], unit[:, 0])
    last_valid = np.maximum.accumulate(np.where(horizontal, np.arange(len(d)), -1)) if len(d) else np.zeros(0, int)
    initial = start_heading if start_heading is not None else (travel[horizontal][0] if horizontal.any() else 0.0)
    heading = np.where(last_valid >= 0, travel[np.maximum(last_valid, 0)], initial)
    previous = np.concatenate([[initial], heading[:-1]])
    turn = wrap_angle(heading - previous)
    rate = profile.max_heading_rate
    t_turn = np.abs(turn) / rate if rate > 0 else np.zeros_like(turn)
    t_segment = t_turn + t_move
    return dict(wp=wp, length=length, unit=unit, acc=acc, t_acc=t_acc, v_peak=v_peak, t_move=t_move,
                heading=heading, previous=previous, turn=turn, t_turn=t_turn,
                start=np.concatenate([[0.0], np.cumsum(t_segment)[:-1]]), total=float(t_segment.sum()),
                initial=float(initial))


def path_duration(waypoints: np.ndarray, profile: ConstraintProfile, start_heading: float | None = None) -> float:
    """Exact flight time of sample_path's continuous profile (before rounding to dt)."""
    return _segments(waypoints, profile, start_heading)["total"]


def sample_path(
    waypoints: np.ndarray, profile: ConstraintProfile, dt: float = DT, start_heading: float | None = None
) -> Path:
    """Fly the polyline through `waypoints` (M, 3), stopping at every waypoint; sample i is
    the state at i·dt, the last sample is the final waypoint."""
    seg = _segments(waypoints, profile, start_heading)
    wp = seg["wp"]
    if len(wp) == 1:
        return wp.copy(), np.array([wrap_angle(seg["initial"])], dtype=np.float64)
    total = seg["total"]
    count = int(np.ceil(total / dt - 1e-9)) + 1
    t = np.minimum(np.arange(count) * dt, total)
    j = np.clip(np.searchsorted(seg["start"], t, side="right") - 1, 0, len(wp) - 2)
    tau = t - seg["start"][j]
    t_turn, t_acc, t_move = seg["t_turn"][j], seg["t_acc"][j], seg["t_move"][j]
    v_peak, length, acc = seg["v_peak"][j], seg["length"][j], seg["acc"]
    tm = np.clip(tau - t_turn, 0.0, t_move)
    t_end = t_move - tm
    s = np.where(tm < t_acc, 0.5 * acc * tm**2,
                 np.where(t_end < t_acc, length - 0.5 * acc * t_end**2, 0.5 * acc * t_acc**2 + v_peak * (tm - t_acc)))
    positions = wp[j] + seg["unit"][j] * s[:, None]
    turning = tau < t_turn
    fraction = np.where(turning, tau / np.where(t_turn > 0, t_turn, 1.0), 1.0)
    headings = wrap_angle(seg["previous"][j] + seg["turn"][j] * fraction)
    return positions, np.asarray(headings, dtype=np.float64)


def hover(position: np.ndarray, heading: float = 0.0) -> Path:
    return np.asarray(position, dtype=np.float64).reshape(1, 3).copy(), np.array([wrap_angle(heading)], dtype=np.float64)


def takeoff(start: np.ndarray, height: float, profile: ConstraintProfile, dt: float = DT,
            heading: float = 0.0) -> Path:
    """Vertical climb to world z = height."""
    start = np.asarray(start, dtype=np.float64).reshape(3)
    return sample_path(np.stack([start, [start[0], start[1], height]]), profile, dt, heading)


def land(start: np.ndarray, ground_z: float, profile: ConstraintProfile, dt: float = DT,
         heading: float = 0.0) -> Path:
    """Vertical descent to world z = ground_z."""
    return takeoff(start, ground_z, profile, dt, heading)


def goto(start: np.ndarray, target: np.ndarray, profile: ConstraintProfile, dt: float = DT,
         heading: float | None = None) -> Path:
    """Straight line to `target` (first version of approach/attack)."""
    return sample_path(np.stack([np.asarray(start, float).reshape(3), np.asarray(target, float).reshape(3)]),
                       profile, dt, heading)


def scan_rectangle(area: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) corners of the area's bounding box shrunk by `offset` (collapsed to
    its middle where the box is narrower than 2·offset)."""
    area = np.asarray(area, dtype=np.float64).reshape(-1, 2)
    low, high = area.min(axis=0) + offset, area.max(axis=0) - offset
    middle = 0.5 * (low + high)
    narrow = high < low
    return np.where(narrow, middle, low), np.where(narrow, middle, high)


def lawnmower_waypoints(area: np.ndarray, height: float, spacing: float, offset: float,
                        start: np.ndarray) -> np.ndarray:
    """Boustrophedon corners (2·lines, 3) over the offset rectangle: lines along its long
    side, `spacing` apart and centred across the short side, from the corner nearest `start`."""
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    low, high = scan_rectangle(area, offset)
    size = high - low
    along = 0 if size[0] >= size[1] else 1
    across = 1 - along
    lines = int(np.floor(size[across] / spacing + 1e-9)) + 1
    first = low[across] + 0.5 * (size[across] - (lines - 1) * spacing)
    across_at = first + spacing * np.arange(lines)
    start = np.asarray(start, dtype=np.float64).reshape(3)
    if abs(start[across] - across_at[-1]) < abs(start[across] - across_at[0]):
        across_at = across_at[::-1]
    begin, end = low[along], high[along]
    if abs(start[along] - end) < abs(start[along] - begin):
        begin, end = end, begin
    forward = np.arange(lines) % 2 == 0
    corners = np.empty((2 * lines, 3))
    corners[0::2, along] = np.where(forward, begin, end)
    corners[1::2, along] = np.where(forward, end, begin)
    corners[:, across] = np.repeat(across_at, 2)
    corners[:, 2] = height
    return corners


def lawnmower(area: np.ndarray, height: float, spacing: float, offset: float = 2.0,
              profile: ConstraintProfile | None = None, start: np.ndarray | None = None,
              dt: float = DT, start_heading: float | None = None) -> Path:
    """Transfer from `start` to the nearest corner at scan height, then sweep the lines."""
    profile = profile if profile is not None else ConstraintProfile()
    area = np.asarray(area, dtype=np.float64).reshape(-1, 2)
    if start is None:
        start = np.array([area[0, 0], area[0, 1], height])
    start = np.asarray(start, dtype=np.float64).reshape(3)
    corners = lawnmower_waypoints(area, height, spacing, offset, start)
    return sample_path(np.vstack([start, corners]), profile, dt, start_heading)
