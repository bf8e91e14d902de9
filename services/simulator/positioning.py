"""The flight controller's position without GNSS: it flies on the onboard localizer's estimate.

A UAV whose positioning is "lidar" gets no odometry from the simulator's truth-plus-noise model;
its flight controller takes each estimate the localizer publishes (falconry/<uav>/localization)
and carries it on between estimates by its own inertial propagation. Simulated: the estimate's
error against the truth at the estimate's own stamp is held until the next estimate, so the
controller believes truth + error; it flies its reference by that belief (Fleet.offset), which
turns the estimation error into a real position error of the vehicle, and publishes the belief as
the UAV's odometry with the localizer's covariance and health. The heading error is held the same
way for the published heading; the simulated airframe's own heading control stays on the truth
(the vehicles are point masses with a heading: a heading error moves nothing). The velocity
published is the true one (a flight controller's inertial velocity is good to centimetres per
second over a scan's interval; the localizer's is in its own message).

An estimate stream that stops (the localizer frozen, starved of IMU samples or far behind) leaves
the controller carrying on a belief nothing refreshes: once the latest estimate is older than
`timeout`, the published health is "lost", whatever the last estimate said, so the job manager
holds and then lands as on a silent LiDAR (services/job_manager/core.py). A vanished localizer
token says the same in the job manager; this covers a localizer that is alive but silent. An
onboard flight-controller bridge has to do the same (PX4's EKF2 likewise drops an external vision
source whose data stop).

Pure: numpy in, numpy out; the stamps are the caller's (int ns of mission time).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from services.lib.geometry import wrap_angle

HISTORY = 200  # ticks of truth kept to meet a late estimate (10 s at the default 20 Hz)


@dataclass(frozen=True)
class EstimateError:
    """The latest estimate's error against the truth at its stamp."""

    stamp: int  # ns, the estimate's
    position: np.ndarray  # (3,) m, estimate − truth
    heading: float  # rad, estimate − truth, wrapped to (−π, π]
    covariance: np.ndarray  # (6, 6), the localizer's
    health: str


@dataclass(frozen=True)
class Belief:
    """What the flight controller publishes of a UAV flying without GNSS, besides its position
    (truth + the held error, which the vehicle flies on)."""

    heading_error: float  # rad, added to the true heading
    covariance: np.ndarray  # (6, 6), the latest estimate's
    health: str  # the latest estimate's, or "lost" once it is older than the timeout


class EstimateRelay:
    """Per UAV flying without GNSS: the true poses of the last HISTORY ticks and the latest estimate's
    error; `timeout` ns without a newer estimate make the belief's health "lost"."""

    def __init__(self, timeout: int) -> None:
        if timeout <= 0:
            raise ValueError(f"the estimate timeout must be positive, not {timeout} ns")
        self.timeout = int(timeout)
        self._truth: dict[str, deque[tuple[int, np.ndarray, float]]] = {}
        self.errors: dict[str, EstimateError] = {}

    def belief(self, uav: str, now: int) -> Belief | None:
        """The belief at mission time `now`; None before the first estimate (the launch pose is
        known without GNSS, so the truth then, with no health)."""
        error = self.errors.get(uav)
        if error is None:
            return None
        health = "lost" if now - error.stamp > self.timeout else error.health
        return Belief(error.heading, error.covariance, health)

    def record_truth(self, uav: str, stamp: int, position: np.ndarray, heading: float) -> None:
        history = self._truth.setdefault(uav, deque(maxlen=HISTORY))
        history.append((int(stamp), np.asarray(position, dtype=np.float64).copy(), float(heading)))

    def take_estimate(self, uav: str, stamp: int, position, heading: float, covariance: np.ndarray | None,
                      health: str) -> EstimateError | None:
        """The estimate's error, kept as the UAV's from now on; None (and nothing kept) when the
        truth at its stamp is no longer or not yet known, or the estimate is not finite."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        if not (np.isfinite(position).all() and math.isfinite(heading)):
            return None
        truth = next((t for t in reversed(self._truth.get(uav, ())) if t[0] == stamp), None)
        if truth is None:
            return None
        previous = self.errors.get(uav)
        if previous is not None and stamp < previous.stamp:
            return None  # an older estimate than the one held
        cov = np.full((6, 6), np.nan) if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(6, 6)
        turn = wrap_angle(heading - truth[2])
        error = EstimateError(int(stamp), position - truth[1], float(turn), cov, health)
        self.errors[uav] = error
        return error
