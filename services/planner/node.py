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

import msgspec
import numpy as np

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Header, MissionCommand, Odometry, TrajectoryReference, UavStatus
from services.planner import core
from services.planner.watchdog import JobManagerWatchdog
from services.runtime.clock import NS
from services.runtime.node import Node


class PlannerParams(msgspec.Struct, forbid_unknown_fields=True):
    """Seed 004 Table 3.1 symbols in brackets."""

    dt: float = core.DT  # s between trajectory samples
    scan_offset: float = 2.0  # m kept inside the working area's inner rectangle
    corner_factor: float = 2.0  # [c_f] the scan's cross legs and corners fly at max_speed / c_f
    wait_distance: float = 4.0  # [d_b] m from the target where an approach ends
    descend_distance: float = 11.0  # [D_p] m from the target inside which the approach descends to it
    deadband: float = 0.5  # [D_f] m: line-of-sight changes smaller than this are ignored
    overshoot: float = 5.0  # [d_o] m beyond the target where an attack ends
    hit_offset: float = 0.3  # [o_h] m above the target centre the attack passes through
    end_offset: float = 0.15  # [o_o] m above the target height where the attack ends
    merge_acceleration: float = 1.5  # m/s² along a moving target's path when merging onto it
    follow_time: float = 4.0  # s flown alongside a moving target after the merge
    pursuit_horizon: float = 12.0  # s a pursuit flies the predicted track before braking (re-planned sooner)
    rejoin_distance: float = 1.5  # m: a re-plan starts on the current trajectory while this close to it
    republish_period: float = 2.0  # s of mission time
    repeat_scan: bool = True  # sweep again once a scan trajectory has ended
    job_manager_timeout: float = 1.0  # s without a status of our job manager: brake to a hover (watchdog.py)


def unplannable(command: MissionCommand) -> str | None:
    """Why the numbers of a command cannot be planned from (None: they can)."""
    profile = command.profile
    limits = (profile.max_speed, profile.max_acceleration, profile.max_heading_rate, profile.max_vertical_speed)
    if not all(0.0 < v < math.inf for v in limits):
        return f"profile {profile.name!r} needs positive finite limits, not {limits}"
    numbers = (command.height, command.spacing, *(command.target or ()), *(command.target_velocity or ()),
               *(c for point in command.area for c in point))
    if not all(math.isfinite(v) for v in numbers):
        return "a target, area, height or spacing that is not finite"
    return None


def yaw_of(quaternion: tuple[float, float, float, float]) -> float:
    w, x, y, z = quaternion
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


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
        try:
            positions, headings = self.plan_path(command, *self.start_state(now_ns))
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

    def start_state(self, now_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Where a new plan starts: on the current trajectory at `now` while the vehicle follows it
        (within `rejoin_distance`), else the odometry. Starting a re-plan from the measured state
        would hand the controller a reference with no error to act on: re-planned every tick, a
        braking manoeuvre would never brake."""
        ref = self.trajectory
        if ref is not None and self.params.rejoin_distance > 0:
            positions = to_numpy(ref.positions).reshape(-1, 3)
            u = (now_ns - ref.start) / NS / ref.dt
            if 0.0 <= u < len(positions) - 1:
                i = int(u)
                here = positions[i] + (u - i) * (positions[i + 1] - positions[i])
                if np.linalg.norm(here - self.position) <= self.params.rejoin_distance:
                    return here, (positions[i + 1] - positions[i]) / ref.dt
        return self.position, self.velocity

    def plan_path(self, command: MissionCommand, p: np.ndarray | None = None, v: np.ndarray | None = None) -> core.Path:
        p = self.position if p is None else p
        v = self.velocity if v is None else v
        if (problem := unplannable(command)) is not None:
            self.log.warning("command %d: %s; hovering", command.command_id, problem)
            return core.hover(p, self.heading)
        dt, profile, prm = self.params.dt, command.profile, self.params
        action, target = command.action, command.target
        moving = dict(start_velocity=v, start_heading=self.heading)
        if action == "takeoff":
            return core.takeoff(p, command.height, profile, dt, self.heading)
        if action in ("land", "emergency_land"):
            ground = target[2] if target is not None else self.first_z
            return core.land(p, ground, profile, dt, self.heading)
        if action == "stop":
            return core.stop(p, v, profile, dt, self.heading)
        if action == "scan" and len(command.area) >= 3:
            return core.lawnmower(np.asarray(command.area), command.height, command.spacing, offset=prm.scan_offset,
                                  corner_factor=prm.corner_factor, profile=profile, start=p, dt=dt, **moving)
        if target is not None:
            target = np.asarray(target, dtype=np.float64)
            if action == "approach":
                return core.approach(p, target, wait_distance=prm.wait_distance, descend_distance=prm.descend_distance,
                                     deadband_band=prm.deadband, profile=profile, dt=dt, **moving)
            if action == "attack":
                return core.attack(p, target, overshoot=prm.overshoot, hit_offset=prm.hit_offset,
                                   end_offset=prm.end_offset, profile=profile, dt=dt, **moving)
            if action == "intercept":
                # pursuit re-plans smoothly from the current state on every new prediction; the
                # merge (wait on the predicted path) is the fallback when no blend fits the profile
                velocity = np.asarray(command.target_velocity or (0.0, 0.0, 0.0), dtype=np.float64)
                path = core.pursuit(p, target, velocity, profile=profile, dt=dt, horizon=prm.pursuit_horizon, **moving)
                if path is None:
                    path = core.intercept(p, target, velocity, profile=profile, dt=dt,
                                          merge_acceleration=prm.merge_acceleration, follow_time=prm.follow_time,
                                          **moving)
                if path is not None:
                    return path
                self.log.info("command %d: no merge onto the target is feasible; chasing its position",
                              command.command_id)
                return core.approach(p, target, wait_distance=0.0, descend_distance=prm.descend_distance,
                                     deadband_band=0.0, profile=profile, dt=dt, **moving)
            if action in ("goto", "hover"):
                return core.goto(p, target, profile, dt, self.heading)
        if action not in ("idle", "hover"):
            self.log.warning("command %d: cannot plan %s with what it carries; hovering",
                             command.command_id, action)
        return core.hover(p, self.heading)

    def publish(self, now_ns: int) -> None:
        self.trajectory.header = Header(stamp=now_ns)
        self.published_at = now_ns
        self.trajectory_pub.put(self.trajectory)


NODE = PlannerNode
