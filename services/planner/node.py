"""planner service: plans a trajectory for every new mission command (commands.py, seed 004 ch. 5),
kept clear of what its UAV knows is occupied (avoid.py), publishes it as a TrajectoryReference and
says what it made of it (PlanReport), and guards the reference in flight (guard.py).

A command with a new id is planned at the next tick, or in real time (not lockstep) as soon as it
arrives, from where the vehicle is meant to be: on the current
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

What is occupied comes from the UAV's mapper (falconry/<uav>/map: the a-priori map and what the
LiDAR showed since); the body's radius, the ground and the height limits from the world model.
Every tick the guard looks at the next `guard_horizon` s of the reference against the latest map:
a conflict far enough ahead is re-planned round (the current command planned again), a near one
is braked for when no new plan avoids it; a command the guard stopped is planned again every
`guard_retry` s until a plan is clear.
"""
from __future__ import annotations

import math

import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import (
    DEFAULT_UAV_RADIUS,
    Header,
    MissionCommand,
    Odometry,
    PlanReport,
    TrajectoryReference,
    UavStatus,
    VoxelMap,
    WorldModel,
)
from services.lib.geometry import yaw_of
from services.planner import core, guard
from services.planner.avoid import Airspace, Clearances, Surroundings, airspace_of, mount_exemption
from services.planner.commands import (ApproachMemory, Plan, PlannerParams, VehicleState, plan_command, start_state,
                                       warm_up)
from services.planner.freespace import FreeSpace
from services.planner.watchdog import JobManagerWatchdog
from services.lib.runtime.clock import NS
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node

EXEMPT_ACTIONS = ("approach", "attack")  # their target's pole and balloon are passed over (avoid.py)


class PlannerNode(Node):
    service = "planner"
    upstream = ("job_manager",)
    params_type = PlannerParams

    @classmethod
    def preload(cls) -> None:
        warm_up(PlannerParams())

    def setup(self) -> None:
        warm_up(self.params)  # compiled now, before the liveliness token: the first plan must not stall a tick
        self.import_when_up("scipy.ndimage")  # the geofence's distance transform, once the arena is known
        self.position: np.ndarray | None = None
        self.velocity = np.zeros(3)
        self.heading = 0.0
        self.first_z: float | None = None  # where we started: the ground when no target says otherwise
        self.command: MissionCommand | None = None
        self.planned_id: int | None = None
        self.trajectory: TrajectoryReference | None = None
        self.trajectory_end = 0
        self.published_at = 0
        self.exempt: np.ndarray | None = None  # the active reference's mount exemption (an approach or attack)
        self.approached = ApproachMemory()
        self.guardian = guard.Guardian(int(self.params.guard_retry * NS))
        self.clearances = Clearances(DEFAULT_UAV_RADIUS, self.params.obstacle_margin, self.params.tracking_allowance)
        self.space = self._free_space()
        self.airspace = Airspace()
        self._bad_input = CountedWarnings(self.log)
        self._refused: dict[str, int] = {}
        self.trajectory_pub = self.publisher(self.topic("trajectory"), TrajectoryReference)
        self.report_pub = self.publisher(self.topic("plan"), PlanReport)
        self.subscribe(self.topic("command"), MissionCommand, self.on_command)
        self.subscribe(self.topic("odometry"), Odometry, self.on_odometry)
        self.subscribe(self.topic("status"), UavStatus, self.on_status)
        self.subscribe(self.topic("map"), VoxelMap, self.on_map, keep=None)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        timeout = self.params.job_manager_timeout
        self.watchdog = JobManagerWatchdog(int(timeout * NS)) if 0 < timeout < math.inf else None
        self.command_seq = 0

    def _free_space(self) -> FreeSpace:
        return FreeSpace(self.clearances.plan)

    @property
    def env(self) -> Surroundings:
        return Surroundings(self.space, self.clearances, self.airspace, self.params.search_margin)

    # ---------------------------------------------------------------- inputs
    def on_world(self, msg: WorldModel, key: str) -> None:
        ground = next((o.center[2] for o in msg.obstacles if o.kind == "plane"), 0.0)
        radius = float(msg.uav_radius.get(self.uav, DEFAULT_UAV_RADIUS))
        try:
            if not 0.0 < radius < math.inf:
                raise ValueError(f"a body radius of {radius} m")
            self.airspace = airspace_of(msg.arena, msg.min_height, msg.max_height, ground, self.params.pursuit_floor,
                                        self.params.fence_margin)
        except ValueError as exc:
            self._refuse("world models refused (ground, heights, body radius or arena impossible)")
            self.log.debug("world refused: %s", exc)
            return
        self.space.set_ground(ground)
        self.space.set_arena(np.asarray(self.airspace.arena), self.params.fence_margin)
        if radius != self.clearances.body:
            self.clearances = Clearances(radius, self.params.obstacle_margin, self.params.tracking_allowance)
            self.log.info("body radius %.2f m: plans keep %.2f m from occupied voxels' boxes", radius,
                          self.clearances.plan)
            self.space = self._rebuilt(self.space)

    def _rebuilt(self, old: FreeSpace) -> FreeSpace:
        """A free space for the new clearances, from the map the old one holds."""
        space = self._free_space()
        if old.ground_z is not None:
            space.set_ground(old.ground_z)
        space.set_arena(old.arena, old.keep_inside)
        if old.replica is not None:
            r = old.replica
            flat = r.grid.reshape(-1)
            changed = np.flatnonzero(flat != np.float32(r.default_value))
            space.apply_map(True, r.origin, r.shape, r.voxel_size, r.default_value, changed, flat[changed])
        return space

    def on_map(self, msg: VoxelMap, key: str) -> None:
        try:
            fits = self.space.apply_map(msg.snapshot, msg.origin, msg.shape, msg.voxel_size, msg.default_value,
                                        to_numpy(msg.indices), to_numpy(msg.values))
        except ValueError as exc:  # a geometry no replica holds, indices and values of other lengths
            self._refuse("map messages refused (geometry or contents impossible)")
            self.log.debug("map refused: %s", exc)
            return
        # a delta before any snapshot is no fault: the mapper's first snapshot is on its way as a run starts
        if not fits and self.space.replica is not None:
            self._refuse("map deltas of another grid than the snapshot held (waiting for the next)")

    def _refuse(self, what: str) -> None:
        self._refused[what] = self._refused.get(what, 0) + 1
        self._bad_input.update({what: self._refused[what]})

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
            self.command = msg  # planned in on_tick, from that tick's position and time, or now:
            if self.real_time:  # a reference that waited for the next tick would be up to a tick older
                self.plan_new_command(self.clock.now_ns())

    def on_odometry(self, msg: Odometry, key: str) -> None:
        self.position = np.asarray(msg.pose.position, dtype=np.float64)
        self.heading = yaw_of(msg.pose.orientation)
        self.velocity = np.asarray(msg.velocity, dtype=np.float64)
        if self.first_z is None:
            self.first_z = float(self.position[2])

    # ------------------------------------------------------------------ tick
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
        elif (self.trajectory is not None and self.params.repeat_scan and command is not None and not self.guardian.held
              and command.action == "scan" and now_ns > self.trajectory_end):
            self.plan(now_ns, command)
        elif self.trajectory is not None and now_ns - self.published_at >= int(self.params.republish_period * NS):
            self.publish(now_ns)
        self.guard(now_ns)

    def plan_new_command(self, now_ns: int) -> None:
        """Plan the newest command now, as the next tick would: once the vehicle's state is known,
        unless the job manager's silence holds the vehicle (a landing goes ahead)."""
        if self.position is None or (self.watchdog is not None and self.watchdog_tripped(now_ns)):
            return
        if self.command is not None and self.command.command_id != self.planned_id:
            self.plan(now_ns, self.command)
            self.guard(now_ns)  # as the tick does after a plan

    def vehicle(self, now_ns: int) -> VehicleState:
        position, velocity = start_state(self.trajectory, now_ns, self.position, self.velocity,
                                         self.params.rejoin_distance)
        ground = self.airspace.ground_z if self.space.ground_z is not None else \
            (self.first_z if self.first_z is not None else float(self.position[2]))
        return VehicleState(position, velocity, self.heading, ground, now_ns)

    def make_plan(self, now_ns: int, command: MissionCommand) -> Plan:
        try:
            plan = plan_command(command, self.vehicle(now_ns), self.params, self.env, self.approached.prefer(command))
        except ValueError as err:  # refused by the core: a trajectory too long, an area with no scan in it, ...
            return Plan(core.stop(self.position, self.velocity, command.profile, self.params.dt, self.heading),
                        f"{err}; braking to a hold", "blocked")
        self.approached.remember(command, plan)
        return plan

    def plan(self, now_ns: int, command: MissionCommand) -> None:
        plan = self.make_plan(now_ns, command)
        if plan.note:  # a fallback or a refusal is a warning; a detour is news
            log = self.log.info if plan.outcome in ("clear", "detour") else self.log.warning
            log("command %d: %s", command.command_id, plan.note)
        self.planned_id = command.command_id
        self.guardian.release()
        if plan.outcome == "blocked":
            self.guardian.hold(now_ns)  # planned again every guard_retry s: the way may clear
        self.adopt(now_ns, command, plan, plan.outcome)
        positions = plan.path[0]
        self.log.info("command %d %s: %d samples, %.1f s (%s)", command.command_id, command.action,
                      len(positions), (len(positions) - 1) * self.params.dt, plan.outcome)

    def adopt(self, now_ns: int, command: MissionCommand, plan: Plan, outcome: str) -> None:
        positions, headings = plan.path
        exempting = command.action in EXEMPT_ACTIONS and command.target is not None
        self.exempt = mount_exemption(np.asarray(command.target), self.params.mount_radius) if exempting else None
        self.set_trajectory(now_ns, command.command_id, positions, headings, command.profile)
        self.report(now_ns, command.command_id, command.action, outcome, plan.note or "", plan.clearance,
                    command.target)

    def report(self, now_ns: int, command_id: int, action: str, outcome: str, note: str, clearance, target) -> None:
        self.report_pub.put(PlanReport(header=Header(stamp=now_ns), command_id=command_id, action=action,
                                       outcome=outcome, note=note, clearance=clearance,
                                       target=None if target is None else tuple(float(v) for v in target)))

    # ----------------------------------------------------------------- guard
    def guard(self, now_ns: int) -> None:
        """The guard's check of the active reference, acted on as the Guardian decides (guard.py)."""
        if self.trajectory is None or not self.space.known:
            return
        verdict = self.verdict(now_ns, self.trajectory)
        command = self.command if self.command is not None and self.command.command_id == self.planned_id else None
        if self.guardian.wants_replan(now_ns, verdict, command is not None):
            self.guardian.tried(now_ns)
            if self.replan(now_ns, command, verdict):
                return
        if self.guardian.must_brake(verdict):
            self.log.warning("guard: %s: braking", verdict.reason)
            profile = self.trajectory.profile
            positions, headings = core.stop(self.position, self.velocity, profile, self.params.dt, self.heading)
            self.set_trajectory(now_ns, self.trajectory.command_id, positions, headings, profile)
            self.guardian.hold(now_ns)
            self.report(now_ns, self.trajectory.command_id, command.action if command else "", "braked",
                        verdict.reason, None, None if command is None else command.target)

    def replan(self, now_ns: int, command: MissionCommand, verdict: guard.GuardVerdict) -> bool:
        """Plan the command again; take the plan when the Guardian finds it better. True when taken."""
        plan = self.make_plan(now_ns, command)
        candidate = TrajectoryReference(header=Header(stamp=now_ns), command_id=command.command_id, start=now_ns,
                                        dt=self.params.dt, positions=from_numpy(plan.path[0]),
                                        headings=from_numpy(plan.path[1]), profile=command.profile)
        found = self.verdict(now_ns, candidate)
        if plan.outcome == "blocked" or not self.guardian.takes(verdict, found):
            self.log.info("guard: re-planned command %d not taken: %s (%s)", command.command_id,
                          found.reason or plan.note, plan.outcome)
            return False
        why = verdict.reason or "the way is clear again"
        self.log.warning("guard: %s: re-planned command %d (%s)", why, command.command_id, plan.outcome)
        self.guardian.release()
        self.adopt(now_ns, command, Plan(plan.path, "; ".join(filter(None, [why, plan.note])), plan.outcome,
                                         plan.clearance), "replanned")
        return True

    def verdict(self, now_ns: int, trajectory: TrajectoryReference) -> guard.GuardVerdict:
        p = self.params
        ahead = guard.upcoming(to_numpy(trajectory.positions), trajectory.start, trajectory.dt, now_ns,
                               p.guard_horizon)
        return guard.check(self.space, ahead, self.position, float(np.linalg.norm(self.velocity)),
                           trajectory.profile.max_acceleration, self.clearances.accept, self.clearances.hard,
                           view=p.guard_view,
                           slack=p.guard_slack, exempt=self.exempt)

    # -------------------------------------------------------------- watchdog
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

    # --------------------------------------------------------------- outputs
    def set_trajectory(self, now_ns: int, command_id: int, positions: np.ndarray, headings: np.ndarray,
                       profile) -> None:
        dt = self.params.dt
        planned = self.command if self.command is not None and self.command.command_id == command_id else None
        source = planned.header.source if planned is not None else 0  # the sighting the command was decided on
        self.trajectory = TrajectoryReference(header=Header(stamp=now_ns, source=source), command_id=command_id,
                                              start=now_ns, dt=dt,
                                              positions=from_numpy(positions), headings=from_numpy(headings),
                                              profile=profile)
        self.trajectory_end = now_ns + int(round((len(positions) - 1) * dt * NS))
        self.publish(now_ns)

    def publish(self, now_ns: int) -> None:
        self.trajectory.header = Header(stamp=now_ns, source=self.trajectory.header.source)
        self.published_at = now_ns
        self.trajectory_pub.put(self.trajectory)


NODE = PlannerNode
