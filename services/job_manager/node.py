"""job_manager service: wires the mission state machine (core.JobManager) to Zenoh.

In: the world (arena, team, mission length), this UAV's odometry, detections (one message per
LiDAR scan, also the abort system's heartbeat), the camera's detections (Object Detect's
balloons, one message per frame) and tracks, its planner's reports (a target every approach to
which is blocked by obstacles becomes a forbidden zone), every partner's status and the
liveliness tokens (pre-flight check of this UAV's services; partners' job managers for revenge
mode). Out: mission commands for the planner and this UAV's status for its partners. Every
decision is the core's; the node only converts messages and logs what the core noted. The core
decides every tick and, in real time (not lockstep), also as soon as a message holding a sighting
arrives.
"""
from __future__ import annotations

import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import (
    ConstraintProfile,
    Decision,
    Detections,
    ForbiddenZoneStatus,
    Header,
    MissionCommand,
    Odometry,
    PlanReport,
    Tracks,
    TrajectoryReference,
    UavStatus,
    WorldModel,
)
from services.job_manager.core import NS, JobManager, MissionDecision
from services.job_manager.params import JobManagerParams
from services.job_manager.plans import PlannedPath
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node
from services.lib.tracks import (path_step, track_path, track_position, track_position_covariance, track_positions,
                                   track_velocities, track_velocity)

class JobManagerNode(Node):
    service = "job_manager"
    upstream = ("tracker", "classifier", keys.ORACLE, "object_detect")  # the detectors that run, and the tracker
    params_type = JobManagerParams

    def setup(self) -> None:
        self._refused_worlds = 0
        self._bad_input = CountedWarnings(self.log)
        self._refused_plans = 0
        self.import_when_up("filterpy.kalman")  # the target filter's library: off the restart's critical path
        self.core = JobManager(self.params, self.uav)
        p = self.params
        self.profiles = {
            "sweeping": ConstraintProfile(name="sweeping", max_speed=p.sweeping_speed,
                                          max_acceleration=p.sweeping_acceleration),
            "attack": ConstraintProfile(name="attack", max_speed=p.attack_speed, max_acceleration=p.attack_acceleration),
            # flying without GNSS on a degraded position (core.py)
            "degraded": ConstraintProfile(name="degraded", max_speed=p.degraded_speed,
                                          max_acceleration=p.sweeping_acceleration),
        }
        self.positioning = ""  # the odometry's health: the localizer's when flying without GNSS
        self.position: np.ndarray | None = None
        self.velocity = np.zeros(3)
        self.position_stamp = 0
        self.alive_services: set[str] = set()
        self.command_id = 0
        self.command: MissionCommand | None = None
        self.command_sent_at = 0
        self.next_status_ns = 0
        self.logged_transitions = 0
        self.command_pub = self.publisher(self.topic("command"), MissionCommand)
        self.status_pub = self.publisher(self.topic("status"), UavStatus)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        self.subscribe(self.topic("odometry"), Odometry, self.on_odometry)
        self.subscribe(self.topic("detections"), Detections, self.on_detections)
        self.subscribe(self.topic("camera_detections"), Detections, self.on_camera_detections)
        self.subscribe(self.topic("tracks"), Tracks, self.on_tracks)
        self.subscribe(self.topic("plan"), PlanReport, self.on_plan)
        self.subscribe(self.topic("trajectory"), TrajectoryReference, self.on_trajectory)
        self.subscribe(keys.ALL_STATUS, UavStatus, self.on_partner_status)
        self.on_liveliness(keys.ALL_ALIVE, self.on_alive)

    # ---------------------------------------------------------------- inputs
    def on_world(self, msg: WorldModel, key: str) -> None:
        ground_z = next((o.center[2] for o in msg.obstacles if o.kind == "plane"), 0.0)
        try:
            changed = self.core.set_world(np.asarray(msg.arena, dtype=np.float64), list(msg.uavs), msg.duration,
                                          ground_z)
        except ValueError as exc:  # an impossible world: keep the last good one
            self._refused_worlds += 1
            self._bad_input.update({"world models refused (arena, team, duration or ground impossible)":
                                    self._refused_worlds})
            if self._refused_worlds == 1:
                self.log.warning("the first refused world model: %s", exc)
            return
        by_localizer = msg.positioning.get(self.uav) == "lidar"
        if by_localizer != self.core.positioning_by_localizer:
            self.core.positioning_by_localizer = by_localizer
            self.log.info("positioning: %s", "the localizer's estimate (no GNSS)" if by_localizer else "GNSS")
        if changed:
            area = self.core.working_area
            self.log.info("working area %d of %d: x %.1f..%.1f, %d vertices; mission %.0f s",
                          msg.uavs.index(self.uav) + 1, len(msg.uavs), area[:, 0].min(), area[:, 0].max(),
                          len(area), msg.duration)

    def on_odometry(self, msg: Odometry, key: str) -> None:
        self.position = np.asarray(msg.pose.position, dtype=np.float64)
        self.velocity = np.asarray(msg.velocity, dtype=np.float64)
        self.position_stamp = msg.header.stamp
        self.positioning = msg.health

    def on_detections(self, msg: Detections, key: str) -> None:
        positions, covariances = _positions_and_covariances(msg)
        self.core.observe_detections(msg.header.stamp, positions, covariances, sensor_health=msg.sensor_health)
        self.act_on_sighting(len(positions))

    def on_camera_detections(self, msg: Detections, key: str) -> None:
        positions, covariances = _positions_and_covariances(msg)
        self.core.observe_camera(msg.header.stamp, positions, covariances, sensor_health=msg.sensor_health)
        self.act_on_sighting(len(positions))

    def on_tracks(self, msg: Tracks, key: str) -> None:
        confirmed = [t for t in msg.tracks if t.confirmed and np.isfinite(track_position(t)).all()
                     and np.isfinite(track_velocity(t)).all()]
        self.core.observe_tracks(msg.header.stamp, np.array([t.id for t in confirmed], dtype=np.int64),
                                 track_positions(confirmed), track_velocities(confirmed),
                                 [track_path(t) for t in confirmed], path_step(confirmed[0]) if confirmed else 0.0,
                                 fleet=np.array([t.source not in ("", self.uav) for t in confirmed], dtype=bool),
                                 covariances=np.array([track_position_covariance(t) for t in confirmed]).reshape(-1, 3, 3),
                                 corrected=np.array([t.last_correction for t in confirmed], dtype=np.int64))
        self.act_on_sighting(len(confirmed))

    def act_on_sighting(self, sightings: int) -> None:
        """In real time a message holding a sighting is decided on as it arrives: a command that
        waited for the next tick would be up to a tick older. One without (most scans and frames
        of a search) changes nothing that cannot wait for the tick."""
        if self.real_time and sightings:
            self.decide(self.clock.now_ns(), repeat=False)

    def on_plan(self, msg: PlanReport, key: str) -> None:
        if self.command is not None and msg.command_id == self.command.command_id:  # older commands are history
            self.core.plan_report(msg.header.stamp, msg.action, msg.outcome, msg.note)

    def on_partner_status(self, msg: UavStatus, key: str) -> None:
        if msg.uav != self.uav:
            self.core.partner_status(msg.uav, msg.header.stamp, flying_normally=msg.flying_normally,
                                     airborne=msg.airborne, position=msg.position, state=msg.state, target=msg.target,
                                     velocity=msg.velocity, plan=self._plan_of(msg))

    def _plan_of(self, msg: UavStatus) -> PlannedPath | None:
        """A partner's shared plan; one that cannot be (not finite, a bad shape or step) is left out,
        counted, and the partner is predicted from its velocity instead."""
        if msg.plan is None:
            return None
        try:
            return PlannedPath(msg.plan_start, msg.plan_dt, to_numpy(msg.plan))
        except ValueError:
            self._refused_plans += 1
            self._bad_input.update({"partner plans refused (not finite (K, 3) positions every plan_dt > 0)":
                                    self._refused_plans})
            return None

    def on_trajectory(self, msg: TrajectoryReference, key: str) -> None:
        try:
            self.core.observe_reference(PlannedPath(msg.start, msg.dt, to_numpy(msg.positions)))
        except ValueError:
            self._refused_plans += 1
            self._bad_input.update({"own references refused (not finite (K, 3) positions every dt > 0)":
                                    self._refused_plans})

    def on_alive(self, key: str, alive: bool) -> None:
        parsed = keys.parse_alive(key)
        if parsed is None or parsed[0] == keys.SIM:
            return
        scope, service = parsed
        if scope == self.uav:
            (self.alive_services.add if alive else self.alive_services.discard)(service)
        else:
            if service == self.service:
                # a partner's job manager: its token vanishing is the quickest sign of a fallen partner
                self.core.partner_token(scope, alive, self.clock.now_ns())
            if not alive:
                self.log.warning("partner %s lost %s (liveliness token gone)", scope, service)

    # ------------------------------------------------------------------ tick
    def positioning_health(self) -> str:
        return self.core.positioning_health(self.positioning, keys.LOCALIZER in self.alive_services)

    def on_tick(self, now_ns: int) -> None:
        self.decide(now_ns, repeat=True)
        if now_ns >= self.next_status_ns:
            self.publish_status(now_ns)
            period = int(NS / self.params.status_rate_hz)
            self.next_status_ns = (now_ns // period + 1) * period

    def decide(self, now_ns: int, repeat: bool) -> None:
        """The core's decision at now_ns, sent when it changed; with `repeat`, the last command is
        sent again when `command_repeat` is due."""
        if self.position is None:
            return
        core = self.core
        decision = core.update(now_ns, self.position, core.is_airborne(self.position[2]),
                               core.services_ready(self.alive_services), position_stamp_ns=self.position_stamp,
                               velocity=self.velocity, positioning=self.positioning_health())
        self.report()
        if decision is not None:
            self.send_command(now_ns, decision)
        elif repeat and self.command is not None and self.params.command_repeat > 0 and \
                now_ns - self.command_sent_at >= int(self.params.command_repeat * NS):
            self.resend_command(now_ns)  # a restarted planner gets it (same id: no re-plan)

    def report(self) -> None:
        """Log what the core did since the last tick."""
        for step in self.core.transitions[self.logged_transitions:]:
            self.log.info("%s -> %s (%s)", step.source.value, step.target.value, step.reason)
        self.logged_transitions = len(self.core.transitions)
        for note in self.core.notes:
            self.log.info("%s", note)
        self.core.notes.clear()

    # --------------------------------------------------------------- outputs
    def send_command(self, now_ns: int, decision: MissionDecision) -> None:
        self.command_id += 1
        self.command = MissionCommand(
            header=Header(stamp=now_ns, source=decision.sighted),
            command_id=self.command_id,
            action=decision.action,
            target=decision.target,
            target_velocity=decision.target_velocity,
            target_path=from_numpy(np.array(decision.target_path, dtype=np.float64).reshape(-1, 3))
            if decision.target_path else None,
            target_path_dt=decision.target_path_dt,
            target_seen=decision.target_seen,
            area=list(decision.area),
            height=decision.height,
            spacing=decision.spacing,
            profile=self.profiles[decision.profile],
        )
        self.command_sent_at = now_ns
        self.command_pub.put(self.command)
        where = "" if decision.target is None else " (%.1f, %.1f, %.1f)" % decision.target
        self.log.info("command %d: %s%s", self.command_id, decision.action, where)

    def resend_command(self, now_ns: int) -> None:
        # an intercept's target and predicted path hold at the stamp it was decided at: a planner that
        # (re)starts on the repeat re-bases them from there, so that stamp stays
        stamp = self.command.header.stamp if self.command.action == "intercept" else now_ns
        self.command.header = Header(stamp=stamp, source=self.command.header.source)
        self.command_sent_at = now_ns
        self.command_pub.put(self.command)

    def publish_status(self, now_ns: int) -> None:
        position = self.position if self.position is not None else np.zeros(3)
        area = self.core.working_area
        plan = self.core.shared_plan(now_ns)
        self.status_pub.put(UavStatus(
            header=Header(stamp=now_ns),
            uav=self.uav,
            state=self.core.state.value,
            flying_normally=self.core.flying_normally,
            airborne=self.position is not None and self.core.is_airborne(position[2]),
            position=(float(position[0]), float(position[1]), float(position[2])),
            velocity=(float(self.velocity[0]), float(self.velocity[1]), float(self.velocity[2])),
            working_area=[] if area is None else [(float(x), float(y)) for x, y in area],
            target=self.core.target,
            fallen_partners=[] if self.core.team is None else self.core.team.fallen,
            forbidden_zones=[ForbiddenZoneStatus(center=z.center, radius=self.core.zones.radius, expires=z.expires,
                                                 reason=z.reason) for z in self.core.zones.zones],
            state_reason=self.core.transitions[-1].reason if self.core.transitions else "",
            plan=None if plan is None else from_numpy(plan.positions),
            plan_start=0 if plan is None else plan.start,
            plan_dt=0.0 if plan is None else plan.dt,
        ))


    def decisions(self) -> list[Decision]:
        return [Decision(stamp=t.stamp, state=t.target.value, reason=t.reason) for t in self.core.transitions]


NODE = JobManagerNode


def _positions_and_covariances(msg: Detections) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) positions and the covariances as sent (the core drops a covariance array of the wrong size)."""
    positions = to_numpy(msg.positions)
    return (positions.reshape(-1, 3) if positions.size else np.zeros((0, 3))), to_numpy(msg.covariances)
