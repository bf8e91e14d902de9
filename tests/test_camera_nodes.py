"""The camera and Object Detect as running services: frames at the camera's rate between the
LiDAR's scans, a balloon detected where it is, a compressed frame for the ground, a colour file
sent live replacing the one Object Detect started with, and a bad one refused, as is a frame whose
image is not the shape its header says (one warning, no detections, the service carries on)."""
from __future__ import annotations

import time

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import (
    CameraFrame,
    ColorUpdate,
    CompressedFrame,
    Detections,
    GroundTruth,
    Header,
    Obstacle,
    Pose,
    SimClock,
    TargetTruth,
    VehicleTruth,
    WorldModel,
)
from tests.conftest import REPO
from tests.tools.health import health
from tests.tools.nodes import collect, start_healthy

pytestmark = pytest.mark.alone  # real-time nodes whose subscriptions meet within fixed sleeps

TICK_NS = 50_000_000
BALLOON = (9.0, 1.0, 5.0)
BAD_FRAME_NS = 470_000_001  # a stamp no camera frame has


def test_the_camera_frames_a_balloon_object_detect_finds_it_and_takes_new_colours_live(hub, processes):
    session, endpoint = hub
    start_healthy(processes, session, endpoint, ("camera", "object_detect"))
    got, subscribers = collect(session, {"camera": CameraFrame, "camera_jpeg": CompressedFrame,
                                         "camera_detections": Detections})
    colors = session.declare_publisher(keys.uav("uav1", "colors"))
    time.sleep(0.5)

    def put(key: str, msg) -> None:
        session.put(key, msgspec.msgpack.encode(msg))

    world = WorldModel(header=Header(sender="sim/simulator", seq=1), scenario="test", arena=[(0, 0), (1, 0), (0, 1)],
                       min_height=0.0, max_height=20.0, uavs=["uav1"], seed=3,
                       obstacles=[Obstacle(kind="plane", center=(0, 0, 0), color=(196, 178, 140))])
    balloon = TargetTruth(id="balloon1", kind="balloon", position=BALLOON, velocity=(0, 0, 0), radius=0.3,
                          color=(200, 30, 30))
    put(keys.WORLD, world)
    time.sleep(0.3)
    for tick in range(1, 41):
        if tick == 10:  # a frame whose image is not what its header says
            put(keys.uav("uav1", "camera"), CameraFrame(
                header=Header(stamp=BAD_FRAME_NS), width=640, height=360, camera_pose=Pose(), fx=460.0, fy=460.0,
                cx=320.0, cy=180.0, color=from_numpy(np.zeros((10, 10, 3), np.uint8))))
        if tick == 20:  # a colour file that is not one, then green: the red balloon is not green
            colors.put(msgspec.msgpack.encode(ColorUpdate(header=Header(seq=1), name="broken", toml="[thresholds")))
            green = (REPO / "services/object_detect/colors/green.toml").read_text()
            colors.put(msgspec.msgpack.encode(ColorUpdate(header=Header(seq=2), name="green", toml=green)))
            time.sleep(0.2)
        now = tick * TICK_NS
        put(keys.TRUTH, GroundTruth(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick,
                                    uavs=[VehicleTruth(name="uav1", position=(0.0, 0.0, 5.0), velocity=(0, 0, 0),
                                                       heading=0.0, airborne=True)], targets=[balloon]))
        put(keys.CLOCK, SimClock(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick, dt=0.05,
                                 lockstep=False))
        time.sleep(0.08)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and len(got["camera_detections"]) < len(got["camera"]):
        time.sleep(0.1)
    for s in subscribers:
        s.undeclare()
    colors.undeclare()

    frames = {m.header.stamp: m for m in got["camera"] if m.header.stamp != BAD_FRAME_NS}
    # 10 Hz half a period after the 10 Hz LiDAR scans: 0.05 s, 0.15 s, ... In real time a loaded
    # machine may shed a tick to a slow renderer; the camera then renders at the next tick of that
    # slot (0.10 s), never twice in one slot, and most frames still sit on the phase.
    slots = [(stamp - 50_000_000) // 100_000_000 for stamp in frames]
    on_phase = [stamp for stamp in frames if stamp % 100_000_000 == 50_000_000]
    assert len(set(slots)) == len(slots) and len(on_phase) >= 12 and len(on_phase) >= 0.75 * len(frames), sorted(frames)
    first = frames[min(frames)]
    assert (first.width, first.height) == (640, 360) and to_numpy(first.color).shape == (360, 640, 3)
    assert to_numpy(first.depth).dtype == np.uint16
    assert got["camera_jpeg"] and got["camera_jpeg"][0].jpeg[:2] == b"\xff\xd8"  # a JPEG, at 1 Hz
    detections = {m.header.stamp: m for m in got["camera_detections"]}
    assert set(detections) == set(frames)  # one message per frame, empty ones included; none for the bad one
    red = [to_numpy(m.positions) for stamp, m in detections.items() if stamp < 950_000_000]
    green = [to_numpy(m.positions) for stamp, m in detections.items() if stamp > 1_200_000_000]
    assert red and all(len(p) == 1 and np.linalg.norm(p[0] - BALLOON) < 0.3 for p in red)
    assert green and all(len(p) == 0 for p in green)
    assert all(m.detector == "camera" for m in detections.values())
    answer = health(session, "uav1", "object_detect")
    assert answer.handler_errors == 0 and answer.received.get(keys.uav("uav1", "colors"), 0) == 2
