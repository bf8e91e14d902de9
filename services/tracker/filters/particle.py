"""The particle-filter baseline of seed 002 (sec. 5.2: 2000 particles, systematic resampling) on the
constant-acceleration model of seed 000 (eq. 27-31).

Particles move by x' = F x + ξ, ξ ~ N(0, Q(dt)) (eq. 28, Q of eq. 31); an update weighs each by the
Gaussian likelihood of the position measurement (eq. 29-30), in log-weights so that a measurement
far from every particle does not underflow them all to 0; the estimate's mean and covariance are
always the weighted particles' moments. Vectorised over particles: no Python loop runs per particle.

Resampling: systematic (one uniform draw for all N), and only when the effective sample size
1/Σw² falls below FilterParams.resample_threshold·N (N/2 by default); the copies are then
regularised (`_kernel_draws`: spread by a Gaussian kernel, so one heavy particle cannot become
the whole cloud). Resampling after every update
(threshold 1.0) throws away the weights' information and duplicates particles even when the
weights are nearly even, which is the sample impoverishment seed 002 observes as jitter.

Determinism: the same inputs give the same outputs, whatever else was computed before. There is
no Generator kept between calls (an Estimate is immutable, and a shared stream would make a
track's future depend on the order tracks were processed or on how often it was predicted for
display). Each step draws from a stream seeded by FilterParams.particle_seed, the kind of step,
its stamps and a digest of the estimate (and measurement) it starts from: distinct tracks get
distinct streams, the same step always the same one.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from services.tracker.filters.base import Estimate, Innovation, Update
from services.tracker.filters.kalman import initial_covariance, innovation_of
from services.tracker.filters.models import (
    MEASUREMENT_MATRIX, STATE_SIZE, seconds_between, symmetrised, transition,
)
from services.tracker.filters.params import FilterParams

_INITIATE, _PREDICT, _UPDATE = 1, 2, 3  # stream kinds: one step's draws never reuse another's
# The regularisation kernel's bandwidth relative to Silverman's rule: at 1 the extra spread blurs a
# smooth target's velocity (RMS 0.63 m/s against 0.26-0.48 for the other filters); at 0.5 the
# cloud keeps its spread and the velocity its accuracy (tests/test_tracker_filters.py, sparse).
KERNEL_SHRINK = 0.5
# Fewer effective particles than this: the cloud cannot represent the posterior (a measurement far
# outside it, after a long dropout: every weight but one or two underflows). The particles are drawn
# anew from the Gaussian posterior of the cloud's moments (the Gaussian particle filter's update,
# Kotecha & Djurić 2003); resampling would keep copies of the particle least far off (on `sparse`,
# 15 m from the measurement with a spread of 0.4 m, never to recover).
RESEED_BELOW = 2.0


@dataclass(frozen=True)
class ParticleMemory:
    """What the particle filter carries in Estimate.memory."""

    particles: np.ndarray  # (N, 9) states
    log_weights: np.ndarray  # (N,) normalised: logsumexp = 0


def digest(*arrays: np.ndarray) -> int:
    """A 64-bit digest of arrays' bytes: what tells one track's stream from another's."""
    h = hashlib.blake2b(digest_size=8)
    for array in arrays:
        h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return int.from_bytes(h.digest(), "little")


def random_stream(seed: int, *keys: int) -> np.random.Generator:
    """A Generator that is a function of its keys only (stamps may be negative: taken mod 2⁶⁴)."""
    return np.random.default_rng(np.random.SeedSequence([seed, *(k % 2**64 for k in keys)]))


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of N particles drawn systematically: the points (u + i) / N, u ~ U[0, 1), read
    against the cumulative weights. Each particle is kept about N·w times (within one), with less
    variance than multinomial resampling and one random number."""
    n = len(weights)
    cumulative = np.cumsum(weights)
    cumulative /= cumulative[-1]  # exactly 1 at the end whatever the rounding
    points = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cumulative, points, side="right"), n - 1)


def normalised(log_weights: np.ndarray) -> np.ndarray:
    """Log-weights shifted so their exponentials sum to 1 (log-sum-exp with the maximum taken out)."""
    top = log_weights.max()
    return log_weights - (top + np.log(np.exp(log_weights - top).sum()))


def weighted_moments(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = weights @ particles
    centred = particles - mean
    return mean, symmetrised((centred * weights[:, None]).T @ centred)


def effective_sample_size(weights: np.ndarray) -> float:
    return float(1.0 / np.sum(weights * weights))


def _from_particles(particles: np.ndarray, log_weights: np.ndarray, stamp: int) -> Estimate:
    mean, covariance = weighted_moments(particles, np.exp(log_weights))
    return Estimate(mean=mean, covariance=covariance, stamp=int(stamp),
                    memory=ParticleMemory(particles=particles, log_weights=log_weights))


def _drawn(mean: np.ndarray, covariance: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` states from N(mean, covariance) (an eigendecomposition, which a PSD but singular
    covariance also has, unlike a Cholesky factor)."""
    values, vectors = np.linalg.eigh(symmetrised(covariance))
    root = vectors * np.sqrt(np.clip(values, 0.0, None))
    return mean + rng.standard_normal((count, STATE_SIZE)) @ root.T


class ParticleInitiator:
    """Particles drawn from eq. 32-33 (position covariance raised to the measurement's, as the
    Kalman filters do)."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params

    def initiate(self, position: np.ndarray, noise: np.ndarray | None, stamp: int) -> Estimate:
        mean = np.concatenate([np.asarray(position, dtype=np.float64).reshape(3), np.zeros(6)])
        covariance = initial_covariance(self.params, noise)
        rng = random_stream(self.params.particle_seed, _INITIATE, stamp, digest(mean, covariance))
        particles = _drawn(mean, covariance, self.params.particles, rng)
        return _from_particles(particles, np.full(len(particles), -np.log(len(particles))), stamp)


def particles_of(estimate: Estimate, params: FilterParams, rng: np.random.Generator) -> ParticleMemory:
    """The estimate's particles; fresh ones from its mean and covariance for an estimate another
    filter made."""
    if isinstance(estimate.memory, ParticleMemory):
        return estimate.memory
    particles = _drawn(estimate.mean, estimate.covariance, params.particles, rng)
    return ParticleMemory(particles=particles, log_weights=np.full(len(particles), -np.log(len(particles))))


class ParticlePredictor:
    """x' = F x + ξ for every particle (eq. 28), ξ from the fixed Q of eq. 31 (diagonal: its square
    root is the per-component standard deviations)."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params

    def predict(self, estimate: Estimate, stamp: int) -> Estimate:
        if stamp <= estimate.stamp:  # never backwards
            return estimate
        dt = seconds_between(estimate.stamp, stamp)
        rng = random_stream(self.params.particle_seed, _PREDICT, estimate.stamp, stamp,
                            digest(estimate.mean, estimate.covariance))
        memory = particles_of(estimate, self.params, rng)
        deviations = np.sqrt(np.repeat(self.params.process_rates, 3) * dt)
        moved = memory.particles @ transition(dt).T
        moved += rng.standard_normal(moved.shape) * deviations
        return _from_particles(moved, memory.log_weights, stamp)


class ParticleUpdater:
    """Weights times the measurement's likelihood; systematic resampling when they degenerate."""

    def __init__(self, params: FilterParams) -> None:
        self.params = params

    def innovation(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Innovation:
        """The Gaussian approximation the gate needs: the particles' moments against the measurement."""
        return innovation_of(predicted.mean, predicted.covariance, position, np.asarray(noise, dtype=np.float64))

    def update(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Update:
        position = np.asarray(position, dtype=np.float64).reshape(3)
        noise = np.asarray(noise, dtype=np.float64)
        rng = random_stream(self.params.particle_seed, _UPDATE, predicted.stamp,
                            digest(predicted.mean, predicted.covariance, position, noise))
        memory = particles_of(predicted, self.params, rng)
        log_weights = normalised(memory.log_weights + log_likelihoods(memory.particles, position, noise))
        particles = memory.particles
        weights = np.exp(log_weights)
        innovation = innovation_of(predicted.mean, predicted.covariance, position, noise)
        if effective_sample_size(weights) < RESEED_BELOW:
            particles = _gaussian_posterior_draws(predicted, innovation, len(particles), rng)
            log_weights = np.full(len(particles), -np.log(len(particles)))
        elif effective_sample_size(weights) < self.params.resample_threshold * len(weights):
            particles = particles[systematic_resample(weights, rng)]
            particles = particles + _kernel_draws(predicted.covariance, innovation.covariance, len(particles), rng)
            log_weights = np.full(len(particles), -np.log(len(particles)))
        return Update(_from_particles(particles, log_weights, predicted.stamp), innovation)


def _gaussian_posterior_draws(predicted: Estimate, innovation: Innovation, count: int,
                              rng: np.random.Generator) -> np.ndarray:
    """N particles drawn from the Kalman posterior of the cloud's prior moments."""
    prior = predicted.covariance
    gain = np.linalg.solve(innovation.covariance, prior[:3, :]).T  # P Hᵀ S⁻¹
    mean = predicted.mean + gain @ innovation.residual
    return _drawn(mean, symmetrised(prior - gain @ prior[:3, :]), count, rng)


def _kernel_draws(prior: np.ndarray, innovation_covariance: np.ndarray, count: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Regularisation after resampling (the regularised particle filter of Musso, Oudjane & Le Gland,
    2001): each copy moves by a draw of a Gaussian kernel of bandwidth h = (4 / (N (d + 2)))^(1/(d+4))
    (Silverman's rule, times KERNEL_SHRINK) times the posterior's covariance. Without it a measurement at the edge of
    the cloud after a dropout leaves all the weight on one particle and resampling makes N copies
    of it, a cloud of zero spread that never recovers (seen on `sparse`: 12 m off, then kilometres).
    The posterior covariance is the Gaussian one from the particles' prior moments,
    P - P Hᵀ S⁻¹ H P, not the resampled particles' own: those are degenerate exactly then."""
    gain = np.linalg.solve(innovation_covariance, prior[:3, :]).T  # P Hᵀ S⁻¹ (S symmetric)
    posterior = symmetrised(prior - gain @ prior[:3, :])
    bandwidth = KERNEL_SHRINK * (4.0 / (count * (STATE_SIZE + 2))) ** (1.0 / (STATE_SIZE + 4))
    eigenvalues, vectors = np.linalg.eigh(posterior)
    root = vectors * np.sqrt(np.clip(eigenvalues, 0.0, None))  # posterior = root rootᵀ, PSD-safe
    return bandwidth * rng.standard_normal((count, STATE_SIZE)) @ root.T


def log_likelihoods(particles: np.ndarray, position: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """log N(z; H x, R) per particle, up to the constant every particle shares."""
    residuals = position - particles @ MEASUREMENT_MATRIX.T  # (N, 3)
    root = np.linalg.cholesky(symmetrised(noise))
    whitened = np.linalg.solve(root, residuals.T)  # L⁻¹ (z - H x): unit covariance
    return -0.5 * np.einsum("ij,ij->j", whitened, whitened)
