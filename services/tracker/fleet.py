"""The fleet picture: a UAV's own tracks joined with the confirmed tracks its partners keep.

Each tracker publishes its tracks; each also listens to its partners' and publishes the union:
- an own track and a partner's track of the same target (positions within the sum of their
  uncertainty radii, seed 000's similarity rule of Alg. 2 line 26; nearest first, one to one)
  are fused by covariance intersection (Julier & Uhlmann 1997):
      P⁻¹ = ω P_a⁻¹ + (1 − ω) P_b⁻¹,   x = P (ω P_a⁻¹ x_a + (1 − ω) P_b⁻¹ x_b),
  with ω ∈ [0, 1] minimising trace(P) (on a grid refined once: `_trace_minimising_omega`). CI is consistent
  whatever the correlation between the two estimates, which is unknown here: the two trackers
  saw the same target, often in the same scans' time, and each may already hold the other's
  information from an earlier exchange. A Kalman-style fusion would count it twice and grow
  overconfident. An own track not yet confirmed is fused too, but published under the
  partner's fleet id and `source` (below) until our tracker confirms it: a tentative number
  published as a confirmed own track would be one identity too many. The node first hands
  its tracker the tentative tracks that a partner's confirmed track of the same target
  corroborates (`corroborating`), which confirms them and gives them their identity (possibly
  a lost track's; core.py, `partner_confirms`). Being the same target is judged more strictly
  there than for fusion: the positions' difference within the χ² gate (`gate_probability`, 3
  degrees of freedom) of the sum of their covariances (leaving out the unknown correlation of
  the two estimates, which shared process noise makes positive, widens the gate), not merely
  within the sum of their uncertainty radii, which is at least 2 r_min = 5 m: a sporadic false
  detection beside a partner's target must not be confirmed by it;
- a partner's track no own track matches is published as a track of ours with `source` set to
  the partner, under a fleet id: 1,000,000 × the partner's number + its id (stable while the
  partner keeps its id, never equal to an own id), so a UAV can go for a target only a partner sees.

Only a partner's own tracks are taken (`source` = that partner): the fleet tracks it publishes
came from someone else, who is heard directly. The fusion is on output only: own filters never
take partner data, so a partner's error cannot feed back into our estimates; a partner's track
can only confirm a tentative one of ours that it corroborates. Partner tracks are
carried to the output's stamp by the constant-acceleration model (eq. 27) and dropped once
older than `stale_after`: a cut link or a fallen partner only removes its contribution (a
confirmation it gave stands, like a count of detections).

Pure: stamps are int ns handed in by the node.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace

import numpy as np

from services.tracker.filters.base import NS
from services.tracker.filters.gating import MahalanobisGater
from services.tracker.filters.kalman import predicted_moments
from services.tracker.filters.models import process_noise, uncertainty_radius

FLEET_ID_BASE = 1_000_000
OMEGA_STEPS = 21


@dataclass(frozen=True)
class PartnerTrack:
    id: int  # the partner's own id
    stamp: int  # ns, the time its mean and covariance hold at
    mean: np.ndarray  # (9,) position, velocity, acceleration
    covariance: np.ndarray  # (9, 9)
    detections: int
    last_correction: int = 0  # ns, its last correction by the partner's scans or detections (0: not said)


@dataclass(frozen=True)
class PartnerReport:
    """One track of a partner's Tracks message, as heard (before the fleet picture admits it)."""

    id: int
    confirmed: bool
    source: str  # the UAV that keeps it (its own tracks: the partner)
    mean: np.ndarray
    covariance: np.ndarray
    detections: int
    last_correction: int  # ns


def admitted(partner: str, heard: int, sensor_healthy: bool,
             reports: list[PartnerReport]) -> tuple[list[PartnerTrack], int]:
    """The partner tracks the fleet picture takes from one message of `partner` heard at `heard`,
    and how many it refused as unsound. None while the partner's LiDAR fails its sanity check (its
    tracks may be of nothing); of the others only its own confirmed tracks (a partner's fleet
    tracks come from their keepers, heard directly), and of those only a finite positive-definite
    CA state with an own id (below FLEET_ID_BASE)."""
    if not sensor_healthy:
        return [], 0
    tracks, refused = [], 0
    for report in reports:
        if not report.confirmed or report.source != partner:
            continue
        covariance = report.covariance.reshape(9, 9) if report.covariance.size == 81 else report.covariance
        if not (sound_partner_track(report.mean, covariance) and 0 <= report.id < FLEET_ID_BASE):
            refused += 1
            continue
        tracks.append(PartnerTrack(report.id, heard, report.mean, covariance, report.detections,
                                   min(report.last_correction, heard)))
    return tracks, refused


@dataclass(frozen=True)
class FleetTrack:
    """One track of the fleet picture at the output's stamp."""

    id: int
    mean: np.ndarray  # (9,)
    covariance: np.ndarray  # (9, 9)
    detections: int
    confirmed: bool
    source: str  # the UAV that keeps it (ours for an own track, fused or not)
    fused_with: tuple[str, ...] = ()  # partners whose tracks were fused into an own track
    last_correction: int = 0  # ns, the latest correction of any track fused into it (0: not known)


@dataclass(frozen=True)
class FusionParams:
    radius_min: float
    radius_confidence: float
    process_rates: tuple[float, float, float]  # per-second variances of position, velocity, acceleration
    stale_after: float = 1.0  # s without news from a partner before its tracks are left out
    gate_probability: float = 0.99  # χ² mass of the gate within which a partner's track corroborates ours


def covariance_intersection(mean_a: np.ndarray, cov_a: np.ndarray, mean_b: np.ndarray, cov_b: np.ndarray,
                            omega: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Fused (mean, covariance, ω); ω = None picks the trace-minimising one in [0, 1]."""
    info_a, info_b = np.linalg.inv(cov_a), np.linalg.inv(cov_b)
    if omega is None:
        omega = _trace_minimising_omega(info_a, info_b)
    covariance = np.linalg.inv(omega * info_a + (1.0 - omega) * info_b)
    mean = covariance @ (omega * info_a @ mean_a + (1.0 - omega) * info_b @ mean_b)
    return mean, 0.5 * (covariance + covariance.T), omega


def _trace_minimising_omega(info_a: np.ndarray, info_b: np.ndarray) -> float:
    """ω of the smallest trace(P), on a grid of OMEGA_STEPS refined once around the best: one batched
    inverse per pass (a scalar minimiser's ~25 separate 9x9 inverses cost ~0.5 ms per fused
    pair and tick; the trace is convex in ω, so a grid finds its minimum to 1/(OMEGA_STEPS-1)²)."""
    low, high = 0.0, 1.0
    for _ in range(2):
        omegas = np.linspace(low, high, OMEGA_STEPS)
        traces = np.trace(np.linalg.inv(omegas[:, None, None] * info_a + (1.0 - omegas)[:, None, None] * info_b),
                          axis1=1, axis2=2)
        best = int(np.argmin(traces))
        step = (high - low) / (OMEGA_STEPS - 1)
        low, high = max(0.0, omegas[best] - step), min(1.0, omegas[best] + step)
    return float(omegas[best])


def partner_number(name: str) -> int:
    """uav2 → 2 (a fleet id's prefix); 0 for a name without a number."""
    found = re.search(r"(\d+)$", name)
    return int(found.group(1)) if found else 0


class FleetPicture:
    def __init__(self, params: FusionParams) -> None:
        self.params = params
        self._partners: dict[str, tuple[int, list[PartnerTrack]]] = {}  # name → (when heard, tracks)
        self._gater = MahalanobisGater(params.gate_probability)

    def partner_tracks(self, partner: str, heard: int, tracks: list[PartnerTrack]) -> None:
        """A partner's latest confirmed own tracks (replacing what it said before)."""
        self._partners[partner] = (heard, list(tracks))

    def partners(self, now: int) -> dict[str, list[PartnerTrack]]:
        """The partners heard within stale_after of `now`, with their tracks."""
        limit = int(self.params.stale_after * NS)
        return {name: tracks for name, (heard, tracks) in sorted(self._partners.items()) if now - heard <= limit}

    def fuse(self, own: list[FleetTrack], now: int) -> list[FleetTrack]:
        """`own` (at `now`) joined with every fresh partner's tracks carried to `now`."""
        out = list(own)
        tentative = {i for i, t in enumerate(own) if not t.confirmed}  # published as a partner's when fused
        for partner, tracks in self.partners(now).items():
            carried = [self._carried(t, now) for t in tracks]
            matches = self._matches(out, carried)
            for k, track in enumerate(carried):
                if k in matches:
                    out[matches[k]] = self._fused(out[matches[k]], track, partner)
                    if matches[k] in tentative:
                        tentative.discard(matches[k])
                        out[matches[k]] = replace(out[matches[k]], id=self.fleet_id(partner, track.id), source=partner)
                else:
                    out.append(FleetTrack(self.fleet_id(partner, track.id), track.mean, track.covariance,
                                          track.detections, True, partner, last_correction=track.last_correction))
        return out

    def corroborating(self, own: list[FleetTrack], now: int) -> dict[int, np.ndarray]:
        """The own tentative tracks a fresh partner's confirmed track corroborates, by id, with that
        partner's velocity of the target: the two positions' difference within the χ² gate of
        their summed covariances (the nearest such partner track by d², over every partner)."""
        velocities: dict[int, np.ndarray] = {}
        carried = [self._carried(t, now) for tracks in self.partners(now).values() for t in tracks]
        if not carried:
            return velocities
        for mine in own:
            if mine.confirmed:
                continue
            gaps = [self._gater.squared_distances(mine.mean[:3], mine.covariance[:3, :3] + t.covariance[:3, :3],
                                                  t.mean[:3])[0] for t in carried]
            best = int(np.argmin(gaps))
            if gaps[best] <= self._gater.threshold:
                velocities[mine.id] = carried[best].mean[3:6].copy()
        return velocities

    @staticmethod
    def fleet_id(partner: str, track_id: int) -> int:
        return partner_number(partner) * FLEET_ID_BASE + track_id

    def _carried(self, track: PartnerTrack, now: int) -> PartnerTrack:
        dt = max(0.0, (now - track.stamp) / NS)
        mean, covariance = predicted_moments(track.mean, track.covariance, dt,
                                             process_noise(self.params.process_rates, dt))
        return replace(track, stamp=now, mean=mean, covariance=covariance)

    def _radius(self, covariance: np.ndarray) -> float:
        return uncertainty_radius(covariance, self.params.radius_min, self.params.radius_confidence)

    def _matches(self, own: list[FleetTrack], theirs: list[PartnerTrack]) -> dict[int, int]:
        """Partner track index → output track index: similar pairs (Alg. 2 line 26), nearest first,
        each track used once (a track another partner added takes part too: two partners seeing
        one target we do not see give one track)."""
        pairs = []
        for i, mine in enumerate(own):
            for k, track in enumerate(theirs):
                gap = float(np.linalg.norm(mine.mean[:3] - track.mean[:3]))
                if gap <= self._radius(mine.covariance) + self._radius(track.covariance):
                    pairs.append((gap, i, k))
        used_own, matches = set(), {}
        for _, i, k in sorted(pairs):
            if i not in used_own and k not in matches:
                used_own.add(i)
                matches[k] = i
        return matches

    def _fused(self, mine: FleetTrack, theirs: PartnerTrack, partner: str) -> FleetTrack:
        try:
            mean, covariance, _ = covariance_intersection(mine.mean, mine.covariance, theirs.mean, theirs.covariance)
        except np.linalg.LinAlgError:  # a singular covariance (a degenerate filter): keep ours
            return mine
        return replace(mine, mean=mean, covariance=covariance, detections=max(mine.detections, theirs.detections),
                       confirmed=True, fused_with=mine.fused_with + (partner,),
                       last_correction=max(mine.last_correction, theirs.last_correction))


def sound_partner_track(mean: np.ndarray, covariance: np.ndarray) -> bool:
    """A partner's state and covariance we can fuse: the CA layout, finite, symmetric positive definite."""
    if mean.shape != (9,) or covariance.shape != (9, 9):
        return False
    if not (np.isfinite(mean).all() and np.isfinite(covariance).all()):
        return False
    if not np.allclose(covariance, covariance.T, atol=1e-9 * max(1.0, float(np.abs(covariance).max()))):
        return False
    return bool(np.linalg.eigvalsh(covariance).min() > 0)
