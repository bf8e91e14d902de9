"""Planned references shared between UAVs, and the closest approach of two of them (pure; stamps
are int ns of mission time).

Each job manager sends, with its status, the next seconds of its own planner's reference (the
trajectory its flight controller is flying), sampled every `step` (`PlannedPath.sampled`). A
partner checks its own reference against it over the same times (`first_breach`), as the MRS
system's MPC trackers share their predicted trajectories: a conflict is seen while both still fly
their plans, seconds before the distance falls. What a plan does not know is widened: a partner's
plan is as old as its last status, and meanwhile it may have planned anew, so the distance it
must keep grows by `widen_rate` m per second of that age; a UAV whose plan is unknown (none sent
yet) is carried on at its last velocity instead. A reference ends at rest: after its last sample
the UAV is taken to stay there.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.lib.runtime.clock import NS


@dataclass(frozen=True)
class PlannedPath:
    """Positions (K, 3) at start + i·dt (dt in s); at rest before the first and after the last."""

    start: int  # ns
    dt: float  # s
    positions: np.ndarray  # (K, 3)

    def __post_init__(self) -> None:
        positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "positions", positions)
        if not len(positions) or not np.isfinite(positions).all() or not (self.dt > 0 or len(positions) == 1):
            raise ValueError("a planned path needs finite positions (K >= 1, 3) and dt > 0 when K > 1")

    def at(self, times: np.ndarray) -> np.ndarray:
        """(N, 3) positions at the mission times (N,) ns, linear between samples."""
        times = np.atleast_1d(np.asarray(times, dtype=np.int64))
        if len(self.positions) == 1:
            return np.broadcast_to(self.positions[0], (len(times), 3)).copy()
        u = np.clip((times - self.start) / NS / self.dt, 0.0, len(self.positions) - 1)
        i = np.minimum(u.astype(np.int64), len(self.positions) - 2)
        f = (u - i)[:, None]
        return self.positions[i] * (1.0 - f) + self.positions[i + 1] * f

    @property
    def end(self) -> int:
        return self.start + int(round((len(self.positions) - 1) * self.dt * NS))

    def sampled(self, now: int, horizon: float, step: float) -> PlannedPath:
        """The next `horizon` s from `now`, every `step` s (what a status carries)."""
        return self.resumed(now, now, horizon, step)

    def resumed(self, paused: int, now: int, horizon: float, step: float) -> PlannedPath:
        """The plan as it would go on from where it was at `paused` if it were taken up again at
        `now`: a yielding UAV's mission, held since `paused`."""
        count = int(np.floor(horizon / step + 1e-9)) + 1
        offsets = np.round(np.arange(count) * step * NS).astype(np.int64)
        return PlannedPath(now, step, self.at(paused + offsets))


def straight_on(position: np.ndarray, velocity: np.ndarray, stamp: int, horizon: float, step: float) -> PlannedPath:
    """A UAV with no known plan, carried on at its velocity from where it was at `stamp`."""
    t = np.arange(int(np.floor(horizon / step + 1e-9)) + 1) * step
    return PlannedPath(stamp, step, np.asarray(position, dtype=np.float64) + t[:, None] * np.asarray(velocity))


@dataclass(frozen=True)
class Approach:
    """How two plans pass each other over the horizon."""

    closest: float  # m, the least distance between them
    at: int  # ns, when
    breach: float  # s from now until they first come closer than the radius asked for (inf: never)


def first_breach(mine: PlannedPath, theirs: PlannedPath, now: int, horizon: float, step: float, radius: float,
                 age: float = 0.0, widen_rate: float = 0.0) -> Approach:
    """Compare two plans at now, now + step, ... now + horizon: the closest approach, and the
    first time they are closer than `radius` widened by `age` s × `widen_rate` m/s (the age of
    the partner's plan)."""
    times = now + np.round(np.arange(int(np.floor(horizon / step + 1e-9)) + 1) * step * NS).astype(np.int64)
    gaps = np.linalg.norm(mine.at(times) - theirs.at(times), axis=1)
    k = int(np.argmin(gaps))
    inside = np.flatnonzero(gaps < radius + max(age, 0.0) * widen_rate)
    breach = (times[inside[0]] - now) / NS if len(inside) else np.inf
    return Approach(float(gaps[k]), int(times[k]), float(breach))
