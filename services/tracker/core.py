"""Tracker core: multi-target tracking of flying-object detections with one
constant-acceleration Kalman filter per track (seed 000, sec. III-F, eq. 24-33).

FIRST VERSION (walking skeleton): tracks are updated from the classifier's detections only,
associated by global nearest neighbour (scipy's linear_sum_assignment) inside each track's
uncertainty radius r = max(r_min, c_r * cbrt(det P_pos)) (eq. 26). Unmatched detections start
tentative tracks (eq. 32-33), a track is confirmed after 2 detections and dropped once r > r_max.
Later issues deepen it to Alg. 2: a buffer of the last N point clouds through which each
detection is tracked to the newest scan, point clusters inside r as measurements, rejection
of clusters near occupied map voxels, track merging by similarity, and alternative filters
(adaptive EKF of seed 002, particle filter baseline).

The Kalman algebra is filterpy's. Pure: stamps are int ns handed in by the node.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from services.geometry import is_covariance, with_variance_floor

NS = 1_000_000_000
H = np.hstack([np.eye(3), np.zeros((3, 6))])  # eq. 30: the measurement is the position


class TrackerParams(msgspec.Struct, forbid_unknown_fields=True):
    # Process noise, per second of prediction (eq. 31): variances of position, velocity, acceleration.
    q_position: float = 0.01
    q_velocity: float = 0.8
    q_acceleration: float = 0.05
    # Initial covariance of a new track (eq. 33), variances.
    p0_position: float = 0.3
    p0_velocity: float = 1.0
    p0_acceleration: float = 0.05
    measurement_variance: float = 0.1  # R = 0.1 I, raised to the detection covariance where larger
    radius_min: float = 2.5  # m, r_min of eq. 26
    radius_confidence: float = 1.5  # c_r of eq. 26
    radius_max: float = 5.0  # m, tracks more uncertain than this are dropped
    confirm_detections: int = 2
    # Bounded work per scan whatever the input: a LiDAR returning garbage must not make the
    # tracker spend the whole tick on thousands of spurious tracks.
    max_tracks: int = 64
    alive_period: float = 1.0  # s; the node sends an empty Tracks at least this often


def transition(dt: float) -> np.ndarray:
    """State-transition matrix of the constant-acceleration model (eq. 27)."""
    eye = np.eye(3)
    return np.block([
        [eye, dt * eye, 0.5 * dt * dt * eye],
        [np.zeros((3, 3)), eye, dt * eye],
        [np.zeros((3, 3)), np.zeros((3, 3)), eye],
    ])


def process_noise(params: TrackerParams, dt: float) -> np.ndarray:
    rates = np.repeat([params.q_position, params.q_velocity, params.q_acceleration], 3)
    return np.diag(rates * dt)


def uncertainty_radius(params: TrackerParams, covariance: np.ndarray) -> float:
    """Eq. 26: r = max(r_min, c_r * cbrt(det(H P H^T)))."""
    det = max(float(np.linalg.det(covariance[:3, :3])), 0.0)
    return float(max(params.radius_min, params.radius_confidence * np.cbrt(det)))


def measurement_noise(params: TrackerParams, detection_covariance: np.ndarray | None) -> np.ndarray:
    """R = the detection covariance with each variance raised to at least the floor (stays PSD)."""
    return with_variance_floor(detection_covariance, params.measurement_variance)


@dataclass
class TrackEstimate:
    id: int
    state: np.ndarray  # (9,) position, velocity, acceleration
    covariance: np.ndarray  # (9, 9)
    detections: int
    confirmed: bool
    uncertainty_radius: float
    last_detection: int  # ns


class _Track:
    def __init__(self, track_id: int, params: TrackerParams, position: np.ndarray, stamp_ns: int) -> None:
        self.id = track_id
        from filterpy.kalman import KalmanFilter  # imported here: see services/runtime/warmup.py

        self.kf = KalmanFilter(dim_x=9, dim_z=3)
        self.kf.H = H.copy()
        self.kf.x = np.concatenate([position, np.zeros(6)])
        self.kf.P = np.diag(np.repeat([params.p0_position, params.p0_velocity, params.p0_acceleration], 3))
        self.stamp_ns = stamp_ns  # time of the filter's state
        self.detections = 1
        self.last_detection = stamp_ns

    def predict_to(self, params: TrackerParams, stamp_ns: int) -> None:
        dt = (stamp_ns - self.stamp_ns) / NS
        if dt > 0:  # never predict backwards: an older detection is applied to the current state
            self.kf.predict(F=transition(dt), Q=process_noise(params, dt))
            self.stamp_ns = stamp_ns


class TrackerCore:
    def __init__(self, params: TrackerParams | None = None) -> None:
        self.params = params or TrackerParams()
        self._tracks: list[_Track] = []
        self._next_id = 1
        self.rejected_detections = 0  # a non-finite position or an impossible covariance: one would poison every track
        self.diverged_tracks = 0  # filters driven to inf or NaN (by extreme detections): dropped

    def __len__(self) -> int:
        return len(self._tracks)

    @property
    def ids(self) -> list[int]:
        return [t.id for t in self._tracks]

    def update(self, stamp_ns: int, positions: np.ndarray, covariances: np.ndarray | None = None) -> list[int]:
        """Apply one set of detections (N, 3) taken at stamp_ns; returns the track id each went to
        (-1: none; a detection with a non-finite position or an impossible covariance is dropped and counted)."""
        p = self.params
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        sound = np.isfinite(positions).all(axis=1)
        if covariances is not None:
            sound &= [is_covariance(c) for c in np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)]
        usable = np.flatnonzero(sound)
        self.rejected_detections += len(positions) - len(usable)
        for track in self._tracks:
            track.predict_to(p, stamp_ns)
        self._drop_diverged()
        self._tracks = [t for t in self._tracks if uncertainty_radius(p, t.kf.P) <= p.radius_max]

        assigned = [-1] * len(positions)
        if self._tracks and len(usable):
            predicted = np.array([t.kf.x[:3] for t in self._tracks])
            gates = np.array([uncertainty_radius(p, t.kf.P) for t in self._tracks])
            distances = np.linalg.norm(predicted[:, None, :] - positions[None, usable, :], axis=2)
            outside = distances > gates[:, None]
            from scipy.optimize import linear_sum_assignment

            rows, cols = linear_sum_assignment(np.where(outside, 1e9, distances))
            for row, col in zip(rows, cols):
                if outside[row, col]:
                    continue
                track, col = self._tracks[row], usable[col]
                cov = None if covariances is None else covariances[col]
                track.kf.update(positions[col], R=measurement_noise(p, cov))
                track.detections += 1
                track.last_detection = max(track.last_detection, stamp_ns)
                assigned[col] = track.id
        for col in usable:
            if assigned[col] < 0 and len(self._tracks) < p.max_tracks:
                track = _Track(self._next_id, p, positions[col], stamp_ns)
                self._next_id += 1
                self._tracks.append(track)
                assigned[col] = track.id
        return assigned

    def _drop_diverged(self) -> None:
        """A filter at inf or NaN never recovers, and one NaN distance fails every association."""
        finite = [t for t in self._tracks if np.isfinite(t.kf.x).all() and np.isfinite(t.kf.P).all()]
        self.diverged_tracks += len(self._tracks) - len(finite)
        self._tracks = finite

    def prune(self, now_ns: int) -> list[int]:
        """Drop the tracks whose uncertainty radius predicted to now_ns exceeds r_max (and diverged ones)."""
        self._drop_diverged()
        dropped = [e.id for e in self.estimates(now_ns) if e.uncertainty_radius > self.params.radius_max]
        self._tracks = [t for t in self._tracks if t.id not in dropped]
        return dropped

    def estimates(self, now_ns: int) -> list[TrackEstimate]:
        """Every track predicted to now_ns, without changing the filters."""
        p = self.params
        out = []
        for track in self._tracks:
            dt = max(0.0, (now_ns - track.stamp_ns) / NS)
            from filterpy.kalman import predict as kf_predict

            state, cov = kf_predict(track.kf.x, track.kf.P, F=transition(dt), Q=process_noise(p, dt))
            out.append(TrackEstimate(
                id=track.id,
                state=np.asarray(state, dtype=np.float64).reshape(9),
                covariance=np.asarray(cov, dtype=np.float64),
                detections=track.detections,
                confirmed=track.detections >= p.confirm_detections,
                uncertainty_radius=uncertainty_radius(p, cov),
                last_detection=track.last_detection,
            ))
        return out
