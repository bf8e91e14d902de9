"""Target bookkeeping of the job manager (seed 004 §3.5.2 and §4.2): the target filter that
locks the chosen target, forbidden zones, attack tries, and the filter every detection goes
through before the state machine sees it.

Pure: numpy in, numpy out; every time is an int ns stamp passed in by the caller.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from services.geometry import point_in_polygon

NS = 1_000_000_000


class TargetFilter:
    """Seed 004 §4.2 "balloon filter": a linear KF with a static-object model in 3D, started
    at the chosen target; each scan it takes the detection closest to its prediction within
    `gate` (d_e) and ignores the rest. `streak_start` is when the current run of detections
    without a gap longer than `max_gap` began: the target counts as confirmed for t_m once
    now − streak_start ≥ t_m.

    Beside the KF, a straight-line fit over the taken detections of the last `history_ns`
    measures the target's velocity, so a target that moves (an intruder drone) is noticed,
    gated where it will be and handed to interception; for a balloon it stays near zero."""

    MIN_FIT_POINTS = 5
    MIN_FIT_SPAN_NS = 500_000_000

    def __init__(self, position: np.ndarray, stamp: int, *, gate: float, measurement_sigma: float,
                 process_sigma: float, max_gap_ns: int, history_ns: int = 2 * NS,
                 velocity: np.ndarray | None = None, max_speed: float = 5.0) -> None:
        from filterpy.kalman import KalmanFilter  # imported here: see services/runtime/warmup.py

        kf = KalmanFilter(dim_x=3, dim_z=3)
        kf.x = np.asarray(position, dtype=np.float64).reshape(3, 1).copy()
        kf.F = np.eye(3)
        kf.H = np.eye(3)
        kf.P = np.eye(3) * measurement_sigma**2
        kf.R = np.eye(3) * measurement_sigma**2
        self._kf = kf
        self._process_variance = process_sigma**2
        self.gate = gate
        self.max_speed = max_speed  # of any target: how far one may go unseen, before its velocity is known
        self.max_gap_ns = max_gap_ns
        self.history_ns = history_ns
        self.last_seen = stamp
        self.streak_start = stamp
        self.updates = 1
        self._last_predict = stamp
        self._history: deque[tuple[int, np.ndarray]] = deque([(stamp, kf.x.reshape(3).copy())])
        self._prior_velocity = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64).reshape(3)
        self.velocity = self._prior_velocity.copy()
        self._velocity_known = velocity is not None

    @property
    def estimate(self) -> np.ndarray:
        return self._kf.x.reshape(3).copy()

    @property
    def last_position(self) -> np.ndarray:
        return self._history[-1][1].copy()

    def predict(self, stamp: int) -> np.ndarray:
        """Where the target is at `stamp`: its last detection carried along the fitted velocity."""
        return self.last_position + self.velocity * ((stamp - self.last_seen) / NS)

    def update(self, positions: np.ndarray, stamp: int) -> bool:
        """One scan's detections (N, 3); True when one of them was taken as the target."""
        elapsed = max(stamp - self._last_predict, 0) / NS
        self._kf.Q = np.eye(3) * self._process_variance * max(elapsed, 1e-3)  # a static target may still sway
        self._kf.predict()
        self._last_predict = stamp
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        if not len(positions):
            return False
        gaps = np.linalg.norm(positions - self.predict(stamp), axis=1)
        best = int(np.argmin(gaps))
        # until its velocity is known, a target may have moved since it was last seen
        unknown = 0.0 if self._velocity_known else self.max_speed * min((stamp - self.last_seen) / NS, 1.0)
        grown = self.gate + unknown
        if gaps[best] > grown:
            return False
        self._kf.update(positions[best].reshape(3, 1))
        if stamp - self.last_seen > self.max_gap_ns:
            self.streak_start = stamp
        self.last_seen = stamp
        self.updates += 1
        self._history.append((stamp, positions[best].copy()))
        while stamp - self._history[0][0] > self.history_ns:
            self._history.popleft()
        self._fit_velocity()
        return True

    def _fit_velocity(self) -> None:
        if len(self._history) < self.MIN_FIT_POINTS or \
                self._history[-1][0] - self._history[0][0] < self.MIN_FIT_SPAN_NS:
            return
        t = np.array([h[0] for h in self._history], dtype=np.float64) / NS
        xyz = np.array([h[1] for h in self._history])
        t -= t.mean()
        self.velocity = (t @ (xyz - xyz.mean(axis=0))) / (t @ t)
        self._velocity_known = True

    def speed(self) -> float:
        return float(np.linalg.norm(self.velocity))

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
                      claimed: np.ndarray, claim_radius: float, min_z: float) -> np.ndarray:
    """(N,) bool: the detections the state machine may act on — inside this UAV's working
    area, outside every forbidden zone, not a target a partner has claimed (`claimed` (K, 3)),
    and above `min_z` (a captured drone lying on the ground is no target)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    keep = positions[:, 2] >= min_z
    if area is not None and len(area) >= 3 and len(positions):
        keep &= np.atleast_1d(point_in_polygon(positions[:, :2], area))
    keep &= ~zones.contains(positions)
    claimed = np.asarray(claimed, dtype=np.float64).reshape(-1, 3)
    if len(claimed) and len(positions):
        keep &= (np.linalg.norm(positions[:, None, :] - claimed[None], axis=2) > claim_radius).all(axis=1)
    return keep
