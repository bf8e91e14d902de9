"""The rerun side of the viewer: every draw record is a valid rerun archetype, and a recording
written by RerunOutput is one `rerun rrd verify` accepts, with its timelines and layout."""
from __future__ import annotations

import os
import signal
import subprocess
import time
import warnings

import cv2
import numpy as np
import pytest
import rerun as rr

from services.lib.runtime.zenoh_config import free_port
from services.tools.viz import draw
from services.tools.viz.output import RerunOutput, archetype, blueprint
from services.tools.viz.settings import grpc_address
from tests.tools.rrd import VIEWER_BINARY, entity_times, verify
from tests.tools.run import wait_for_port

S = 1_000_000_000
RECORDS = [
    draw.Points(np.zeros((3, 3)), np.zeros((3, 4), np.uint8), 0.1, ["a", "b", "c"]),
    draw.Points(np.zeros((0, 3)), (1, 2, 3, 4), 0.1),
    draw.Lines([np.zeros((4, 3)), np.ones((2, 3))], (1, 2, 3, 255), 0.05, ["x", "y"]),
    draw.Ellipsoids(np.zeros((2, 3)), np.ones((2, 3)), np.tile([0.0, 0, 0, 1], (2, 1)), (255, 0, 0, 255), ["p", "q"]),
    draw.Ellipsoids(np.zeros((1, 3)), np.ones((1, 3)), None, (255, 0, 0, 90), solid=True),
    draw.Boxes(np.zeros((5, 3)), np.array([0.2, 0.2, 0.2]), np.zeros((5, 4), np.uint8)),
    draw.Cylinders(np.zeros((1, 3)), np.ones(1), np.ones(1), (0, 255, 0, 255), ["tree"]),
    draw.Mesh(np.eye(3), np.array([[0, 1, 2]], np.uint32), (9, 9, 9, 255)),
    draw.Pose(np.array([1.0, 2, 3]), np.array([0.0, 0, 0, 1])),
    draw.Axes(1.0),
    draw.Text("fault_injected uav1: kill", "WARN"),
    draw.Document("## uav1\n| a | b |\n| --- | --- |\n| 1 | 2 |"),
    draw.Image(bytes(cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))[1])),
    draw.State("IDLE"),
    draw.StateStyle(["IDLE", "LANDED"], [(1, 2, 3, 255), (4, 5, 6, 255)]),
    draw.Scalar(2.5),
    draw.SeriesStyle("uav1", (31, 119, 180, 255)),
    draw.ZUp(),
]


@pytest.fixture
def strict_rerun():
    """Rerun turns bad input into warnings (slow, and easy to miss); here they must raise."""
    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)


def test_every_draw_record_is_a_valid_rerun_archetype(strict_rerun):
    for record in RECORDS:
        archetype(record)
    blueprint(["uav1", "uav2", "uav3"])
    with pytest.raises(TypeError):
        archetype(object())


def test_a_written_recording_verifies_and_keeps_mission_time_and_static_data(tmp_path, strict_rerun):
    path = tmp_path / "out.rrd"
    output = RerunOutput(rrd=str(path), recording_name="unit")
    output.layout(["uav1"])
    logs = [draw.Log("world", draw.ZUp(), None)]
    logs += [draw.Log(f"entity/{i}", record, i * S // 10, i * 2) for i, record in enumerate(RECORDS) if
             not isinstance(record, draw.ZUp)]
    logs += [draw.Log("uav1/pose", draw.Pose(np.array([float(i), 0, 5]), np.array([0.0, 0, 0, 1])), i * S)
             for i in range(5)]
    output.write(logs)
    output.close()
    assert verify(path).returncode == 0
    entities = entity_times(path)
    assert entities["world"] == {-1}
    assert entities["uav1/pose"] == {i * S for i in range(5)}
    assert entities["entity/1"] == {S // 10}


def _draw_something(output: RerunOutput, count: int = 20) -> None:
    output.write([draw.Log("uav1/pose", draw.Pose(np.array([float(i), 0, 5]), np.array([0.0, 0, 0, 1])), i * S)
                  for i in range(count)])


def test_a_viewer_that_goes_away_costs_the_file_nothing(tmp_path):
    port = free_port()
    receiver = subprocess.Popen([VIEWER_BINARY, f"--port={port}", "--bind", "127.0.0.1", "--save",
                                 str(tmp_path / "live.rrd")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for_port(port)
        output = RerunOutput(rrd=str(tmp_path / "out.rrd"), viewer=grpc_address(port), recording_name="unit")
    finally:
        receiver.kill()
        receiver.wait()
    _draw_something(output)
    problem = output.close(timeout=2.0)
    assert problem and "connect" in problem, problem
    assert verify(tmp_path / "out.rrd").returncode == 0
    assert entity_times(tmp_path / "out.rrd")["uav1/pose"] == {i * S for i in range(20)}


@pytest.fixture
def stub_viewer(tmp_path, monkeypatch):
    """`rerun` on the PATH is a script that records its pid and runs the real viewer headless,
    saving what it receives; and there is a display to spawn it on."""
    saved, pid = tmp_path / "spawned.rrd", tmp_path / "viewer.pid"
    stub = tmp_path / "bin" / "rerun"
    stub.parent.mkdir()
    stub.write_text(f"#!/bin/sh\necho $$ > {pid}\nexec {VIEWER_BINARY} --save {saved} \"$@\"\n")
    stub.chmod(0o755)
    monkeypatch.setenv("PATH", f"{stub.parent}:{os.environ['PATH']}")
    monkeypatch.setenv("DISPLAY", ":0")
    yield saved, pid
    if pid.exists():
        try:
            os.kill(int(pid.read_text()), signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_spawn_starts_a_viewer_of_its_own_that_outlives_the_output(stub_viewer):
    saved, pid = stub_viewer
    port = free_port()
    output = RerunOutput(viewer="spawn", recording_name="unit", port=port)
    _draw_something(output)
    assert output.close() is None
    viewer_pid = int(pid.read_text())
    assert os.getsid(viewer_pid) == viewer_pid  # a session of its own: the run's end does not reach it
    os.kill(viewer_pid, 0)  # still there after the output closed
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and "uav1/pose" not in _quiet_entity_times(saved):
        time.sleep(0.2)
    assert _quiet_entity_times(saved).get("uav1/pose") == {i * S for i in range(20)}


def _quiet_entity_times(path) -> dict:
    if not path.exists():
        return {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file still being written has no footer yet
        try:
            return entity_times(path)
        except Exception:
            return {}
