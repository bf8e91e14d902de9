"""`falconry export --format foxglove`: a recording becomes an MCAP file Foxglove decodes.

A synthetic recording of real encoded messages (every catalogue type, plus scans, odometry,
tracks, detections, truth, world and camera frames made to be checked, plus messages that cannot
be converted) is exported through the real CLI and read back with the `mcap` library: every
message must validate against the JSON Schema its channel declares, every schema must be one
Foxglove's JSON decoder reads, and the Foxglove messages must carry what went in. One test does
the same with a short real run (`falconry sim --record`).
"""
from __future__ import annotations

import base64
import contextlib
import io
import json
import math
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import jsonschema
import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation

from schemas.arrays import from_numpy
from schemas.catalogue import CATALOGUE
from schemas.messages import (ALL_MESSAGES, CompressedFrame, Detections, GroundTruth, Header, Obstacle, Odometry,
                              PointCloud, Pose, TargetTruth, Track, Tracks, VehicleTruth, WorldModel)
from services.tools.launcher.cli import main
from services.tools.viz.foxglove_export import ScanInfo, foxglove_quaternion
from services.tools.recorder.json_view import json_bytes, struct_view
from services.tools.recorder.mcap_io import McapRecordWriter
from tests.conftest import REPO, falconry_argv
from tests.tools.run import record_short_run
from tests.tools.samples import sample

WALL_START = 1_750_000_000_000_000_000  # a receive time in June 2025, ns
MISSION_STAMP = 1_500_000_000  # 1.5 s of mission time: the 1970-based stamp in headers
YEAR_2020 = int(datetime(2020, 1, 1, tzinfo=timezone.utc).timestamp()) * 1_000_000_000
HALF = math.sqrt(0.5)
YAW_90 = (HALF, 0.0, 0.0, HALF)  # Falconry's (w, x, y, z): 90° about z
encode = msgspec.msgpack.encode


# --------------------------------------------------------------------------- what Foxglove reads
def assert_foxglove_can_read(schema: dict, where: str = "") -> None:
    """The JSON Schema subset Foxglove's JSON decoder accepts (its parseJsonSchema): an object whose
    properties are each typed boolean, number, integer, string (plain or base64), object, or an
    array of those (no arrays of arrays, no base64 items), or an enum as oneOf numeric constants."""
    assert schema.get("type") == "object", f"{where or schema.get('title')}: not an object"
    for name, prop in schema["properties"].items():
        path = f"{where}.{name}"
        if "oneOf" in prop:
            assert all(isinstance(alt.get("const"), int) for alt in prop["oneOf"]), path
            continue
        kind = prop.get("type")
        assert kind in ("boolean", "number", "integer", "string", "object", "array"), f"{path}: type {kind!r}"
        if kind == "string":
            assert prop.get("contentEncoding") in (None, "base64"), path
        elif kind == "object":
            assert_foxglove_can_read(prop, path)
        elif kind == "array":
            item = prop["items"]
            assert item.get("type") in ("boolean", "number", "integer", "string", "object"), f"{path}: items"
            assert not (item["type"] == "string" and "contentEncoding" in item), f"{path}: base64 items"
            if item["type"] == "object":
                assert_foxglove_can_read(item, path)


def every_field_required(schema: dict) -> dict:
    """A copy of a schema that also demands every property (recursively) and no others: a Foxglove
    message must be complete, as the SDK's types are, for the viewer to draw it."""
    schema = dict(schema)
    if schema.get("type") == "object":
        schema["properties"] = {k: every_field_required(v) for k, v in schema["properties"].items()}
        schema["required"] = list(schema["properties"])
        schema["additionalProperties"] = False
    elif schema.get("type") == "array":
        schema["items"] = every_field_required(schema["items"])
    return schema


# --------------------------------------------------------------------------- a recording
def scan() -> PointCloud:
    """An organised 4 × 8 scan with a row of rays that returned nothing (NaN) and intensities."""
    points = np.arange(4 * 8 * 3, dtype=np.float32).reshape(4, 8, 3) / 10
    points[2] = np.nan
    intensity = np.linspace(0, 1, 32, dtype=np.float32).reshape(4, 8)
    return PointCloud(header=Header(sender="uav1/sensor_driver", seq=1, stamp=MISSION_STAMP), width=8, height=4,
                      sensor_pose=Pose((1.0, 2.0, 3.0), YAW_90), points=from_numpy(points),
                      intensity=from_numpy(intensity), sensor_model="test", max_range=50.0)


def odometry(velocity=(1.0, 0.0, 0.0)) -> Odometry:
    return Odometry(header=Header(sender="sim/simulator", seq=1, stamp=MISSION_STAMP),
                    pose=Pose((10.0, 20.0, 5.0), YAW_90), velocity=velocity,
                    covariance=from_numpy(np.eye(6)))


def tracks() -> Tracks:
    track = Track(id=7, state=from_numpy(np.arange(9, dtype=np.float64)), covariance=from_numpy(np.eye(9)),
                  detections=4, confirmed=True, uncertainty_radius=0.8, last_detection=MISSION_STAMP)
    return Tracks(header=Header(stamp=MISSION_STAMP), tracks=[track])


def detections() -> Detections:
    return Detections(header=Header(stamp=MISSION_STAMP), detector="classifier",
                      positions=from_numpy(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])),
                      covariances=from_numpy(np.stack([np.eye(3)] * 2)),
                      point_counts=from_numpy(np.array([12, 30], dtype=np.int32)),
                      extents=from_numpy(np.array([0.5, 1.0], dtype=np.float32)))


def truth() -> GroundTruth:
    return GroundTruth(header=Header(stamp=MISSION_STAMP), step=30,
                       uavs=[VehicleTruth(name="uav1", position=(10.0, 20.0, 5.0), velocity=(0.0, 0.0, 0.0),
                                          heading=0.0, airborne=True)],
                       targets=[TargetTruth(id="drone1", kind="drone", position=(30.0, 5.0, 8.0),
                                            velocity=(1.0, 0.0, 0.0), radius=0.4)])


def world() -> WorldModel:
    obstacles = [Obstacle(kind="plane", center=(0.0, 0.0, 0.0), name="ground"),
                 Obstacle(kind="box", center=(5.0, 5.0, 1.0), size=(2.0, 2.0, 2.0), color=(90, 60, 30)),
                 Obstacle(kind="cylinder", center=(8.0, 0.0, 0.0), radius=0.5, height=6.0, name="pole"),
                 Obstacle(kind="sphere", center=(0.0, 8.0, 3.0), radius=1.0),
                 Obstacle(kind="cone", center=(-5.0, 0.0, 0.0), radius=2.0, height=4.0)]
    return WorldModel(header=Header(stamp=MISSION_STAMP), scenario="test",
                      arena=[(-20.0, -20.0), (20.0, -20.0), (20.0, 20.0), (-20.0, 20.0)],
                      min_height=2.0, max_height=20.0, obstacles=obstacles, uavs=["uav1"])


def camera_frame() -> CompressedFrame:
    return CompressedFrame(header=Header(stamp=MISSION_STAMP), width=4, height=2, camera_pose=Pose(),
                           fx=2.0, fy=2.0, cx=2.0, cy=1.0, jpeg=b"\xff\xd8 not really a JPEG \xff\xd9")


def concrete_key(pattern: str) -> str:
    return pattern.replace("<uav>", "uav1").replace("<scope>", "uav1").replace("<service>", "tracker")


# Checked one by one below; `sample()` fills every other type (its arrays do not fit a scan's layout).
MADE_TO_CHECK = {PointCloud: scan(), Odometry: odometry(), Tracks: tracks(), Detections: detections(),
                 GroundTruth: truth(), WorldModel: world(), CompressedFrame: camera_frame()}
UNCONVERTIBLE = [
    ("falconry/uav1/alive/tracker", b"", "no message type for this key"),
    ("falconry/uav1/odometry", b"\x01 not msgpack of an Odometry", "does not decode as Odometry"),
    ("falconry/uav1/odometry", encode(odometry(velocity=(math.nan, 0.0, 0.0))), "NaN or infinite"),
]


def write_recording(path: Path) -> dict[str, int]:
    """Every catalogue type on a concrete key, then the unconvertible ones; returns messages per key."""
    writer = McapRecordWriter(str(path))
    written: dict[str, int] = {}
    receive = WALL_START
    for entry in CATALOGUE:
        if entry.type is None:
            continue
        key = concrete_key(entry.key)
        message = MADE_TO_CHECK.get(entry.type) or sample(entry.type)
        writer.write(key, encode(message), receive)
        written[key] = written.get(key, 0) + 1
        receive += 10_000_000
    for key, payload, _ in UNCONVERTIBLE:
        writer.write(key, payload, receive)
        receive += 10_000_000
    writer.close()
    return written


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path, str]:
    folder = tmp_path_factory.mktemp("export")
    source, target = folder / "run.mcap", folder / "run.foxglove.mcap"
    write_recording(source)
    return source, target, export(source, target)


def export(source: Path, target: Path, *extra: str) -> str:
    """The real command line in this process; its printed summary."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["export", "--format", "foxglove", str(source), str(target), *extra]) == 0
    return out.getvalue()


def read_export(path: Path) -> list[tuple]:
    with open(path, "rb") as f:
        return list(make_reader(f).iter_messages())


def messages_on(path: Path, topic: str) -> list[dict]:
    return [json.loads(m.data) for _, channel, m in read_export(path) if channel.topic == topic]


def schema_on(path: Path, topic: str):
    return next(schema for schema, channel, _ in read_export(path) if channel.topic == topic)


# --------------------------------------------------------------------------- the whole file
def assert_every_message_validates(path: Path) -> int:
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    count = 0
    for schema, channel, message in read_export(path):
        assert channel.message_encoding == "json", channel.topic
        assert schema is not None and schema.encoding == "jsonschema", channel.topic
        validator = validators.get(schema.id)
        if validator is None:
            declared = json.loads(schema.data)
            jsonschema.Draft202012Validator.check_schema(declared)
            assert_foxglove_can_read(declared)
            if schema.name.startswith("foxglove."):
                declared = every_field_required(declared)
            validator = validators[schema.id] = jsonschema.Draft202012Validator(declared)
        validator.validate(json.loads(message.data))
        count += 1
    return count


def test_every_exported_message_validates_against_the_schema_its_channel_declares(exported):
    _, target, _ = exported
    assert assert_every_message_validates(target) > len(CATALOGUE)


def test_every_recorded_type_is_exported_and_the_foxglove_views_are_added(exported):
    _, target, _ = exported
    schemas = {channel.topic: schema.name for schema, channel, _ in read_export(target)}
    for entry in CATALOGUE:
        if entry.type is not None and entry.type is not PointCloud:
            assert schemas[concrete_key(entry.key)] == f"falconry.{entry.type.__name__}"
    assert schemas["falconry/uav1/points"] == "foxglove.PointCloud"
    assert schemas["falconry/uav1/points/scan"] == "falconry.ScanInfo"
    assert schemas["falconry/uav1/odometry/pose"] == "foxglove.PoseInFrame"
    assert schemas["falconry/uav1/odometry/tf"] == "foxglove.FrameTransform"
    assert schemas["falconry/uav1/camera_jpeg/image"] == "foxglove.CompressedImage"
    for key in ("falconry/uav1/tracks", "falconry/uav1/detections", "falconry/uav1/camera_detections",
                "falconry/sim/truth", "falconry/sim/world"):
        assert schemas[f"{key}/scene"] == "foxglove.SceneUpdate"


def test_times_are_wall_clock_and_the_payload_keeps_the_mission_time(exported):
    _, target, _ = exported
    for _, channel, message in read_export(target):
        assert message.log_time > YEAR_2020 and message.publish_time == message.log_time, channel.topic
    assert messages_on(target, "falconry/uav1/odometry")[0]["header"]["stamp"] == MISSION_STAMP
    assert messages_on(target, "falconry/uav1/points/scan")[0]["header"]["stamp"] == MISSION_STAMP
    cloud = messages_on(target, "falconry/uav1/points")[0]
    assert cloud["timestamp"]["sec"] * 10**9 + cloud["timestamp"]["nsec"] > YEAR_2020


def test_the_point_cloud_has_foxglove_fields_and_every_returned_point(exported):
    _, target, _ = exported
    assert schema_on(target, "falconry/uav1/points").name == "foxglove.PointCloud"
    cloud = messages_on(target, "falconry/uav1/points")[0]
    assert {"timestamp", "frame_id", "pose", "point_stride", "fields", "data"} <= set(cloud)
    data = base64.b64decode(cloud["data"])
    assert len(data) % cloud["point_stride"] == 0
    expected = scan()
    points = np.frombuffer(expected.points.data, dtype=np.float32).reshape(-1, 3)
    returned = np.isfinite(points).all(axis=1)
    assert len(data) // cloud["point_stride"] == returned.sum() == 24  # the NaN row of 8 is left out
    layout = np.dtype({"names": [f["name"] for f in cloud["fields"]], "formats": ["<f4"] * len(cloud["fields"]),
                       "offsets": [f["offset"] for f in cloud["fields"]], "itemsize": cloud["point_stride"]})
    decoded = np.frombuffer(data, dtype=layout)
    assert [f["name"] for f in cloud["fields"]] == ["x", "y", "z", "intensity"]
    np.testing.assert_array_equal(np.stack([decoded["x"], decoded["y"], decoded["z"]], axis=1), points[returned])
    intensity = np.frombuffer(expected.intensity.data, dtype=np.float32)
    np.testing.assert_array_equal(decoded["intensity"], intensity[returned])
    assert cloud["frame_id"] == "world"


def test_quaternions_turn_from_w_first_to_w_last():
    assert foxglove_quaternion(YAW_90) == {"x": 0.0, "y": 0.0, "z": HALF, "w": HALF}
    q = foxglove_quaternion(YAW_90)
    turned = Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).apply([1.0, 0.0, 0.0])  # scipy: x, y, z, w
    np.testing.assert_allclose(turned, [0.0, 1.0, 0.0], atol=1e-12)  # 90° about z takes x to y


def test_odometry_places_its_uav_with_the_rotation_converted(exported):
    _, target, _ = exported
    transform = messages_on(target, "falconry/uav1/odometry/tf")[0]
    assert (transform["parent_frame_id"], transform["child_frame_id"]) == ("world", "uav1")
    assert transform["translation"] == {"x": 10.0, "y": 20.0, "z": 5.0}
    assert transform["rotation"] == {"x": 0.0, "y": 0.0, "z": HALF, "w": HALF}
    pose = messages_on(target, "falconry/uav1/odometry/pose")[0]
    assert pose["pose"]["orientation"] == transform["rotation"] and pose["frame_id"] == "world"


def test_scene_updates_show_tracks_detections_targets_and_obstacles_with_ids(exported):
    _, target, _ = exported
    track_scene = messages_on(target, "falconry/uav1/tracks/scene")[0]
    assert track_scene["deletions"][0]["type"] == 1  # all: each update replaces the previous one
    (track,) = track_scene["entities"]
    assert track["id"] == "track 7" and track["spheres"][0]["size"]["x"] == pytest.approx(1.6)
    assert track["spheres"][0]["pose"]["position"] == {"x": 0.0, "y": 1.0, "z": 2.0}
    detection_ids = [e["id"] for e in messages_on(target, "falconry/uav1/detections/scene")[0]["entities"]]
    assert detection_ids == ["classifier 0", "classifier 1"]
    truth_ids = [e["id"] for e in messages_on(target, "falconry/sim/truth/scene")[0]["entities"]]
    assert truth_ids == ["target drone1", "uav uav1"]
    world_entities = {e["id"]: e for e in messages_on(target, "falconry/sim/world/scene")[0]["entities"]}
    assert set(world_entities) == {"ground", "obstacle 1", "pole", "obstacle 3", "obstacle 4", "arena"}
    pole = world_entities["pole"]["cylinders"][0]
    assert pole["pose"]["position"]["z"] == 3.0 and pole["top_scale"] == 1.0  # stands on its base
    assert world_entities["obstacle 4"]["cylinders"][0]["top_scale"] == 0.0  # the cone
    assert len(world_entities["arena"]["lines"][0]["points"]) == 4


def test_camera_frames_become_compressed_images(exported):
    _, target, _ = exported
    image = messages_on(target, "falconry/uav1/camera_jpeg/image")[0]
    assert image["format"] == "jpeg" and base64.b64decode(image["data"]) == camera_frame().jpeg


def test_messages_that_cannot_be_converted_are_counted_and_reported(exported):
    _, target, summary = exported
    recorded = sum(1 for e in CATALOGUE if e.type is not None) + len(UNCONVERTIBLE)
    assert f"exported {recorded - len(UNCONVERTIBLE)} of {recorded} recorded messages" in summary
    assert f"skipped {len(UNCONVERTIBLE)} messages that cannot be converted" in summary
    for key, _, reason in UNCONVERTIBLE:
        assert any(key in line and reason in line for line in summary.splitlines()), (key, reason)
    assert len(messages_on(target, "falconry/uav1/odometry")) == 1  # only the good one


# --------------------------------------------------------------------------- the pieces
@pytest.mark.parametrize("message_type", ALL_MESSAGES + (ScanInfo,), ids=lambda t: t.__name__)
def test_every_message_type_has_a_json_view_foxglove_reads(message_type):
    view = struct_view(message_type, f"falconry.{message_type.__name__}")
    assert_foxglove_can_read(view.schema)
    jsonschema.validate(json.loads(json_bytes(view.to_json(sample(message_type)))), view.schema)


def test_scan_info_is_a_point_cloud_without_its_points():
    assert set(ScanInfo.__struct_fields__) == set(PointCloud.__struct_fields__) - {"points", "intensity"}


# --------------------------------------------------------------------------- the command line
def test_force_replaces_an_export_and_no_partial_file_is_left(exported, tmp_path):
    source, _, _ = exported
    target = tmp_path / "out.mcap"
    target.write_bytes(b"old")
    export(source, target, "--force")
    assert target.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.mcap"]


def test_a_long_export_shows_progress(exported, tmp_path):
    source, _, _ = exported
    summary = export(source, tmp_path / "out.mcap", "--progress", "1e-9")
    assert "exporting: 1 messages read, 0 skipped" in summary


def test_a_recording_cut_short_exports_its_complete_chunks_with_a_warning(tmp_path):
    whole, cut = tmp_path / "whole.mcap", tmp_path / "cut.mcap"
    writer = McapRecordWriter(str(whole), chunk_size=1)  # a chunk per message
    for step in range(10):
        writer.write("falconry/uav1/odometry", encode(odometry()), WALL_START + step)
    writer.close()
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    summary = export(cut, tmp_path / "out.mcap")
    exported_count = len(messages_on(tmp_path / "out.mcap", "falconry/uav1/odometry"))
    assert 0 < exported_count < 10
    assert f"exported {exported_count} of {exported_count} recorded messages" in summary
    assert "warning: " in summary and "was cut short" in summary


@pytest.mark.parametrize("case, expected", [
    ("missing", "no such recording"),
    ("not_mcap", "is not an MCAP file"),
    ("exists", "exists (add --force to replace it)"),
    ("same_file", "is the recording itself"),
    ("no_directory", "no such directory"),
])
def test_bad_files_are_one_line_errors(exported, tmp_path, capsys, case, expected):
    source, _, _ = exported
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"keep me")
    source, target = {
        "missing": (tmp_path / "missing.mcap", tmp_path / "out.mcap"),
        "not_mcap": (REPO / "README.md", tmp_path / "out.mcap"),
        "exists": (source, existing),
        "same_file": (source, source),
        "no_directory": (source, tmp_path / "no" / "such" / "out.mcap"),
    }[case]
    assert main(["export", "--format", "foxglove", str(source), str(target)]) == 2
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err
    assert existing.read_bytes() == b"keep me"


def test_an_unknown_format_is_a_one_line_error(exported, tmp_path, capsys):
    source, _, _ = exported
    with pytest.raises(SystemExit) as exit_:
        main(["export", "--format", "rosbag", str(source), str(tmp_path / "out.mcap")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'rosbag'" in err and err.count("\n") == 1
    assert not (tmp_path / "out.mcap").exists()


# --------------------------------------------------------------------------- a real run
@pytest.mark.slow(26)
def test_a_short_real_run_exports_and_validates(tmp_path):
    recording, target = tmp_path / "run.mcap", tmp_path / "run.foxglove.mcap"
    record_short_run(recording, "takeoff", "--uavs", "2", "--duration", "2")
    result = subprocess.run(falconry_argv("export", "--format", "foxglove", str(recording), str(target)),
                            cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "cannot be converted" not in result.stdout, result.stdout  # (a progress line says "0 skipped")
    assert assert_every_message_validates(target) > 0
    schemas = {channel.topic: schema.name for schema, channel, _ in read_export(target)}
    assert schemas["falconry/uav1/points"] == "foxglove.PointCloud"
    assert schemas["falconry/uav2/odometry/tf"] == "foxglove.FrameTransform"
    cloud = messages_on(target, "falconry/uav1/points")[0]
    assert len(base64.b64decode(cloud["data"])) // cloud["point_stride"] > 0
