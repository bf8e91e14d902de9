"""Mahalanobis gating (seed 002 sec. 4.3, eq. 19): a measurement may update an estimate only if its
normalised innovation squared d² = yᵀ S⁻¹ y is within the χ² quantile of the gate probability for
3 degrees of freedom (a position measurement): d² ≤ 11.34 at 0.99. The gate is an ellipsoid that
follows S = H P Hᵀ + R: tighter when the estimate is certain, wider after measurement gaps."""
from __future__ import annotations

from typing import Protocol

import numpy as np

from services.tracker.filters.base import Innovation
from services.tracker.filters.models import symmetrised

MEASUREMENT_DIMENSIONS = 3


class Gater(Protocol):
    def accepts(self, innovation: Innovation) -> bool:
        """Whether this innovation may update the estimate."""

    def squared_distances(self, predicted_position: np.ndarray, covariance: np.ndarray,
                          positions: np.ndarray) -> np.ndarray:
        """The gate's distance² of each of `positions` (N, 3) from a predicted position."""


class MahalanobisGater:
    def __init__(self, probability: float) -> None:
        if not 0.0 < probability < 1.0:
            raise ValueError(f"gate probability must be in (0, 1), got {probability}")
        # the χ² quantile as scipy.special's inverse survival function: scipy.stats (chi2.ppf, the same
        # figure) takes 0.45 s more to import, which the tracker's setup would spend before its
        # liveliness token (the launcher's 2 s restart promise)
        from scipy.special import chdtri

        self.probability = probability
        self.threshold = float(chdtri(MEASUREMENT_DIMENSIONS, 1.0 - probability))

    def accepts(self, innovation: Innovation) -> bool:
        return innovation.squared_mahalanobis <= self.threshold

    def squared_distances(self, predicted_position: np.ndarray, covariance: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """d² of each of the (N, 3) positions from the predicted position under the innovation
        covariance S (3, 3): (N,). Through S's Cholesky factor L, d² = |L⁻¹ y|²."""
        residuals = np.asarray(positions, dtype=np.float64).reshape(-1, 3) - np.asarray(predicted_position).reshape(3)
        root = np.linalg.cholesky(symmetrised(np.asarray(covariance, dtype=np.float64)))
        whitened = np.linalg.solve(root, residuals.T)
        return np.einsum("ij,ij->j", whitened, whitened)

    def within(self, predicted_position: np.ndarray, covariance: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(N,) bool: which positions pass the gate."""
        return self.squared_distances(predicted_position, covariance, positions) <= self.threshold
