"""The parts every tracking filter is made of, after Stone Soup's decomposition.

A filter is a Predictor (carry an estimate forward in time) and an Updater (correct it with a
position measurement) sharing one Estimate type; an Initiator starts an estimate from a first
measurement, a Gater decides which measurements may update it, a Deleter decides when a track is
lost. Trackers (services/tracker/core.py for seed 000's multi-target tracker,
services/tracker/single.py for seed 002's single-target loop) use a filter only through these
protocols, so filters are compared by swapping one part (`make_filter(name, ...)`).

All parts are pure: numpy in, numpy out; time is an int stamp in ns handed in by the caller.
Estimates are never changed in place; every step returns a new one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from services.lib.runtime.clock import NS


@dataclass(frozen=True)
class Estimate:
    """A filter's belief at `stamp`: mean and covariance of the state (the constant-acceleration
    layout of seed 000 eq. 24: position, velocity, acceleration) plus whatever the filter carries
    besides (an adaptive filter's current Q and R, a particle filter's particles): `memory`."""

    mean: np.ndarray  # (9,)
    covariance: np.ndarray  # (9, 9)
    stamp: int  # ns
    memory: object = None

    @property
    def position(self) -> np.ndarray:
        return self.mean[:3]

    @property
    def velocity(self) -> np.ndarray:
        return self.mean[3:6]

    @property
    def position_covariance(self) -> np.ndarray:
        return self.covariance[:3, :3]


@dataclass(frozen=True)
class Innovation:
    """What a measurement would change: z - H x̂ and its covariance S = H P Hᵀ + R."""

    residual: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)

    @property
    def squared_mahalanobis(self) -> float:
        """d² = yᵀ S⁻¹ y (normalised innovation squared)."""
        return float(self.residual @ np.linalg.solve(self.covariance, self.residual))


@dataclass(frozen=True)
class Update:
    estimate: Estimate  # the corrected estimate
    innovation: Innovation  # before the correction


class Predictor(Protocol):
    def predict(self, estimate: Estimate, stamp: int) -> Estimate:
        """The estimate carried forward to `stamp` (never backwards: an older stamp returns it unchanged)."""


class Updater(Protocol):
    def innovation(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Innovation:
        """The innovation a position measurement (3,) with covariance `noise` (3, 3) would give."""

    def update(self, predicted: Estimate, position: np.ndarray, noise: np.ndarray) -> Update:
        """Correct `predicted` (already at the measurement's stamp) with the measurement."""


class Initiator(Protocol):
    def initiate(self, position: np.ndarray, noise: np.ndarray | None, stamp: int) -> Estimate:
        """A new estimate at `position` at rest (seed 000 eq. 32-33)."""


@dataclass(frozen=True)
class Filter:
    """One swappable filter: how estimates start, move and are corrected, under one name."""

    name: str
    initiator: Initiator
    predictor: Predictor
    updater: Updater


@dataclass
class InnovationStatistics:
    """Per-track running statistics for diagnosis: how many updates, the mean normalised innovation
    squared (about 3 for a consistent filter of 3-D measurements) and the last innovation's length."""

    updates: int = 0
    nis_sum: float = 0.0
    last_residual: float = 0.0
    extra: dict = field(default_factory=dict)

    def add(self, innovation: Innovation) -> None:
        self.updates += 1
        self.nis_sum += innovation.squared_mahalanobis
        self.last_residual = float(np.linalg.norm(innovation.residual))

    def merge(self, other: InnovationStatistics) -> None:
        if other.updates:
            self.updates += other.updates
            self.nis_sum += other.nis_sum
            self.last_residual = other.last_residual

    @property
    def mean_nis(self) -> float:
        return self.nis_sum / self.updates if self.updates else 0.0
