"""A Falconry recording as an MCAP file Foxglove decodes (`falconry export --format foxglove`).

Every message is JSON ("json" message encoding) with a JSON Schema ("jsonschema" schema
encoding), the pair Foxglove decodes natively and any JSON Schema validator can check. Why not
the SDK's own writer and encoding (protobuf): Falconry's own types have only a JSON view
(services/tools/recorder/json_view.py), so JSON keeps the whole file in one encoding that any tool
reads without descriptors. So the Foxglove types' schemas are converted from the SDK's protobuf
descriptors (services/tools/viz/foxglove_schemas.py, parsed by Google's protobuf library: none is
written by hand) and the file is written with the `mcap` library, like the recorder's.

What each recorded message becomes (a derived topic is the recorded key plus a suffix):

- `PointCloud`: foxglove.PointCloud on the key (the returns: x, y, z, intensity, in the world
  frame), and falconry.ScanInfo on `<key>/scan` (the rest of the scan: header, sensor pose, ...);
- `Odometry`: itself, foxglove.PoseInFrame on `<key>/pose` and foxglove.FrameTransform world →
  `<uav>` on `<key>/tf` (the 3D panel places each UAV);
- `Tracks`, `Detections`, `GroundTruth`, `WorldModel`: itself, and foxglove.SceneUpdate on
  `<key>/scene` (a sphere of the uncertainty radius per track, a cube per detection, targets and
  UAVs' true positions, obstacles and the arena);
- `CompressedFrame`: itself, and foxglove.CompressedImage (the JPEG) on `<key>/image`;
- any other message: itself, falconry.<Type> (services/tools/recorder/json_view.py).

Times: log_time and publish_time are the recording's wall-clock receive time (the recorder keeps
the mission time in publish_time; Foxglove's timeline needs a real time), and so is the
`timestamp` of every foxglove.* message, so the 3D panel's time-indexed transforms and its
playback clock share one time base. The mission time stays in each falconry.* message's header.
Quaternions: Falconry's (w, x, y, z) become Foxglove's {x, y, z, w}.

A message that cannot be converted (a key with no message type, a payload that does not decode,
a NaN or infinite number, which JSON cannot carry) is skipped, counted and reported by reason.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import BinaryIO, Callable

import msgspec
import numpy as np
from foxglove import messages as fg
from mcap.writer import CompressionType, Writer

from schemas import keys
from schemas.arrays import Array, to_numpy
from schemas.catalogue import catalogue_entry
from schemas.messages import (CompressedFrame, Detections, GroundTruth, Header, Obstacle, Odometry, PointCloud,
                              Pose, Quat, Tracks, Vec3, WorldModel)
from services.tools.viz.foxglove_schemas import json_schema_of
from services.tools.recorder.json_view import JsonView, NotFinite, base64_text, json_bytes, struct_view
from services.tools.recorder.mcap_io import ReadReport, read_recording
from services.lib.runtime.clock import NS
from services.lib.tracks import track_position
from services.tools.viz.style import DETECTION_COLOR, TRUTH_COLOR

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
# Entities of a SceneUpdate replace the previous update's: Foxglove keeps entities until deleted.
DELETE_ALL = int(fg.SceneEntityDeletionType.All)
FLOAT32 = int(fg.PackedElementFieldNumericType.Float32)
LINE_LOOP = int(fg.LinePrimitiveLineType.LineLoop)
RGBA = tuple[int, int, int, int]
CONFIRMED_TRACK: RGBA = (255, 127, 14, 110)
TENTATIVE_TRACK: RGBA = (200, 200, 200, 80)
DESTROYED: RGBA = (90, 90, 90, 120)
LABEL: RGBA = (255, 255, 255, 255)
MIN_SIZE = 0.2  # m: a detection or track drawn smaller than this is invisible from a fleet-wide view
TRUTH_UAV_SIZE = 0.6  # m


class ScanInfo(msgspec.Struct, kw_only=True):
    """A LiDAR scan (`PointCloud`) without its points and intensities, which are on the
    foxglove.PointCloud of the same scan: its header (mission time), sensor pose, model, ranges,
    beam frame, self-hit mask, pose covariance and why the driver's sanity check failed it."""

    header: Header
    width: int
    height: int
    sensor_pose: Pose
    sensor_model: str = ""
    min_range: float = 0.0
    max_range: float = 0.0
    frame: int = 0
    mask: Array | None = None
    pose_covariance: Array | None = None
    sanity: str = ""


@dataclass(frozen=True)
class Schema:
    name: str  # "foxglove.PointCloud", "falconry.Odometry"
    json_schema: dict

    def encoded(self) -> bytes:
        return json.dumps(self.json_schema, sort_keys=True).encode()


@dataclass(frozen=True)
class ExportedMessage:
    topic: str
    schema: Schema
    data: bytes  # JSON


class Unconvertible(ValueError):
    """This recorded message cannot be exported; the text says why (one reason per kind of failure)."""


# ----------------------------------------------------------------------------- Foxglove values
def foxglove_time(ns: int) -> dict:
    sec, nsec = divmod(int(ns), NS)
    return {"sec": sec, "nsec": nsec}


def foxglove_vector(v: Vec3) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def foxglove_quaternion(q: Quat) -> dict:
    """Falconry stores (w, x, y, z); Foxglove's Quaternion is {x, y, z, w}."""
    w, x, y, z = (float(c) for c in q)
    return {"x": x, "y": y, "z": z, "w": w}


IDENTITY: Quat = (1.0, 0.0, 0.0, 0.0)


def foxglove_pose(position: Vec3, orientation: Quat = IDENTITY) -> dict:
    return {"position": foxglove_vector(position), "orientation": foxglove_quaternion(orientation)}


def foxglove_color(rgba: tuple[int, ...]) -> dict:
    r, g, b, a = (tuple(rgba) + (255,))[:4]
    return {"r": r / 255, "g": g / 255, "b": b / 255, "a": a / 255}


# ----------------------------------------------------------------------------- Foxglove messages
def point_cloud(cloud: PointCloud, stamp: dict) -> dict:
    """The scan's returns as foxglove.PointCloud: x, y, z (and intensity when recorded) float32,
    in the world frame (identity pose); rays that returned nothing (NaN) are left out."""
    points = to_numpy(cloud.points).reshape(-1, 3)
    returned = np.isfinite(points).all(axis=1)
    columns = {"x": points[returned, 0], "y": points[returned, 1], "z": points[returned, 2]}
    if cloud.intensity is not None:
        intensity = to_numpy(cloud.intensity).reshape(-1)
        if len(intensity) != len(points):
            raise Unconvertible("intensity and points differ in length")
        columns["intensity"] = intensity[returned]
    packed = np.empty(int(returned.sum()), dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        packed[name] = values
    fields = [{"name": name, "offset": packed.dtype.fields[name][1], "type": FLOAT32} for name in columns]
    return {"timestamp": stamp, "frame_id": cloud.header.frame, "pose": foxglove_pose((0.0, 0.0, 0.0)),
            "point_stride": packed.dtype.itemsize, "fields": fields,
            "data": base64_text(packed.tobytes())}


def pose_in_frame(odometry: Odometry, stamp: dict) -> dict:
    return {"timestamp": stamp, "frame_id": odometry.header.frame,
            "pose": foxglove_pose(odometry.pose.position, odometry.pose.orientation)}


def frame_transform(odometry: Odometry, child_frame: str, stamp: dict) -> dict:
    return {"timestamp": stamp, "parent_frame_id": odometry.header.frame, "child_frame_id": child_frame,
            "translation": foxglove_vector(odometry.pose.position),
            "rotation": foxglove_quaternion(odometry.pose.orientation)}


def compressed_image(frame: CompressedFrame, camera_frame: str, stamp: dict) -> dict:
    return {"timestamp": stamp, "frame_id": camera_frame, "data": base64_text(frame.jpeg), "format": "jpeg"}


# ----------------------------------------------------------------------------- scene updates
def _shape(position: Vec3, size: Vec3, color: dict) -> dict:
    """A cube or sphere primitive (both have pose, size, color)."""
    return {"pose": foxglove_pose(position), "size": foxglove_vector(size), "color": color}


def _label(position: Vec3, text: str) -> dict:
    return {"pose": foxglove_pose(position), "billboard": True, "font_size": 14.0, "scale_invariant": True,
            "color": foxglove_color(LABEL), "text": text}


def _entity(stamp: dict, entity_id: str, frame_id: str = "world", metadata: dict[str, str] | None = None,
            **primitives: list[dict]) -> dict:
    """A foxglove.SceneEntity with every field present (primitives not given are empty lists)."""
    entity = {"timestamp": stamp, "frame_id": frame_id, "id": entity_id, "lifetime": {"sec": 0, "nsec": 0},
              "frame_locked": False,
              "metadata": [{"key": k, "value": v} for k, v in (metadata or {}).items()]}
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        entity[kind] = primitives.pop(kind, [])
    if primitives:
        raise TypeError(f"not SceneEntity primitives: {sorted(primitives)}")
    return entity


def scene_update(stamp: dict, entities: list[dict]) -> dict:
    """Replaces everything the topic showed before (a deletion of all, then the new entities)."""
    return {"deletions": [{"timestamp": stamp, "type": DELETE_ALL, "id": ""}], "entities": entities}


def tracks_scene(tracks: Tracks, stamp: dict) -> dict:
    entities = []
    for track in tracks.tracks:
        position = tuple(float(v) for v in track_position(track))
        diameter = max(2 * track.uncertainty_radius, MIN_SIZE)
        color = CONFIRMED_TRACK if track.confirmed else TENTATIVE_TRACK
        entities.append(_entity(
            stamp, f"track {track.id}",
            metadata={"confirmed": str(track.confirmed), "detections": str(track.detections),
                      "uncertainty_radius": f"{track.uncertainty_radius:.2f}"},
            spheres=[_shape(position, (diameter,) * 3, foxglove_color(color))],
            texts=[_label(position, f"#{track.id}")]))
    return scene_update(stamp, entities)


def detections_scene(detections: Detections, stamp: dict) -> dict:
    positions = to_numpy(detections.positions).reshape(-1, 3)
    extents = to_numpy(detections.extents).reshape(-1)
    counts = to_numpy(detections.point_counts).reshape(-1)
    if not len(extents) == len(counts) == len(positions):
        raise Unconvertible("detection arrays differ in length")
    entities = []
    for i, (position, extent, count) in enumerate(zip(positions, extents, counts)):
        size = max(float(extent), MIN_SIZE)
        entities.append(_entity(stamp, f"{detections.detector} {i}",
                                metadata={"detector": detections.detector, "points": str(int(count))},
                                cubes=[_shape(tuple(position), (size,) * 3, foxglove_color(DETECTION_COLOR))]))
    return scene_update(stamp, entities)


def truth_scene(truth: GroundTruth, stamp: dict) -> dict:
    """The evaluation layer, in the viewer's truth colour: targets as spheres of their radius (in
    their own colour, grey once destroyed), the UAVs' true positions as cubes."""
    entities = []
    for target in truth.targets:
        color = DESTROYED if target.destroyed else tuple(target.color) + (TRUTH_COLOR[3],)
        entities.append(_entity(
            stamp, f"target {target.id}", metadata={"kind": target.kind, "destroyed": str(target.destroyed)},
            spheres=[_shape(target.position, (2 * target.radius,) * 3, foxglove_color(color))],
            texts=[_label(target.position, f"truth: {target.id}")]))
    for uav in truth.uavs:
        color = TRUTH_COLOR if uav.alive else DESTROYED
        entities.append(_entity(
            stamp, f"uav {uav.name}", metadata={"airborne": str(uav.airborne), "alive": str(uav.alive)},
            cubes=[_shape(uav.position, (TRUTH_UAV_SIZE,) * 3, foxglove_color(color))],
            texts=[_label(uav.position, f"truth: {uav.name}")]))
    return scene_update(stamp, entities)


def world_scene(world: WorldModel, stamp: dict) -> dict:
    entities = [_entity(stamp, obstacle.name or f"obstacle {i}", metadata={"kind": obstacle.kind},
                        **_obstacle_primitives(obstacle, world))
                for i, obstacle in enumerate(world.obstacles)]
    if world.arena:
        corners = [{"x": float(x), "y": float(y), "z": 0.0} for x, y in world.arena]
        entities.append(_entity(stamp, "arena", lines=[{
            "type": LINE_LOOP, "pose": foxglove_pose((0.0, 0.0, 0.0)), "thickness": 0.1,
            "scale_invariant": False, "points": corners, "color": foxglove_color(LABEL), "colors": [],
            "indices": []}]))
    return scene_update(stamp, entities)


def _obstacle_primitives(obstacle: Obstacle, world: WorldModel) -> dict[str, list[dict]]:
    """Falconry's primitives (schemas/messages.py Obstacle) as Foxglove's: a cylinder and a cone
    stand on their base centre, Foxglove's cylinder is placed by its middle; a cone is a cylinder
    with a zero top; a plane becomes a thin slab under the arena."""
    look = world.appearance
    color = foxglove_color(tuple(obstacle.color or (look.ground if obstacle.kind == "plane" else look.obstacle)))
    x, y, z = obstacle.center
    if obstacle.kind == "box":
        return {"cubes": [_shape(obstacle.center, obstacle.size, color)]}
    if obstacle.kind == "sphere":
        return {"spheres": [_shape(obstacle.center, (2 * obstacle.radius,) * 3, color)]}
    if obstacle.kind in ("cylinder", "cone"):
        diameter = 2 * obstacle.radius
        return {"cylinders": [{"pose": foxglove_pose((x, y, z + obstacle.height / 2)),
                               "size": foxglove_vector((diameter, diameter, obstacle.height)),
                               "bottom_scale": 1.0, "top_scale": 0.0 if obstacle.kind == "cone" else 1.0,
                               "color": color}]}
    if obstacle.kind == "plane" and world.arena:
        xs, ys = [p[0] for p in world.arena], [p[1] for p in world.arena]
        middle = ((min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2, z - 0.01)
        return {"cubes": [_shape(middle, (max(xs) - min(xs), max(ys) - min(ys), 0.02), color)]}
    return {}


# ----------------------------------------------------------------------------- the conversion
@dataclass(frozen=True)
class _Derived:
    """A Foxglove message made from a recorded one, on the topic `<key>/<suffix>` ("" = the key)."""

    suffix: str
    schema: Schema
    build: Callable[[msgspec.Struct, str, dict], dict]  # (message, key, stamp) -> JSON value


class FoxgloveConverter:
    """Recorded payloads in, JSON messages with their schemas out. Keeps only per-type caches."""

    def __init__(self) -> None:
        self._decoders: dict[type, msgspec.msgpack.Decoder] = {}
        self._views: dict[type, tuple[JsonView, Schema]] = {}
        fox = {cls.__name__: Schema(f"foxglove.{cls.__name__}", json_schema_of(cls))
               for cls in (fg.PointCloud, fg.PoseInFrame, fg.FrameTransform, fg.SceneUpdate, fg.CompressedImage)}
        scan = self._view(ScanInfo)
        self._derived: dict[type, list[_Derived]] = {
            PointCloud: [
                _Derived("", fox["PointCloud"], lambda m, key, stamp: point_cloud(m, stamp)),
                _Derived("scan", scan[1], lambda m, key, stamp: scan[0].to_json(_scan_info(m)))],
            Odometry: [
                _Derived("pose", fox["PoseInFrame"], lambda m, key, stamp: pose_in_frame(m, stamp)),
                _Derived("tf", fox["FrameTransform"], lambda m, key, stamp: frame_transform(m, keys.uav_of(key), stamp))],
            Tracks: [_Derived("scene", fox["SceneUpdate"], lambda m, key, stamp: tracks_scene(m, stamp))],
            Detections: [_Derived("scene", fox["SceneUpdate"], lambda m, key, stamp: detections_scene(m, stamp))],
            GroundTruth: [_Derived("scene", fox["SceneUpdate"], lambda m, key, stamp: truth_scene(m, stamp))],
            WorldModel: [_Derived("scene", fox["SceneUpdate"], lambda m, key, stamp: world_scene(m, stamp))],
            CompressedFrame: [_Derived("image", fox["CompressedImage"],
                                       lambda m, key, stamp: compressed_image(m, f"{keys.uav_of(key)}_camera", stamp))],
        }
        # the recorded message itself is kept, as JSON, except a scan's (its points are the foxglove.PointCloud)
        self._replaced = {PointCloud}

    def _view(self, message_type: type) -> tuple[JsonView, Schema]:
        view = self._views.get(message_type)
        if view is None:
            name = f"falconry.{message_type.__name__}"
            json_view = struct_view(message_type, name)
            view = self._views[message_type] = (json_view, Schema(name, json_view.schema))
        return view

    def convert(self, key: str, payload: bytes, receive_ns: int) -> list[ExportedMessage]:
        """The exported messages of one recorded message; Unconvertible says why there are none."""
        entry = catalogue_entry(key)
        if entry is None or entry.type is None:
            raise Unconvertible("no message type for this key")
        message_type = entry.type
        decoder = self._decoders.get(message_type)
        if decoder is None:
            decoder = self._decoders[message_type] = msgspec.msgpack.Decoder(message_type)
        try:
            message = decoder.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError) as exc:
            raise Unconvertible(f"does not decode as {message_type.__name__}: {exc}") from None
        stamp = foxglove_time(receive_ns)
        try:
            out = []
            if message_type not in self._replaced:
                view, schema = self._view(message_type)
                out.append(ExportedMessage(key, schema, json_bytes(view.to_json(message))))
            for derived in self._derived.get(message_type, ()):
                topic = f"{key}/{derived.suffix}" if derived.suffix else key
                out.append(ExportedMessage(topic, derived.schema, json_bytes(derived.build(message, key, stamp))))
            return out
        except NotFinite as exc:
            raise Unconvertible(str(exc)) from None
        except ValueError as exc:  # e.g. an array whose shape does not fit its message
            raise Unconvertible(f"malformed {message_type.__name__}: {exc}") from None


def _scan_info(cloud: PointCloud) -> ScanInfo:
    return ScanInfo(**{name: getattr(cloud, name) for name in ScanInfo.__struct_fields__})


# ----------------------------------------------------------------------------- the file
@dataclass
class ExportStats:
    read: int = 0  # recorded messages read
    converted: int = 0  # ... that were exported
    written: dict[str, int] = field(default_factory=dict)  # exported messages per topic
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> schema name
    skipped: dict[tuple[str, str], int] = field(default_factory=dict)  # (key, reason) -> messages
    source: ReadReport = field(default_factory=ReadReport)

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())


class FoxgloveMcapWriter:
    """One channel per topic, one schema per schema name, zstd chunks; single-threaded."""

    def __init__(self, file: BinaryIO, source_name: str) -> None:
        self._writer = Writer(file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="falconry export")
        self._writer.add_metadata("falconry_export", {
            "source": source_name,
            "message_encoding": "JSON of the msgspec Structs in schemas/messages.py, or of Foxglove's types",
            "log_time": "wall-clock receive time of the recording, ns since the Unix epoch",
            "publish_time": "the same receive time (the recording keeps mission time there)",
            "mission_time": "header.stamp of each falconry.* message, ns",
        })
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}

    def write(self, message: ExportedMessage, log_time: int, sequence: int) -> None:
        channel = self._channels.get(message.topic)
        if channel is None:
            schema_id = self._schemas.get(message.schema.name)
            if schema_id is None:
                schema_id = self._schemas[message.schema.name] = self._writer.register_schema(
                    message.schema.name, SCHEMA_ENCODING, message.schema.encoded())
            channel = self._channels[message.topic] = self._writer.register_channel(
                message.topic, MESSAGE_ENCODING, schema_id)
        self._writer.add_message(channel, log_time=log_time, data=message.data, publish_time=log_time,
                                 sequence=sequence)

    def finish(self) -> None:
        self._writer.finish()


def export_recording(source: str, target: BinaryIO, on_message: Callable[[ExportStats], None] | None = None,
                     source_name: str = "") -> ExportStats:
    """Convert every message of the recording at `source` and write the result to `target`;
    `on_message` is called after each recorded message (for progress)."""
    stats = ExportStats()
    converter = FoxgloveConverter()
    writer = FoxgloveMcapWriter(target, source_name or source)
    for recorded in read_recording(source, report=stats.source):
        stats.read += 1
        try:
            exported = converter.convert(recorded.key, recorded.payload, recorded.log_time)
        except Unconvertible as exc:
            reason = (recorded.key, str(exc))
            stats.skipped[reason] = stats.skipped.get(reason, 0) + 1
            exported = []
        else:
            stats.converted += 1
        for message in exported:
            writer.write(message, recorded.log_time, recorded.sequence)
            stats.written[message.topic] = stats.written.get(message.topic, 0) + 1
            stats.schemas[message.topic] = message.schema.name
        if on_message is not None:
            on_message(stats)
    writer.finish()
    return stats
