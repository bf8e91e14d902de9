"""Target bookkeeping of the job manager (seed 004 §3.5.2 and §4.2): the target filter that
locks the chosen target, forbidden zones, attack tries, and the filter every detection goes
through before the state machine sees it.

Pure: numpy in, numpy out; every time is an int ns stamp passed in by the caller.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from services.lib.geometry import distance_to_edges, is_covariance, point_in_polygon, with_variance_floor
from services.lib.runtime.clock import NS


class TargetFilter:
    """Seed 004 §4.2 "balloon filter": a linear KF with a static-object model in 3D, started
    at the chosen target; each scan or frame it takes the detection that fits its prediction best
    and ignores the rest. `streak_start` is when the current run of detections without a gap
    longer than `max_gap` began: the target counts as confirmed for t_m once
    now − streak_start ≥ t_m.

    Beside the KF, a straight-line fit over the taken detections of the last `history_ns`
    measures the target's velocity, so a target that moves (an intruder drone) is noticed,
    gated where it will be and handed to interception; for a balloon it stays near zero.

    Detections carry their covariance (the LiDAR's are a few decimetres; a camera's range from a
    far balloon's size is metres off along the line of sight, a few centimetres across it). The
    seed's filter takes one fixed noise; here each detection weighs by its own (raised to at
    least `measurement_sigma`², which also covers a balloon's sway): in the KF update, in the gate
    (a detection is the target when it lies within `gate` of the prediction, or within the 99 %
    ellipsoid of the prediction's and the detection's covariances — long along a camera's ray,
    narrow across it), and in the velocity fit (weighted least squares, whose standard error says
    whether a fitted speed is motion or noise: `moves`). Without that, ten camera frames of a
    balloon 30 m away "move" at metres per second.

    A target the camera's balloon detector saw (`update(..., tethered=True)`) is a balloon on its
    tether: it never moves and is predicted where the KF holds it. The camera's range is also
    biased, not only noisy — from the balloon's size until the depth image reaches it (10 m), then
    from depth — and a metre's jump between the two reads as motion to any velocity fit."""

    MIN_FIT_POINTS = 5
    MIN_FIT_SPAN_NS = 500_000_000
    GATE_CHI2 = 11.34  # χ² with 3 degrees of freedom, 99 %

    def __init__(self, position: np.ndarray, stamp: int, *, gate: float, measurement_sigma: float,
                 process_sigma: float, max_gap_ns: int, history_ns: int = 2 * NS,
                 velocity: np.ndarray | None = None, max_speed: float = 5.0,
                 covariance: np.ndarray | None = None, tethered: bool = False,
                 observed: int | None = None) -> None:
        from filterpy.kalman import KalmanFilter  # imported here: see services/lib/runtime/warmup.py

        self._floor = measurement_sigma**2
        first_noise = self._noise(covariance)
        kf = KalmanFilter(dim_x=3, dim_z=3)
        kf.x = np.asarray(position, dtype=np.float64).reshape(3, 1).copy()
        kf.F = np.eye(3)
        kf.H = np.eye(3)
        kf.P = first_noise.copy()
        kf.R = np.eye(3) * self._floor
        self._kf = kf
        self._process_variance = process_sigma**2
        self.gate = gate
        self.max_speed = max_speed  # of any target: how far one may go unseen, before its velocity is known
        self.max_gap_ns = max_gap_ns
        self.history_ns = history_ns
        self.last_seen = stamp
        # When the newest taken detection was really made: a partner's track is a detection at its
        # message's stamp, predicted there from the partner's last scan of it (`observed`).
        self.last_observed = stamp if observed is None else min(observed, stamp)
        self.streak_start = stamp
        self.updates = 1
        self._last_predict = stamp
        self._history: deque[tuple[int, np.ndarray, float]] = deque(
            [(stamp, kf.x.reshape(3).copy(), self._weight(first_noise))])
        self._prior_velocity = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64).reshape(3)
        self.velocity = self._prior_velocity.copy()
        self.velocity_sigma = math.inf  # standard error of the fitted velocity, m/s per axis
        self._fit_anchor: tuple[float, np.ndarray] | None = None  # (weighted mean time s, position there)
        self._velocity_known = velocity is not None
        self.tethered = tethered  # the camera's balloon detector saw it: a balloon

    def _noise(self, covariance: np.ndarray | None) -> np.ndarray:
        usable = covariance is not None and is_covariance(covariance)
        return with_variance_floor(covariance if usable else None, self._floor)

    @staticmethod
    def _weight(noise: np.ndarray) -> float:
        """The velocity fit's weight of a detection: 1 / its largest variance (a scalar weight
        that never trusts a detection more than its worst direction deserves)."""
        return 1.0 / float(np.linalg.eigvalsh(noise)[-1])

    @property
    def estimate(self) -> np.ndarray:
        return self._kf.x.reshape(3).copy()

    @property
    def last_position(self) -> np.ndarray:
        return self._history[-1][1].copy()

    def predict(self, stamp: int) -> np.ndarray:
        """Where the target is at `stamp`: a balloon where the KF holds it; else on the fitted line
        once there is one, else its last detection carried along the velocity it was handed."""
        if self.tethered:
            return self.estimate
        if self._fit_anchor is not None:
            t_mean, at_mean = self._fit_anchor
            return at_mean + self.velocity * (stamp / NS - t_mean)
        return self.last_position + self.velocity * ((stamp - self.last_seen) / NS)

    def _extrapolation_variance(self, stamp: int) -> float:
        """Per axis, m²: what the fitted velocity's standard error adds to the line's prediction."""
        if self._fit_anchor is None:
            return 0.0
        return (self.velocity_sigma * (stamp / NS - self._fit_anchor[0])) ** 2

    def update(self, positions: np.ndarray, stamp: int, covariances: np.ndarray | None = None,
               tethered: bool = False, observed: np.ndarray | None = None) -> bool:
        """One scan's or frame's detections (N, 3) with their covariances (N, 3, 3) if known,
        `tethered` when they come from the balloon detector, `observed` (N,) when each was really
        made if earlier than `stamp`; True when one of them was taken."""
        elapsed = max(stamp - self._last_predict, 0) / NS
        self._kf.Q = np.eye(3) * self._process_variance * max(elapsed, 1e-3)  # a static target may still sway
        self._kf.predict()
        self._last_predict = stamp
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        if not len(positions):
            return False
        noises = [self._noise(None if covariances is None else covariances[k]) for k in range(len(positions))]
        offsets = positions - self.predict(stamp)
        gaps = np.linalg.norm(offsets, axis=1)
        # until its velocity is known, a target may have moved since it was last seen
        unknown = 0.0 if self._velocity_known else self.max_speed * min((stamp - self.last_seen) / NS, 1.0)
        spread = self._kf.P + np.eye(3) * (unknown**2 + self._extrapolation_variance(stamp))
        mahalanobis = np.array([float(d @ np.linalg.solve(spread + r, d)) for d, r in zip(offsets, noises)])
        inside = (gaps <= self.gate + unknown) | (mahalanobis <= self.GATE_CHI2)
        if not inside.any():
            return False
        best = int(np.argmin(np.where(inside, mahalanobis, np.inf)))
        self._kf.update(positions[best].reshape(3, 1), R=noises[best])
        self.tethered = self.tethered or tethered
        if stamp - self.last_seen > self.max_gap_ns:
            self.streak_start = stamp
        self.last_seen = stamp
        made = stamp if observed is None else min(int(np.asarray(observed).reshape(-1)[best]), stamp)
        self.last_observed = max(self.last_observed, made)
        self.updates += 1
        self._history.append((stamp, positions[best].copy(), self._weight(noises[best])))
        while stamp - self._history[0][0] > self.history_ns:
            self._history.popleft()
        self._fit_velocity()
        return True

    def reanchor(self, position: np.ndarray, stamp: int, velocity: np.ndarray,
                 covariance: np.ndarray | None = None, observed: int | None = None) -> None:
        """Start again from a sighting the gate refused, on the tracker's word that it is the
        target: the same confirmed track, corrected by a scan just now. A drone that brakes and
        turns while out of sight leaves the straight line fitted before for good, and every later
        sighting falls outside the gate; without this the target counts as gone while the tracker
        still sees it a few centimetres from where it is. The fit starts afresh from here, along
        the tracker's velocity until it has points of its own."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        noise = self._noise(covariance)
        self._kf.x = position.reshape(3, 1).copy()
        self._kf.P = noise.copy()
        self._last_predict = stamp
        if stamp - self.last_seen > self.max_gap_ns:
            self.streak_start = stamp
        self.last_seen = stamp
        self.last_observed = max(self.last_observed, stamp if observed is None else min(observed, stamp))
        self.updates += 1
        self._history = deque([(stamp, position.copy(), self._weight(noise))])
        self.velocity = np.asarray(velocity, dtype=np.float64).reshape(3).copy()
        self.velocity_sigma = math.inf
        self._fit_anchor = None
        self._velocity_known = True

    def _fit_velocity(self) -> None:
        """Weighted least-squares line through the history: velocity, its standard error, and the
        weighted mean time and position the line passes through."""
        if len(self._history) < self.MIN_FIT_POINTS or \
                self._history[-1][0] - self._history[0][0] < self.MIN_FIT_SPAN_NS:
            return
        t = np.array([h[0] for h in self._history], dtype=np.float64) / NS
        xyz = np.array([h[1] for h in self._history])
        w = np.array([h[2] for h in self._history])
        t_mean = float(w @ t / w.sum())
        at_mean = w @ xyz / w.sum()
        dt = t - t_mean
        spread = float(w @ dt**2)
        self.velocity = (w * dt) @ (xyz - at_mean) / spread
        self.velocity_sigma = math.sqrt(1.0 / spread)
        self._fit_anchor = (t_mean, at_mean)
        self._velocity_known = True

    def adopt_velocity(self, velocity: np.ndarray) -> None:
        """A velocity found elsewhere (the tracker's), taken while the filter has fitted none."""
        if self._fit_anchor is None:
            self.velocity = np.asarray(velocity, dtype=np.float64).reshape(3).copy()
            self._velocity_known = True

    def speed(self) -> float:
        return float(np.linalg.norm(self.velocity))

    def moves(self, min_speed: float, sigmas: float) -> bool:
        """Not a balloon, and the fitted speed is at least `min_speed` and `sigmas` standard errors
        above zero."""
        if self.tethered:
            return False
        speed = self.speed()
        return speed >= min_speed and speed >= sigmas * self.velocity_sigma

    def confirmed_for(self, now: int) -> float:
        """Seconds the target has been seen without a gap (0 once the gap exceeds max_gap)."""
        if now - self.last_seen > self.max_gap_ns:
            return 0.0
        return (now - self.streak_start) / NS


@dataclass(frozen=True)
class ForbiddenZone:
    center: tuple[float, float, float]
    created: int  # ns
    expires: int  # ns
    reason: str


@dataclass
class ForbiddenZones:
    """Spheres of radius r_f that filter out every detection inside them for t_f (seed 004
    §3.5.2). `tries` counts finished attacks per place: the n_f-th try at the same place (within
    r_f) makes a forbidden zone too."""

    radius: float
    lifetime_ns: int
    max_tries: int
    zones: list[ForbiddenZone] = field(default_factory=list)
    _tries: list[list] = field(default_factory=list)  # [center (3,), count]

    def add(self, center: np.ndarray, now: int, reason: str) -> ForbiddenZone:
        c = np.asarray(center, dtype=np.float64).reshape(3)
        zone = ForbiddenZone((float(c[0]), float(c[1]), float(c[2])), now, now + self.lifetime_ns, reason)
        self.zones.append(zone)
        self._tries = [t for t in self._tries if np.linalg.norm(t[0] - c) > self.radius]
        return zone

    def expire(self, now: int) -> list[ForbiddenZone]:
        gone = [z for z in self.zones if now >= z.expires]
        self.zones = [z for z in self.zones if now < z.expires]
        return gone

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: inside a live zone (call `expire` first)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not self.zones or not len(points):
            return np.zeros(len(points), dtype=bool)
        centers = np.array([z.center for z in self.zones])
        return (np.linalg.norm(points[:, None, :] - centers[None], axis=2) <= self.radius).any(axis=1)

    def count_try(self, place: np.ndarray, now: int) -> ForbiddenZone | None:
        """One more finished attack at `place`; the n_f-th one forbids the place."""
        p = np.asarray(place, dtype=np.float64).reshape(3)
        for entry in self._tries:
            if np.linalg.norm(entry[0] - p) <= self.radius:
                entry[1] += 1
                if entry[1] >= self.max_tries:
                    return self.add(p, now, f"{entry[1]} tries")
                return None
        self._tries.append([p, 1])
        if self.max_tries <= 1:
            return self.add(p, now, "1 try")
        return None

    def tries_at(self, place: np.ndarray) -> int:
        p = np.asarray(place, dtype=np.float64).reshape(3)
        return next((int(t[1]) for t in self._tries if np.linalg.norm(t[0] - p) <= self.radius), 0)


def usable_detections(positions: np.ndarray, *, area: np.ndarray | None, zones: ForbiddenZones,
                      claimed: np.ndarray, claim_radius: float, min_z: float, area_overlap: float = 0.0,
                      arena: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: the detections the state machine may act on — inside this UAV's working
    area or within `area_overlap` of it inside the `arena`, outside every forbidden zone, not a target a partner
    has claimed (`claimed` (K, 3)), and above `min_z` (a captured drone lying on the ground is
    no target).

    The overlap is not in the seed: a balloon on the line between two areas is seen a few
    decimetres on either side from frame to frame (a camera's range from size is metres off
    far away), so with strict areas each UAV may leave it to the other for a minute; with the
    overlap both may take it, and the claims keep it to one chaser."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    keep = positions[:, 2] >= min_z
    if area is not None and len(area) >= 3 and len(positions):
        inside = np.atleast_1d(point_in_polygon(positions[:, :2], area))
        if area_overlap > 0:
            near = distance_to_edges(positions[:, :2], area) <= area_overlap
            if arena is not None:
                near &= np.atleast_1d(point_in_polygon(positions[:, :2], arena))
            inside |= near
        keep &= inside
    keep &= ~zones.contains(positions)
    claimed = np.asarray(claimed, dtype=np.float64).reshape(-1, 3)
    if len(claimed) and len(positions):
        keep &= (np.linalg.norm(positions[:, None, :] - claimed[None], axis=2) > claim_radius).all(axis=1)
    return keep
