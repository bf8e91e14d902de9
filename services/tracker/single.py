"""Seed 002's single-target tracking loop (sec. 2 Stages II-III, sec. 4.3), composed from the parts
of services/tracker/filters (base.py's protocols).

Per scan, given the front end's candidates (services/tracker/frontend.py):

1. Before the first estimate: initialise from a valid candidate (eq. 32-33 through the filter's
   initiator): the one nearest to a seed position handed in, if within its radius, otherwise the
   cluster with the most returns (the most drone-like evidence in a scan of 1-4 returns).
2. Predict the estimate to the scan's stamp (eq. 11-12).
3. Gate (eq. 19): the candidates' squared Mahalanobis distances under the innovation covariance S;
   the nearest one updates the estimate (eq. 13-16) if it passes the χ² gate. Every candidate is
   given the same measurement noise, so S is the same for all and the nearest in d² is the only
   one worth testing.
4. Otherwise the step is missed and the estimate coasts on the prediction alone (eq. 20).
5. Recovery, a part that is there or not (a Deleter, filters/deleting.py): once the deleter says
   the track is lost (seed 002: N consecutive missed steps), the estimate stops being carried
   forward ("bounding the prediction horizon": it stays where the N-th prediction left it) and the
   next scan with a valid candidate re-initialises it from the candidate nearest to where the
   target was last seen (its last update). Not to the coasted prediction: after N missed steps
   that is the constant-acceleration extrapolation that diverges, while a single target is still
   most likely near where it was last measured. Without a deleter (seed 002's fixed CA-KF) the
   estimate coasts for as long as nothing passes the gate, and the gate, which widens with P,
   eventually lets the target back in wherever the extrapolation has gone.

Pure: stamps are int ns handed in, no clock; the time per step is the benchmark's to measure.
"""
from __future__ import annotations

import enum
from collections.abc import Iterable
from dataclasses import dataclass

import msgspec
import numpy as np

from services.tracker.filters.base import Estimate, Filter, Innovation
from services.tracker.filters.deleting import Deleter
from services.tracker.filters.gating import Gater
from services.tracker.frontend import Candidates


class SingleTargetParams(msgspec.Struct, forbid_unknown_fields=True):
    # Eq. 19: the χ² probability inside the gate (3 degrees of freedom: d² <= 11.34 at 0.99), the
    # seed's example value.
    gate_probability: float = 0.99
    # Seed 002's recovery after N consecutive missed steps (its N was lost). 5 steps, 0.5 s at
    # 10 Hz: long enough not to cut the track in the ordinary gaps of a target returning 1-4
    # points (about 45 % of the sparse scenario's scans give no valid candidate, so runs of 3-4
    # misses are common), short enough that the constant-acceleration extrapolation has not yet
    # left the target: a reversed 3 m/s² acceleration puts it 0.5·6·0.5² = 0.75 m off by then, 3 m
    # after 1 s. Chosen on held-out seeds (11-20 of benchmarks/tracking_comparison.py, not the
    # reported 1-5): the adaptive EKF's 3-D RMSE was 0.54 / 0.51 / 0.53 / 0.55 / 0.59 / 0.65 /
    # 0.73 m for N = 3 / 4 / 5 / 6 / 8 / 10 / 15; the fixed KF with recovery prefers 10 (0.41 m
    # against 0.44 m at 5). 5 rather than 4: the flat optimum, and fewer resets of the velocity.
    recovery: bool = True
    max_missed: int = 5
    # m², the measurement noise R given with every candidate (the fixed KF and the particle filter take it as
    # given; the adaptive one adapts above it). Not the cluster's covariance (eq. 5): that is the
    # spread of 1-4 returns over the drone's surface, rank 1 for two returns, not the error of
    # their centroid. The centroids are about 0.25 m from the drone's centre in the sparse
    # scenario (the LiDAR sees its near side): σ ≈ 0.15 m per axis, 0.02 m². Kept at 0.1 m², the
    # filters' own floor (FilterParams.measurement_variance, seed 000's value), one R for every
    # filter and not tuned: on seeds 11-20 less R helps the fixed KF with recovery (0.35 m 3-D
    # RMSE at 0.03 m² against 0.41 m) and makes it diverge further without (2.0 m against 1.0 m).
    measurement_variance: float = 0.1
    # m: with a seed position, the first estimate starts only from a candidate within this of it.
    seed_radius: float = 5.0

    def __post_init__(self) -> None:
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if self.max_missed < 1:
            raise ValueError(f"max_missed must be >= 1, got {self.max_missed}")
        if not self.measurement_variance > 0 or not self.seed_radius > 0:
            raise ValueError("measurement_variance and seed_radius must be > 0")


class Outcome(enum.Enum):
    WAITING = "waiting"  # no estimate yet, no valid candidate
    INITIATED = "initiated"  # the first estimate, from a candidate
    UPDATED = "updated"  # a candidate passed the gate
    COASTED = "coasted"  # predicted only (eq. 20)
    LOST = "lost"  # recovery declared the track lost: held, waiting for a candidate
    REINITIATED = "reinitiated"  # recovery: a fresh estimate from a candidate


MEASURED = (Outcome.INITIATED, Outcome.UPDATED, Outcome.REINITIATED)


@dataclass(frozen=True)
class ScanRecord:
    """What one scan did to the track."""

    stamp: int  # ns, the scan's
    estimate: Estimate | None  # after the scan (None before the first candidate)
    outcome: Outcome
    innovation: Innovation | None  # of the candidate that updated, before the correction
    candidates: int  # valid candidates offered
    missed: int  # consecutive missed steps after this scan

    @property
    def updated(self) -> bool:
        """Whether a measurement went into the estimate (an update or a (re)initialisation)."""
        return self.outcome in MEASURED


class SingleTargetTracker:
    def __init__(self, filter: Filter, gater: Gater, deleter: Deleter | None, noise: np.ndarray,
                 seed: np.ndarray | None = None, seed_radius: float = np.inf) -> None:
        """`deleter` None: no recovery. `noise` (3, 3): the R given with every candidate. `seed`:
        where to look for the target first (None: anywhere)."""
        self.filter = filter
        self.gater = gater
        self.deleter = deleter
        self.noise = np.asarray(noise, dtype=np.float64).reshape(3, 3)
        self.seed = None if seed is None else np.asarray(seed, dtype=np.float64).reshape(3)
        self.seed_radius = seed_radius
        self.estimate: Estimate | None = None
        self.missed = 0
        self.lost = False
        self.last_seen: np.ndarray | None = None  # position of the last measurement used

    def step(self, stamp: int, candidates: Candidates) -> ScanRecord:
        positions = np.asarray(candidates.positions, dtype=np.float64).reshape(-1, 3)
        if self.estimate is None:
            return self._first(stamp, positions, np.asarray(candidates.sizes))
        if self.lost:
            return self._recover(stamp, positions)
        predicted = self.filter.predictor.predict(self.estimate, stamp)
        chosen = self._gated(predicted, positions)
        if chosen is not None:
            update = self.filter.updater.update(predicted, positions[chosen], self.noise)
            self.estimate = update.estimate
            self.missed, self.last_seen = 0, positions[chosen]
            return self._record(stamp, Outcome.UPDATED, positions, update.innovation)
        self.estimate = predicted
        self.missed += 1
        self.lost = self.deleter is not None and self.deleter.deletes(predicted, self.missed)
        return self._record(stamp, Outcome.COASTED, positions)

    def _first(self, stamp: int, positions: np.ndarray, sizes: np.ndarray) -> ScanRecord:
        chosen = self._seeded(positions, sizes)
        if chosen is None:
            return self._record(stamp, Outcome.WAITING, positions)
        self._start(stamp, chosen)
        return self._record(stamp, Outcome.INITIATED, positions)

    def _seeded(self, positions: np.ndarray, sizes: np.ndarray) -> np.ndarray | None:
        """The candidate to start from: the nearest to the seed if within its radius; with no seed
        the one with the most returns (the first of those)."""
        if not len(positions):
            return None
        if self.seed is None:
            return positions[int(np.argmax(sizes))]
        distances = np.linalg.norm(positions - self.seed, axis=1)
        nearest = int(np.argmin(distances))
        return positions[nearest] if distances[nearest] <= self.seed_radius else None

    def _recover(self, stamp: int, positions: np.ndarray) -> ScanRecord:
        if not len(positions):
            self.missed += 1
            return self._record(stamp, Outcome.LOST, positions)  # held: no more extrapolation
        nearest = int(np.argmin(np.linalg.norm(positions - self.last_seen, axis=1)))
        self._start(stamp, positions[nearest])
        return self._record(stamp, Outcome.REINITIATED, positions)

    def _start(self, stamp: int, position: np.ndarray) -> None:
        self.estimate = self.filter.initiator.initiate(position, self.noise, stamp)
        self.missed, self.lost, self.last_seen = 0, False, position

    def _gated(self, predicted: Estimate, positions: np.ndarray) -> int | None:
        """The index of the candidate nearest in d² if it passes the gate (eq. 19), else None."""
        if not len(positions):
            return None
        first = self.filter.updater.innovation(predicted, positions[0], self.noise)
        centre = positions[0] - first.residual  # H x̂ as the filter sees it
        distances = self.gater.squared_distances(centre, first.covariance, positions)
        nearest = int(np.argmin(distances))
        innovation = Innovation(residual=positions[nearest] - centre, covariance=first.covariance)
        return nearest if self.gater.accepts(innovation) else None

    def _record(self, stamp: int, outcome: Outcome, positions: np.ndarray,
                innovation: Innovation | None = None) -> ScanRecord:
        return ScanRecord(int(stamp), self.estimate, outcome, innovation, len(positions), self.missed)


def single_target_tracker(filter: Filter, params: SingleTargetParams,
                          seed: np.ndarray | None = None) -> SingleTargetTracker:
    """The loop with seed 002's parts: a χ² Mahalanobis gate, recovery after N missed steps when
    params.recovery, and R = measurement_variance · I for every candidate."""
    from services.tracker.filters.deleting import MissedStepsDeleter
    from services.tracker.filters.gating import MahalanobisGater

    deleter = MissedStepsDeleter(params.max_missed) if params.recovery else None
    return SingleTargetTracker(filter, MahalanobisGater(params.gate_probability), deleter,
                               params.measurement_variance * np.eye(3), seed, params.seed_radius)


def track(tracker: SingleTargetTracker, scans: Iterable[tuple[int, Candidates]]) -> list[ScanRecord]:
    """Run the loop over (stamp, candidates) in time order."""
    return [tracker.step(stamp, candidates) for stamp, candidates in scans]
