"""Trajectory generation (seed 004 ch. 5): approach with deadband, attack with overshoot and
height offsets, lawnmower scan, braking stop and interception of moving targets.

Every trajectory is a Path: positions (N, 3) and headings (N,), sample i at i·dt, respecting
the whole ConstraintProfile (speed, vertical speed, acceleration, heading rate) including at
corners, which are rounded (or stopped at when sharper than 120°). The time parameterisation
lives in timing.py, the scan in scan.py, interception in pursuit.py (close onto the predicted
track as fast as the limits allow, re-planned on every update) and intercept.py (merge: wait on the predicted path); this
module is the seed's geometry and re-exports them. Keeping each manoeuvre clear of obstacles is
avoid.py's, which commands.py calls.
"""
from __future__ import annotations

import numpy as np

from schemas.messages import ConstraintProfile
from services.planner.intercept import InterceptPlan, intercept, plan_intercept
from services.planner.pursuit import meeting_length, pursuit
from services.planner.scan import inner_rectangle, lawnmower, lawnmower_line, lawnmower_waypoints, scan_rectangle
from services.planner.timing import (
    DT,
    STOP_ANGLE,
    Path,
    evaluate,
    fly,
    path_duration,
    plan_timing,
    sample_path,
    speed_caps,
    steer,
    wrap_angle,
)

__all__ = [
    "DT", "HIT_OFFSET", "STOP_ANGLE", "Path", "InterceptPlan", "approach", "approach_goal", "approach_waypoints", "attack",
    "attack_waypoints", "deadband", "evaluate", "facing", "fly", "goto", "hover", "inner_rectangle", "intercept",
    "land", "lawnmower", "lawnmower_line", "lawnmower_waypoints",
    "meeting_length", "path_duration", "plan_intercept", "pursuit", "plan_timing", "sample_path", "scan_rectangle", "speed_caps", "steer",
    "stop", "takeoff", "wrap_angle",
]

# Seed 004 Table 3.1
WAIT_DISTANCE = 4.0  # d_b
DESCEND_DISTANCE = 11.0  # D_p
DEADBAND = 0.5  # D_f
OVERSHOOT = 5.0  # d_o
# o_h: seed 004 flew 0.3 m. Passing a balloon whose centre floats 0.5 m over its pole's top, a 0.4 m
# body then keeps 0.4 m from the top, 0.3 m once a camera-found balloon's 0.1 m height error (seen on
# mbzirc) is taken off: the least the body may keep in an attack. 0.4 m keeps 0.1 m more and stays
# 0.2 m inside the needle's reach (balloon radius + 0.3 m).
HIT_OFFSET = 0.4
END_OFFSET = 0.15  # o_o
HIT_DEVIATION = 0.02  # m the rounded junction at the hit point may pass from it


def _vec3(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).reshape(3)


def hover(position: np.ndarray, heading: float = 0.0) -> Path:
    return _vec3(position).reshape(1, 3).copy(), np.array([wrap_angle(heading)], dtype=np.float64)


def takeoff(start: np.ndarray, height: float, profile: ConstraintProfile, dt: float = DT,
            heading: float = 0.0) -> Path:
    """Vertical climb to world z = height."""
    start = _vec3(start)
    return sample_path(np.stack([start, [start[0], start[1], height]]), profile, dt, heading)


def land(start: np.ndarray, ground_z: float, profile: ConstraintProfile, dt: float = DT,
         heading: float = 0.0) -> Path:
    """Vertical descent to world z = ground_z."""
    return takeoff(start, ground_z, profile, dt, heading)


def goto(start: np.ndarray, target: np.ndarray, profile: ConstraintProfile, dt: float = DT,
         heading: float | None = None) -> Path:
    """Straight line to `target`, heading along travel (slewed from `heading`)."""
    return fly(np.stack([_vec3(start), _vec3(target)]), profile, dt, start_heading=heading)


def deadband(reference: np.ndarray, uav_position: np.ndarray, target: np.ndarray, band: float) -> np.ndarray:
    """Eq. 5.3-5.6: a new reference less than `band` from the UAV along the line of sight
    loses that component (noise in the target's range would otherwise make the vehicle and
    its reference chase each other); its lateral part is kept."""
    reference, uav, target = _vec3(reference), _vec3(uav_position), _vec3(target)
    line = uav - target
    distance = np.linalg.norm(line)
    if distance < 1e-9:
        return reference.copy()
    t = line / distance
    offset = reference - uav
    along = np.dot(t, offset)
    if abs(along) < band:
        return offset - along * t + uav
    return reference.copy()


def _horizontal_direction(position: np.ndarray, target: np.ndarray, fallback_heading: float | None) -> np.ndarray:
    """Unit (3,) horizontal direction from position to target; the fallback heading (or +x)
    when the vehicle is right above or below it."""
    d = np.array([target[0] - position[0], target[1] - position[1], 0.0])
    n = np.linalg.norm(d)
    if n > 1e-9:
        return d / n
    angle = 0.0 if fallback_heading is None else float(fallback_heading)
    return np.array([np.cos(angle), np.sin(angle), 0.0])


def approach_goal(position: np.ndarray, target: np.ndarray, wait_distance: float = WAIT_DISTANCE,
                  deadband_band: float = DEADBAND, heading: float | None = None, level: float = 0.0) -> np.ndarray:
    """Alg. 1 lines 2-6: `wait_distance` short of the target on the horizontal line from the
    UAV, at the target's height raised by `level`, then the deadband. The planner raises it by the
    attack's hit offset o_h, which Alg. 1 does not: the attack's run-in is then level, and a vehicle
    still descending when the attack starts passes over the pole higher, not lower (with the goal
    at the target's height, mbzirc seed 1's attacks passed 0.24 m from the pole tops)."""
    position, target = _vec3(position), _vec3(target)
    goal = target - wait_distance * _horizontal_direction(position, target, heading)
    goal[2] += level
    return deadband(goal, position, target, deadband_band)


def approach_waypoints(position: np.ndarray, target: np.ndarray, goal: np.ndarray,
                       descend_distance: float = DESCEND_DISTANCE, wait_distance: float = WAIT_DISTANCE) -> np.ndarray:
    """Alg. 1's polyline to the approach `goal`: level at the current height while farther than
    `descend_distance` (horizontally) from the target, then down to the goal."""
    position, target, goal = _vec3(position), _vec3(target), _vec3(goal)
    waypoints = [position]
    along = goal[:2] - target[:2]
    reach = np.linalg.norm(along)
    direction = -along / reach if reach > 1e-9 else _horizontal_direction(position, target, None)[:2]
    if np.hypot(*(target - position)[:2]) > descend_distance and descend_distance > wait_distance:
        level = target[:2] - descend_distance * direction
        waypoints.append(np.array([level[0], level[1], position[2]]))
    waypoints.append(goal)
    return np.stack(waypoints)


def approach(position: np.ndarray, target: np.ndarray, *, wait_distance: float = WAIT_DISTANCE,
             descend_distance: float = DESCEND_DISTANCE, deadband_band: float = DEADBAND,
             profile: ConstraintProfile, dt: float = DT, start_velocity=None,
             start_heading: float | None = None) -> Path:
    """Alg. 1: straight to the approach goal facing the target (eq. 5.2), at the current height
    while farther than `descend_distance` (horizontally) from the target, then descending to
    its height. The junction is rounded, so the descent begins up to one tangent length
    (at most half the shorter adjacent leg) before D_p. Ends at rest at the goal."""
    position, target = _vec3(position), _vec3(target)
    goal = approach_goal(position, target, wait_distance, deadband_band, start_heading)
    waypoints = approach_waypoints(position, target, goal, descend_distance, wait_distance)
    return fly(waypoints, profile, dt, start_velocity=start_velocity, start_heading=start_heading,
               heading=facing(position, target, start_heading))


def facing(position: np.ndarray, target: np.ndarray, fallback_heading: float | None = None) -> float:
    """The heading towards the target (eq. 5.2), horizontally."""
    direction = _horizontal_direction(_vec3(position), _vec3(target), fallback_heading)
    return float(np.arctan2(direction[1], direction[0]))


def attack_waypoints(position: np.ndarray, target: np.ndarray, overshoot: float = OVERSHOOT,
                     hit_offset: float = HIT_OFFSET, end_offset: float = END_OFFSET,
                     heading: float | None = None) -> np.ndarray:
    """§5.2's polyline: through the target raised by `hit_offset`, to `overshoot` beyond it along the
    horizontal attack direction at target z + `end_offset`."""
    position, target = _vec3(position), _vec3(target)
    direction = _horizontal_direction(position, target, heading)
    hit = target + np.array([0.0, 0.0, hit_offset])
    end = target + overshoot * direction + np.array([0.0, 0.0, end_offset])
    return np.stack([position, hit, end])


def attack(position: np.ndarray, target: np.ndarray, *, overshoot: float = OVERSHOOT, hit_offset: float = HIT_OFFSET,
           end_offset: float = END_OFFSET, profile: ConstraintProfile, dt: float = DT, start_velocity=None,
           start_heading: float | None = None) -> Path:
    """§5.2: through the target raised by `hit_offset` (the pole is below the balloon), to
    `overshoot` beyond it along the horizontal attack direction at target z + `end_offset`,
    ending at rest, facing the target. The junction at the hit point is rounded at most
    HIT_DEVIATION from it, so the vehicle really passes through."""
    waypoints = attack_waypoints(position, target, overshoot, hit_offset, end_offset, start_heading)
    return fly(waypoints, profile, dt, start_velocity=start_velocity, start_heading=start_heading,
               heading=facing(position, target, start_heading), corner_deviation=HIT_DEVIATION)


def stop(position: np.ndarray, velocity: np.ndarray, profile: ConstraintProfile, dt: float = DT,
         heading: float = 0.0) -> Path:
    """Brake to rest along the current velocity at max_acceleration (the seed's stop before
    checking a target). A speed above the profile's caps is clipped to them first."""
    position, velocity = _vec3(position), _vec3(velocity)
    speed = np.linalg.norm(velocity)
    if speed < 1e-9:
        return hover(position, heading)
    unit = velocity / speed
    speed = min(speed, float(speed_caps(unit, profile)))
    brake = speed**2 / (2.0 * profile.max_acceleration)
    return fly(np.stack([position, position + brake * unit]), profile, dt, start_velocity=velocity,
               start_heading=heading, heading=heading)
