"""What the job manager has seen lately (pure; stamps are int ns of mission time): the latest
scan's detections, the scans of the last t_m, the tracker's confirmed tracks and the last target
found to move — and the questions the state machine asks of them: does this detection move,
has it held still, is it where the last mover would be by now."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from services.job_manager.params import JobManagerParams
from services.job_manager.targets import NS, TargetFilter

STILL_RADIUS = 0.5  # m
STILL_TIME = 1.0  # s

Motion = tuple  # (track id or None, position (3,), velocity (3,), stamp)


@dataclass(frozen=True)
class Seen:
    """One scan's or camera frame's detections."""

    stamp: int  # ns
    positions: np.ndarray  # (N, 3)
    covariances: np.ndarray  # (N, 3, 3), NaN where the detector gave none
    tethered: bool = False  # from the camera's balloon detector


class Sightings:
    def __init__(self, params: JobManagerParams) -> None:
        self.params = params
        self.scan_stamp: int | None = None  # stamp of the latest Detections (the LiDAR heartbeat)
        self.latest = np.zeros((0, 3))
        self.latest_stamp = 0
        self.camera_latest = np.zeros((0, 3))  # the latest camera frame's detections (balloons by colour)
        self.camera_stamp: int | None = None
        self.recent: deque[Seen] = deque()  # the last t_m of scans' and frames' detections
        self.tracks: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None  # stamp, ids, pos, vel
        self.last_mover: TargetFilter | None = None  # the filter of the last target found to move

    def scan(self, stamp: int, positions: np.ndarray,
             covariances: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """One scan's detections (N, 3) and covariances (N, 3, 3) or None; returns both without
        the rows whose position is not finite."""
        positions, covariances = _finite(positions, covariances)
        self.scan_stamp = stamp if self.scan_stamp is None else max(self.scan_stamp, stamp)
        self.latest, self.latest_stamp = positions, stamp
        self._remember(stamp, positions, covariances)
        return positions, covariances

    def camera(self, stamp: int, positions: np.ndarray,
               covariances: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """One camera frame's detections, as `scan`. They join the LiDAR's in view and in the
        recent scans (a balloon on its pole is background to the LiDAR perception: the camera is
        what sees it)."""
        positions, covariances = _finite(positions, covariances)
        self.camera_latest, self.camera_stamp = positions, stamp
        self._remember(stamp, positions, covariances, tethered=True)
        return positions, covariances

    def _remember(self, stamp: int, positions: np.ndarray, covariances: np.ndarray | None,
                  tethered: bool = False) -> None:
        if covariances is None:
            covariances = np.full((len(positions), 3, 3), np.nan)
        self.recent.append(Seen(stamp, positions, covariances, tethered))
        while self.recent and stamp - self.recent[0].stamp > int(self.params.target_time * NS):
            self.recent.popleft()

    def confirmed_tracks(self, stamp: int, ids: np.ndarray, positions: np.ndarray, velocities: np.ndarray) -> None:
        self.tracks = (stamp, np.asarray(ids, dtype=np.int64).reshape(-1), np.asarray(positions, float).reshape(-1, 3),
                       np.asarray(velocities, float).reshape(-1, 3))

    def in_view(self, now: int) -> np.ndarray | None:
        """The latest scan's and camera frame's detections, those not older than detection_max_age;
        None when neither is."""
        fresh = int(self.params.detection_max_age * NS)
        parts = []
        if self.scan_stamp is not None and now - self.latest_stamp <= fresh:
            parts.append(self.latest)
        if self.camera_stamp is not None and now - self.camera_stamp <= fresh:
            parts.append(self.camera_latest)
        return np.concatenate(parts) if parts else None

    @property
    def view_stamp(self) -> int:
        """The stamp of the newest detections in view."""
        return max(self.latest_stamp, self.camera_stamp or 0)

    def moving_track(self, detection: np.ndarray, now: int, seen: int | None = None) -> Motion | None:
        """(id, position, velocity, stamp) of a fast confirmed track at this detection (made at
        `seen`, default: now; the tracks are carried back to then), else None."""
        if self.tracks is None:
            return None
        stamp, ids, positions, velocities = self.tracks
        if not len(ids) or now - stamp > int(self.params.detection_max_age * NS):
            return None
        back = (stamp - (now if seen is None else seen)) / NS
        gaps = np.linalg.norm(positions - back * velocities - detection, axis=1)
        k = int(np.argmin(gaps))
        if gaps[k] <= self.params.track_gate and np.linalg.norm(velocities[k]) >= self.params.moving_speed:
            return int(ids[k]), positions[k].copy(), velocities[k].copy(), stamp
        return None

    def known_mover(self, detection: np.ndarray, seen: int) -> Motion | None:
        """(None, position, velocity, stamp) when the detection is where the last target found to
        move would be by now (the tracker may not have confirmed it), else None."""
        mover = self.last_mover
        if mover is None or seen - mover.last_seen > int(self.params.target_time * NS):
            return None
        if np.linalg.norm(mover.predict(seen) - detection) > self.params.detection_gate:
            return None
        return None, detection.copy(), mover.velocity.copy(), seen

    def motion(self, detection: np.ndarray, now: int, seen: int) -> Motion | None:
        return self.moving_track(detection, now, seen) or self.known_mover(detection, seen)

    def held_still(self, candidate: np.ndarray, now: int) -> bool:
        """Seen at this very place (within STILL_RADIUS) over at least STILL_TIME of the recent
        scans: a balloon, not a drone passing through (which is a metre away a second later)."""
        stamps = [seen.stamp for seen in self.recent if len(seen.positions)
                  and np.linalg.norm(seen.positions - candidate, axis=1).min() <= STILL_RADIUS]
        return bool(stamps) and now - min(stamps) >= int(STILL_TIME * NS)


def _finite(positions: np.ndarray, covariances: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The rows with a finite position; covariances of the wrong count are dropped whole (the
    target filter then weighs each detection by its default noise; it checks each matrix itself)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if covariances is not None:
        covariances = np.asarray(covariances, dtype=np.float64)
        if covariances.size != 9 * len(positions):
            covariances = None
        else:
            covariances = covariances.reshape(-1, 3, 3)
    finite = np.isfinite(positions).all(axis=1)
    return positions[finite], None if covariances is None else covariances[finite]
