"""The tracker's re-identifier: a confirmed track dropped as too uncertain is remembered for a while,
so that the same target back in sight takes its identity (and its detections) back instead of
starting over under a new id. Two moments look it up:
- at a new track's birth (`at_birth`, within `reidentify_time`): the remembered track whose target
  would now be nearest the new one, its last corrected state carried on by the tracker's manoeuvre
  model, within r_max;
- at a track's confirmation (`at_confirmation`, within `stitch_time`): one that moves like it
  (both faster than `moving_speed`, or both slower) and lies within its reach (r_max, plus
  `stitch_speed` × the time since for a mover), nearest relative to that reach.
A track found is taken out of the memory. Pure: numpy in, numpy out; stamps in ns.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.lib.runtime.clock import NS
from services.lib.tracks import manoeuvre_path
from services.tracker.filters.base import Estimate


@dataclass(frozen=True)
class LostTrack:
    """A confirmed track dropped as too uncertain, remembered for re-identification."""

    id: int
    corrected: Estimate  # its last corrected state
    detections: int
    dropped: int  # ns
    half_width: float = 0.0  # m, its target's size as it knew it


class LostTracks:
    def __init__(self, radius_max: float, reidentify_time: float, stitch_time: float, manoeuvre_time: float,
                 moving_speed: float, stitch_speed: float) -> None:
        self.radius_max, self.reidentify_time, self.stitch_time = radius_max, reidentify_time, stitch_time
        self.manoeuvre_time, self.moving_speed, self.stitch_speed = manoeuvre_time, moving_speed, stitch_speed
        self._lost: list[LostTrack] = []

    def __len__(self) -> int:
        return len(self._lost)

    def remember(self, lost: LostTrack) -> None:
        self._lost.append(lost)

    def forget_before(self, now: int) -> None:
        """Forget the tracks dropped longer ago than either lookup reaches."""
        limit = int(max(self.reidentify_time, self.stitch_time) * NS)
        self._lost = [lost for lost in self._lost if now - lost.dropped <= limit]

    def at_birth(self, estimate: Estimate) -> LostTrack | None:
        """The remembered track whose target would be nearest `estimate` by its stamp (within
        radius_max; its last corrected state carried on by the published trajectory's manoeuvre
        model), taken out of the memory; None when none is that close."""
        limit = int(self.reidentify_time * NS)
        best, best_gap = None, self.radius_max
        for lost in self._lost:
            elapsed = (estimate.stamp - lost.corrected.stamp) / NS
            if elapsed <= 0.0 or estimate.stamp - lost.dropped > limit:
                continue
            (expected,) = manoeuvre_path(lost.corrected.mean, elapsed, 1, self.manoeuvre_time)
            gap = float(np.linalg.norm(expected - estimate.position))
            if gap <= best_gap:
                best, best_gap = lost, gap
        return self._taken(best)

    def at_confirmation(self, estimate: Estimate, velocity: np.ndarray) -> LostTrack | None:
        """The lost track, remembered within stitch_time, that `estimate` moving at `velocity` moves
        like and is nearest to relative to its reach; taken out of the memory. None when there is none."""
        moving = float(np.linalg.norm(velocity)) > self.moving_speed
        best, best_share = None, 1.0
        for lost in self._lost:
            elapsed = (estimate.stamp - lost.corrected.stamp) / NS
            was_moving = float(np.linalg.norm(lost.corrected.mean[3:6])) > self.moving_speed
            if elapsed <= 0.0 or elapsed > self.stitch_time or moving != was_moving:
                continue
            reach = self.radius_max + (self.stitch_speed * elapsed if moving else 0.0)
            share = float(np.linalg.norm(estimate.mean[:3] - lost.corrected.mean[:3])) / reach
            if share <= best_share:
                best, best_share = lost, share
        return self._taken(best)

    def _taken(self, lost: LostTrack | None) -> LostTrack | None:
        if lost is not None:
            self._lost.remove(lost)
        return lost
