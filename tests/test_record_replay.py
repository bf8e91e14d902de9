"""`falconry record` / `falconry replay`: real runs, real Zenoh, real MCAP files.

One live lockstep run is recorded (module fixture); its sensor stream is replayed in lockstep
into freshly started perception services, whose detections must be the live ones bit for bit;
the recording is cut short at several byte offsets and must still yield exactly its complete
chunks. The schedule and the file format also get fast tests without processes.
"""
from __future__ import annotations

import queue
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, LabelSet, SimClock, StepAck
from schemas.voxels import BACKGROUND, UNKNOWN
from services.lib.runtime import shm
from services.lib.runtime.zenoh_config import free_port
from services.tools.recorder.mcap_io import McapRecordWriter, ReadReport, RecordedMessage, read_recording
from services.tools.recorder.schedule import AwaitAck, AwaitAll, LockstepSchedule, Tick
from tests.conftest import REPO, falconry_argv

UAV1_DETECTIONS = "falconry/uav1/detections"
UAV1_LABELS = "falconry/uav1/labels"
encode = msgspec.msgpack.encode


# ------------------------------------------------------------------ fast, no processes
def _msg(key: str, payload: bytes, seq: int = 0) -> RecordedMessage:
    return RecordedMessage(key, payload, 0, 0, seq)


def _data(key: str, sender: str, seq: int) -> RecordedMessage:
    return _msg(key, encode({"header": Header(sender=sender, seq=seq)}), seq)


def _tick(step: int, bounds: dict[str, int]) -> RecordedMessage:
    clock = SimClock(header=Header(sender="sim/simulator", seq=step + 1, stamp=step * 50_000_000), step=step,
                     dt=0.05, lockstep=True, bounds=bounds)
    return _msg(keys.CLOCK, encode(clock), step + 1)


def _ack(owner: str, step: int, published: dict[str, int]) -> RecordedMessage:
    scope, service = owner.split("/")
    return _msg(keys.ack(scope, service), encode(StepAck(header=Header(sender=owner, seq=step + 1), step=step,
                                                         published=published)), step + 1)


def _describe(action) -> str:
    if isinstance(action, Tick):
        return f"tick{action.clock.step}"
    if isinstance(action, AwaitAck):
        return f"await {action.service}@{action.step}"
    if isinstance(action, AwaitAll):
        return f"await all@{action.step}"
    header = msgspec.msgpack.decode(action.payload)["header"]
    return f"{action.key.split('/', 1)[1]}#{header['seq']}"


def _pipeline_recording(classifier_first_ack: dict[str, int]) -> list[RecordedMessage]:
    odo, points, det, map_ = (keys.uav("uav1", t) for t in ("odometry", "points", "detections", "map"))
    # File order as a recorder may receive it: the classifier's ack and the mapper's map overtake
    # tick 0 and the sensor driver's ack; odometry of tick 1 overtakes the mapper's ack of tick 0.
    return [
        _data(keys.WORLD, "sim/simulator", 1),
        _ack("uav1/classifier", 0, classifier_first_ack),
        _data(map_, "uav1/mapper", 1),
        _data(odo, "sim/simulator", 1),
        _tick(0, {keys.WORLD: 1, odo: 1}),
        _data(points, "uav1/sensor_driver", 1),
        _data(odo, "sim/simulator", 2),
        _ack("uav1/sensor_driver", 0, {points: 1}),
        _ack("uav1/mapper", 0, {map_: 1}),
        _tick(1, {keys.WORLD: 1, odo: 2, points: 1, map_: 1, **classifier_first_ack}),
        _ack("uav1/sensor_driver", 1, {points: 1}),
        _ack("uav1/classifier", 1, {det: 1}),
    ]


def _schedule(recorded: list[RecordedMessage]) -> list[str]:
    schedule = LockstepSchedule({"sim/simulator", "uav1/sensor_driver", "uav1/mapper"},
                                ["sensor_driver", "classifier", "mapper"])
    return [_describe(a) for a in schedule.actions(recorded)]


def test_schedule_restores_pipeline_order_from_lockstep_bookkeeping_not_file_order():
    # A service joining at the replay's first tick takes what it holds: the upstream stand-in's
    # output of that tick goes out before it. Later ticks follow the pipeline after the tick.
    assert _schedule(_pipeline_recording({"falconry/uav1/detections": 1})) == [
        "sim/world#1", "uav1/odometry#1", "uav1/points#1", "uav1/ack/sensor_driver#1", "tick0",
        "await uav1/classifier@0", "uav1/map#1", "uav1/ack/mapper#1",
        "await all@0", "uav1/odometry#2", "tick1",
        "uav1/ack/sensor_driver#2", "await uav1/classifier@1",
    ]


def test_writer_channels_schemas_and_times_round_trip(tmp_path):
    path = tmp_path / "small.mcap"
    writer = McapRecordWriter(str(path), ("falconry/**",))
    det = Detections(header=Header(sender="uav1/classifier", seq=7, stamp=1_500_000_000), detector="classifier",
                     positions=from_numpy(np.ones((2, 3))), covariances=from_numpy(np.zeros((2, 3, 3))),
                     point_counts=from_numpy(np.array([5, 6], dtype="<i4")),
                     extents=from_numpy(np.array([0.5, 0.6], dtype="<f4")))
    writer.write(UAV1_DETECTIONS, encode(det), 111)
    writer.write("falconry/custom/thing", b"\x01\x02", 222)  # not in the catalogue, not msgpack of a Struct
    writer.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        assert channels[UAV1_DETECTIONS].message_encoding == "msgpack"
        assert channels[UAV1_DETECTIONS].metadata == {"catalogue": "falconry/<uav>/detections"}
        schema = summary.schemas[channels[UAV1_DETECTIONS].schema_id]
        assert (schema.name, schema.encoding) == ("falconry.Detections", "jsonschema")
        assert b'"positions"' in schema.data
        assert channels["falconry/custom/thing"].schema_id == 0
        messages = [(c.topic, m.log_time, m.publish_time, m.sequence) for _, c, m in reader.iter_messages()]
    assert messages == [(UAV1_DETECTIONS, 111, 1_500_000_000, 7), ("falconry/custom/thing", 222, 222, 0)]
    got = list(read_recording(str(path)))
    assert [m.payload for m in got] == [encode(det), b"\x01\x02"]
    decoded = msgspec.msgpack.decode(got[0].payload, type=Detections)
    assert to_numpy(decoded.point_counts).tolist() == [5, 6]


def test_user_mistakes_are_one_line_errors(tmp_path):
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    for argv, message in (
        (["replay", str(not_mcap), "--connect", "tcp/127.0.0.1:9"], "is not an MCAP file"),
        (["replay", str(tmp_path / "missing.mcap"), "--connect", "tcp/127.0.0.1:9"], "no such recording"),
        (["record", str(tmp_path / "x.mcap"), "--keys", "a//b", "--connect", "tcp/127.0.0.1:9"], "invalid key expression"),
        (["record", str(tmp_path / "no" / "x.mcap"), "--connect", "tcp/127.0.0.1:9"], "cannot write"),
        (["record", str(tmp_path / "x.mcap")], "--connect"),
    ):
        result = subprocess.run(falconry_argv(*argv), cwd=REPO, capture_output=True, text=True, timeout=30)
        assert result.returncode == 2 and message in result.stderr, (argv, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr


# ------------------------------------------------------------------ one live run, recorded
@dataclass
class Recording:
    path: Path
    recorder_output: str


def _start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen(falconry_argv(*argv), cwd=REPO, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen, timeout: float = 10) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        output, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        output, _ = proc.communicate()
    return output or ""


def _wait_for_line(proc: subprocess.Popen, text: str, timeout: float = 20) -> None:
    lines: queue.SimpleQueue = queue.SimpleQueue()

    def pump():
        for line in proc.stdout:
            lines.put(line)
            if text in line:
                return

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if text in lines.get(timeout=0.2):
                return
        except queue.Empty:
            assert proc.poll() is None, f"exited before printing {text!r}"
    raise AssertionError(f"no {text!r} within {timeout} s")


# the recording is stopped 0.3 s of wall time after its run: the recorder must keep up
pytestmark = pytest.mark.alone


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Recording:
    path = tmp_path_factory.mktemp("recording") / "run.mcap"
    segments_before = shm.segments()
    recorder_port = free_port()
    recorder = _start(["record", str(path), "--listen", f"tcp/127.0.0.1:{recorder_port}", "--progress", "0"])
    try:
        _wait_for_line(recorder, "recording falconry/**")
        run = subprocess.run(
            falconry_argv("sim", "mbzirc", "--uavs", "2", "--lockstep", "--duration", "8", "--quiet",
                          "--progress", "0", "--port", str(free_port()),
                          "--connect", f"tcp/127.0.0.1:{recorder_port}", "--wall-timeout", "90"),
            cwd=REPO, capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        time.sleep(0.3)  # the last acknowledgements are on their way
    finally:
        output = _stop(recorder)
        shm.remove_orphans(shm.segments() - segments_before)
    assert recorder.returncode == 0, output
    return Recording(path, output)


def _payloads(path: Path, key: str) -> list[bytes]:
    return [m.payload for m in read_recording(str(path), lambda k: k == key)]


def test_recording_opens_with_the_mcap_reader_and_holds_the_whole_run(recording):
    assert "recorded" in recording.recorder_output and "falconry/uav1/points" in recording.recorder_output
    with open(recording.path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "falconry"
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        for key in (keys.CLOCK, keys.WORLD, keys.TRUTH, "falconry/uav1/points", "falconry/uav2/points",
                    UAV1_DETECTIONS, "falconry/uav1/map", "falconry/uav1/odometry", "falconry/uav1/ack/classifier"):
            assert key in topics, f"no channel {key}"
            assert counts[topics[key].id] > 0
            assert topics[key].message_encoding == "msgpack"
            assert summary.schemas[topics[key].schema_id].encoding == "jsonschema"
        assert len(summary.chunk_indexes) >= 5, "chunks are closed every second"
    ticks = [msgspec.msgpack.decode(p, type=SimClock) for p in _payloads(recording.path, keys.CLOCK)]
    steps = sorted({t.step for t in ticks})
    assert steps == list(range(161)), "every tick of the 8 s run, from the first"
    report = ReadReport()
    assert sum(1 for _ in read_recording(str(recording.path), report=report)) == summary.statistics.message_count
    assert report.complete


def _replay_detections(recording: Recording, processes, hub, services: list[str], extra: list[str]
                       ) -> dict[str, list[bytes]]:
    """What the replayed classifier published, per key: detections and label sets."""
    session, endpoint = hub
    got: queue.SimpleQueue = queue.SimpleQueue()
    subs = [session.declare_subscriber(key, lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
            for key in (UAV1_DETECTIONS, UAV1_LABELS)]
    try:
        for service in services:
            processes.start("run", service, "--uav", "uav1", "--connect", endpoint)
        replay = processes.start("replay", str(recording.path), "--connect", endpoint, "--lockstep",
                                 "--wait-for", ",".join(f"uav1/{s}" for s in services), "--progress", "0", *extra)
        output, _ = replay.communicate(timeout=60)
        assert replay.returncode == 0, output
        assert "acknowledgement timeouts" not in output, output
        assert "standing in for sim/simulator" in output and "uav1/sensor_driver" in output
        replayed: dict[str, list[bytes]] = {UAV1_DETECTIONS: [], UAV1_LABELS: []}
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            try:
                key, payload = got.get(timeout=0.3)
                replayed[key].append(payload)
            except queue.Empty:
                if replayed[UAV1_DETECTIONS]:
                    break
        return replayed
    finally:
        for sub in subs:
            sub.undeclare()


def _assert_identical(recording: Recording, replayed: dict[str, list[bytes]]) -> None:
    """Detections and label sets bit for bit: the classification of every point of every scan, made
    against a map that is itself built from the scans, is a function of the recorded sensor stream."""
    acks = [msgspec.msgpack.decode(p, type=StepAck) for p in _payloads(recording.path, "falconry/uav1/ack/classifier")]
    for key, message in ((UAV1_DETECTIONS, Detections), (UAV1_LABELS, LabelSet)):
        live = _payloads(recording.path, key)
        decode = msgspec.msgpack.Decoder(message).decode
        # The launcher stops the services once the last tick is out: a scan the live classifier
        # did not finish is not in the recording, so compare what it acknowledged.
        last = max([decode(p).header.stamp for p in live] + [a.header.stamp for a in acks])
        mine = [p for p in replayed[key] if decode(p).header.stamp <= last]
        print(f"{key}: {len(live)} messages live, {len(mine)} replayed")
        assert len(live) >= 70
        for i, (a, b) in enumerate(zip(live, mine)):  # same stamps, seqs, contents, bit for bit
            assert a == b, f"{key} message {i} differs: live {decode(a)} replayed {decode(b)}"
        assert len(mine) == len(live)
    labels = [msgspec.msgpack.decode(p, type=LabelSet) for p in _payloads(recording.path, UAV1_LABELS)]
    classes = set(np.concatenate([to_numpy(s.voxel_labels) for s in labels]).tolist())
    assert {BACKGROUND, UNKNOWN} <= classes, classes  # a scan's worth of real decisions, not empty messages


def test_sensor_stream_replayed_in_lockstep_into_classifier_and_mapper_gives_identical_detections(
        recording, processes, hub):
    """Default keys: clock, world, points, odometry. The classifier's map comes from the live
    mapper fed by the classifier's own labels: the whole perception loop is a function of the scans."""
    _assert_identical(recording, _replay_detections(recording, processes, hub, ["classifier", "mapper"], []))


def test_classifier_alone_with_the_recorded_map_gives_identical_detections(recording, processes, hub):
    replayed = _replay_detections(recording, processes, hub, ["classifier"], ["--also", "falconry/uav1/map"])
    _assert_identical(recording, replayed)


# ------------------------------------------------------------------ cut short by a crash
def _chunks(path: Path) -> list[tuple[int, int, list[tuple[str, int, bytes]]]]:
    """(start, end, messages) of every chunk, found through the summary's chunk index."""
    out = []
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        topics = {c.id: c.topic for c in summary.channels.values()}
        for index in summary.chunk_indexes:
            f.seek(index.chunk_start_offset)
            chunk = next(StreamReader(f, skip_magic=True, emit_chunks=True).records)
            assert isinstance(chunk, Chunk)
            messages = [(topics[r.channel_id], r.log_time, r.data) for r in breakup_chunk(chunk) if isinstance(r, Message)]
            out.append((index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, messages))
    return out


def test_truncated_recording_yields_exactly_its_complete_chunks(recording, tmp_path):
    chunks = _chunks(recording.path)
    size = recording.path.stat().st_size
    data = recording.path.read_bytes()
    total = sum(len(ms) for _, _, ms in chunks)
    offsets = {20, chunks[0][1] - 1, chunks[0][1], chunks[1][0] + 100, chunks[len(chunks) // 2][1] + 3,
               (chunks[-2][0] + chunks[-2][1]) // 2, chunks[-1][1], size - 10}
    counts = []
    for offset in sorted(offsets):
        cut = tmp_path / f"cut{offset}.mcap"
        cut.write_bytes(data[:offset])
        expected = [m for start, end, ms in chunks if end <= offset for m in ms]
        report = ReadReport()
        got = [(m.key, m.log_time, m.payload) for m in read_recording(str(cut), report=report)]
        assert got == expected, f"cut at {offset}"
        assert not report.complete and report.cut_at is not None and report.cut_at <= offset
        assert "was cut short" in report.describe(str(cut))
        print(f"cut at byte {offset}/{size}: {len(got)} of {total} messages, {report.chunks} complete chunks")
        counts.append(len(got))
    assert counts[0] == 0 and counts[-1] == total
    assert sum(0 < c < total for c in counts) >= 4


def test_truncated_recording_replays_up_to_its_last_complete_chunk(recording, processes, hub, tmp_path):
    session, endpoint = hub
    chunks = _chunks(recording.path)
    middle = chunks[len(chunks) // 2]
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(recording.path.read_bytes()[:(middle[0] + middle[1]) // 2])
    expected = [m for _, end, ms in chunks if end <= middle[0] for m in ms if m[0] == "falconry/uav1/points"]
    got: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber("falconry/uav1/points", lambda s: got.put(s.payload.to_bytes()))
    try:
        replay = processes.start("replay", str(cut), "--connect", endpoint, "--rate", "0", "--progress", "0")
        output, _ = replay.communicate(timeout=30)
        time.sleep(0.3)
    finally:
        sub.undeclare()
    assert replay.returncode == 0, output
    assert "was cut short" in output and "complete chunks" in output, output
    received = []
    while not got.empty():
        received.append(got.get())
    assert 0 < len(received) == len(expected)
    assert received == [m[2] for m in expected]
