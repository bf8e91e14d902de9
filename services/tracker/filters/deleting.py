"""When a track is lost: seed 000 drops a track whose uncertainty radius grew beyond r_max (Alg. 2
line 15: no measurement corrected it for a while); seed 002 re-initialises a track after N
consecutive steps without a measurement in its gate (sec. 4.3), which bounds how far it
extrapolates. The tracker counts the missed steps (it knows when a step had no measurement); a
deleter only decides."""
from __future__ import annotations

from typing import Protocol

from services.tracker.filters.base import Estimate
from services.tracker.filters.models import uncertainty_radius


class Deleter(Protocol):
    def deletes(self, estimate: Estimate | None, missed_steps: int) -> bool:
        """Whether the track with this estimate, unmatched for `missed_steps` consecutive steps, is lost."""


class UncertaintyDeleter:
    """Seed 000: lost when r_unc (eq. 26) > r_max."""

    def __init__(self, r_max: float, r_min: float, c_r: float) -> None:
        self.r_max, self.r_min, self.c_r = r_max, r_min, c_r

    def deletes(self, estimate: Estimate, missed_steps: int = 0) -> bool:
        return uncertainty_radius(estimate.covariance, self.r_min, self.c_r) > self.r_max


class MissedStepsDeleter:
    """Seed 002: lost after `max_missed` consecutive missed steps (then re-initialised from the next
    valid cluster by the tracker)."""

    def __init__(self, max_missed: int) -> None:
        if max_missed < 1:
            raise ValueError(f"max_missed must be at least 1, got {max_missed}")
        self.max_missed = max_missed

    def deletes(self, estimate: Estimate | None, missed_steps: int) -> bool:
        return missed_steps >= self.max_missed
