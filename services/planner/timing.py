"""Time parameterisation of a polyline under a ConstraintProfile (seed 004 ch. 5, common rules).

A polyline is flown as straight pieces joined by circular arcs at its interior waypoints.
Each arc is flown at constant speed v with radius r >= v²/a_max (and >= v/ω when the heading
follows travel), so its centripetal acceleration never adds to the along-path one; the
straight pieces carry trapezoid (or triangle) speed profiles between the junction speeds
found by the classic forward/backward pass. The continuous trajectory therefore has a
continuous velocity and |acceleration| <= a_max everywhere, which is what makes the sampled
first and second differences respect the profile too (a second difference is an average of
the continuous acceleration).

Default corner rule: an interior waypoint whose turn exceeds `STOP_ANGLE` (120°) is a stop
(speed 0, sharp corner); any other corner is rounded at the highest speed its limits allow
(segment speed caps, vertical speed over the arc, a_max and ω against the radius, the room
left on the adjacent segments: at most half of each, and an optional deviation bound).

Headings never hold the vehicle back: they are slewed towards the desired value at
max_heading_rate while it translates; only when the path has ended at rest and the heading
is still off are a few samples appended at the final position to finish the turn.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.messages import ConstraintProfile
from services.lib.geometry import wrap_angle

DT = 0.1
STOP_ANGLE = 2.0 * np.pi / 3.0
# The longest trajectory planned (a mission lasts minutes): a command asking for more (a target
# thousands of kilometres away, limits near zero) is refused before its samples are made.
MAX_DURATION = 3600.0  # s
_EPS = 1e-9

Path = tuple[np.ndarray, np.ndarray]  # positions (N, 3), headings (N,)


def speed_caps(unit: np.ndarray, profile: ConstraintProfile) -> np.ndarray:
    """Highest speed along each unit direction (..., 3): total and vertical limits."""
    vertical = np.abs(np.asarray(unit)[..., 2])
    return np.minimum(profile.max_speed, profile.max_vertical_speed / np.maximum(vertical, _EPS))


def trapezoid(length, v_in, v_out, v_cap, acc):
    """(peak, t_up, t_cruise, t_down) of the fastest accelerate-cruise-decelerate profile
    over `length` between the given end speeds (which the caller keeps mutually reachable)."""
    peak = np.minimum(v_cap, np.sqrt(acc * length + 0.5 * (v_in**2 + v_out**2)))
    peak = np.maximum(peak, np.maximum(v_in, v_out))  # rounding must not undercut an end speed
    t_up, t_down = (peak - v_in) / acc, (peak - v_out) / acc
    cruise = np.maximum(length - (2.0 * peak**2 - v_in**2 - v_out**2) / (2.0 * acc), 0.0)
    t_cruise = np.where(peak > _EPS, cruise / np.maximum(peak, _EPS), 0.0)
    return peak, t_up, t_cruise, t_down


@dataclass(frozen=True)
class Timing:
    """Pieces (P,) of a timed path: straight (radius 0) or arc; `begin` their start times."""

    start: np.ndarray  # (P, 3)
    unit: np.ndarray  # (P, 3) tangent at the piece's start
    normal: np.ndarray  # (P, 3) towards an arc's centre (zero for straight pieces)
    radius: np.ndarray
    length: np.ndarray
    v_in: np.ndarray
    v_out: np.ndarray
    peak: np.ndarray
    t_up: np.ndarray
    t_cruise: np.ndarray
    t_down: np.ndarray
    begin: np.ndarray
    duration: float
    acc: float


def _clean(waypoints, corner_speeds, segment_speeds):
    """Drop repeated waypoints; a dropped waypoint's corner cap merges into the one kept."""
    wp = np.asarray(waypoints, dtype=np.float64).reshape(-1, 3)
    if len(wp) == 0:
        raise ValueError("a path needs at least one waypoint")
    m = len(wp)
    corners = np.full(m, np.inf) if corner_speeds is None else np.asarray(corner_speeds, float).reshape(m)
    segments = np.full(m - 1, np.inf) if segment_speeds is None else np.asarray(segment_speeds, float).reshape(m - 1)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(wp, axis=0), axis=1) > _EPS])
    merged = np.full(int(keep.sum()), np.inf)
    np.minimum.at(merged, np.cumsum(keep) - 1, corners)
    return wp[keep], merged, segments[keep[1:]]


def _arc_vertical_peak(u_in: np.ndarray, normal: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Largest |z| of the tangent cos(φ)·u_in + sin(φ)·n over φ in [0, θ]: an arc can be
    steeper in the middle than at either end."""
    a, b = u_in[:, 2], normal[:, 2]
    ends = np.maximum(np.abs(a), np.abs(a * np.cos(theta) + b * np.sin(theta)))
    extremum = np.arctan2(b, a) % np.pi
    return np.where(extremum <= theta, np.hypot(a, b), ends)


@dataclass(frozen=True)
class _Corners:
    """The interior waypoints of a polyline as plan_timing rounds them: each with the unit
    directions in and out, how far it turns (theta, 0 where it does not bend), the arc's unit normal,
    whether the vehicle stops there instead, and whether the heading turns with it."""

    u_in: np.ndarray  # (M-2, 3)
    normal: np.ndarray  # (M-2, 3)
    theta: np.ndarray  # (M-2,)
    bending: np.ndarray  # (M-2,) bool
    stop: np.ndarray  # (M-2,) bool
    turns_heading: np.ndarray  # (M-2,) bool

    @property
    def half_tan(self) -> np.ndarray:
        return np.tan(0.5 * self.theta)


def _corners(unit: np.ndarray, follow_travel: bool, rate: float, stop_angle: float) -> _Corners:
    u_in, u_out = unit[:-1], unit[1:]
    cos_turn = np.clip(np.sum(u_in * u_out, axis=1), -1.0, 1.0)
    theta = np.arccos(cos_turn)
    perpendicular = u_out - cos_turn[:, None] * u_in
    norm = np.linalg.norm(perpendicular, axis=1)
    reversing = cos_turn < 0.0
    bending = norm > 1e-12
    stop = (theta > stop_angle) | (reversing & ~bending)  # an exact reversal has no arc at all
    normal = np.where(bending[:, None], perpendicular / np.where(bending, norm, 1.0)[:, None], 0.0)
    theta = np.where(bending, theta, 0.0)
    # Heading follows the horizontal direction; only a change of it costs heading rate.
    h_in, h_out = u_in[:, :2], u_out[:, :2]
    h_cross = np.abs(h_in[:, 0] * h_out[:, 1] - h_in[:, 1] * h_out[:, 0])
    yawing = follow_travel and rate > 0
    turns_heading = yawing & ((h_cross > 1e-9) | (np.sum(h_in * h_out, axis=1) < 0))
    return _Corners(u_in, normal, theta, bending, stop, turns_heading)


def _needed_radius(v, corners: _Corners, acc: float, rate: float) -> np.ndarray:
    """The arc radius a corner needs at speed v: within the acceleration, and where the heading
    turns with it, within the heading rate."""
    return np.where(corners.turns_heading, np.maximum(v**2 / acc, v / max(rate, _EPS)), v**2 / acc)


def _corner_speeds(corners: _Corners, length: np.ndarray, v_segment: np.ndarray, corner_cap: np.ndarray,
                   profile: ConstraintProfile, corner_deviation: float) -> tuple[np.ndarray, np.ndarray]:
    """(speed, arc radius) through each corner: the tightest of the segments' and the corner's
    caps, the vertical speed along the arc, the room the segments leave, the deviation allowed."""
    acc, rate = profile.max_acceleration, profile.max_heading_rate
    c = corners
    v_cap = np.minimum.reduce([v_segment[:-1], v_segment[1:], corner_cap[1:-1],
                               profile.max_vertical_speed / np.maximum(_arc_vertical_peak(c.u_in, c.normal, c.theta),
                                                                       _EPS)])
    half_tan = c.half_tan
    sagitta = 1.0 / np.cos(0.5 * c.theta) - 1.0  # arc's distance from its waypoint per metre of radius
    r_room = 0.5 * np.minimum(length[:-1], length[1:]) / np.maximum(half_tan, 1e-300)
    r_deviation = corner_deviation / np.maximum(sagitta, 1e-300)
    radius = np.where(c.bending, np.minimum.reduce([_needed_radius(v_cap, c, acc, rate), r_room, r_deviation]), 0.0)
    v_round = np.sqrt(acc * radius)
    v_round = np.where(c.turns_heading, np.minimum(v_round, rate * radius), v_round)
    v_corner = np.where(c.bending, np.minimum(v_cap, v_round), v_cap)
    return np.where(c.stop, 0.0, v_corner), np.where(c.stop, 0.0, radius)


def _straight_lengths(radius: np.ndarray, corners: _Corners, length: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tangent length at each waypoint, the straight piece of each segment between its arcs)."""
    tangent = np.concatenate([[0.0], radius * corners.half_tan, [0.0]])
    return tangent, length - tangent[:-1] - tangent[1:]


def _reachable(junction: np.ndarray, straight: np.ndarray, acc: float) -> np.ndarray:
    """The junction speeds lowered to what the straights between them allow: reachable from the
    previous one (forward pass), and braking for the next one still possible (backward pass)."""
    junction = junction.copy()
    for k in range(len(straight)):
        junction[k + 1] = min(junction[k + 1], math.sqrt(junction[k] ** 2 + 2.0 * acc * straight[k]))
    for k in range(len(straight) - 1, -1, -1):
        junction[k] = min(junction[k], math.sqrt(junction[k + 1] ** 2 + 2.0 * acc * straight[k]))
    return junction


def plan_timing(waypoints: np.ndarray, profile: ConstraintProfile, *, corner_speeds=None, segment_speeds=None,
                start_velocity=None, follow_travel: bool = True, corner_deviation: float = np.inf,
                stop_angle: float = STOP_ANGLE) -> Timing:
    """Time the polyline (M, 3): see the module docstring. corner_speeds (M,) caps the speed
    through each interior waypoint (inf: no extra cap, 0: stop there), segment_speeds (M-1,)
    caps each segment, corner_deviation bounds how far an arc may pass from its waypoint."""
    wp, corner_cap, segment_cap = _clean(waypoints, corner_speeds, segment_speeds)
    acc, rate = profile.max_acceleration, profile.max_heading_rate
    if len(wp) == 1:
        zero = np.zeros(1)
        return Timing(wp.copy(), np.zeros((1, 3)), np.zeros((1, 3)), zero, zero, zero, zero, zero, zero, zero,
                      zero, zero, 0.0, acc)
    delta = np.diff(wp, axis=0)
    length = np.linalg.norm(delta, axis=1)
    unit = delta / length[:, None]
    v_segment = np.minimum(speed_caps(unit, profile), segment_cap)
    corners = _corners(unit, follow_travel, rate, stop_angle)
    v_corner, radius = _corner_speeds(corners, length, v_segment, corner_cap, profile, corner_deviation)
    v_start = 0.0
    if start_velocity is not None:
        v_start = float(np.clip(np.dot(np.asarray(start_velocity, float).reshape(3), unit[0]), 0.0, v_segment[0]))
    _, straight = _straight_lengths(radius, corners, length)
    junction = _reachable(np.concatenate([[v_start], v_corner, [0.0]]), straight, acc)
    # Corners the passes slowed down get the tighter arc their speed allows; the straight
    # pieces only grow, so the junction speeds stay reachable.
    radius = np.minimum(radius, _needed_radius(junction[1:-1], corners, acc, rate))
    return _pieces(wp, unit, length, corners, radius, junction, v_segment, acc)


def _pieces(wp: np.ndarray, unit: np.ndarray, length: np.ndarray, corners: _Corners, radius: np.ndarray,
            junction: np.ndarray, v_segment: np.ndarray, acc: float) -> Timing:
    """The Timing of the straights and arcs, interleaved: straight k at 2k, the arc at waypoint
    k+1 at 2k+1, each a speed trapezoid between its junction speeds."""
    tangent, straight = _straight_lengths(radius, corners, length)
    count = 2 * len(straight) - 1
    start, piece_unit, piece_normal = np.zeros((count, 3)), np.zeros((count, 3)), np.zeros((count, 3))
    piece_radius, piece_length = np.zeros(count), np.zeros(count)
    v_in, v_out, v_limit = np.zeros(count), np.zeros(count), np.zeros(count)
    start[0::2] = wp[:-1] + tangent[:-1, None] * unit
    piece_unit[0::2], piece_length[0::2] = unit, straight
    v_in[0::2], v_out[0::2], v_limit[0::2] = junction[:-1], junction[1:], v_segment
    start[1::2] = wp[1:-1] - tangent[1:-1, None] * corners.u_in
    piece_unit[1::2], piece_normal[1::2] = corners.u_in, corners.normal
    piece_radius[1::2], piece_length[1::2] = radius, radius * corners.theta
    v_in[1::2] = v_out[1::2] = v_limit[1::2] = junction[1:-1]
    peak, t_up, t_cruise, t_down = trapezoid(piece_length, v_in, v_out, v_limit, acc)
    durations = t_up + t_cruise + t_down
    begin = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
    return Timing(start, piece_unit, piece_normal, piece_radius, piece_length, v_in, v_out, peak, t_up, t_cruise,
                  t_down, begin, float(durations.sum()), acc)


def evaluate(timing: Timing, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) and unit tangents (N, 3) at `times` (clamped to the path's span)."""
    t = np.clip(np.asarray(times, dtype=np.float64), 0.0, timing.duration)
    i = np.clip(np.searchsorted(timing.begin, t, side="right") - 1, 0, len(timing.begin) - 1)
    total = timing.t_up[i] + timing.t_cruise[i] + timing.t_down[i]
    tau = np.clip(t - timing.begin[i], 0.0, total)
    remaining = total - tau
    acc, v_in, v_out, peak = timing.acc, timing.v_in[i], timing.v_out[i], timing.peak[i]
    s_up = v_in * tau + 0.5 * acc * tau**2
    s_cruise = (peak**2 - v_in**2) / (2.0 * acc) + peak * (tau - timing.t_up[i])
    s_down = timing.length[i] - (v_out * remaining + 0.5 * acc * remaining**2)
    s = np.where(tau < timing.t_up[i], s_up, np.where(remaining < timing.t_down[i], s_down, s_cruise))
    radius = timing.radius[i]
    arc = radius > 0
    phi = np.where(arc, s / np.where(arc, radius, 1.0), 0.0)
    along = np.where(arc, radius * np.sin(phi), s)
    inward = np.where(arc, radius * (1.0 - np.cos(phi)), 0.0)
    unit, normal = timing.unit[i], timing.normal[i]
    positions = timing.start[i] + along[:, None] * unit + inward[:, None] * normal
    tangents = np.cos(phi)[:, None] * unit + np.sin(phi)[:, None] * normal
    return positions, tangents


def check_duration(duration: float, what: str = "trajectory") -> None:
    if not duration <= MAX_DURATION:  # NaN included
        raise ValueError(f"a {what} of {duration:.3g} s is longer than the {MAX_DURATION:.0f} s planned at most")


def sample_times(duration: float, dt: float) -> np.ndarray:
    """i·dt up to the first sample at or after `duration`, that one clamped to it."""
    check_duration(duration)
    count = int(np.ceil(duration / dt - 1e-9)) + 1
    return np.minimum(np.arange(count) * dt, duration)


def travel_headings(tangents: np.ndarray, fallback: float | None) -> np.ndarray:
    """Direction of horizontal travel; held through vertical or motionless stretches."""
    horizontal = np.linalg.norm(tangents[:, :2], axis=1) > 1e-6
    raw = np.arctan2(tangents[:, 1], tangents[:, 0])
    if fallback is None:
        fallback = float(raw[horizontal][0]) if horizontal.any() else 0.0
    last = np.maximum.accumulate(np.where(horizontal, np.arange(len(raw)), -1))
    return np.where(last >= 0, raw[np.maximum(last, 0)], fallback)


def steer(positions: np.ndarray, desired: np.ndarray, start_heading: float | None, rate: float, dt: float) -> Path:
    """Slew from `start_heading` towards `desired` (N,) at <= rate; if still off at the end,
    append samples at the final position until the heading arrives."""
    desired = np.asarray(wrap_angle(desired), dtype=np.float64)
    current = float(desired[0] if start_heading is None else wrap_angle(start_heading))
    if rate <= 0:
        return positions, desired
    step = rate * dt
    headings = np.empty(len(desired))
    headings[0] = current
    for i in range(1, len(desired)):  # inherently sequential: each step depends on the last
        gap = (desired[i] - current + math.pi) % (2.0 * math.pi) - math.pi
        current = (current + min(max(gap, -step), step) + math.pi) % (2.0 * math.pi) - math.pi
        headings[i] = current
    gap = float(wrap_angle(desired[-1] - current))
    check_duration(abs(gap) / rate, "turn")
    extra = int(np.ceil(abs(gap) / step - 1e-9))
    if extra > 0:
        turn = np.sign(gap) * np.minimum(step * np.arange(1, extra + 1), abs(gap))
        headings = np.concatenate([headings, wrap_angle(current + turn)])
        positions = np.vstack([positions, np.repeat(positions[-1:], extra, axis=0)])
    return positions, headings


def fly(waypoints: np.ndarray, profile: ConstraintProfile, dt: float = DT, *, corner_speeds=None,
        segment_speeds=None, start_velocity=None, start_heading: float | None = None, heading: float | None = None,
        corner_deviation: float = np.inf, stop_angle: float = STOP_ANGLE) -> Path:
    """Fly the polyline (M, 3) from rest (or from `start_velocity`) to rest at its last
    waypoint, sampled every dt. heading None: face the direction of horizontal travel;
    a float: face that way. Both slewed from `start_heading` (None: start at the desired one)."""
    timing = plan_timing(waypoints, profile, corner_speeds=corner_speeds, segment_speeds=segment_speeds,
                         start_velocity=start_velocity, follow_travel=heading is None,
                         corner_deviation=corner_deviation, stop_angle=stop_angle)
    positions, tangents = evaluate(timing, sample_times(timing.duration, dt))
    if heading is None:
        desired = travel_headings(tangents, start_heading)
    else:
        desired = np.full(len(positions), float(heading))
    return steer(positions, desired, start_heading, profile.max_heading_rate, dt)


def sample_path(waypoints: np.ndarray, profile: ConstraintProfile, dt: float = DT,
                start_heading: float | None = None) -> Path:
    """Fly the polyline stopping at every waypoint, heading along travel."""
    m = len(np.asarray(waypoints).reshape(-1, 3))
    return fly(waypoints, profile, dt, corner_speeds=np.zeros(m), start_heading=start_heading)


def path_duration(waypoints: np.ndarray, profile: ConstraintProfile, start_heading: float | None = None) -> float:
    """Flight time of sample_path's continuous profile. Headings never add time in flight, so
    `start_heading` no longer matters; it stays for callers of the first version."""
    m = len(np.asarray(waypoints).reshape(-1, 3))
    return plan_timing(waypoints, profile, corner_speeds=np.zeros(m)).duration
