"""planner service: plans a trajectory for every new mission command (core.py, seed 004 ch. 5)
and publishes it as a TrajectoryReference.

A command with a new id is planned from where the vehicle is meant to be: on the current
trajectory while it follows it (`rejoin_distance`), else from the latest odometry (position,
heading and velocity), so a re-plan in flight neither stops the vehicle nor hides its braking
from the controller: take-off/land/hover, stop (the brake before
checking a target), scan (lawnmower over the working area's inner rectangle), approach (to the
waiting point d_b with deadband), attack (through the target + o_h, d_o beyond), intercept (a
pursuit that blends onto a moving target's predicted track, or else a merge that waits on it),
goto. The current trajectory is re-published
every `republish_period` s of mission time with the same start (a restarted simulator or late
subscriber picks it up) and, like the seed's state machine (§3.4.2), a scan that has been
flown to its end starts again. A job manager that has said nothing for `job_manager_timeout`
makes it brake to a hover until it speaks again (watchdog.py).
"""
from __future__ import annotations

import math

import numpy as np

from schemas.arrays import from_numpy
from schemas.messages import Header, MissionCommand, Odometry, TrajectoryReference, UavStatus
from services.geometry import yaw_of
from services.planner import core
from services.planner.commands import PlannerParams, VehicleState, plan_command, start_state
from services.planner.watchdog import JobManagerWatchdog
from services.runtime.clock import NS
from services.runtime.node import Node


class PlannerNode(Node):
    service = "planner"
    upstream = ("job_manager",)
    params_type = PlannerParams

    def setup(self) -> None:
        self.position: np.ndarray | None = None
        self.velocity = np.zeros(3)
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
        self.subscribe(self.topic("status"), UavStatus, self.on_status)
        timeout = self.params.job_manager_timeout
        self.watchdog = JobManagerWatchdog(int(timeout * NS)) if 0 < timeout < math.inf else None
        self.command_seq = 0

    def on_status(self, msg: UavStatus, key: str) -> None:
        if self.watchdog is not None and self.watchdog.heard(msg.header.stamp):
            # what it said before it fell silent is history: hover until it commands again
            self.log.warning("the job manager speaks again: waiting for its next command")
            self.command = self.planned_id = None

    def on_command(self, msg: MissionCommand, key: str) -> None:
        if msg.header.seq < self.command_seq:
            self.planned_id = None  # a restarted job manager numbers its commands from 1 again
        self.command_seq = msg.header.seq
        if msg.command_id != self.planned_id:
            self.command = msg  # planned in on_tick, from that tick's position and time

    def on_odometry(self, msg: Odometry, key: str) -> None:
        self.position = np.asarray(msg.pose.position, dtype=np.float64)
        self.heading = yaw_of(msg.pose.orientation)
        self.velocity = np.asarray(msg.velocity, dtype=np.float64)
        if self.first_z is None:
            self.first_z = float(self.position[2])

    def on_tick(self, now_ns: int) -> None:
        if self.position is None:
            return
        if self.watchdog is not None and self.watchdog_tripped(now_ns):
            if self.trajectory is not None and now_ns - self.published_at >= int(self.params.republish_period * NS):
                self.publish(now_ns)
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
        position, velocity = start_state(self.trajectory, now_ns, self.position, self.velocity,
                                         self.params.rejoin_distance)
        ground = self.first_z if self.first_z is not None else float(self.position[2])
        try:
            plan = plan_command(command, VehicleState(position, velocity, self.heading, ground, now_ns), self.params)
            positions, headings = plan.path
            if plan.note:
                self.log.warning("command %d: %s", command.command_id, plan.note)
        except ValueError as err:  # refused by the core: a trajectory too long, an area with no scan in it, ...
            self.log.warning("command %d: %s; hovering", command.command_id, err)
            positions, headings = core.hover(self.position, self.heading)
        self.planned_id = command.command_id
        self.set_trajectory(now_ns, command.command_id, positions, headings, command.profile)
        self.log.info("command %d %s: %d samples, %.1f s", command.command_id, command.action,
                      len(positions), (len(positions) - 1) * self.params.dt)

    def set_trajectory(self, now_ns: int, command_id: int, positions: np.ndarray, headings: np.ndarray,
                       profile) -> None:
        dt = self.params.dt
        self.trajectory = TrajectoryReference(header=Header(stamp=now_ns), command_id=command_id, start=now_ns, dt=dt,
                                              positions=from_numpy(positions), headings=from_numpy(headings),
                                              profile=profile)
        self.trajectory_end = now_ns + int(round((len(positions) - 1) * dt * NS))
        self.publish(now_ns)

    def watchdog_tripped(self, now_ns: int) -> bool:
        """Whether the job manager's silence holds the vehicle (braking at its start); a landing
        goes on to the ground whoever is silent."""
        if self.command is not None and self.command.action in ("land", "emergency_land"):
            return False
        if self.watchdog.silent_too_long(now_ns) and self.trajectory is not None:
            self.brake(now_ns)
        return self.watchdog.tripped

    def brake(self, now_ns: int) -> None:
        """Stop where we are (the job manager has been silent too long): brake along the current
        velocity at the last trajectory's limits, then hover."""
        self.log.warning("no status from the job manager for %.1f s: braking to a hover", self.params.job_manager_timeout)
        profile = self.trajectory.profile
        positions, headings = core.stop(self.position, self.velocity, profile, self.params.dt, self.heading)
        self.set_trajectory(now_ns, -1, positions, headings, profile)
        self.planned_id = None

    def publish(self, now_ns: int) -> None:
        self.trajectory.header = Header(stamp=now_ns)
        self.published_at = now_ns
        self.trajectory_pub.put(self.trajectory)


NODE = PlannerNode
