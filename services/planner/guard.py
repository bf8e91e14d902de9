"""The planner's guard (MRS calls theirs a bumper): every cycle, the next `horizon` s of the active
reference against the latest map. Pure: the reference, the vehicle's state and the map in, a
verdict out; the node acts on it.

A plan was clear of what the UAV knew when it was made; since then the mapper may have learnt an
obstacle the a-priori map lacks, or the vehicle may be flying a reference that was never checked
(a brake). The guard finds the first point of the reference's next seconds that is
- closer than the promise (`accept`: body radius + obstacle_margin) to an occupied voxel: the
  reference no longer keeps the margin, so it asks for a re-plan ("replan"); when the point is
  closer than half the margin (`hard`: body radius + obstacle_margin / 2) and no farther ahead than
  the vehicle needs to stop (its braking distance at 0.8 of the profile's acceleration, plus
  `slack`), for braking now ("brake"), unless a re-plan avoids it;
- in space never seen that the LiDAR looks at from here (within `view` of the horizontal: its
  vertical field of view), close enough ahead that it could not stop short of it ("brake").
  Seen but never cleared, that space is hidden by something; space outside the field of view
  (straight up on a take-off) is flown on the map's word, as every multirotor with a horizontal
  LiDAR must. Unseen means a region (FreeSpace.unseen), not a lone voxel: the map keeps a flying
  object's voxels at the unknown value, so a drone being chased would otherwise stop its chaser.
Two levels, because a surface on a voxel boundary grows by a voxel as the LiDAR's returns land
on either side of it (agile seed 2: a tree's crown, 0.5 m nearer a sweep that had passed it at
1.7 m): that costs the margin, not the body, and a re-plan is the answer, not a stop.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.planner.freespace import SAMPLE_STEP, FreeSpace, densify

BRAKING_SHARE = 0.8  # of max_acceleration the stopping distance is reckoned with (the flight controller's)
OWN_BODY = 1.0  # m: unseen space nearer than this is the LiDAR's own body mask, not the world


@dataclass(frozen=True)
class GuardVerdict:
    action: str  # "clear", "replan" or "brake"
    reason: str = ""
    where: tuple[float, float, float] | None = None  # the first conflict
    ahead: float = math.inf  # m along the reference from the vehicle to it


CLEAR = GuardVerdict("clear")


def upcoming(positions: np.ndarray, start_ns: int, dt: float, now_ns: int, horizon: float) -> np.ndarray:
    """The reference's samples from `now` (interpolated) to `now + horizon` (its last point held)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) == 1 or dt <= 0:
        return positions[-1:].copy()
    u = (np.arange(int(math.ceil(horizon / dt)) + 1) * dt + (now_ns - start_ns) / 1e9) / dt
    u = np.clip(u, 0.0, len(positions) - 1)
    i = np.minimum(u.astype(np.int64), len(positions) - 2)
    f = (u - i)[:, None]
    return positions[i] + f * (positions[i + 1] - positions[i])


def check(space: FreeSpace, ahead: np.ndarray, vehicle: np.ndarray, speed: float, acceleration: float,
          accept: float, hard: float, *, view: float = 45.0, slack: float = 2.0,
          exempt: np.ndarray | None = None) -> GuardVerdict:
    """The verdict on the reference's next samples `ahead` (N, 3, from now) for a vehicle at
    `vehicle` moving at `speed` that brakes at up to `acceleration` (see the module docstring)."""
    if not space.known or len(ahead) == 0:
        return CLEAR
    points, _ = densify(np.vstack([vehicle, ahead]))
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    stopping = speed**2 / (2.0 * BRAKING_SHARE * max(acceleration, 1e-6)) + slack
    found = []  # (m ahead, point, why, braking)
    for need, braking in ((hard, True), (accept, False)):
        conflict = space.path_conflict(points, need, exempt)
        if conflict is not None:
            k = min(int(math.ceil(conflict)), len(points) - 1)
            found.append((along[k], points[k], f"closer than {need:.1f} m to an obstacle",
                          braking and along[k] <= stopping))
    unseen = _unseen_in_view(space, points, along, vehicle, stopping, view)
    if unseen is not None:
        found.append((along[unseen], points[unseen], "into space the LiDAR has not seen", True))
    if not found:
        return CLEAR
    distance, point, why, braking = min(found, key=lambda item: (not item[3], item[0]))
    return GuardVerdict("brake" if braking else "replan", f"the reference goes {why} {distance:.1f} m ahead",
                        tuple(map(float, point)), float(distance))


def _unseen_in_view(space: FreeSpace, points: np.ndarray, along: np.ndarray, vehicle: np.ndarray, reach: float,
                    view: float) -> int | None:
    """Index of the first point within `reach` along the reference that lies in unseen space inside
    the LiDAR's view from the vehicle (and beyond its own body)."""
    near = (along <= reach) & (along >= OWN_BODY - SAMPLE_STEP)
    if not near.any():
        return None
    offset = points - vehicle
    horizontal = np.linalg.norm(offset[:, :2], axis=1)
    distance = np.linalg.norm(offset, axis=1)
    elevation = np.degrees(np.arctan2(np.abs(offset[:, 2]), np.maximum(horizontal, 1e-9)))
    candidates = np.flatnonzero(near & (distance >= OWN_BODY) & (elevation <= view))
    if not len(candidates):
        return None
    unseen = space.unseen(points[candidates])
    return int(candidates[np.argmax(unseen)]) if unseen.any() else None


RANK = {"clear": 0, "replan": 1, "brake": 2}  # verdicts, best first


class Guardian:
    """What to do with the guard's verdicts, as state over the ticks (pure: times in, decisions out).

    A verdict other than clear asks for the command to be planned again, at most once every `retry`
    ns; the new plan is taken when the guard finds it better than the active reference (clear, or a
    re-plan where the reference would brake). A brake verdict that no new plan answers stops the
    vehicle: it holds (braking to rest) and the command is planned again every `retry` ns until a
    plan is clear. A command planned blocked holds the same way."""

    def __init__(self, retry_ns: int) -> None:
        self.retry_ns = retry_ns
        self.held = False  # the vehicle is braking or holding for the command
        self.retry_at = 0  # mission ns of the next re-plan allowed

    def wants_replan(self, now: int, verdict: GuardVerdict, has_command: bool) -> bool:
        """Whether to plan the command again now (then call `tried`)."""
        if not has_command or now < self.retry_at:
            return False
        if verdict.action == "clear":
            return self.held
        return not (self.held and verdict.action == "replan")  # holding already: the hold is what it is

    def tried(self, now: int) -> None:
        self.retry_at = now + self.retry_ns

    @staticmethod
    def takes(current: GuardVerdict, candidate: GuardVerdict) -> bool:
        """Whether a new plan with verdict `candidate` replaces the reference with verdict `current`."""
        return RANK[candidate.action] < max(RANK[current.action], RANK["replan"])

    def must_brake(self, verdict: GuardVerdict) -> bool:
        return verdict.action == "brake" and not self.held

    def hold(self, now: int) -> None:
        """The vehicle brakes to a hold for the command (the guard braked it, or it was planned blocked)."""
        self.held = True
        self.retry_at = now + self.retry_ns

    def release(self) -> None:
        """A new plan was taken."""
        self.held = False
