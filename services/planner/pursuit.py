"""Pursuit of a moving target: blend from the vehicle's state onto the target's predicted
track, then fly along it. Made for re-planning on every update of the prediction — each plan
starts from the current position and velocity, so a curving target (whose straight-line
prediction keeps changing) is followed smoothly, where the merge of intercept.py would stop
and wait again at every new prediction.

Under the constant-velocity prediction p_T(t) = p + v·t, the blend is a cubic Hermite curve
per axis from (position, velocity) at t = 0 to (p_T(T), v) at t = T; T is the shortest
horizon (searched on a grid) for which every sample keeps within the profile's speed,
vertical speed and acceleration. Then it flies along the prediction for `follow_time` and
brakes to rest at the profile's acceleration.
"""
from __future__ import annotations

import numpy as np

from schemas.messages import ConstraintProfile
from services.planner.timing import DT, Path, sample_times, steer

_MARGIN = 0.98  # of each limit, so second differences of the samples stay inside it too


def _hermite(t: np.ndarray, horizon: float, p0, v0, p1, v1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations (N, 3) of the cubic from (p0, v0) to (p1, v1)."""
    s = (t / horizon)[:, None]
    dp = p1 - p0
    # p(s) = p0 + v0·T·s + (3Δ − (2v0 + v1)T)·s² + (−2Δ + (v0 + v1)T)·s³
    c2 = 3.0 * dp - (2.0 * v0 + v1) * horizon
    c3 = -2.0 * dp + (v0 + v1) * horizon
    position = p0 + v0 * horizon * s + c2 * s**2 + c3 * s**3
    velocity = v0 + (2.0 * c2 * s + 3.0 * c3 * s**2) / horizon
    acceleration = (2.0 * c2 + 6.0 * c3 * s) / horizon**2
    return position, velocity, acceleration


def _within(velocity: np.ndarray, acceleration: np.ndarray, profile: ConstraintProfile) -> bool:
    return bool(np.linalg.norm(velocity, axis=1).max() <= _MARGIN * profile.max_speed
                and np.abs(velocity[:, 2]).max() <= _MARGIN * profile.max_vertical_speed
                and np.linalg.norm(acceleration, axis=1).max() <= _MARGIN * profile.max_acceleration)


def blend_horizon(position, velocity, target_position, target_velocity, profile: ConstraintProfile,
                  shortest: float = 0.5, longest: float = 30.0, step: float = 0.1) -> float | None:
    """The shortest T on the grid for which the blend keeps within the profile (None: none)."""
    p0, v0 = np.asarray(position, float).reshape(3), np.asarray(velocity, float).reshape(3)
    pt, vt = np.asarray(target_position, float).reshape(3), np.asarray(target_velocity, float).reshape(3)
    if np.linalg.norm(vt) > _MARGIN * profile.max_speed or abs(vt[2]) > _MARGIN * profile.max_vertical_speed:
        return None
    for horizon in np.arange(shortest, longest + 1e-9, step):
        t = np.linspace(0.0, horizon, 41)
        _, vel, acc = _hermite(t, horizon, p0, v0, pt + vt * horizon, vt)
        if _within(vel, acc, profile):
            return float(horizon)
    return None


def pursuit(position, target_position, target_velocity, *, profile: ConstraintProfile, dt: float = DT,
            start_velocity=None, start_heading: float | None = None, follow_time: float = 4.0) -> Path | None:
    """Blend onto the predicted track, follow it for `follow_time`, brake to rest; heading along
    the target's velocity. None when no blend within 30 s keeps within the profile."""
    p0 = np.asarray(position, float).reshape(3)
    v0 = np.zeros(3) if start_velocity is None else np.asarray(start_velocity, float).reshape(3)
    pt, vt = np.asarray(target_position, float).reshape(3), np.asarray(target_velocity, float).reshape(3)
    horizon = blend_horizon(p0, v0, pt, vt, profile)
    if horizon is None:
        return None
    speed = float(np.linalg.norm(vt))
    brake = speed / profile.max_acceleration
    duration = horizon + follow_time + brake
    t = sample_times(duration, dt)
    positions = np.empty((len(t), 3))
    blending = t <= horizon
    positions[blending] = _hermite(t[blending], horizon, p0, v0, pt + vt * horizon, vt)[0]
    after = np.clip(t[~blending] - horizon, 0.0, None)
    following = np.minimum(after, follow_time)
    braking = np.clip(after - follow_time, 0.0, brake)
    direction = vt / speed if speed > 1e-9 else np.zeros(3)
    travelled = speed * following + speed * braking - 0.5 * profile.max_acceleration * braking**2
    positions[~blending] = pt + vt * horizon + travelled[:, None] * direction
    facing = vt[:2] if np.linalg.norm(vt[:2]) > 1e-6 else (pt - p0)[:2]
    heading = float(np.arctan2(facing[1], facing[0])) if np.linalg.norm(facing) > 1e-6 else (start_heading or 0.0)
    return steer(positions, np.full(len(t), heading), start_heading, profile.max_heading_rate, dt)
