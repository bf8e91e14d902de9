"""The adaptive EKF of seed 002 (sec. 4.2, eq. 11-18): the constant-acceleration Kalman filter whose
process noise Q and measurement noise R follow the innovation and the residual, after Akhlaghi,
Zhou and Huang (2017). With a linear measurement (eq. 30) the "extended" filter is the linear one.

Each update, with the innovation d = z - H x⁻, the gain K and the residual ε = z - H x⁺:

    Q_k = α Q_k-1 + (1 - α) K d dᵀ Kᵀ                 (eq. 17)
    R_k = α R_k-1 + (1 - α) (ε εᵀ + H P Hᵀ)           (eq. 18)

Both are convex combinations of positive semi-definite terms (an outer product, a covariance), so
they stay PSD; only rounding can push an eigenvalue a hair below 0, which the bounds below remove.

What the seed leaves open, and how it is settled here:

- Which P debiases R. For ε = z - H x⁺ = R S⁻¹ d, E[ε εᵀ] = R S⁻¹ E[d dᵀ] S⁻¹ R, which is
  R - H P⁺ Hᵀ when the filter's P is the true error covariance (E[d dᵀ] = S): then the corrected P
  makes eq. 18 unbiased and the predicted P over-estimates R by H P⁻ Hᵀ S⁻¹ H P⁻ Hᵀ. But P is
  the true error covariance only if Q is, and the CA model's Q is a generous tuning knob (and
  eq. 17's estimate of it is biased, below). Per axis, with the filter's H P⁻ Hᵀ = m and the true
  one m_t, the corrected-P update settles at R = R_true - (m - m_t): an over-cautious P drives R
  down, to 0 when m - m_t > R_true. The predicted P errs the other way and never collapses (R
  stays above about H P⁻ Hᵀ). Measured on straight flight (10 Hz, σ 0.1 m, the caller's noise too
  small to floor anything, no ceiling): the corrected P settled at 0.5-0.7x the true R (NIS 4.4-5.9
  instead of 3), collapsed to 0.01x with the adapted Q and α 0.9; the predicted P at 3x (NIS
  0.8-0.9). Over five simulated flights (straight, turning, accelerating, noise stepping
  0.3 → 1.2 m; σ 0.3 m) the two tied when the caller's noise was about right; with it 10x too small
  the predicted P gave 0.8-0.9x the position error of the corrected one on four of five (the turn,
  whose model error is taken for measurement noise, 1.07x), with it 1000x too small 0.74-0.86x on
  all five, its NIS 2.1-5.2 against 6-28: it calibrates itself whatever the caller claims. The seed's
  eq. 18 was lost in extraction and seeds/README.md writes "H P Hᵀ" without saying which P;
  implementations of Akhlaghi's filter differ (a public MATLAB port, AbrahamLinc0ln/
  control-theory-practice, adds the predicted one). Default: the predicted P
  (FilterParams.adaptive_r_uses_prior = True); both are available and tested.
- Q per step or per second. Akhlaghi's Q is per (fixed-length) step. Our steps are irregular, so
  Q is kept as a rate per second, updated with the per-second sample K d dᵀ Kᵀ / Δt, where Δt is
  the time predicted since the last update (all of which the correction K d answers for, coasting
  included), and used as Q_rate · dt for every prediction. At a fixed period this is Akhlaghi's
  update exactly. Δt is taken no shorter than FilterParams.adaptive_min_interval, and Q is left
  alone after a zero-length prediction (two measurements at one stamp): no process noise acts in
  no time; such a correction fixes the earlier estimate, not the model.
- Bounds. Q is kept between adaptive_q_min_scale and adaptive_q_max_scale times the fixed Q, R at
  most adaptive_r_max, in the Loewner order (params.py says why).
- Which R the update uses: the adapted R raised (in the Loewner order) to at least the noise the
  caller gives, the detection's own covariance floored at measurement_variance. Poor returns (one or
  two LiDAR points on the target) make residuals large and R grow: the filter then trusts its
  model more. Below the caller's noise it never goes: a few smooth updates must not make the filter
  trust measurements more than the sensor model allows, which with sparse returns would make it
  follow their scatter. The stored R is the filter's own estimate, unfloored, so it shrinks back
  as soon as measurements improve.
- The gate (gating.py) sees the innovation covariance with this R and the adapted Q: "tighter when
  certain, wider after measurement gaps" (sec. 4.3).

E[K d dᵀ Kᵀ] = K S Kᵀ = P⁻ - P⁺, so the Q estimate is a heuristic: it matches Q only where
F P⁺ Fᵀ ≈ P⁺. It is what the seed specifies; the floor keeps its bias from starving the filter.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.tracker.filters.base import NS, Estimate, Innovation, Update
from services.tracker.filters.kalman import CAInitiator, Correction, corrected, innovation_of, predicted_moments
from services.tracker.filters.models import (
    bounded_in_units_of, clipped_eigenvalues, covariance_at_least, seconds_between,
)
from services.tracker.filters.params import FilterParams


@dataclass(frozen=True)
class AdaptiveMemory:
    """What the adaptive filter carries in Estimate.memory."""

    q_rate: np.ndarray  # (9, 9) process noise per second of prediction
    r: np.ndarray  # (3, 3) measurement noise as estimated from the residuals
    since_update: int = 0  # ns predicted since the last update: the span the next correction covers


def initial_memory(params: FilterParams, noise: np.ndarray | None) -> AdaptiveMemory:
    """The fixed filter's noise to start from: Q of eq. 31, R the measurement's (floored)."""
    floor = params.measurement_variance * np.eye(3)
    r = floor if noise is None else covariance_at_least(np.asarray(noise, dtype=np.float64), floor)
    return AdaptiveMemory(q_rate=np.diag(np.repeat(params.process_rates, 3)), r=r)


class AdaptiveInitiator:
    """Eq. 32-33 as the fixed filter, with the fixed noise as the first Q and R."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params
        self._start = CAInitiator(params)

    def initiate(self, position: np.ndarray, noise: np.ndarray | None, stamp: int) -> Estimate:
        estimate = self._start.initiate(position, noise, stamp)
        return replace(estimate, memory=initial_memory(self.params, noise))


def memory_of(estimate: Estimate, params: FilterParams) -> AdaptiveMemory:
    """The estimate's adapted noise; the fixed one for an estimate another filter started."""
    memory = estimate.memory
    return memory if isinstance(memory, AdaptiveMemory) else initial_memory(params, None)


class AdaptivePredictor:
    """Eq. 11-12 with the estimate's own current Q (per second, times dt)."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params

    def predict(self, estimate: Estimate, stamp: int) -> Estimate:
        if stamp <= estimate.stamp:  # never backwards: a late measurement is applied to the current state
            return estimate
        memory = memory_of(estimate, self.params)
        dt = seconds_between(estimate.stamp, stamp)
        mean, covariance = predicted_moments(estimate.mean, estimate.covariance, dt, memory.q_rate * dt)
        memory = replace(memory, since_update=memory.since_update + (stamp - estimate.stamp))
        return Estimate(mean=mean, covariance=covariance, stamp=int(stamp), memory=memory)


class AdaptiveUpdater:
    """Eq. 13-16 with the adapted R, then eq. 17-18 (module docstring)."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params
        self._q_unit = np.repeat(params.process_rates, 3)

    def measurement_noise(self, memory: AdaptiveMemory, noise: np.ndarray) -> np.ndarray:
        """The R an update uses: the adapted one, at least the caller's in every direction."""
        return covariance_at_least(memory.r, np.asarray(noise, dtype=np.float64))

    def innovation(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Innovation:
        r = self.measurement_noise(memory_of(predicted, self.params), noise)
        return innovation_of(predicted.mean, predicted.covariance, position, r)

    def update(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Update:
        memory = memory_of(predicted, self.params)
        c = corrected(predicted.mean, predicted.covariance, position, self.measurement_noise(memory, noise))
        adapted = AdaptiveMemory(
            q_rate=self._adapted_q(memory, c),
            r=self._adapted_r(memory, predicted, c, np.asarray(position, dtype=np.float64).reshape(3)),
        )
        estimate = Estimate(mean=c.mean, covariance=c.covariance, stamp=predicted.stamp, memory=adapted)
        return Update(estimate, c.innovation)

    def _adapted_q(self, memory: AdaptiveMemory, c: Correction) -> np.ndarray:
        """Eq. 17 per second of prediction."""
        if memory.since_update <= 0:
            return memory.q_rate
        p, span = self.params, max(memory.since_update / NS, self.params.adaptive_min_interval)
        step = c.gain @ c.innovation.residual  # K d: how far the correction moved the state
        q = p.alpha * memory.q_rate + (1.0 - p.alpha) * np.outer(step, step) / span
        return bounded_in_units_of(q, self._q_unit, p.adaptive_q_min_scale, p.adaptive_q_max_scale)

    def _adapted_r(self, memory: AdaptiveMemory, predicted: Estimate, c: Correction, position: np.ndarray) -> np.ndarray:
        """Eq. 18, debiased with the predicted (by default) or the corrected position covariance."""
        p = self.params
        residual = position - c.mean[:3]  # ε = z - H x⁺
        debias = predicted.covariance[:3, :3] if p.adaptive_r_uses_prior else c.covariance[:3, :3]
        r = p.alpha * memory.r + (1.0 - p.alpha) * (np.outer(residual, residual) + debias)
        return clipped_eigenvalues(r, 0.0, p.adaptive_r_max)
