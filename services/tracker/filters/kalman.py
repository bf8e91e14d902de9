"""The fixed-noise constant-acceleration Kalman filter of seed 000 (sec. III-F1, eq. 27-33), the
"Fixed CA-KF" baseline of seed 002 (sec. 5.2), and the Kalman algebra the adaptive EKF reuses.

Plain numpy rather than filterpy: a 9×9 filter is a handful of small matrix products, which numpy
does directly in a few µs, while filterpy's KalmanFilter object carries mutable state (at odds with
estimates that are never changed in place) and takes over a second to import with scipy. The
measurement selects the position (eq. 30), so P Hᵀ and H P Hᵀ are slices of P, not products.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.tracker.filters.base import Estimate, Innovation, Update
from services.tracker.filters.models import (
    STATE_SIZE, covariance_at_least, process_noise, seconds_between, symmetrised, transition,
)
from services.tracker.filters.params import FilterParams


def initial_covariance(params: FilterParams, noise: np.ndarray | None) -> np.ndarray:
    """Eq. 33, with the position block raised to at least the measurement's own covariance when
    given (the seed's note to eq. 33: a known sensor uncertainty replaces the empirical value
    where it is larger). Raised in the Loewner order, so every direction is covered."""
    covariance = np.diag(np.repeat(params.initial_variances, 3))
    if noise is not None:
        floor = params.p0_position * np.eye(3)
        covariance[:3, :3] = covariance_at_least(np.asarray(noise, dtype=np.float64), floor)
    return covariance


def predicted_moments(mean: np.ndarray, covariance: np.ndarray, dt: float, noise: np.ndarray):
    """(F x, F P Fᵀ + Q) over dt seconds (eq. 28) with the process noise Q for that dt."""
    f = transition(dt)
    return f @ mean, symmetrised(f @ covariance @ f.T + noise)


@dataclass(frozen=True)
class Correction:
    """A Kalman correction with what the adaptive filter needs besides the corrected moments."""

    mean: np.ndarray  # x⁺
    covariance: np.ndarray  # P⁺
    gain: np.ndarray  # K (9, 3)
    innovation: Innovation  # d = z - H x⁻ and S = H P⁻ Hᵀ + R


def innovation_of(mean: np.ndarray, covariance: np.ndarray, position: np.ndarray, noise: np.ndarray) -> Innovation:
    residual = np.asarray(position, dtype=np.float64).reshape(3) - mean[:3]
    return Innovation(residual=residual, covariance=symmetrised(covariance[:3, :3] + noise))


def corrected(mean: np.ndarray, covariance: np.ndarray, position: np.ndarray, noise: np.ndarray) -> Correction:
    """The Kalman update with the position measurement, P⁺ in Joseph form,
    (I - K H) P (I - K H)ᵀ + K R Kᵀ: a sum of PSD terms, so P⁺ stays symmetric positive
    semi-definite under rounding, where the short form (I - K H) P slowly loses both."""
    noise = np.asarray(noise, dtype=np.float64)
    innovation = innovation_of(mean, covariance, position, noise)
    gain = np.linalg.solve(innovation.covariance, covariance[:, :3].T).T  # K = P Hᵀ S⁻¹ (S symmetric)
    keep = np.eye(STATE_SIZE)
    keep[:, :3] -= gain  # I - K H
    joseph = keep @ covariance @ keep.T + gain @ noise @ gain.T
    return Correction(mean + gain @ innovation.residual, symmetrised(joseph), gain, innovation)


class CAInitiator:
    """A new estimate at the detection, at rest (eq. 32), with the covariance of eq. 33."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params

    def initiate(self, position: np.ndarray, noise: np.ndarray | None, stamp: int) -> Estimate:
        mean = np.concatenate([np.asarray(position, dtype=np.float64).reshape(3), np.zeros(6)])
        return Estimate(mean=mean, covariance=initial_covariance(self.params, noise), stamp=int(stamp))


class KalmanPredictor:
    """Eq. 28 with the fixed process noise of eq. 31 (per second, times dt)."""

    def __init__(self, params: FilterParams) -> None:
        self.rates = params.process_rates

    def predict(self, estimate: Estimate, stamp: int) -> Estimate:
        if stamp <= estimate.stamp:  # never backwards: a late measurement is applied to the current state
            return estimate
        dt = seconds_between(estimate.stamp, stamp)
        mean, covariance = predicted_moments(estimate.mean, estimate.covariance, dt, process_noise(self.rates, dt))
        return replace(estimate, mean=mean, covariance=covariance, stamp=int(stamp))


class KalmanUpdater:
    """The standard Kalman correction with the measurement noise the caller gives."""

    def innovation(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Innovation:
        return innovation_of(predicted.mean, predicted.covariance, position, np.asarray(noise, dtype=np.float64))

    def update(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Update:
        c = corrected(predicted.mean, predicted.covariance, position, noise)
        return Update(replace(predicted, mean=c.mean, covariance=c.covariance), c.innovation)
