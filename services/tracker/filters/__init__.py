"""Tracking filters as swappable parts (base.py): "kf" the fixed-noise constant-acceleration Kalman
filter (seed 000 sec. III-F), "adaptive" the adaptive EKF of seed 002 (sec. 4.2), "particle" the
particle-filter baseline of seed 002 (sec. 5.2). All on the constant-acceleration model (models.py)."""
from __future__ import annotations

from services.tracker.filters.adaptive import AdaptiveInitiator, AdaptivePredictor, AdaptiveUpdater
from services.tracker.filters.base import Filter
from services.tracker.filters.kalman import CAInitiator, KalmanPredictor, KalmanUpdater
from services.tracker.filters.params import FilterParams
from services.tracker.filters.particle import ParticleInitiator, ParticlePredictor, ParticleUpdater

FILTERS = ("kf", "adaptive", "particle")

__all__ = ["FILTERS", "FilterParams", "make_filter"]


def make_filter(name: str, params: FilterParams) -> Filter:
    """The filter called `name` (one of FILTERS) with these parameters."""
    if name == "kf":
        return Filter(name, CAInitiator(params), KalmanPredictor(params), KalmanUpdater())
    if name == "adaptive":
        return Filter(name, AdaptiveInitiator(params), AdaptivePredictor(params), AdaptiveUpdater(params))
    if name == "particle":
        return Filter(name, ParticleInitiator(params), ParticlePredictor(params), ParticleUpdater(params))
    raise ValueError(f"unknown filter {name!r}: choose one of {', '.join(FILTERS)}")
