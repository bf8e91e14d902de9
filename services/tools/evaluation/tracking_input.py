"""What `falconry evaluate tracking` reads from a recording: the ground truth (falconry/sim/truth),
each UAV's LiDAR model (falconry/sim/world), each UAV's confirmed tracks (falconry/<uav>/tracks;
beside them, every track it keeps, tentative ones too) and detections (falconry/<uav>/detections,
the baseline), as the numpy records of services/tools/evaluation/tracking.py. One pass over the file; a
file cut short by a crash is read up to its last complete chunk (`ReadReport`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import Detections, GroundTruth, Tracks, WorldModel
from services.lib.lidar.models import lidar_model
from services.lib.tracks import track_positions
from services.tools.evaluation.tracking import ScanDetections, TrackSet, TruthSnapshot, TruthTimeline
from services.tools.recorder.mcap_io import ReadReport, read_recording
from services.tools.recorder.selection import KeyFilter

TRACKS = keys.uav("*", "tracks")
DETECTIONS = keys.uav("*", "detections")


@dataclass
class TrackingInput:
    """Everything the tracking evaluation takes from one recording."""

    truth: TruthTimeline
    tracks: dict[str, list[TrackSet]]  # UAV -> its confirmed tracks per Tracks message, in stamp order
    detections: dict[str, list[ScanDetections]]  # UAV -> its Detections messages, in stamp order
    sensors: dict[str, str]  # UAV -> its LiDAR model (WorldModel.sensors)
    report: ReadReport
    undecodable: dict[str, int] = field(default_factory=dict)  # key -> payloads skipped
    # UAV -> every track it keeps, tentative ones too, per Tracks message, in stamp order
    kept_tracks: dict[str, list[TrackSet]] = field(default_factory=dict)

    def sensor_range(self, uav: str) -> float | None:
        """The datasheet range of the UAV's LiDAR, m (None: the recording does not say which)."""
        try:
            return lidar_model(self.sensors[uav]).max_range
        except (KeyError, ValueError):
            return None


def confirmed_tracks(message: Tracks, uav: str) -> TrackSet:
    """The confirmed tracks `uav`'s tracker keeps itself (fused with a partner's where both see a
    target); the fleet tracks it passes on from partners are scored under the partner that keeps
    them ("" in recordings made before the fleet picture)."""
    return own_tracks(message, uav, confirmed_only=True)


def own_tracks(message: Tracks, uav: str, confirmed_only: bool = False) -> TrackSet:
    """The tracks `uav`'s tracker publishes as its own (`confirmed_tracks`), tentative ones too unless
    `confirmed_only`. An own tentative track the fleet picture fused with a partner's confirmed
    track is published under the partner's fleet id and `source` (services/tracker/fleet.py) and,
    as the recording cannot tell it from the partner's track passed on, is not among them."""
    kept = [track for track in message.tracks
            if (track.confirmed or not confirmed_only) and track.source in ("", uav)]
    return TrackSet(stamp=message.header.stamp, ids=np.array([t.id for t in kept], dtype=np.int64),
                    positions=track_positions(kept))


def scan_detections(message: Detections) -> ScanDetections:
    positions = np.asarray(to_numpy(message.positions), dtype=np.float64).reshape(-1, 3)
    # a non-finite detection never reaches a track (the tracker drops it), and has no distance
    return ScanDetections(stamp=message.header.stamp, detector=message.detector,
                          positions=positions[np.isfinite(positions).all(axis=1)])


def truth_snapshot(truth: GroundTruth) -> TruthSnapshot:
    targets = truth.targets
    return TruthSnapshot(
        stamp=truth.header.stamp, target_ids=tuple(t.id for t in targets), kinds=tuple(t.kind for t in targets),
        positions=np.array([t.position for t in targets], dtype=np.float64).reshape(-1, 3),
        standing=np.array([not t.destroyed for t in targets], dtype=bool),
        uavs={v.name: np.array(v.position, dtype=np.float64) for v in truth.uavs})


def read_tracking_input(path: str) -> TrackingInput:
    """Raises UsageError when the file is not an MCAP file."""
    decoders = {keys.TRUTH: msgspec.msgpack.Decoder(GroundTruth), keys.WORLD: msgspec.msgpack.Decoder(WorldModel)}
    tracks_decoder, detections_decoder = msgspec.msgpack.Decoder(Tracks), msgspec.msgpack.Decoder(Detections)
    snapshots: list[TruthSnapshot] = []
    tracks: dict[str, list[TrackSet]] = {}
    kept: dict[str, list[TrackSet]] = {}
    detections: dict[str, list[ScanDetections]] = {}
    sensors: dict[str, str] = {}
    report, undecodable = ReadReport(), {}
    for message in read_recording(path, KeyFilter((keys.TRUTH, keys.WORLD, TRACKS, DETECTIONS)), report):
        try:
            if message.key == keys.TRUTH:
                snapshots.append(truth_snapshot(decoders[keys.TRUTH].decode(message.payload)))
            elif message.key == keys.WORLD:
                sensors.update(decoders[keys.WORLD].decode(message.payload).sensors)
            elif message.key.endswith("/tracks"):
                uav, decoded = keys.uav_of(message.key), tracks_decoder.decode(message.payload)
                tracks.setdefault(uav, []).append(confirmed_tracks(decoded, uav))
                kept.setdefault(uav, []).append(own_tracks(decoded, uav))
            else:
                detections.setdefault(keys.uav_of(message.key), []).append(
                    scan_detections(detections_decoder.decode(message.payload)))
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
            undecodable[message.key] = undecodable.get(message.key, 0) + 1
    for messages in [*tracks.values(), *kept.values(), *detections.values()]:
        messages.sort(key=lambda m: m.stamp)  # file order is receive order
    return TrackingInput(TruthTimeline(snapshots), tracks, detections, sensors, report, undecodable, kept)
