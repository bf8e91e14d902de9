"""The age of sensor data at each stage of the pipeline (issue 39): header.source carried from the
scan to the planner's reference, the run monitor dating arrivals in mission time, and the summary."""
from __future__ import annotations

import json
import subprocess

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import Detections, Header, MissionCommand, SimClock, TrajectoryReference, Tracks
from services.tools.evaluation import PipelineAges
from services.tools.launcher.monitor import RunMonitor
from services.tools.launcher.sim_cmd import WATCHED, data_age_lines
from services.tools.recorder.mcap_io import McapRecordWriter
from tests.conftest import REPO, falconry_argv

MS = 1_000_000
encode = msgspec.msgpack.encode


def detections(stamp: int, detector: str = "classifier") -> bytes:
    return encode(Detections(header=Header(stamp=stamp, source=stamp), detector=detector,
                             positions=from_numpy(np.zeros((0, 3))), covariances=from_numpy(np.zeros((0, 3, 3))),
                             point_counts=from_numpy(np.zeros(0, dtype=np.int32)),
                             extents=from_numpy(np.zeros(0, dtype=np.float32))))


def tick(monitor: RunMonitor, stamp: int, arrived: int) -> None:
    monitor.handle(keys.CLOCK, encode(SimClock(header=Header(stamp=stamp), step=stamp // (10 * MS), dt=0.01,
                                               lockstep=False)), arrived)


def test_ages_count_only_when_a_streams_source_moves_on():
    ages = PipelineAges()
    ages.add("uav1", "sensor → tracks", 1000 * MS, 1.05)
    ages.add("uav1", "sensor → tracks", 1000 * MS, 1.15)  # an alive message with the same data: not an age
    ages.add("uav1", "sensor → tracks", 900 * MS, 1.2)  # older data than already seen
    ages.add("uav2", "sensor → tracks", 1000 * MS, 1.09)  # another UAV's stream counts apart
    ages.add("uav1", "sensor → tracks", 0, 1.3)  # derived from no sensor data
    assert ages.ages == {"sensor → tracks": [pytest.approx(0.05), pytest.approx(0.09)]}
    row = ages.summary()["sensor → tracks"]
    assert row["count"] == 2 and row["max_ms"] == 90.0 and row["p50_ms"] == 70.0


def test_the_monitor_dates_arrivals_by_the_wall_clock_since_the_last_tick_in_real_time():
    monitor = RunMonitor()
    monitor.speed = 1.0
    tick(monitor, 2000 * MS, arrived=50_000 * MS)
    monitor.handle("falconry/uav1/detections", detections(1950 * MS), 50_030 * MS)  # 30 ms after the tick
    tick(monitor, 2010 * MS, arrived=50_060 * MS)
    monitor.handle("falconry/uav1/tracks", encode(Tracks(header=Header(stamp=2010 * MS, source=1950 * MS))),
                   50_070 * MS)
    command = MissionCommand(header=Header(stamp=2010 * MS, source=1950 * MS), command_id=3, action="intercept",
                             target=(1.0, 2.0, 3.0))
    monitor.handle("falconry/uav1/command", encode(command), 50_080 * MS)
    reference = TrajectoryReference(header=Header(stamp=2010 * MS, source=1950 * MS), command_id=3, start=0, dt=0.1,
                                    positions=from_numpy(np.zeros((2, 3))), headings=from_numpy(np.zeros(2)))
    monitor.handle("falconry/uav1/trajectory", encode(reference), 50_100 * MS)
    stages = monitor.summary()["data_age"]["stages"]
    assert {stage: row["max_ms"] for stage, row in stages.items()} == {
        "scan → detections": 80.0, "sensor → tracks": 70.0, "sighting → command": 80.0,
        "sighting → reference": 100.0}
    assert monitor.summary()["data_age"]["real_time"]
    assert keys.uav("*", "trajectory") in WATCHED  # the launcher hears the planner's references


def test_in_lockstep_an_arrival_is_the_ticks_mission_time():
    monitor = RunMonitor()  # speed 0: lockstep
    tick(monitor, 2000 * MS, arrived=50_000 * MS)
    monitor.handle("falconry/uav1/camera_detections", detections(1900 * MS, "camera"), 59_000 * MS)
    assert monitor.summary()["data_age"]["stages"]["frame → camera detections"]["p50_ms"] == 100.0
    lines = data_age_lines(monitor.summary()["data_age"])
    assert lines[0].endswith("(lockstep: in ticks of mission time):")
    assert lines[1] == "  frame → camera detections: 100 / 100 / 100 ms (1)"
    assert data_age_lines({"real_time": True, "stages": {}}) == []


def test_falconry_evaluate_ages_reads_them_from_a_recording(tmp_path):
    """The recorder's receive times are the arrivals; the recorded ticks give the run's speed (here
    half real time: 10 ms of mission time every 20 ms of wall time)."""
    path = tmp_path / "run.mcap"
    writer = McapRecordWriter(str(path))
    wall = 1_700_000_000_000 * MS
    for k in range(11):
        writer.write(keys.CLOCK, encode(SimClock(header=Header(stamp=k * 10 * MS), step=k, dt=0.01, lockstep=False)),
                     wall + k * 20 * MS)
        if k == 5:  # a scan of 20 ms of mission time ago, received 10 ms of wall time after the tick: 25 ms old
            writer.write("falconry/uav1/detections", detections(30 * MS), wall + k * 20 * MS + 10 * MS)
    writer.close()
    result = subprocess.run(falconry_argv("evaluate", "ages", str(path), "--json"), cwd=REPO, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stderr
    ages = json.loads(result.stdout)
    assert ages["real_time"] and ages["stages"] == {
        "scan → detections": {"count": 1, "p50_ms": 25.0, "p95_ms": 25.0, "max_ms": 25.0}}
    empty = tmp_path / "empty.mcap"
    McapRecordWriter(str(empty)).close()
    result = subprocess.run(falconry_argv("evaluate", "ages", str(empty)), cwd=REPO, capture_output=True, text=True)
    assert result.returncode != 0 and "no mission clock" in result.stderr and "Traceback" not in result.stderr
