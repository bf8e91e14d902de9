"""The sensor driver and the oracle as running services: every scan comes with its truth
(same stamp, same shape), the oracle turns the target hits into detections, a scheduled
`lidar_silent` fault silences exactly its window of mission time, and the LiDAR model is the
parameters' or else the one the world model names for the UAV; the sensor driver and the camera
see the obstacles only the ground truth carries."""
from __future__ import annotations

import math
import subprocess
import sys
import time

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import (
    CameraFrame,
    Detections,
    FaultCommand,
    GroundTruth,
    Header,
    Obstacle,
    PointCloud,
    PointTruth,
    SimClock,
    TargetTruth,
    VehicleTruth,
    WorldModel,
)
from services.lib.lidar.models import DEFAULT_MOUNT, BeamSpacing
from services.lib.lidar.uncertainty import sampling_covariance
from tests.conftest import REPO
from tests.tools.health import wait_healthy
from tests.tools.nodes import collect, start_healthy

pytestmark = pytest.mark.alone  # real-time nodes whose subscriptions meet within fixed sleeps

TICK_NS = 50_000_000
# The oracle started the way `falconry run oracle --uav uav1` does once the launcher treats it
# as a per-UAV service.
ORACLE = """
import sys
from services.tools.launcher.cli import main
from schemas import keys
keys.UAV_SERVICES = keys.UAV_SERVICES + (keys.ORACLE,)
sys.exit(main(sys.argv[1:]))
"""


def stamp_ns(tick: int) -> int:
    return tick * TICK_NS


def test_scans_carry_truth_the_oracle_detects_and_faults_silence(hub, processes, tmp_path):
    session, endpoint = hub
    config = tmp_path / "params.toml"
    config.write_text('[sensor_driver]\nmodel = "os1-64-1024"\nrange_noise = 0.0\n[oracle]\nsigma = 0.05\n')
    processes.start("run", "sensor_driver", "--uav", "uav1", "--connect", endpoint, "--config", str(config),
                    "--exit-with-parent")
    processes.start("run", "sensor_driver", "--uav", "uav2", "--connect", endpoint, "--exit-with-parent")
    processes.procs.append(subprocess.Popen(
        [sys.executable, "-c", ORACLE, "run", "oracle", "--uav", "uav1", "--connect", endpoint,
         "--config", str(config), "--exit-with-parent"], cwd=REPO))
    wait_healthy(session, [("uav1", "sensor_driver"), ("uav2", "sensor_driver"), ("uav1", "oracle")])

    got: dict[str, list] = {"points": [], "points_truth": [], "detections": [], "uav2": []}
    decoders = {"points": PointCloud, "points_truth": PointTruth, "detections": Detections}
    subscribers = [session.declare_subscriber(keys.uav("uav1", topic), lambda s, t=topic: got[t].append(
        msgspec.msgpack.decode(s.payload.to_bytes(), type=decoders[t]))) for topic in decoders]
    subscribers.append(session.declare_subscriber(keys.uav("uav2", "points"), lambda s: got["uav2"].append(
        msgspec.msgpack.decode(s.payload.to_bytes(), type=PointCloud))))
    time.sleep(0.5)

    def put(key: str, msg) -> None:
        session.put(key, msgspec.msgpack.encode(msg))

    world = WorldModel(header=Header(sender="sim/simulator", seq=1), scenario="test", arena=[(0, 0), (1, 0), (0, 1)],
                       min_height=0.0, max_height=20.0, uavs=["uav1", "uav2"], seed=3,
                       sensors={"uav1": "mid360", "uav2": "mid360"},  # uav1's parameters name its own
                       obstacles=[Obstacle(kind="plane", center=(0, 0, 0)),
                                  Obstacle(kind="box", center=(0, 20, 4), size=(6, 2, 8))])
    targets = [TargetTruth(id="balloon1", kind="balloon", position=(10.0, 0.0, 5.0), velocity=(0, 0, 0), radius=0.3),
               TargetTruth(id="hidden", kind="balloon", position=(0.0, 25.0, 5.0), velocity=(0, 0, 0), radius=0.3),
               TargetTruth(id="drone1", kind="drone", position=(0.0, -12.0, 6.0), velocity=(1, 0, 0),
                           radius=0.325)]
    put(keys.WORLD, world)
    put(keys.FAULTS, FaultCommand(header=Header(sender="sim/simulator", seq=1, stamp=stamp_ns(20)),
                                  kind="lidar_silent", uav="uav1", duration=0.5))
    time.sleep(0.3)
    for tick in range(1, 41):
        now = stamp_ns(tick)
        put(keys.TRUTH, GroundTruth(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick,
                                    uavs=[VehicleTruth(name="uav1", position=(0.0, 0.0, 5.0), velocity=(0, 0, 0),
                                                       heading=0.4, airborne=True),
                                          VehicleTruth(name="uav2", position=(5.0, 5.0, 5.0), velocity=(0, 0, 0),
                                                       heading=0.0, airborne=True)],
                                    targets=targets))
        put(keys.CLOCK, SimClock(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick, dt=0.05,
                                 lockstep=False))
        time.sleep(0.06)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and len(got["detections"]) < len(got["points"]):
        time.sleep(0.1)
    for s in subscribers:
        s.undeclare()

    clouds = {m.header.stamp: m for m in got["points"]}
    truths = {m.header.stamp: m for m in got["points_truth"]}
    scanned = sorted(clouds)
    # 10 Hz from the first tick, nothing in the silent window [1.0, 1.5) s of mission time
    assert scanned and set(scanned) == set(truths)
    assert not [s for s in scanned if stamp_ns(20) <= s < stamp_ns(30)]
    assert stamp_ns(18) in scanned and stamp_ns(30) in scanned and stamp_ns(40) in scanned
    for stamp in scanned:
        cloud, truth = clouds[stamp], truths[stamp]
        points, hits = to_numpy(cloud.points), to_numpy(truth.hits)
        assert points.shape == (64, 1024, 3) and hits.shape == (64, 1024) and cloud.sensor_model == "os1-64-1024"
        assert np.array_equal(hits == -1, np.isnan(points).any(axis=-1))
        assert truth.targets == ["balloon1", "hidden", "drone1"]
        assert set(np.unique(hits)) <= {-1, 0, 1, 3}  # the building hides target 2

    detections = {m.header.stamp: m for m in got["detections"]}
    assert set(detections) == set(scanned)
    for stamp, msg in detections.items():
        assert msg.detector == "oracle"
        positions = to_numpy(msg.positions)
        assert len(positions) == 2, stamp  # the balloon and the drone, not the hidden balloon
        assert np.linalg.norm(positions[0] - [10.0, 0.0, 5.0]) < 0.5
        assert np.linalg.norm(positions[1] - [0.0, -12.0, 6.0]) < 0.6
        mounted = (0.0, 0.0, 5.0 + DEFAULT_MOUNT[2])  # the sensor sits on top of the carrier
        # the added noise's, and where between os1-64-1024's beams (0.71° × 0.35°) the balloon's centre lies
        between = sampling_covariance(positions[0], mounted, BeamSpacing(math.radians(45.0 / 63), 2 * math.pi / 1024))
        assert np.allclose(to_numpy(msg.covariances)[0], 0.05 ** 2 * np.eye(3) + between, atol=2e-4)
        assert (to_numpy(msg.point_counts) >= 2).all() and msg.sensor_position == pytest.approx(mounted)

    uav2 = got["uav2"]
    assert uav2 and all(m.sensor_model == "mid360" and to_numpy(m.points).shape == (4, 5000, 3) for m in uav2)
    assert (uav2[0].min_range, uav2[0].max_range) == (0.1, 40.0)


SHED = Obstacle(kind="box", center=(8.0, 0.0, 3.0), size=(2.0, 6.0, 6.0), name="shed", color=(20, 20, 200))


def test_the_simulated_sensors_see_an_obstacle_the_survey_lacks(hub, processes):
    """An obstacle only the ground truth carries (unsurveyed): the LiDAR's rays and the camera's
    pixels meet it from the tick it appears in the truth, beside the world model's ground."""
    session, endpoint = hub
    start_healthy(processes, session, endpoint, ("sensor_driver", "camera"))
    got, subscribers = collect(session, {"points": PointCloud, "points_truth": PointTruth, "camera": CameraFrame})
    time.sleep(0.5)

    def put(key: str, msg) -> None:
        session.put(key, msgspec.msgpack.encode(msg))

    put(keys.WORLD, WorldModel(header=Header(sender="sim/simulator", seq=1), scenario="test",
                               arena=[(0, 0), (1, 0), (0, 1)], min_height=0.0, max_height=20.0, uavs=["uav1"], seed=3,
                               obstacles=[Obstacle(kind="plane", center=(0, 0, 0), name="ground")]))
    time.sleep(0.3)
    appears = 20  # the shed is in the truth from this tick on
    for tick in range(1, 41):
        now = stamp_ns(tick)
        put(keys.TRUTH, GroundTruth(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick,
                                    uavs=[VehicleTruth(name="uav1", position=(0.0, 0.0, 3.0), velocity=(0, 0, 0),
                                                       heading=0.0, airborne=True)],
                                    obstacles=[SHED] if tick >= appears else []))
        put(keys.CLOCK, SimClock(header=Header(sender="sim/simulator", seq=tick, stamp=now), step=tick, dt=0.05,
                                 lockstep=False))
        time.sleep(0.08)
    time.sleep(1.0)
    for s in subscribers:
        s.undeclare()

    hits = {m.header.stamp: to_numpy(m.hits) for m in got["points_truth"]}
    on_shed = {}  # scan stamp -> returns from the shed's face (x = 7), off the ground
    for cloud in got["points"]:
        points = to_numpy(cloud.points).reshape(-1, 3)
        face = (np.abs(points[:, 0] - 7.0) < 0.1) & (np.abs(points[:, 1]) < 3.0) & (points[:, 2] > 0.3)
        assert (hits[cloud.header.stamp].reshape(-1)[face] == 0).all()  # the static world's id
        on_shed[cloud.header.stamp] = int(face.sum())
    # in real time a tick may overtake its own truth: the scan at the appearance tick may miss it
    before = [n for stamp, n in on_shed.items() if stamp < stamp_ns(appears)]
    after = [n for stamp, n in on_shed.items() if stamp > stamp_ns(appears)]
    assert len(before) >= 5 and len(after) >= 5, sorted(on_shed)
    assert max(before) == 0 and min(after) > 50, (before, after)
    # the camera's optical axis (10° down from 3.15 m) meets the face 6.85 m ahead: 6.96 m along the
    # axis; without the shed it meets the ground 17.9 m away, beyond the depth image's 10 m
    centre = {m.header.stamp: np.median(to_numpy(m.depth)[170:190, 310:330]) / 1000.0 for m in got["camera"]}
    seen = [d for stamp, d in centre.items() if stamp > stamp_ns(appears)]
    unseen = [d for stamp, d in centre.items() if stamp < stamp_ns(appears)]
    assert len(seen) >= 5 and len(unseen) >= 5, sorted(centre)
    assert all(d == 0.0 for d in unseen) and all(abs(d - 6.96) < 0.3 for d in seen), (unseen, seen)
