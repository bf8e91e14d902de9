"""tracker node: clouds, detections and the map in, tracks out (seed 000 Alg. 2; see core.py).

Subscribes falconry/<uav>/map (VoxelMap: the occupied voxels line 39 keeps clusters away from),
falconry/<uav>/points (PointCloud: every scan updates every track) and falconry/<uav>/detections
(Detections: each starts or counts to a track, replayed through the buffered scans newer than
it). Lockstep releases a tick's scan before its detections (subscription order; the sensor
driver is upstream of the detector anyway). Publishes falconry/<uav>/tracks (Tracks) on every
tick while there are tracks, each predicted to the tick's time with a short predicted
trajectory, and an empty Tracks at least once per alive_period of mission time otherwise so
subscribers know the tracker is alive. In real time (not lockstep) it also publishes right
after each detection set that holds a detection, so a sighting does not wait up to a tick to
reach the job manager.

The fleet picture (fleet.py): it also subscribes every partner's falconry/<partner>/tracks and
publishes its own tracks fused (covariance intersection) with the partners' tracks of the same
targets, plus the partners' other confirmed tracks under fleet ids with `source` = the partner.
Before that, every tick, the own tentative tracks a partner's confirmed track of the same target
corroborates are handed to the core (`partner_confirms`), which confirms them.
"""
from __future__ import annotations

import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, PointCloud, Track, Tracks, VoxelMap
from services.lib.runtime.clock import to_ns
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node
from services.tracker.core import (OccupiedVoxels, TrackEstimate, TrackerCore, TrackerParams, published_trajectory,
                                   warm_up)
from services.tracker.fleet import (FleetPicture, FleetTrack, FusionParams, PartnerReport, admitted,
                                    partner_number)
from services.lib.voxels.replica import MapReplica


FUTURE_TOLERANCE_NS = 1_000_000_000  # a stamp may lead the node's clock by this much (clock skew, a late tick)


class TrackerNode(Node):
    service = "tracker"
    upstream = ("sensor_driver", "classifier", keys.ORACLE)  # the scans and whichever detector runs
    params_type = TrackerParams

    @classmethod
    def preload(cls) -> None:
        warm_up(TrackerParams())

    def setup(self) -> None:
        warm_up(self.params)  # compiled now, before the liveliness token: the first scan must not stall a tick
        self.core = TrackerCore(self.params)
        self.replica: MapReplica | None = None
        self.tracks_pub = self.publisher(self.topic("tracks"), Tracks)
        self.subscribe(self.topic("map"), VoxelMap, self.on_map, keep=None)  # deltas: each one counts
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self.subscribe(self.topic("detections"), Detections, self.on_detections)
        self.subscribe(keys.ALL_TRACKS, Tracks, self.on_partner_tracks)
        p = self.params
        self.fleet = FleetPicture(FusionParams(p.radius_min, p.radius_confidence,
                                               (p.noise.q_position, p.noise.q_velocity, p.noise.q_acceleration),
                                               p.partner_timeout, p.noise.gate_probability))
        self._refused: dict[str, int] = {}  # what was refused → how many
        self._alive_period_ns = to_ns(self.params.alive_period)
        self._last_published_ns: int | None = None
        self._refused_maps = 0
        self._bad_input = CountedWarnings(self.log)

    def on_map(self, msg: VoxelMap, key: str) -> None:
        try:
            if self.replica is None:
                if not msg.snapshot:
                    return  # a delta means nothing before the first snapshot
                self.replica = MapReplica(msg.origin, msg.shape, msg.voxel_size, msg.default_value)
            self.replica.apply(msg.snapshot, msg.origin, msg.shape, msg.voxel_size, msg.default_value,
                               to_numpy(msg.indices), to_numpy(msg.values))
        except (ValueError, MemoryError):  # an impossible geometry or contents, or a grid too large to hold
            self._refused_maps += 1
            self._report()
            return
        r = self.replica
        self.core.set_occupied(OccupiedVoxels(r.states, np.asarray(r.origin, dtype=np.float64), r.voxel_size,
                                              np.asarray(r.shape, dtype=np.int64)))

    def on_points(self, msg: PointCloud, key: str) -> None:
        if msg.sanity:  # the driver found the scan broken: its points correct no track
            return
        points = to_numpy(msg.points)
        if points.size % 3 or self._from_the_future(msg.header.stamp):
            self._refuse("scans refused (not (N, 3) points, or stamped ahead of the clock)")
            return
        sensor = np.asarray(msg.sensor_pose.position, dtype=np.float64)
        for track_id in self.core.new_point_cloud(msg.header.stamp, points,
                                                  sensor if np.isfinite(sensor).all() else None):
            self.log.debug("track %d lost", track_id)
        self._report()

    def on_detections(self, msg: Detections, key: str) -> None:
        positions, covariances = to_numpy(msg.positions), to_numpy(msg.covariances)
        if positions.size % 3 or self._from_the_future(msg.header.stamp):
            self._refuse("detection sets refused (not (N, 3) positions, or stamped ahead of the clock)")
            return
        positions = positions.reshape(-1, 3)
        # a covariance per detection or none (each one is still checked by the core)
        covariances = covariances.reshape(-1, 3, 3) if covariances.size == 9 * len(positions) else None
        self.core.new_detections(msg.header.stamp, positions, covariances, msg.sensor_health)
        self._report()
        if self.real_time and len(positions):  # the tracks go out now, not up to a tick later, at the newest time known
            self.publish_tracks(max(self.clock.now_ns(), msg.header.stamp), keep_alive=False)

    def _from_the_future(self, stamp: int) -> bool:
        """A stamp beyond the clock by more than FUTURE_TOLERANCE_NS: a track predicted to it would
        never take a correction again (it never predicts backwards)."""
        return stamp > self.clock.now_ns() + FUTURE_TOLERANCE_NS

    def _refuse(self, what: str) -> None:
        self._refused[what] = self._refused.get(what, 0) + 1
        self._report()

    def on_partner_tracks(self, msg: Tracks, key: str) -> None:
        partner = keys.uav_of(key)
        if partner == self.uav or not self.params.fleet or partner_number(partner) <= 0:
            return  # ourselves, or no UAV (a fleet id needs the partner's number)
        reports = [PartnerReport(t.id, t.confirmed, t.source, _numbers(t.state).reshape(-1), _numbers(t.covariance),
                                 t.detections, t.last_correction) for t in msg.tracks]
        tracks, refused = admitted(partner, msg.header.stamp, not msg.sensor_health, reports)
        for _ in range(refused):
            self._refuse("partner tracks refused (not a finite positive-definite CA state, or an id out of range)")
        self.fleet.partner_tracks(partner, msg.header.stamp, tracks)
        self._report()

    def _report(self) -> None:
        c = self.core.counters
        self._bad_input.update({"detections with a non-finite position or an impossible covariance dropped":
                                c.rejected_detections,
                                "tracks dropped whose filter diverged to inf or NaN": c.diverged_tracks,
                                "detections left out: the LiDAR failed its sanity check or was settling":
                                c.untrusted_detections,
                                "map messages refused (impossible geometry or contents)": self._refused_maps,
                                **self._refused})

    def on_tick(self, now_ns: int) -> None:
        for track_id in self.core.prune(now_ns):
            self.log.debug("track %d lost", track_id)
        self.publish_tracks(now_ns, keep_alive=True)

    def publish_tracks(self, now_ns: int, keep_alive: bool) -> None:
        """The fleet picture at now_ns; with no track, only as the keep-alive that is due
        (`keep_alive`: every alive period)."""
        estimates, own = self._own_tracks(now_ns)
        if self.params.fleet and self.params.partner_confirms:
            if self.core.corroborate(self.fleet.corroborating(own, now_ns)):
                estimates, own = self._own_tracks(now_ns)
        fleet = self.fleet.fuse(own, now_ns) if self.params.fleet else own
        quiet = self._last_published_ns is None or now_ns - self._last_published_ns >= self._alive_period_ns
        if not fleet and not (keep_alive and quiet):
            return
        self._last_published_ns = now_ns
        health = "" if self.core.sensor.trusted(now_ns) else "LiDAR failed its sanity check or is settling"
        newest = max((f.last_correction for f in fleet), default=0)  # the freshest sensor data in them
        self.tracks_pub.put(Tracks(header=Header(stamp=now_ns, source=newest),
                                   tracks=[self._track(f, estimates.get(f.id)) for f in fleet], sensor_health=health))

    def _own_tracks(self, now_ns: int) -> tuple[dict[int, TrackEstimate], list[FleetTrack]]:
        estimates = {e.id: e for e in self.core.estimates(now_ns)}
        return estimates, [FleetTrack(e.id, e.state, e.covariance, e.detections, e.confirmed, self.uav,
                                      last_correction=e.last_correction) for e in estimates.values()]

    def _track(self, track: FleetTrack, own: TrackEstimate | None) -> Track:
        """A fleet track as sent; an own track unfused keeps its trajectory (from its own state) and statistics."""
        p = self.params
        trajectory = own.trajectory if own is not None and not track.fused_with else \
            published_trajectory(track.mean, p, None if own is None else own.turn)
        return Track(
            id=track.id,
            state=from_numpy(track.mean),
            covariance=from_numpy(track.covariance),
            detections=track.detections,
            confirmed=track.confirmed,
            uncertainty_radius=self.core.radius_of(track.covariance),
            last_detection=own.last_detection if own is not None else 0,
            filter=p.filter if own is not None else "fleet",
            position=tuple(float(v) for v in track.mean[:3]),
            velocity=tuple(float(v) for v in track.mean[3:6]),
            trajectory_dt=p.trajectory_step,
            trajectory=from_numpy(trajectory),
            updates=own.updates if own is not None else 0,
            mean_nis=own.mean_nis if own is not None else 0.0,
            last_innovation=own.last_innovation if own is not None else 0.0,
            primary=own.primary if own is not None else False,
            source=track.source,
            last_correction=track.last_correction,
            half_width=own.half_width if own is not None else 0.0,
        )


NODE = TrackerNode


def _numbers(array) -> np.ndarray:
    """A received array's numbers as float64; none when its dtype or shape does not fit its data or
    is not a number (the fleet picture then refuses the track as unsound)."""
    try:
        return np.asarray(to_numpy(array), dtype=np.float64)
    except (ValueError, TypeError):
        return np.zeros(0)

