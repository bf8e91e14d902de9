"""How well the fleet saw, against ground truth: for the run summary, --summary-json and the viewer.

Evaluation only: the launcher and the viewer read truth, no flying service does. Per UAV:
- a detection matched a target when it lies within MATCH_DISTANCE of the target's true position at
  the scan's stamp; otherwise it is false;
- a target was in sight in a scan when at least MIN_HITS of the scan's rays hit it (points_truth),
  and missed when no detection of that scan matched it;
- a confirmed track is false when it never came within MATCH_DISTANCE of any target, in any UAV's
  picture: a partner's track shown in the fleet picture is its keeper's track (`origin`), so the
  copy of a track that followed a target is no false track, although it shows up only once its
  target was captured (the partner's track coasts on; the own one, fused with it until then, ends);
- an engagement (the job manager's first attack or intercept command at a target) went for a
  target when it was aimed within AIM_DISTANCE of one's true position, else at something that is
  no target (a pole, a tree, a red wall, nothing).
Camera detections are scored like the LiDAR's, matched within MATCH_DISTANCE or CAMERA_RANGE_SHARE
of their distance from the camera, whichever is larger (beyond the depth image's reach a balloon's
range comes from its size, whose error grows with the square of the distance:
benchmarks/camera.py); they have no in-sight count: a camera frame carries no per-pixel truth on
the wire.
Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.lib.runtime.clock import NS

MATCH_DISTANCE = 1.0  # m
MIN_HITS = 3  # rays of one scan on a target for it to count as in sight
CAMERA_RANGE_SHARE = 0.1  # of a camera detection's distance: its match tolerance when larger than 1 m
AIM_DISTANCE = 2.0  # m between an attack's or interception's aim point and a target's true position


def matched(positions: np.ndarray, targets: np.ndarray, tolerance: np.ndarray | float = MATCH_DISTANCE) -> np.ndarray:
    """(N,) bool: which of the (N, 3) positions lie within `tolerance` (one, or (N,) one per
    position) of one of the (K, 3) targets."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if not len(p) or not len(t):
        return np.zeros(len(p), dtype=bool)
    reach = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (len(p),))
    return (np.linalg.norm(p[:, None] - t[None], axis=2) <= reach[:, None]).any(axis=1)


def camera_tolerance(positions: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """(N,) match distance of camera detections seen from `camera` (3,)."""
    distance = np.linalg.norm(np.asarray(positions, dtype=np.float64).reshape(-1, 3) - np.asarray(camera), axis=1)
    return np.maximum(MATCH_DISTANCE, CAMERA_RANGE_SHARE * distance)


def found(targets: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(K,) bool: which targets have a detection within MATCH_DISTANCE."""
    return matched(targets, positions)


# s a target that went down still counts for an engagement aimed where it went down: the job
# manager's t_m, how long a locked target must go unseen before it counts as gone
UNSEEN_BEFORE_GONE = 3.0


@dataclass(frozen=True)
class Engagement:
    """One attack or interception a UAV started: where it aimed and at what."""

    t: float  # mission time of its first command, s
    action: str  # "attack" (a static target) or "intercept" (a mover)
    aim: tuple[float, float, float]
    target: str | None  # the target within AIM_DISTANCE of the aim, None: no target there
    miss_m: float  # distance from the aim to the nearest target (inf: none standing)

    def summary(self) -> dict:
        return {"t": round(self.t, 2), "action": self.action, "aim": [round(v, 2) for v in self.aim],
                "target": self.target, "miss_m": round(self.miss_m, 2) if np.isfinite(self.miss_m) else None}


def aimed_at(aim, targets: dict[str, tuple[float, float, float]]) -> tuple[str | None, float]:
    """(id of the target the aim point is within AIM_DISTANCE of, or None; distance to the nearest)."""
    if not targets:
        return None, float("inf")
    ids = list(targets)
    gaps = np.linalg.norm(np.array([targets[i] for i in ids], dtype=np.float64) - np.asarray(aim, float), axis=1)
    k = int(np.argmin(gaps))
    return (ids[k] if gaps[k] <= AIM_DISTANCE else None), float(gaps[k])


TrackOrigin = tuple[str, int]  # the UAV whose tracker keeps a track, and its id there


@dataclass
class TrackRecord:
    confirmed_at: float  # mission time it was first seen confirmed, s
    at: tuple[float, float, float]  # where it was then
    origin: TrackOrigin | None = None  # None: the track is its own (no fleet picture)
    nearest_m: float = float("inf")  # its closest approach to a standing target while confirmed
    last_t: float = 0.0  # the last time it was seen confirmed, s

    @property
    def matched(self) -> bool:
        return self.nearest_m <= MATCH_DISTANCE

    def summary(self, track_id: int) -> dict:
        return {"id": track_id, "t": round(self.confirmed_at, 2), "at": [round(v, 2) for v in self.at],
                "until": round(self.last_t, 2),
                "nearest_m": round(self.nearest_m, 2) if np.isfinite(self.nearest_m) else None}


@dataclass
class PerceptionScore:
    """One UAV's perception over a run."""

    detections: int = 0
    matched: int = 0
    false: int = 0
    in_sight: dict[str, int] = field(default_factory=dict)  # target kind -> (scan, target) pairs in sight
    missed: dict[str, int] = field(default_factory=dict)  # ... of which no detection matched the target
    first_t: float | None = None
    last_t: float = 0.0
    tracks: dict[int, TrackRecord] = field(default_factory=dict)

    def add_detections(self, t: float, positions: np.ndarray, targets: np.ndarray,
                       tolerance: np.ndarray | float = MATCH_DISTANCE) -> np.ndarray:
        """Count one scan's detections; returns which matched a target (within `tolerance`)."""
        hit = matched(positions, targets, tolerance)
        self.detections += len(hit)
        self.matched += int(hit.sum())
        self.false += int((~hit).sum())
        self.first_t = t if self.first_t is None else min(self.first_t, t)
        self.last_t = max(self.last_t, t)
        return hit

    def add_sight(self, seen: np.ndarray, kinds: list[str], positions: np.ndarray) -> None:
        """One scan's targets in sight (K, 3) and their kinds against its detections."""
        seen = np.asarray(seen, dtype=np.float64).reshape(-1, 3)
        for kind, hit in zip(kinds, found(seen, positions).tolist()):
            self.in_sight[kind] = self.in_sight.get(kind, 0) + 1
            self.missed[kind] = self.missed.get(kind, 0) + (not hit)

    def add_tracks(self, t: float, ids: list[int], positions: np.ndarray, targets: np.ndarray,
                   origins: list[TrackOrigin] | None = None) -> None:
        """Confirmed tracks of one Tracks message (with each one's keeper and id there, if known)."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
        gaps = np.linalg.norm(positions[:, None] - targets[None], axis=2).min(axis=1, initial=np.inf)
        origins = origins if origins is not None else [None] * len(ids)
        for track_id, gap, position, origin in zip(ids, gaps.tolist(), positions.tolist(), origins):
            record = self.tracks.setdefault(track_id, TrackRecord(t, tuple(position), origin))
            record.nearest_m = min(record.nearest_m, gap)
            record.last_t = t

    def matched_origins(self) -> set[TrackOrigin]:
        """The keepers' tracks that matched a target in this UAV's picture."""
        return {r.origin for r in self.tracks.values() if r.matched and r.origin is not None}

    def _false(self, matched_elsewhere: set[TrackOrigin]) -> dict[int, TrackRecord]:
        return {i: r for i, r in sorted(self.tracks.items())
                if not r.matched and (r.origin is None or r.origin not in matched_elsewhere)}

    def false_tracks(self, after: float = 0.0, matched_elsewhere: set[TrackOrigin] = frozenset()) -> int:
        return sum(1 for r in self._false(matched_elsewhere).values() if r.confirmed_at >= after)

    def summary(self, matched_elsewhere: set[TrackOrigin] = frozenset()) -> dict:
        """`matched_elsewhere`: tracks that matched a target in any UAV's picture (matched_origins)."""
        minutes = max((self.last_t - (self.first_t or 0.0)) / 60.0, 1e-9)
        return {
            "detections": self.detections, "matched": self.matched, "false": self.false,
            "false_per_minute": round(self.false / minutes, 2) if self.detections else 0.0,
            "in_sight": dict(sorted(self.in_sight.items())), "missed": dict(sorted(self.missed.items())),
            "recall": {kind: round(1.0 - self.missed[kind] / n, 3) for kind, n in sorted(self.in_sight.items())},
            "confirmed_tracks": len(self.tracks), "false_tracks": self.false_tracks(0.0, matched_elsewhere),
            "false_tracks_after_10s": self.false_tracks(10.0, matched_elsewhere),
            "false_track_list": [r.summary(i) for i, r in self._false(matched_elsewhere).items()],
        }


def in_sight(hits: np.ndarray, target_count: int) -> np.ndarray:
    """(K,) bool: which of the scan's K targets at least MIN_HITS rays hit (`hits` holds each ray's
    hit id, PointTruth: k >= 1 is the target of index k-1)."""
    h = np.asarray(hits).reshape(-1)
    counts = np.bincount(h[h > 0], minlength=target_count + 1)[1:target_count + 1]
    return counts >= MIN_HITS


# Stages of the pipeline whose data age a run measures (issue 39): what a message of each carries
# in header.source is the stamp of the newest scan or frame it derives from.
LATENCY_STAGES = ("scan → detections", "frame → camera detections", "sensor → tracks", "sighting → command",
                  "sighting → reference")


@dataclass
class PipelineAges:
    """The age of sensor data as it leaves each stage: arrival time (mission time, s) minus the
    stamp of the newest scan or frame the message derives from (header.source). Counted only when
    a stream's source moves on (per UAV and stage): a tracker's alive messages and a job manager's
    re-sends carry old data on purpose, which says nothing of how fast new data travels."""

    ages: dict[str, list[float]] = field(default_factory=dict)  # stage -> ages, s
    _last: dict[tuple[str, str], int] = field(default_factory=dict)

    def add(self, uav: str, stage: str, source_ns: int, arrival_s: float) -> None:
        if source_ns <= 0 or source_ns <= self._last.get((uav, stage), 0):
            return
        self._last[(uav, stage)] = source_ns
        self.ages.setdefault(stage, []).append(arrival_s - source_ns / 1e9)

    def summary(self) -> dict[str, dict[str, float]]:
        """Per stage with data: count and p50 / p95 / max age in ms."""
        table = {}
        for stage in LATENCY_STAGES:
            values = np.asarray(self.ages.get(stage, []), dtype=float) * 1e3
            if len(values):
                table[stage] = {"count": int(len(values)), "p50_ms": round(float(np.percentile(values, 50)), 1),
                                "p95_ms": round(float(np.percentile(values, 95)), 1),
                                "max_ms": round(float(values.max()), 1)}
        return table
