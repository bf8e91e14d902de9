"""The classifier and mapper services on bad scans, over real Zenoh: NaN and infinite points, wrong
shapes, a sensor pose that is not finite, points far outside the map. Each is refused or clipped
with a counted warning, the services keep running without a handler error, and the map they
publish stays sound (seed 000's services, issue: perception)."""
from __future__ import annotations

import math
import queue
import signal
import time

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Header, PointCloud, Pose, SimClock, VoxelMap
from tests.tools.health import health, wait_healthy

pytestmark = pytest.mark.alone  # real-time nodes whose subscriptions meet within fixed sleeps

CONFIG = '[mapper]\napriori = ""\n'  # no world model in this test: learn everything


def cloud(stamp_s: float, points: np.ndarray, position=(20.0, 20.0, 5.0), orientation=(1.0, 0.0, 0.0, 0.0),
          width: int = 64) -> bytes:
    points = np.asarray(points, dtype=np.float32)
    return msgspec.msgpack.encode(PointCloud(
        header=Header(sender="uav1/sensor_driver", stamp=int(stamp_s * 1e9)), width=width,
        height=max(1, points.size // 3 // width), sensor_pose=Pose(position=position, orientation=orientation),
        points=from_numpy(points), sensor_model="os0-32-64"))


def ground_scan(rng) -> np.ndarray:
    points = np.column_stack([rng.uniform(10, 30, 32 * 64), rng.uniform(10, 30, 32 * 64), np.zeros(32 * 64)])
    return points.reshape(32, 64, 3)


def test_bad_scans_are_refused_with_counted_warnings_and_the_map_stays_sound(hub, processes, tmp_path):
    session, endpoint = hub
    config = tmp_path / "learn.toml"
    config.write_text(CONFIG)
    procs = {s: processes.start("run", s, "--uav", "uav1", "--connect", endpoint, "--config", str(config),
                                "--exit-with-parent") for s in ("classifier", "mapper")}
    wait_healthy(session, [("uav1", "classifier"), ("uav1", "mapper")])
    maps: queue.SimpleQueue = queue.SimpleQueue()
    subscriber = session.declare_subscriber(keys.uav("uav1", "map"), lambda s: maps.put(s.payload.to_bytes()))
    time.sleep(0.5)  # the subscriptions meet
    try:
        def tick(stamp_s: float) -> None:
            session.put(keys.CLOCK, msgspec.msgpack.encode(SimClock(
                header=Header(sender="sim/simulator", seq=1, stamp=int(stamp_s * 1e9)), step=int(stamp_s * 20),
                dt=0.05, lockstep=False)))
        tick(0.0)  # real time from now on: every scan is handled as it comes
        time.sleep(0.3)
        rng = np.random.default_rng(3)
        points_key = keys.uav("uav1", "points")

        def scan_out(message: bytes) -> None:  # at a LiDAR's pace: in real time a burst is shed to its newest
            session.put(points_key, message)
            time.sleep(0.1)
        for k in range(10):  # sound scans first: the ground becomes occupied, the air above it free
            scan_out(cloud(0.1 * k, ground_scan(rng)))
        bad = ground_scan(rng)
        bad[0, :10] = np.inf
        bad[1, :10] = [np.nan, 1.0, np.inf]
        scan_out(cloud(1.1, bad))  # infinities: dropped and counted
        scan_out(cloud(1.2, rng.uniform(0, 20, (100, 2))))  # not (…, 3)
        scan_out(cloud(1.3, ground_scan(rng), position=(math.nan, 0.0, 0.0)))  # pose not finite
        scan_out(cloud(1.35, ground_scan(rng), orientation=(0.0, 0.0, 0.0, 0.0)))  # no rotation
        far = ground_scan(rng)
        far[:16] += [-500.0, 0.0, 0.0]  # half the scan far outside the map
        scan_out(cloud(1.4, far))
        scan_out(cloud(1.5, ground_scan(rng)))  # and a sound one after it all
        time.sleep(1.0)
        while not maps.empty():  # the first tick's snapshot: before any scan
            maps.get()
        tick(6.0)  # the next snapshot is due (every 5 s)
        snapshot = None
        deadline = time.monotonic() + 10
        while snapshot is None and time.monotonic() < deadline:
            try:
                message = msgspec.msgpack.decode(maps.get(timeout=0.5), type=VoxelMap)
            except queue.Empty:
                continue
            snapshot = message if message.snapshot else None
        assert snapshot is not None, "the mapper published no snapshot"
        values = to_numpy(snapshot.values)
        assert len(values) > 0 and not np.isnan(values).any()  # the sound scans mapped the ground; nothing NaN
        for service in ("classifier", "mapper"):
            h = health(session, "uav1", service)
            assert h is not None and h.state == "running" and h.handler_errors == 0, (service, h)
    finally:
        subscriber.undeclare()
    logs = {}
    for service, proc in procs.items():
        proc.send_signal(signal.SIGTERM)
        logs[service] = proc.communicate(timeout=20)[0]
    dropped = [int(line.rsplit(":", 1)[1]) for line in logs["classifier"].splitlines()
               if "points with infinite coordinates dropped so far" in line]
    assert dropped and dropped[-1] >= 10, logs["classifier"]
    assert "scans refused (shape or sensor pose) so far: 1" in logs["classifier"]
    assert "scans refused (shape or sensor pose) so far: 2" not in logs["classifier"]  # said again at 10, not 2
    cast_refused = [int(line.rsplit(":", 1)[1]) for line in logs["mapper"].splitlines()
                    if "scans whose rays could not be cast (pose or field lengths) so far" in line]
    assert cast_refused == [1], logs["mapper"]  # three refused, said once: at 1 (the next word at 10)
    assert "Traceback" not in logs["classifier"] + logs["mapper"]
