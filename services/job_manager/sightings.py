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
from services.lib.tracks import PredictedPath

STILL_RADIUS = 0.5  # m
STILL_TIME = 1.0  # s
AGREE_CHI2 = 11.34  # χ² of 3 degrees of freedom at 99 %: two 3D sightings of one object


@dataclass(frozen=True)
class Motion:
    """A detection found to move: the confirmed track it belongs to (None: the last mover's
    filter says so, the tracker has not confirmed it), where it is and how fast, at `stamp`."""

    track_id: int | None
    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    stamp: int  # ns


@dataclass(frozen=True)
class ConfirmedTracks:
    """The tracker's confirmed tracks of one Tracks message, predicted to `stamp`, each with its
    filter's predicted path (positions at stamp + (i + 1)·path_dt)."""

    stamp: int  # ns
    ids: np.ndarray  # (K,) int
    positions: np.ndarray  # (K, 3)
    velocities: np.ndarray  # (K, 3)
    paths: tuple[np.ndarray, ...] = ()  # K arrays (M, 3); empty: no predicted paths
    path_dt: float = 0.0  # s

    @staticmethod
    def of(stamp: int, ids, positions, velocities, paths=(), path_dt: float = 0.0) -> ConfirmedTracks:
        return ConfirmedTracks(stamp, np.asarray(ids, dtype=np.int64).reshape(-1),
                               np.asarray(positions, dtype=np.float64).reshape(-1, 3),
                               np.asarray(velocities, dtype=np.float64).reshape(-1, 3),
                               tuple(np.asarray(q, dtype=np.float64).reshape(-1, 3) for q in paths), float(path_dt))

    def prediction(self, track_id: int) -> PredictedPath | None:
        """Where the track says its target will be, time 0 at `stamp` (None: no such track)."""
        found = np.flatnonzero(self.ids == track_id)
        if not len(found):
            return None
        k = int(found[0])
        path = self.paths[k] if k < len(self.paths) else np.zeros((0, 3))
        return PredictedPath(self.positions[k], self.velocities[k], path, self.path_dt)


@dataclass(frozen=True)
class Seen:
    """One scan's or camera frame's detections."""

    stamp: int  # ns
    positions: np.ndarray  # (N, 3)
    covariances: np.ndarray  # (N, 3, 3), NaN where the detector gave none
    tethered: bool = False  # from the camera's balloon detector
    confirmed: bool = False  # partners' confirmed tracks (the fleet): seen consistently by their keepers
    observed: np.ndarray | None = None  # (N,) ns: when each was really seen (a partner's last scan of it); None: stamp

    def made(self) -> np.ndarray:
        """(N,) ns: when each detection was really made."""
        return np.full(len(self.positions), self.stamp, dtype=np.int64) if self.observed is None else self.observed


class Sightings:
    def __init__(self, params: JobManagerParams) -> None:
        self.params = params
        self.scan_stamp: int | None = None  # stamp of the latest Detections (the LiDAR heartbeat)
        self.latest = np.zeros((0, 3))
        self.latest_stamp = 0
        self.camera_latest = np.zeros((0, 3))  # the latest camera frame's detections (balloons by colour)
        self.camera_stamp: int | None = None
        self.fleet_latest = np.zeros((0, 3))  # the latest confirmed tracks only partners see
        self.fleet_stamp: int | None = None
        self.recent: deque[Seen] = deque()  # the last t_m of scans' and frames' detections
        self.tracks: ConfirmedTracks | None = None  # the latest
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
                  tethered: bool = False, confirmed: bool = False, observed: np.ndarray | None = None) -> None:
        if covariances is None:
            covariances = np.full((len(positions), 3, 3), np.nan)
        self.recent.append(Seen(stamp, positions, covariances, tethered, confirmed, observed))
        while self.recent and stamp - self.recent[0].stamp > int(self.params.target_time * NS):
            self.recent.popleft()

    def confirmed_tracks(self, tracks: ConfirmedTracks) -> None:
        self.tracks = tracks

    def fleet(self, stamp: int, positions: np.ndarray, covariances: np.ndarray | None = None,
              observed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """The confirmed tracks only partners see (the tracker's fleet picture), as detections: they
        join the scans' in view and in the recent scans, so a target in our working area that
        only a partner sees can be locked, and a locked one stays seen while a partner sees it.
        `observed` (N,): when the partner last corrected each (its position at `stamp` is predicted
        from then); returns positions, covariances and those times of the finite rows."""
        observed = np.full(len(np.asarray(positions).reshape(-1, 3)), stamp, dtype=np.int64) if observed is None \
            else np.minimum(np.asarray(observed, dtype=np.int64).reshape(-1), stamp)
        finite = np.isfinite(np.asarray(positions, dtype=np.float64).reshape(-1, 3)).all(axis=1)
        positions, covariances = _finite(positions, covariances)
        observed = observed[finite]
        self.fleet_latest, self.fleet_stamp = positions, stamp
        self._remember(stamp, positions, covariances, confirmed=True, observed=observed)
        return positions, covariances, observed

    def in_view(self, now: int) -> np.ndarray | None:
        """The latest scan's, camera frame's and partners' (fleet) detections, those not older than
        detection_max_age; None when none is."""
        fresh = int(self.params.detection_max_age * NS)
        parts = []
        if self.scan_stamp is not None and now - self.latest_stamp <= fresh:
            parts.append(self.latest)
        if self.camera_stamp is not None and now - self.camera_stamp <= fresh:
            parts.append(self.camera_latest)
        if self.fleet_stamp is not None and now - self.fleet_stamp <= fresh:
            parts.append(self.fleet_latest)
        return np.concatenate(parts) if parts else None

    @property
    def view_stamp(self) -> int:
        """The stamp of the newest detections in view."""
        return max(self.latest_stamp, self.camera_stamp or 0, self.fleet_stamp or 0)

    def moving_track(self, detection: np.ndarray, now: int, seen: int | None = None) -> Motion | None:
        """The fast confirmed track at this detection (made at `seen`, default: now; the tracks are
        carried back to then), else None."""
        tracks = self.fresh_tracks(now)
        if tracks is None or not len(tracks.ids):
            return None
        back = (tracks.stamp - (now if seen is None else seen)) / NS
        gaps = np.linalg.norm(tracks.positions - back * tracks.velocities - detection, axis=1)
        k = int(np.argmin(gaps))
        if gaps[k] <= self.params.track_gate and np.linalg.norm(tracks.velocities[k]) >= self.params.moving_speed:
            return Motion(int(tracks.ids[k]), tracks.positions[k].copy(), tracks.velocities[k].copy(), tracks.stamp)
        return None

    def fresh_tracks(self, now: int) -> ConfirmedTracks | None:
        """The latest confirmed tracks unless older than detection_max_age."""
        if self.tracks is None or now - self.tracks.stamp > int(self.params.detection_max_age * NS):
            return None
        return self.tracks

    def followed_track(self, track_id: int | None, near: np.ndarray, now: int) -> tuple[int, PredictedPath] | None:
        """The fresh confirmed track an interception follows: `track_id` while the tracker keeps it,
        else the moving track nearest `near` within track_gate (a new identity for the same target),
        with its prediction re-based to `now`."""
        tracks = self.fresh_tracks(now)
        if tracks is None or not len(tracks.ids):
            return None
        if track_id is None or track_id not in tracks.ids:
            motion = self.moving_track(near, now)
            if motion is None:
                return None
            track_id = motion.track_id
        prediction = tracks.prediction(track_id)
        return track_id, prediction.rebased((now - tracks.stamp) / NS, len(prediction.path), prediction.dt)

    def known_mover(self, detection: np.ndarray, seen: int) -> Motion | None:
        """A Motion without a track when the detection is where the last target found to move would
        be by now (the tracker may not have confirmed it), else None."""
        mover = self.last_mover
        if mover is None or seen - mover.last_seen > int(self.params.target_time * NS):
            return None
        if np.linalg.norm(mover.predict(seen) - detection) > self.params.detection_gate:
            return None
        return Motion(None, detection.copy(), mover.velocity.copy(), seen)

    def motion(self, detection: np.ndarray, now: int, seen: int) -> Motion | None:
        return self.moving_track(detection, now, seen) or self.known_mover(detection, seen)

    def consistent(self, candidate: np.ndarray, covariance: np.ndarray, now: int) -> bool:
        """Seen consistently: at a confirmed track (the tracker's own, or a partner's) it is;
        otherwise at least `lock_sightings`
        scans or frames of the last t_m (each counted once) hold a detection that agrees with it
        in 3D: within the 99 % ellipsoid of both covariances (floored at filter_sigma², the NaN of a
        detector that gives none read as detection_gate), or within detection_gate. A single
        blob, or a handful of garbage returns, is not a target."""
        p = self.params
        tracks = self.fresh_tracks(now)
        if tracks is not None and len(tracks.ids) and \
                np.linalg.norm(tracks.positions - candidate, axis=1).min() <= p.track_gate:
            return True  # the tracker confirmed it
        floor = p.filter_sigma ** 2 * np.eye(3)
        mine = np.where(np.isfinite(covariance), covariance, p.detection_gate ** 2 * np.eye(3))
        stamps = set()
        for seen in self.recent:
            if now - seen.stamp > int(p.target_time * NS) or not len(seen.positions):
                continue
            gaps = seen.positions - candidate
            close = np.linalg.norm(gaps, axis=1) <= p.detection_gate
            if seen.confirmed and close.any():
                return True
            theirs = np.where(np.isfinite(seen.covariances), seen.covariances, p.detection_gate ** 2 * np.eye(3))
            spread = np.linalg.inv(theirs + mine + floor)
            agree = np.einsum("ni,nij,nj->n", gaps, spread, gaps) <= AGREE_CHI2
            if (close | agree).any():
                stamps.add(seen.stamp)
        return len(stamps) >= p.lock_sightings

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
