"""Tracker core: seed 000's buffered point-cloud multi-target tracker (sec. III-F, Alg. 2).

Inputs are the LiDAR's clouds, the detector's detections and the map's occupied voxels, each by
its stamp. The core keeps a FIFO buffer B of the last N_buf clouds and a set of tracks, each a
filter estimate (services/tracker/filters: the constant-acceleration Kalman filter of eq. 27-31,
seed 002's adaptive EKF or the particle filter, chosen by `filter`) with its detection count.

- `new_point_cloud` (Alg. 2 lines 8-18) updates every track with the cloud and drops those whose
  uncertainty radius r_unc (eq. 26) exceeds r_max.
- `update_track` (lines 33-46) predicts a track to the cloud's stamp, takes the returns within
  r_unc of it, clusters them (the classifier's Euclidean clusters, sec. III-B), drops clusters
  whose centroid lies within d_min of an occupied voxel and corrects with the nearest centroid.
- `new_detections` (lines 19-32) starts a tentative track per detection (eq. 32-33), replays it
  through the buffered clouds newer than the detection (the detector's latency is compensated)
  and either counts it to a similar track or adds it.

Where Falconry departs from the seed, and why:
- Line 26 reads "if ∀T ∈ 𝒯" but the text says "if a similar track already exists": it is ∃.
  Among the similar tracks the nearest takes the detection, and within one set of detections a
  track takes at most one (two targets closer than r_unc(T) + r_unc(T*) would otherwise share one
  track forever).
- A detection counted to a track that no cloud has corrected since the detection was taken also
  corrects it: the track is rewound to its last correction, corrected with the detection at the
  detection's stamp and replayed through the newer buffered clouds. Replay makes this exactly
  what in-order processing would have given. Without it a target whose returns the cloud update
  rejects (a balloon beside its pole, a target the map has not yet cleared) would only ever be
  predicted, and dropped at r_max while its detections keep coming.
- A confirmed track dropped as too uncertain keeps its identity for a target that comes back.
  Alg. 2 gives a target that left the sensor's reach a new identity each time, and the job
  manager follows an interception by identity. Two rules, both after track-segment association:
  within `reidentify_time` a new track starting within r_max of where the lost one would be by
  then (its manoeuvre model) takes its identity back at once; within `stitch_time` a new track
  takes it when it is confirmed, if it moves like the lost one did (both faster than
  `moving_speed`, or both slower) and lies within reach of where it was last seen: r_max plus
  `stitch_speed` × the time since for a mover, r_max for a standing target. Among several such
  lost tracks the one nearest relative to its reach is taken (the re-identifier, reidentify.py).
  Waiting for confirmation keeps sporadic false detections from taking an identity; the motion
  check keeps a drone passing a balloon that went out of sight from taking the balloon's.
- Two tracks that end up on the same cluster are merged, keeping the older identity: the cloud
  update lets both take the nearest centroid, and two copies of one target would otherwise
  coexist until one drifts off.
- The surface offset of a cloud's centroid (services/lib/lidar/surface.py: the returns lie on
  the near side, `surface_bias` × the half-width short of the centre along the line of sight) is
  taken with the target's half-width as the track knows it: the widest its returns were across
  the line of sight in this or any earlier correction (capped at `max_half_width`), not this
  scan's alone. A sparse scan's outermost rays miss the rim, so one scan under-measures the
  half-width, the more the farther the target, and the classifier, which sees one scan, can do
  no better: on intruder its detections lie 0.05 m (uav1) and 0.07 m (uav2) short of the centre
  along the line of sight on average, 0.10 m beyond 20 m, most of their error. The track's
  half-width reaches the drone's 0.3 m within a second of close scans, and the like-for-like
  error of the tracks falls below the detections' (`falconry evaluate tracking`). What is left
  along the line of sight, 0.02-0.04 m short, is the shape: the simulated drones are upright
  discs, whose visible side lies πa/4 deep seen edge-on, not the sphere's 2a/3 that
  `surface_bias` assumes (the smaller of the two, classifier/core.py).
- Seed 000 confirms by n_det alone. A tentative track is also confirmed when a partner's confirmed
  track of the same target corroborates it (`corroborate`, handed in by the node from the fleet
  picture every tick, fleet.py): a second UAV acquiring a target the first follows would otherwise
  hold it unconfirmed for `confirm_detections` - 1 scans, and confirmation only guards against
  sporadic false detections, which a partner's confirmed target is not. Like a count of
  detections, this confirmation stands: a confirmation withdrawn when the partner's track next
  fell outside the gate (a one-detection track coasting between scans, on intruder) made the
  confirmed track flicker and counted fragments. A track that took a confirmed lost track's
  identity back at birth is confirmed too.
- Clouds arriving out of stamp order are inserted in order; a track never predicts backwards,
  so a cloud older than a track's estimate does not update it.

Pure: stamps are int ns handed in by the node; the map is a replica the node keeps current.
"""
from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field, replace

import msgspec
import numpy as np

from schemas.voxels import STATE_OCCUPIED
from services.lib.lidar.surface import half_width_across, surface_offset
from services.lib.geometry import is_covariance
from services.lib.lidar.sanity import SETTLE_TIME, SensorTrust
from services.tracker.filters import FILTERS, FilterParams, make_filter
from services.tracker.filters.base import NS, Estimate, InnovationStatistics
from services.tracker.filters.deleting import Deleter, UncertaintyDeleter
from services.tracker.filters.models import covariance_at_least, manoeuvre_state, turning_path, uncertainty_radius
from services.tracker.filters.turning import Turn, TurnHistory
from services.tracker.kernels import points_near
from services.tracker.reidentify import LostTrack, LostTracks
from services.lib.voxels.kernels import clusters_near_occupied, euclidean_clusters

TURN_MIN_SPEED = 1.0  # m/s: slower, a track's heading is noise and its trajectory does not turn


class TrackerParams(msgspec.Struct, forbid_unknown_fields=True):
    filter: str = "kf"  # kf | adaptive | particle (services/tracker/filters)
    noise: FilterParams = msgspec.field(default_factory=FilterParams)  # the filter's noise and initial covariance
    buffer_size: int = 6  # N_buf clouds: a detection up to this many scans old is replayed
    radius_min: float = 2.5  # m, r_min of eq. 26
    radius_confidence: float = 1.5  # c_r of eq. 26
    radius_max: float = 5.0  # m, tracks more uncertain than this are dropped (Alg. 2 line 15)
    cluster_distance: float = 0.5  # m, returns closer than this are one cluster (sec. III-B)
    # A cluster whose centroid is this close to an occupied voxel's centre is background (line 39).
    # Smaller than the classifier's d_close: the track already knows the target is not background.
    occupied_distance: float = 0.8
    # m², the variance of a cluster centroid as a measurement (eq. 29's Z²): σ = 0.1 m, about the
    # classifier's detection error (benchmarks/detection_quality.py); replaying intruder runs, larger values
    # lag behind a manoeuvring drone more than they smooth. Smaller ones fit the corrected centroids
    # better (0.0025, σ 0.05 m per axis: 0.058 / 0.066 m at the scans against 0.064 / 0.071, uav1 /
    # uav2) but shake a new track's velocity: a standing target seen as 12 returns of σ 0.15 m
    # then shows 0.68 m/s at confirmation (median of 40 draws; 0.35 with 0.01), above
    # moving_speed, and is taken for a mover
    cloud_noise: float = 0.01
    surface_bias: float = 0.667  # the classifier's: × the target's half-width, away from the sensor
    # m, the widest a track takes its target to be: the classifier's largest flying object
    # (cluster_max_extent 3 m) halved. A cloud whose nearest cluster merged the target with
    # something unmapped must not push every later correction that far back
    max_half_width: float = 1.5
    confirm_detections: int = 3  # n_det at which a track is confirmed (sporadic false positives stay below)
    # A tentative track is confirmed when a partner's confirmed track of the same target (within
    # the χ² gate, fleet.py) corroborates it (`corroborate`): the partner's detections are
    # independent evidence, and a sporadic false detection is not where a partner keeps a
    # confirmed target. Takes effect with `fleet`
    partner_confirms: bool = True
    # s a confirmed track dropped as too uncertain is remembered: a new track starting within
    # radius_max of where it would be by then takes its identity and its detections back
    # (the target went out of sight and came back; Alg. 2 alone would give it a new identity)
    reidentify_time: float = 3.0
    # s a confirmed track dropped is remembered for a new track that is confirmed later: it takes
    # the identity if it moves like the lost one and is within its reach (the module's text)
    stitch_time: float = 30.0
    stitch_speed: float = 8.0  # m/s, the fastest a target is expected to fly while out of sight
    # m/s, a track faster than this is a mover. A new track is confirmed on ~0.2 s of detections and
    # its speed is still shrunk toward 0 then: a 3 m/s drone shows 0.9-1.5 m/s, a standing target
    # below 0.5 in 95 % of simulated cases (σ = 0.1 m detections)
    moving_speed: float = 0.5
    # Bounded work per scan whatever the input: a LiDAR returning garbage must not make the
    # tracker spend the whole tick on thousands of spurious tracks.
    max_tracks: int = 64
    trajectory_horizon: float = 2.0  # s of predicted positions published with each track
    trajectory_step: float = 0.25  # s between them
    # s an estimated acceleration is expected to last in the published trajectory (Singer's model,
    # filters/models.py: manoeuvre_path); inf extrapolates the constant acceleration of eq. 27
    manoeuvre_time: float = 1.0
    # The published trajectory turns at the rate the last turn_window s of corrected headings
    # show (filters/turning.py, models.py: turning_path), at most max_turn_rate (rad/s; 0: never,
    # Singer's straight-on extrapolation alone). A 4 m circle at 3.2 m/s is 0.8 rad/s, agile's
    # manoeuvrer turns at up to 4 m/s² / 3 m/s = 1.3 rad/s.
    turn_window: float = 1.0
    max_turn_rate: float = 1.5
    alive_period: float = 1.0  # s; the node sends an empty Tracks at least this often
    fleet: bool = True  # join the partners' tracks into the published picture (fleet.py)
    partner_timeout: float = 1.0  # s without a partner's tracks before they are left out
    # s after the LiDAR's last scan that failed its sanity check (services/lib/lidar/sanity.py) during
    # which detections neither start nor count to a track, and partners leave our tracks out
    sensor_settle_time: float = SETTLE_TIME

    def __post_init__(self) -> None:
        if self.filter not in FILTERS:
            raise msgspec.ValidationError(f"filter must be one of {', '.join(FILTERS)}, not {self.filter!r}")
        for name in ("radius_min", "radius_confidence", "radius_max", "cluster_distance", "cloud_noise",
                     "trajectory_step", "manoeuvre_time", "moving_speed", "max_half_width", "turn_window"):
            if not getattr(self, name) > 0:
                raise msgspec.ValidationError(f"{name} must be positive")
        if not self.max_turn_rate >= 0:
            raise msgspec.ValidationError("max_turn_rate must be at least 0")
        if not (self.reidentify_time >= 0 and self.stitch_time >= 0 and self.stitch_speed >= 0):
            raise msgspec.ValidationError("reidentify_time, stitch_time and stitch_speed must be at least 0")
        if not 0.0 <= self.surface_bias <= 1.0:
            raise msgspec.ValidationError("surface_bias must be from 0 to 1")
        if self.buffer_size < 1 or self.confirm_detections < 1 or self.max_tracks < 1:
            raise msgspec.ValidationError("buffer_size, confirm_detections and max_tracks must be at least 1")


@dataclass(frozen=True)
class Cloud:
    stamp: int
    points: np.ndarray  # (N, 3) float32 world frame; NaN rows (no return) are never selected
    sensor: np.ndarray | None = None  # (3,) where the scan was taken from (the centroid's surface correction)


@dataclass(frozen=True)
class OccupiedVoxels:
    """The map's voxel states (schemas/voxels.py codes) and geometry, as Alg. 2's 𝒪."""

    states: np.ndarray  # (V,) uint8, flat C order
    corner: np.ndarray  # (3,)
    voxel_size: float
    shape: np.ndarray  # (3,) int


@dataclass
class _Track:
    id: int
    estimate: Estimate
    corrected: Estimate  # the estimate right after its last correction (what a detection rewinds to)
    detections: int
    last_detection: int  # ns
    statistics: InnovationStatistics = field(default_factory=InnovationStatistics)
    half_width: float = 0.0  # m, the target's size: the widest its returns were across the line of sight
    stitch_checked: bool = False  # a lost identity was looked for when it was confirmed (or it took one at birth)
    corroborated: bool = False  # a partner's confirmed track of its target confirmed it (`corroborate`)
    reidentified: bool = False  # it took a confirmed lost track's identity back at birth
    turn: TurnHistory | None = None  # its last corrections, for how it turns


@dataclass(frozen=True)
class Replayed:
    """A tentative track carried through the buffered clouds newer than its detection."""

    estimate: Estimate
    corrected: Estimate  # right after its last correction
    statistics: InnovationStatistics
    half_width: float  # m, the widest its returns were across the line of sight


@dataclass(frozen=True)
class CloudUpdate:
    """One estimate carried to a cloud's stamp and, when the cloud held its target, corrected."""

    estimate: Estimate
    innovation: np.ndarray | None  # None: predicted only
    half_width: float  # m, the target's size known after this cloud


@dataclass(frozen=True)
class ClusterMeasurement:
    position: np.ndarray  # (3,) the target's centre estimate
    half_width: float  # m, the cluster's half-width across the line of sight in this cloud


@dataclass(frozen=True)
class SimilarityView:
    """The tracks as line 26 compares them: predicted to one stamp (tracks added later are not in it)."""

    stamp: int
    ids: np.ndarray  # (T,)
    positions: np.ndarray  # (T, 3)
    radii: np.ndarray  # (T,)


@dataclass(frozen=True)
class TrackEstimate:
    id: int
    state: np.ndarray  # (9,) position, velocity, acceleration
    covariance: np.ndarray  # (9, 9)
    detections: int
    confirmed: bool
    uncertainty_radius: float
    last_detection: int  # ns
    trajectory: np.ndarray  # (K, 3) predicted positions at stamp + (i + 1)·trajectory_step
    updates: int
    mean_nis: float
    last_innovation: float
    last_correction: int = 0  # ns, when a scan or a detection last corrected it
    primary: bool = False
    half_width: float = 0.0  # m, the target's half-width across the line of sight: the widest its returns were
    turn: Turn | None = None  # how its trajectory turns (None: it does not)

    @property
    def position(self) -> np.ndarray:
        return self.state[:3]

    @property
    def velocity(self) -> np.ndarray:
        return self.state[3:6]


@dataclass
class TrackerCounters:
    rejected_detections: int = 0  # a non-finite position or an impossible covariance: one would poison every track
    diverged_tracks: int = 0  # filters driven to inf or NaN (by extreme input): dropped
    merged_tracks: int = 0  # duplicates of one target
    late_clouds: int = 0  # clouds older than the buffer's oldest: no detection can need them
    reidentified: int = 0  # new tracks that took back a lost track's identity at birth (reidentify_time)
    untrusted_detections: int = 0  # detections of scans while the sensor failed its sanity check or settled
    stitched: int = 0  # new tracks that took a lost track's identity when confirmed (stitch_time)


class TrackerCore:
    def __init__(self, params: TrackerParams | None = None) -> None:
        self.params = params or TrackerParams()
        self.filter = make_filter(self.params.filter, self.params.noise)
        self.buffer: deque[Cloud] = deque()
        self.occupied: OccupiedVoxels | None = None
        self.counters = TrackerCounters()
        self._tracks: list[_Track] = []
        p = self.params
        self.lost = LostTracks(p.radius_max, p.reidentify_time, p.stitch_time, p.manoeuvre_time, p.moving_speed,
                               p.stitch_speed)  # the re-identifier: confirmed tracks dropped a while ago
        self._next_id = 1
        self.sensor = SensorTrust(self.params.sensor_settle_time)
        # Alg. 2 lines 15 and 25: a track, or a tentative one replayed, too uncertain to keep
        self.deleter: Deleter = UncertaintyDeleter(self.params.radius_max, self.params.radius_min,
                                                   self.params.radius_confidence)

    def __len__(self) -> int:
        return len(self._tracks)

    @property
    def ids(self) -> list[int]:
        return [t.id for t in self._tracks]

    def radius(self, estimate: Estimate) -> float:
        return self.radius_of(estimate.covariance)

    def radius_of(self, covariance: np.ndarray) -> float:
        """r_unc of eq. 26 for a state covariance."""
        p = self.params
        return uncertainty_radius(covariance, p.radius_min, p.radius_confidence)

    # ------------------------------------------------------------------ map
    def set_occupied(self, occupied: OccupiedVoxels | None) -> None:
        self.occupied = occupied

    # ---------------------------------------------------------------- clouds
    def new_point_cloud(self, stamp: int, points: np.ndarray, sensor: np.ndarray | None = None) -> list[int]:
        """Alg. 2 lines 8-18: buffer the cloud (taken from `sensor`, if known), update every track
        with it, drop the too uncertain. Returns the ids dropped."""
        cloud = Cloud(stamp, np.asarray(points, dtype=np.float32).reshape(-1, 3),
                      None if sensor is None else np.asarray(sensor, dtype=np.float64).reshape(3))
        if not self._buffer(cloud):
            return []
        updated = self._update_tracks([t.estimate for t in self._tracks], [t.half_width for t in self._tracks], cloud)
        for track, update in zip(self._tracks, updated):
            track.estimate, track.half_width = update.estimate, update.half_width
            if update.innovation is not None:
                track.corrected = update.estimate
                self._turned(track)
                track.statistics.add(update.innovation)
        self._drop_diverged()
        dropped = [t.id for t in self._tracks if self.deleter.deletes(t.estimate, 0)]
        self._remove(dropped, stamp)
        self._merge_duplicates()
        return dropped

    def _buffer(self, cloud: Cloud) -> bool:
        """Insert by stamp; False (and counted) when it is older than everything the buffer holds."""
        stamps = [c.stamp for c in self.buffer]
        if len(stamps) >= self.params.buffer_size and cloud.stamp <= stamps[0]:
            self.counters.late_clouds += 1
            return False
        self.buffer.insert(bisect.bisect_right(stamps, cloud.stamp), cloud)
        while len(self.buffer) > self.params.buffer_size:
            self.buffer.popleft()
        return True

    def _update_tracks(self, estimates: list[Estimate], half_widths: list[float], cloud: Cloud) -> list[CloudUpdate]:
        """updateTrack (lines 33-46) for several estimates, with their targets' half-widths so far,
        against one cloud, sharing the per-point pass."""
        if not estimates:
            return []
        predictor = self.filter.predictor
        predicted = [predictor.predict(e, cloud.stamp) if e.stamp <= cloud.stamp else e for e in estimates]
        centres = np.array([e.position for e in predicted], dtype=np.float64)
        radii = np.array([self.radius(e) for e in predicted], dtype=np.float64)
        fresh = np.array([e.stamp <= cloud.stamp for e in estimates])
        if not np.isfinite(centres).all() or not np.isfinite(radii).all():
            # a diverged filter: dropped by the caller
            return [CloudUpdate(e, None, w) for e, w in zip(predicted, half_widths)]
        indices, starts = points_near(cloud.points, centres, radii)
        out = []
        for k, (estimate, half_width) in enumerate(zip(predicted, half_widths)):
            selected = cloud.points[indices[starts[k]:starts[k + 1]]].astype(np.float64)
            measured = self._nearest_clear_cluster(selected, estimate.position, cloud.sensor, half_width) \
                if fresh[k] else None
            if measured is None:
                out.append(CloudUpdate(estimate, None, half_width))
                continue
            update = self.filter.updater.update(estimate, measured.position, self.params.cloud_noise * np.eye(3))
            out.append(CloudUpdate(update.estimate, update.innovation, max(half_width, measured.half_width)))
        return out

    def _nearest_clear_cluster(self, points: np.ndarray, position: np.ndarray, sensor: np.ndarray | None,
                               half_width: float) -> ClusterMeasurement | None:
        """Lines 37-43: clusters of the selected returns, those clear of occupied voxels, the
        nearest centroid to the track's position, moved from the returns' centroid to the
        target's centre as the classifier moves its detections (`surface_bias`: a LiDAR sees only
        the near side, so the returns' centroid lies short of the centre along the line of sight),
        but by the target's half-width as the track knows it (the module's text). The measurement's
        half_width is this cluster's, capped at max_half_width."""
        if len(points) == 0:
            return None
        labels, count = euclidean_clusters(points, self.params.cluster_distance)
        sizes = np.bincount(labels, minlength=count).astype(np.float64)
        centroids = np.stack([np.bincount(labels, points[:, axis], minlength=count) for axis in range(3)], axis=1)
        centroids /= sizes[:, None]
        clear = np.flatnonzero(~self._near_occupied(centroids))
        if not len(clear):
            return None
        best = int(clear[np.argmin(np.linalg.norm(centroids[clear] - position, axis=1))])
        if sensor is None:
            return ClusterMeasurement(centroids[best], half_width)
        seen = min(half_width_across(points[labels == best], centroids[best], sensor), self.params.max_half_width)
        offset = surface_offset(centroids[best], sensor, self.params.surface_bias, max(half_width, seen))
        return ClusterMeasurement(centroids[best] + offset, seen)

    def _near_occupied(self, centroids: np.ndarray) -> np.ndarray:
        occupied = self.occupied
        if occupied is None:
            return np.zeros(len(centroids), dtype=bool)
        count = len(centroids)
        return clusters_near_occupied(centroids, np.arange(count), count, np.ones(count, dtype=np.bool_),
                                      occupied.states, occupied.corner, occupied.voxel_size, occupied.shape,
                                      self.params.occupied_distance)

    def _replay(self, estimates: list[Estimate], after: int, half_widths: list[float] | None = None) -> list[Replayed]:
        """Lines 22-24 for several estimates at once (one per-point pass per cloud): carry each,
        with its target's half-width so far (none: 0), through every buffered cloud newer than `after`."""
        current = list(estimates)
        corrected = list(estimates)
        widths = [0.0] * len(estimates) if half_widths is None else list(half_widths)
        statistics = [InnovationStatistics() for _ in estimates]
        for cloud in self.buffer:
            if cloud.stamp <= after or not current:
                continue
            for k, update in enumerate(self._update_tracks(current, widths, cloud)):
                current[k], widths[k] = update.estimate, update.half_width
                if update.innovation is not None:
                    corrected[k] = update.estimate
                    statistics[k].add(update.innovation)
        return [Replayed(*parts) for parts in zip(current, corrected, statistics, widths)]

    # ------------------------------------------------------------ detections
    def new_detections(self, stamp: int, positions: np.ndarray, covariances: np.ndarray | None = None,
                       sensor_health: str = "") -> list[int]:
        """Alg. 2 lines 19-32 for one set of detections (N, 3) taken at `stamp`; returns the track
        id each went to (-1: none: an unusable detection, dropped and counted, or a tentative track
        that its replay made too uncertain, or no room for another track, or a set made while the
        sensor failed its sanity check (`sensor_health` says why) or within sensor_settle_time after)."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        self.sensor.note(stamp, not sensor_health)
        if not self.sensor.trusted(stamp):
            self.counters.untrusted_detections += len(positions)
            return [-1] * len(positions)
        usable = self._usable(positions, covariances)
        covs = None if covariances is None else np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
        assigned = [-1] * len(positions)
        rows = np.flatnonzero(usable)
        if not len(rows):
            return assigned  # the common case: an empty set, one per scan
        floor = self.params.noise.measurement_variance * np.eye(3)
        # raised in every direction (Loewner order), not only on the diagonal: a singular covariance
        # stays invertible, which every filter's update needs
        noises = [floor if covs is None else covariance_at_least(covs[k], floor) for k in rows]
        initiate = self.filter.initiator.initiate
        replayed = self._replay([initiate(positions[k], noise, stamp) for k, noise in zip(rows, noises)], stamp)
        view = self._similarity_view(max([r.estimate.stamp for r in replayed] +
                                         [t.estimate.stamp for t in self._tracks], default=stamp))
        taken: set[int] = set()
        for k, noise, tentative in zip(rows, noises, replayed):
            assigned[k] = self._admit(stamp, positions[k], noise, tentative, view, taken)
        renamed = self._stitch_confirmed()
        return [renamed.get(track_id, track_id) for track_id in assigned]

    def _usable(self, positions: np.ndarray, covariances: np.ndarray | None) -> np.ndarray:
        sound = np.isfinite(positions).all(axis=1)
        if covariances is not None:
            covs = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
            sound &= np.array([is_covariance(c) for c in covs], dtype=bool)
        self.counters.rejected_detections += int((~sound).sum())
        return sound

    def _admit(self, stamp: int, position: np.ndarray, noise: np.ndarray, tentative: Replayed,
               view: SimilarityView, taken: set[int]) -> int:
        """Lines 25-31 for one replayed tentative track: dropped, counted to a similar track, or added."""
        if self.deleter.deletes(tentative.estimate, 0):
            return -1  # lost or a false positive (line 25)
        similar = self._most_similar(tentative.estimate, view, taken)
        if similar is not None:
            self._count(similar, stamp, position, noise)
            taken.add(similar.id)
            return similar.id
        if len(self._tracks) >= self.params.max_tracks:
            return -1
        track = _Track(self._next_id, tentative.estimate, tentative.corrected, 1, stamp, tentative.statistics,
                       tentative.half_width)
        self._turned(track)
        lost = self.lost.at_birth(tentative.estimate)
        if lost is not None:  # the same target back in sight: its identity and its detections
            track.id, track.detections, track.stitch_checked = lost.id, lost.detections + 1, True
            track.reidentified = True  # a lost track was confirmed, however it was (a partner's may have)
            track.half_width = max(track.half_width, lost.half_width)
            self.counters.reidentified += 1
        else:
            self._next_id += 1
        self._tracks.append(track)
        taken.add(track.id)
        return track.id

    def _most_similar(self, tentative: Estimate, view: SimilarityView, taken: set[int]) -> _Track | None:
        """Line 26: the nearest track T with ‖r_T - r_T*‖ ≤ r_unc(T) + r_unc(T*), both at the view's stamp."""
        if not len(view.radii):
            return None
        at = self.filter.predictor.predict(tentative, view.stamp)
        gaps = np.linalg.norm(view.positions - at.position, axis=1)
        similar = (gaps <= view.radii + self.radius(at)) & ~np.isin(view.ids, list(taken))
        if not similar.any():
            return None
        best = int(np.flatnonzero(similar)[np.argmin(gaps[similar])])
        return self._tracks[best]

    def _similarity_view(self, stamp: int) -> SimilarityView:
        """The tracks' positions and radii predicted to one stamp, once per set of detections."""
        predict = self.filter.predictor.predict
        at = [predict(track.estimate, stamp) for track in self._tracks]
        return SimilarityView(stamp, np.array([t.id for t in self._tracks], dtype=np.int64),
                              np.array([e.position for e in at], dtype=np.float64).reshape(-1, 3),
                              np.array([self.radius(e) for e in at], dtype=np.float64))

    def _count(self, track: _Track, stamp: int, position: np.ndarray, noise: np.ndarray) -> None:
        """Line 27, plus the correction of a track no cloud has corrected since the detection."""
        track.detections += 1
        track.last_detection = max(track.last_detection, stamp)
        if track.corrected.stamp >= stamp:
            return
        at_detection = self.filter.predictor.predict(track.corrected, stamp)
        update = self.filter.updater.update(at_detection, position, noise)
        track.statistics.add(update.innovation)
        [replayed] = self._replay([update.estimate], stamp, [track.half_width])
        track.estimate = replayed.estimate if replayed.estimate.stamp >= track.estimate.stamp else \
            self.filter.predictor.predict(replayed.estimate, track.estimate.stamp)
        track.corrected, track.half_width = replayed.corrected, replayed.half_width
        self._turned(track)
        track.statistics.merge(replayed.statistics)  # these clouds did not correct it when they first came

    def _turned(self, track: _Track) -> None:
        """The track's last correction into its turn rate's history."""
        p = self.params
        if track.turn is None:
            track.turn = TurnHistory(p.turn_window, TURN_MIN_SPEED, p.max_turn_rate)
        track.turn.add(track.corrected.stamp / NS, track.corrected.mean[:3], track.corrected.mean[3:6])

    # ----------------------------------------------------------- bookkeeping
    def _drop_diverged(self) -> None:
        """A filter at inf or NaN never recovers, and one NaN distance fails every association."""
        finite = [t for t in self._tracks
                  if np.isfinite(t.estimate.mean).all() and np.isfinite(t.estimate.covariance).all()]
        self.counters.diverged_tracks += len(self._tracks) - len(finite)
        self._tracks = finite

    def _merge_duplicates(self) -> None:
        """Tracks whose estimates sit within one cluster distance of each other follow one target:
        keep the older identity (the lower id) and the sum of the detections."""
        kept: list[_Track] = []
        for track in sorted(self._tracks, key=lambda t: t.id):
            twin = next((k for k in kept if np.linalg.norm(k.estimate.position - track.estimate.position)
                         <= self.params.cluster_distance), None)
            if twin is None:
                kept.append(track)
                continue
            twin.detections += track.detections
            twin.half_width = max(twin.half_width, track.half_width)
            twin.corroborated = twin.corroborated or track.corroborated
            twin.reidentified = twin.reidentified or track.reidentified
            twin.last_detection = max(twin.last_detection, track.last_detection)
            self.counters.merged_tracks += 1
        self._tracks = kept

    def prune(self, now_ns: int) -> list[int]:
        """Drop the tracks whose uncertainty radius predicted to now_ns exceeds r_max (and diverged ones)."""
        self._drop_diverged()
        dropped = [e.id for e in self.estimates(now_ns, trajectory=False) if self.deleter.deletes(e, 0)]
        self._remove(dropped, now_ns)
        return dropped

    def _remove(self, ids: list[int], now: int) -> None:
        """Drop tracks; the confirmed ones are remembered for re-identification."""
        for track in self._tracks:
            if track.id in ids and self._confirmed(track):
                self.lost.remember(LostTrack(track.id, track.corrected, track.detections, now, track.half_width))
        self._tracks = [t for t in self._tracks if t.id not in ids]
        self.lost.forget_before(now)

    def _confirmed(self, track: _Track) -> bool:
        return track.detections >= self.params.confirm_detections or track.corroborated or track.reidentified

    def corroborate(self, velocities: dict[int, np.ndarray]) -> bool:
        """Confirm the tracks a partner's confirmed track of the same target corroborates, by id,
        with the partner's velocity of it; unknown ids are left alone. A track that becomes
        confirmed so looks for a lost identity as at its own confirmation, judging whether it
        moves by the partner's velocity: its own is still near 0 after one or two detections
        (moving_speed). Returns whether any track's confirmation or identity changed."""
        changed = False
        for track in self._tracks:
            if track.id in velocities and not self._confirmed(track):
                track.corroborated = changed = True
        return bool(self._stitch_confirmed(velocities)) or changed

    def _stitch_confirmed(self, velocities: dict[int, np.ndarray] | None = None) -> dict[int, int]:
        """Tracks confirmed since the last look take the identity of a lost track they move like
        and are within reach of (stitch_time); `velocities` replaces some tracks' own velocity in
        that judgement. Returns new id by old id."""
        renamed, velocities = {}, velocities or {}
        for track in self._tracks:
            if track.stitch_checked or not self._confirmed(track):
                continue
            track.stitch_checked = True
            lost = self.lost.at_confirmation(track.estimate, velocities.get(track.id, track.estimate.mean[3:6]))
            if lost is not None:
                renamed[track.id] = lost.id
                track.id, track.detections = lost.id, track.detections + lost.detections
                track.half_width = max(track.half_width, lost.half_width)
                self.counters.stitched += 1
        return renamed

    def estimates(self, now_ns: int, trajectory: bool = True) -> list[TrackEstimate]:
        """Every track predicted to now_ns (never backwards), without changing the filters; the
        confirmed track with the most detections is marked primary. The state published is the
        last correction carried on by the manoeuvre model (manoeuvre_time), the covariance the
        filter's prediction: a track coasting through missed scans would otherwise hold a
        manoeuvre's acceleration for as long as it lasts (eq. 27), and in agile seed 4 a drone
        braking behind a tree was reported running on south at 6 m/s and into the ground."""
        p, predict = self.params, self.filter.predictor.predict
        out = []
        for track in self._tracks:
            now = predict(track.estimate, now_ns)
            coasted = max(now.stamp - track.corrected.stamp, 0) / NS
            state = manoeuvre_state(track.corrected.mean, coasted, p.manoeuvre_time)
            turn = None if track.turn is None or p.max_turn_rate <= 0 else track.turn.turn(now.stamp / NS)
            out.append(TrackEstimate(
                id=track.id,
                state=state,
                covariance=np.asarray(now.covariance, dtype=np.float64),
                detections=track.detections,
                confirmed=self._confirmed(track),
                uncertainty_radius=self.radius(now),
                last_detection=track.last_detection,
                trajectory=published_trajectory(state, p, turn) if trajectory else np.zeros((0, 3)),
                updates=track.statistics.updates,
                mean_nis=track.statistics.mean_nis,
                last_innovation=track.statistics.last_residual,
                last_correction=track.corrected.stamp,
                half_width=track.half_width,
                turn=turn,
            ))
        confirmed = [e for e in out if e.confirmed]
        if confirmed:
            best = max(confirmed, key=lambda e: (e.detections, -e.id))
            out = [replace(e, primary=e is best) for e in out]
        return out


def published_trajectory(state: np.ndarray, params: TrackerParams, turn: Turn | None = None) -> np.ndarray:
    """(K, 3) the positions published with a track of this state: every trajectory_step s up to
    trajectory_horizon, its horizontal motion the coordinated turn `turn` (turning_path)."""
    return turning_path(state, params.trajectory_step, int(params.trajectory_horizon / params.trajectory_step),
                        params.manoeuvre_time, turn)


def warm_up(params: TrackerParams) -> int:
    """Track a small synthetic target through three scans on a throwaway core, beside a mapped
    voxel, so that the cloud update's compiled kernels (numba, cached on disk after a machine's
    first run) are ready before the first real scan (see classifier/core.py, `warm_up`, for why).
    Returns the tracks confirmed (one)."""
    core = TrackerCore(params)
    states = np.zeros(20 * 20 * 10, dtype=np.uint8)
    states[0] = STATE_OCCUPIED  # the map check runs on something
    core.set_occupied(OccupiedVoxels(states, np.array([-5.0, -5.0, -1.0]), 0.5, np.array([20, 20, 10])))
    offsets = 0.15 * np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [0]), -1).reshape(-1, 3)
    for scan in range(3):
        target = np.array([3.0 + 0.3 * scan, 2.0, 4.0])
        stamp = scan * 100_000_000
        core.new_point_cloud(stamp, (target + offsets).astype(np.float32), np.zeros(3))
        core.new_detections(stamp, target[None], 0.01 * np.eye(3)[None])
    core.prune(300_000_000)
    return sum(e.confirmed for e in core.estimates(300_000_000))
