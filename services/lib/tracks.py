"""How a consumer reads a Track message: its position and velocity, whatever the filter's layout,
and the target's predicted path (job manager, planner, the tools alike); and the tracker's motion
model's prediction of a position-velocity-acceleration state (`manoeuvre_path`), which the tracker
publishes and a reader of an older recording extrapolates by.

Tracks carry both explicitly; recordings made before those fields existed only have the
constant-acceleration state (position, velocity, acceleration), read as such as a fallback.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from schemas.arrays import to_numpy
from schemas.messages import Track


def manoeuvre_path(mean: np.ndarray, step: float, count: int, manoeuvre_time: float) -> np.ndarray:
    """(count, 3) predicted positions every `step` s ahead of a position-velocity-acceleration
    state, the acceleration taken to fade with time constant τ = `manoeuvre_time` (Singer's
    manoeuvre model, 1970): p + v t + a τ² (e^(-t/τ) - 1 + t/τ). τ = inf is the constant-acceleration
    extrapolation of eq. 27 (p + v t + a t²/2), which over seconds turns the few tenths of a second
    a manoeuvre lasts into metres; a smaller τ keeps the acceleration's short-term effect and
    then flies straight on at v + a τ."""
    m = np.asarray(mean, dtype=np.float64).reshape(-1)
    t = step * np.arange(1, count + 1, dtype=np.float64)[:, None]
    if np.isinf(manoeuvre_time):
        reach = 0.5 * t * t
    else:
        tau = manoeuvre_time
        reach = tau * tau * (np.exp(-t / tau) - 1.0 + t / tau)
    return (m[:3] + m[3:6] * t + m[6:9] * reach).reshape(-1, 3)


def track_position(track: Track) -> np.ndarray:
    """(3,); NaN when the track has neither a position nor a state that long."""
    if track.position is not None:
        return np.array(track.position, dtype=np.float64)
    return _state_part(track, 0)


def track_velocity(track: Track) -> np.ndarray:
    """(3,); NaN when the track has neither a velocity nor a state that long."""
    if track.velocity is not None:
        return np.array(track.velocity, dtype=np.float64)
    return _state_part(track, 3)


def _state_part(track: Track, start: int) -> np.ndarray:
    state = np.asarray(to_numpy(track.state), dtype=np.float64).reshape(-1)
    return state[start:start + 3].copy() if len(state) >= start + 3 else np.full(3, np.nan)


def track_positions(tracks: list[Track]) -> np.ndarray:
    """(K, 3) positions of the tracks."""
    return np.array([track_position(t) for t in tracks], dtype=np.float64).reshape(-1, 3)


def track_velocities(tracks: list[Track]) -> np.ndarray:
    return np.array([track_velocity(t) for t in tracks], dtype=np.float64).reshape(-1, 3)


def predicted_path(track: Track, horizon: float, step: float = 0.1) -> np.ndarray:
    """(K, 3): the track's position now, then its filter's predicted positions up to `horizon` s
    ahead (the message's trajectory); for a recording without one, the constant-acceleration
    extrapolation of its state (seed 000 eq. 27) every `step` s."""
    start = track_position(track)[None]
    future = track_path(track)
    if len(future):
        return np.vstack([start, future[: int(round(horizon / track.trajectory_dt))]])
    state = np.asarray(to_numpy(track.state), dtype=np.float64).reshape(-1)
    if len(state) < 9:
        return start
    return np.vstack([start, manoeuvre_path(state[:9], step, int(horizon / step + 1e-9), np.inf)])


@dataclass(frozen=True)
class PredictedPath:
    """Where a tracked target will be: at `position` with `velocity` at time 0, then through its
    filter's predicted positions `path[i]` at (i + 1)·dt, then straight on with the velocity of
    the path's last step. Without a path (or before time 0), a straight line along `velocity`."""

    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3)
    dt: float = 0.0  # s

    def state(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities (N, 3) at the times t (N,), s from time 0."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p0, v0 = np.asarray(self.position, dtype=np.float64), np.asarray(self.velocity, dtype=np.float64)
        positions, velocities = p0 + t[:, None] * v0, np.broadcast_to(v0, (len(t), 3)).copy()
        path = np.asarray(self.path, dtype=np.float64).reshape(-1, 3)
        if not len(path) or self.dt <= 0:
            return positions, velocities
        knots = np.vstack([p0, path])
        steps = np.diff(knots, axis=0) / self.dt  # (K, 3) velocity on each step
        end = len(path) * self.dt
        inside = (t >= 0) & (t <= end)
        segment = np.minimum((t[inside] / self.dt).astype(np.int64), len(path) - 1)
        positions[inside] = knots[segment] + (t[inside] - segment * self.dt)[:, None] * steps[segment]
        velocities[inside] = steps[segment]
        after = t > end
        positions[after] = knots[-1] + (t[after] - end)[:, None] * steps[-1]
        velocities[after] = steps[-1]
        return positions, velocities

    def turning_on(self, until: float) -> PredictedPath:
        """The prediction with its path carried on to `until` s at the turn rate (about the
        vertical), speed and climb of its last step, where it ends before then (the straight line
        `state` carries it on with is not where a turning target goes)."""
        path = np.asarray(self.path, dtype=np.float64).reshape(-1, 3)
        if len(path) < 2 or self.dt <= 0 or len(path) * self.dt >= until:
            return self
        knots = np.vstack([np.asarray(self.position, dtype=np.float64), path])
        before, last = knots[-2] - knots[-3], knots[-1] - knots[-2]
        turn = np.arctan2(before[0] * last[1] - before[1] * last[0], before[0] * last[0] + before[1] * last[1])
        angles = turn * np.arange(1, int(np.ceil(until / self.dt)) - len(path) + 1)
        steps = np.stack([np.cos(angles) * last[0] - np.sin(angles) * last[1],
                          np.sin(angles) * last[0] + np.cos(angles) * last[1], np.full(len(angles), last[2])], axis=1)
        carried = path[-1] + np.cumsum(steps, axis=0)
        return PredictedPath(self.position, self.velocity, np.vstack([path, carried]), self.dt)

    def rebased(self, offset: float, count: int, dt: float) -> PredictedPath:
        """The same prediction seen from `offset` s later, its path resampled every dt (count points)."""
        (position,), (velocity,) = self.state([offset])
        path, _ = self.state(offset + dt * np.arange(1, count + 1))
        return PredictedPath(position, velocity, path, dt)


def path_step(track: Track) -> float:
    """The track's trajectory_dt, s; 0 when it is no step a prediction can mean (none, not
    finite, not positive, absurdly long)."""
    dt = float(track.trajectory_dt)
    return dt if 0.0 < dt < 1e6 else 0.0


def track_path(track: Track) -> np.ndarray:
    """(K, 3) the track's predicted positions every trajectory_dt s after its stamp (empty: none)."""
    if track.trajectory is None or not path_step(track):
        return np.zeros((0, 3))
    path = np.asarray(to_numpy(track.trajectory), dtype=np.float64).reshape(-1)
    if path.size % 3 or not np.isfinite(path).all():
        return np.zeros((0, 3))  # not positions: ignored like a missing path
    return path.reshape(-1, 3)


def track_position_covariance(track: Track) -> np.ndarray:
    """(3, 3) the position block of the track's covariance (NaN when it has none of that size)."""
    covariance = np.asarray(to_numpy(track.covariance), dtype=np.float64).reshape(-1)
    size = int(round(np.sqrt(covariance.size)))
    if size < 3 or size * size != covariance.size:
        return np.full((3, 3), np.nan)
    return covariance.reshape(size, size)[:3, :3].copy()
