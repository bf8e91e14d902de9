"""planner service: plans a trajectory for every new mission command (core.py) and
publishes it as a TrajectoryReference.

FIRST VERSION (walking skeleton): plans from the latest odometry position when a command
with a new id arrives, re-publishes the current trajectory every `republish_period` s of
mission time with the same start (a restarted simulator or late subscriber picks it up),
and, like the seed's state machine (seed 004 §3.4.2), starts the sweep again when a scan
trajectory has been flown to its end. Interception and re-planning on target updates come
later.
"""
from __future__ import annotations

import math

import msgspec
import numpy as np

from schemas.arrays import from_numpy
from schemas.messages import Header, MissionCommand, Odometry, TrajectoryReference
from services.planner import core
from services.runtime.clock import NS
from services.runtime.node import Node


class PlannerParams(msgspec.Struct, forbid_unknown_fields=True):
    dt: float = core.DT  # s between trajectory samples
    scan_offset: float = 2.0  # m kept from the working area's bounding box
    republish_period: float = 2.0  # s of mission time
    repeat_scan: bool = True  # sweep again once a scan trajectory has ended


def yaw_of(quaternion: tuple[float, float, float, float]) -> float:
    w, x, y, z = quaternion
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class PlannerNode(Node):
    service = "planner"
    upstream = ("job_manager",)
    params_type = PlannerParams

    def setup(self) -> None:
        self.position: np.ndarray | None = None
        self.heading = 0.0
        self.first_z: float | None = None  # where we started: the ground when no target says otherwise
        self.command: MissionCommand | None = None
        self.planned_id: int | None = None
        self.trajectory: TrajectoryReference | None = None
        self.trajectory_end = 0
        self.published_at = 0
        self.trajectory_pub = self.publisher(self.topic("trajectory"), TrajectoryReference)
        self.subscribe(self.topic("command"), MissionCommand, self.on_command)
        self.subscribe(self.topic("odometry"), Odometry, self.on_odometry)

    def on_command(self, msg: MissionCommand, key: str) -> None:
        if msg.command_id != self.planned_id:
            self.command = msg  # planned in on_tick, from that tick's position and time

    def on_odometry(self, msg: Odometry, key: str) -> None:
        self.position = np.asarray(msg.pose.position, dtype=np.float64)
        self.heading = yaw_of(msg.pose.orientation)
        if self.first_z is None:
            self.first_z = float(self.position[2])

    def on_tick(self, now_ns: int) -> None:
        if self.position is None:
            return
        command = self.command
        if command is not None and command.command_id != self.planned_id:
            self.plan(now_ns, command)
        elif (self.trajectory is not None and self.params.repeat_scan and command is not None
              and command.action == "scan" and now_ns > self.trajectory_end):
            self.plan(now_ns, command)
        elif self.trajectory is not None and now_ns - self.published_at >= int(self.params.republish_period * NS):
            self.publish(now_ns)

    def plan(self, now_ns: int, command: MissionCommand) -> None:
        positions, headings = self.plan_path(command)
        self.planned_id = command.command_id
        dt = self.params.dt
        self.trajectory = TrajectoryReference(
            header=Header(stamp=now_ns),
            command_id=command.command_id,
            start=now_ns,
            dt=dt,
            positions=from_numpy(positions),
            headings=from_numpy(headings),
            profile=command.profile,
        )
        self.trajectory_end = now_ns + int(round((len(positions) - 1) * dt * NS))
        self.log.info("command %d %s: %d samples, %.1f s", command.command_id, command.action,
                      len(positions), (len(positions) - 1) * dt)
        self.publish(now_ns)

    def plan_path(self, command: MissionCommand) -> core.Path:
        p, dt, profile = self.position, self.params.dt, command.profile
        action = command.action
        if action == "takeoff":
            return core.takeoff(p, command.height, profile, dt, self.heading)
        if action in ("land", "emergency_land"):
            ground = command.target[2] if command.target is not None else self.first_z
            return core.land(p, ground, profile, dt, self.heading)
        if action == "scan" and len(command.area) >= 3:
            return core.lawnmower(np.asarray(command.area), command.height, command.spacing,
                                  self.params.scan_offset, profile, p, dt, self.heading)
        if action in ("goto", "attack") and command.target is not None:
            return core.goto(p, command.target, profile, dt, self.heading)
        if action not in ("idle", "hover"):
            self.log.warning("command %d: cannot plan %s with what it carries; hovering",
                             command.command_id, action)
        return core.hover(p, self.heading)

    def publish(self, now_ns: int) -> None:
        self.trajectory.header = Header(stamp=now_ns)
        self.published_at = now_ns
        self.trajectory_pub.put(self.trajectory)


NODE = PlannerNode
