"""Interception of a moving target under a constant-velocity prediction p_T(t) = p + v·t
(t from now). Not in the seed (its targets are tethered balloons); the merge idea is the
usual one for catching a moving object without a high closing speed.

The UAV flies rest-to-rest to a merge point W = p_T(τ) on the target's predicted path, waits
there, then accelerates along the target's direction at a_m so it reaches the target's speed
v exactly when the target catches up with it: the target covers v·t_m during the merge
(t_m = v/a_m) and the UAV v·t_m/2, so the merge starts t_m/2 before the target passes W.
It then flies along for `follow_time` and brakes to rest at a_m.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.messages import ConstraintProfile
from services.planner.timing import DT, Path, Timing, evaluate, plan_timing, sample_times, speed_caps, steer, trapezoid


@dataclass(frozen=True)
class InterceptPlan:
    merge_point: np.ndarray  # W (3,)
    direction: np.ndarray  # unit (3,) of the target's velocity (zero for a still target)
    speed: float  # target speed
    acceleration: float  # merge acceleration actually used (<= the profile's)
    passing: float  # τ: when the target passes W, s from now
    arrival: float  # when the UAV is at rest at W
    merge_start: float
    merge_end: float  # the UAV is at the target's position with its velocity
    follow_end: float
    duration: float  # at rest again
    transfer: Timing  # the flight to W


def _transfer_times(position: np.ndarray, goals: np.ndarray, profile: ConstraintProfile,
                    start_velocity: np.ndarray | None) -> np.ndarray:
    """Flight time of the straight flight to each goal (G, 3), as plan_timing would time it."""
    delta = goals - position
    length = np.linalg.norm(delta, axis=1)
    unit = delta / np.maximum(length, 1e-12)[:, None]
    cap = speed_caps(unit, profile)
    acc = profile.max_acceleration
    v0 = np.zeros(len(goals)) if start_velocity is None else np.clip(unit @ start_velocity, 0.0, cap)
    v0 = np.minimum(v0, np.sqrt(2.0 * acc * length))
    _, t_up, t_cruise, t_down = trapezoid(length, v0, np.zeros_like(v0), cap, acc)
    return np.where(length > 1e-9, t_up + t_cruise + t_down, 0.0)


def plan_intercept(position: np.ndarray, target_position: np.ndarray, target_velocity: np.ndarray, *,
                   profile: ConstraintProfile, start_velocity=None, merge_acceleration: float = 1.5,
                   follow_time: float = 4.0, lead_margin: float = 1.0, horizon: float = 30.0,
                   step: float = 0.01) -> InterceptPlan | None:
    """The merge with the smallest τ (searched every `step` s up to `horizon`) for which the
    UAV is at W at least `lead_margin` s before the merge starts; None if there is none or
    the target is faster than the profile allows."""
    position, target = np.asarray(position, float).reshape(3), np.asarray(target_position, float).reshape(3)
    velocity = np.asarray(target_velocity, float).reshape(3)
    start_velocity = None if start_velocity is None else np.asarray(start_velocity, float).reshape(3)
    speed = float(np.linalg.norm(velocity))
    direction = velocity / speed if speed > 1e-9 else np.zeros(3)
    if speed > 1e-9 and speed > float(speed_caps(direction, profile)) * (1 + 1e-9):
        return None
    acceleration = min(merge_acceleration, profile.max_acceleration)
    lead = 0.5 * speed / acceleration  # merge starts this long before the target passes W
    passing = np.arange(lead + lead_margin, horizon + 0.5 * step, step)
    goals = target + passing[:, None] * velocity
    feasible = _transfer_times(position, goals, profile, start_velocity) <= passing - lead - lead_margin + 1e-9
    if not feasible.any():
        return None
    k = int(np.argmax(feasible))
    tau = float(passing[k])
    transfer = plan_timing(np.stack([position, goals[k]]), profile, start_velocity=start_velocity,
                           follow_travel=False)
    merge_start = tau - lead
    merge_end = merge_start + 2.0 * lead
    follow_end = merge_end + follow_time
    return InterceptPlan(goals[k], direction, speed, acceleration, tau, transfer.duration, merge_start, merge_end,
                         follow_end, follow_end + 2.0 * lead, transfer)


def sample_intercept(plan: InterceptPlan, profile: ConstraintProfile, dt: float = DT,
                     start_heading: float | None = None) -> Path:
    """Sample the plan every dt; heading along the target's velocity (towards W for a still
    or vertical target), slewed from `start_heading`."""
    t = sample_times(plan.duration, dt)
    positions, _ = evaluate(plan.transfer, t)
    a, v = plan.acceleration, plan.speed
    merge = np.clip(t - plan.merge_start, 0.0, plan.merge_end - plan.merge_start)
    follow = np.clip(t - plan.merge_end, 0.0, plan.follow_end - plan.merge_end)
    brake = np.clip(t - plan.follow_end, 0.0, plan.duration - plan.follow_end)
    travelled = 0.5 * a * merge**2 + v * follow + v * brake - 0.5 * a * brake**2
    moving = t > plan.merge_start
    positions[moving] = plan.merge_point + travelled[moving, None] * plan.direction
    facing = plan.direction[:2]
    if np.linalg.norm(facing) < 1e-6:
        facing = (plan.merge_point - plan.transfer.start[0])[:2]
    if np.linalg.norm(facing) > 1e-6:
        heading = float(np.arctan2(facing[1], facing[0]))
    else:
        heading = 0.0 if start_heading is None else float(start_heading)
    return steer(positions, np.full(len(t), heading), start_heading, profile.max_heading_rate, dt)


def intercept(position: np.ndarray, target_position: np.ndarray, target_velocity: np.ndarray, *,
              profile: ConstraintProfile, dt: float = DT, start_velocity=None, start_heading: float | None = None,
              merge_acceleration: float = 1.5, follow_time: float = 4.0, lead_margin: float = 1.0) -> Path | None:
    """Merge onto a constant-velocity target and fly along with it (see the module docstring);
    None when no merge within 30 s is feasible or the target is too fast for the profile."""
    plan = plan_intercept(position, target_position, target_velocity, profile=profile, start_velocity=start_velocity,
                          merge_acceleration=merge_acceleration, follow_time=follow_time, lead_margin=lead_margin)
    return None if plan is None else sample_intercept(plan, profile, dt, start_heading)
