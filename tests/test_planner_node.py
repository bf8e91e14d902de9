"""The planner service over real Zenoh: it keeps its UAV's map from the mapper's messages, plans a
command round what the map holds occupied and says so (PlanReport), and its guard brakes when a map
delta puts an obstacle where the vehicle could not stop short of it (issue 34)."""
from __future__ import annotations

import queue
import time

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import (ConstraintProfile, Header, MissionCommand, Obstacle, Odometry, PlanReport, Pose,
                              SimClock, TrajectoryReference, VoxelMap, WorldModel)
from services.planner.freespace import FreeSpace
from services.lib.voxels.grid import GridGeometry
from tests.tools.health import health, wait_healthy

pytestmark = pytest.mark.alone  # a real-time node whose subscriptions meet within fixed sleeps

GRID = GridGeometry((-10.0, -10.0, -1.0), (120, 80, 30), 0.5)
WALL = (slice(58, 60), slice(30, 70), slice(2, 24))  # x 19-20, y 5-25, up to 11 m


def voxel_map(stamp: int, snapshot: bool, flats: np.ndarray, values: np.ndarray) -> bytes:
    return msgspec.msgpack.encode(VoxelMap(
        header=Header(sender="uav1/mapper", stamp=stamp), snapshot=snapshot, voxel_size=GRID.voxel_size,
        origin=GRID.origin, shape=GRID.shape, indices=from_numpy(flats.astype(np.int64)),
        values=from_numpy(values.astype(np.float32)), default_value=-740.0))


def block(where: tuple[slice, slice, slice]) -> np.ndarray:
    return np.ravel_multi_index(np.mgrid[where].reshape(3, -1), GRID.shape)


def test_the_planner_flies_round_a_mapped_wall_and_brakes_for_one_that_appears(hub, processes):
    session, endpoint = hub
    processes.start("run", "planner", "--uav", "uav1", "--connect", endpoint, "--exit-with-parent")
    wait_healthy(session, [("uav1", "planner")])
    trajectories: queue.SimpleQueue = queue.SimpleQueue()
    reports: queue.SimpleQueue = queue.SimpleQueue()
    subscribers = [
        session.declare_subscriber(keys.uav("uav1", "trajectory"), lambda s: trajectories.put(
            msgspec.msgpack.decode(s.payload.to_bytes(), type=TrajectoryReference))),
        session.declare_subscriber(keys.uav("uav1", "plan"), lambda s: reports.put(
            msgspec.msgpack.decode(s.payload.to_bytes(), type=PlanReport))),
    ]
    time.sleep(0.5)  # the subscriptions meet
    try:
        clock = [0.0]

        def tick(seconds: float | None = None) -> None:
            clock[0] = clock[0] + 0.05 if seconds is None else seconds
            session.put(keys.CLOCK, msgspec.msgpack.encode(SimClock(
                header=Header(sender="sim/simulator", seq=1, stamp=int(clock[0] * 1e9)), step=int(clock[0] * 20),
                dt=0.05, lockstep=False)))
            time.sleep(0.1)

        def odometry(seconds: float, position, velocity) -> None:
            session.put(keys.uav("uav1", "odometry"), msgspec.msgpack.encode(Odometry(
                header=Header(sender="sim/simulator", stamp=int(seconds * 1e9)), pose=Pose(position=position),
                velocity=velocity)))

        def latest(source: queue.SimpleQueue, wanted=lambda message: True, ticks: int = 100):
            """The first message `wanted` while the clock ticks on (a command is planned on a tick
            after it arrived; which tick depends on the machine's load)."""
            for _ in range(ticks):
                tick()
                while True:
                    try:
                        message = source.get_nowait()
                    except queue.Empty:
                        break
                    if wanted(message):
                        return message
            return None

        tick(0.0)
        session.put(keys.WORLD, msgspec.msgpack.encode(WorldModel(
            header=Header(sender="sim/simulator"), scenario="test", arena=[(0.0, 0.0), (40.0, 0.0), (40.0, 30.0),
                                                                           (0.0, 30.0)],
            min_height=1.0, max_height=15.0, obstacles=[Obstacle(kind="plane", center=(0.0, 0.0, 0.0))],
            uavs=["uav1"], uav_radius={"uav1": 0.4})))
        values = np.full(GRID.size, -1000.0, np.float32)  # everything seen free ...
        values[block(WALL)] = np.inf  # ... but the wall, pinned
        session.put(keys.uav("uav1", "map"), voxel_map(0, True, np.arange(GRID.size), values))
        odometry(0.0, (10.0, 15.0, 5.0), (0.0, 0.0, 0.0))
        tick()
        session.put(keys.uav("uav1", "command"), msgspec.msgpack.encode(MissionCommand(
            header=Header(sender="uav1/job_manager", seq=1, stamp=int(clock[0] * 1e9)), command_id=1, action="goto",
            target=(30.0, 15.0, 5.0), profile=ConstraintProfile())))
        report = latest(reports)
        assert report is not None and report.command_id == 1 and report.outcome == "detour", report
        trajectory = latest(trajectories)
        space = FreeSpace(1.7)
        space.set_ground(0.0)
        space.apply_map(True, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, np.arange(GRID.size), values)
        positions = to_numpy(trajectory.positions)
        assert np.allclose(positions[-1], [30.0, 15.0, 5.0], atol=0.05)
        assert space.path_clearance(positions) - 0.4 >= 1.0  # round or over the wall, a metre off it
        assert report.clearance is not None and report.clearance >= 1.0

        # a wall appears 10.5 m ahead of a vehicle going 5 m/s, half a metre beyond the point it was sent to
        session.put(keys.uav("uav1", "command"), msgspec.msgpack.encode(MissionCommand(
            header=Header(sender="uav1/job_manager", seq=2, stamp=int(clock[0] * 1e9)), command_id=2, action="goto",
            target=(12.0, 15.0, 12.0), profile=ConstraintProfile())))
        odometry(clock[0], (2.0, 15.0, 12.0), (5.0, 0.0, 0.0))
        assert latest(reports, lambda r: r.command_id == 2) is not None
        odometry(clock[0], (2.0, 15.0, 12.0), (5.0, 0.0, 0.0))
        appeared = (slice(45, 47), slice(30, 70), slice(20, 30))  # x 12.5-13.5, y 5-25, z 9-14
        session.put(keys.uav("uav1", "map"), voxel_map(int(clock[0] * 1e9), False, block(appeared),
                                                       np.zeros(block(appeared).size, np.float32)))
        acted = latest(reports, lambda r: r.outcome in ("braked", "replanned"))
        assert acted is not None and "ahead" in acted.note, acted
        after = latest(trajectories, lambda t: t.start == acted.header.stamp)
        assert after is not None and to_numpy(after.positions)[:, 0].max() <= 12.5 - 1.0  # stops a metre off it
        answer = health(session, "uav1", "planner")
        assert answer is not None and answer.handler_errors == 0
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
