"""job_manager service: wires the mission state machine (core.JobManager) to Zenoh.

FIRST VERSION (walking skeleton): pre-flight check on liveliness, take-off, lawnmower
sweep of this UAV's equal-area share of the arena, landing on the mission timer. Tracks
and partners' statuses are only logged; targets, forbidden zones and revenge mode come
with the full state machine (see core.py).
"""
from __future__ import annotations

import numpy as np

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import (
    ConstraintProfile,
    Header,
    MissionCommand,
    Odometry,
    Tracks,
    UavStatus,
    WorldModel,
)
from services.job_manager.core import NS, JobManager, JobManagerParams, MissionDecision
from services.runtime.node import Node

# Pre-flight check (seed 004 §3.6): every service this UAV's mission depends on is alive,
# and one detector (the classifier, or the evaluation oracle that replaces it).
REQUIRED_SERVICES = ("sensor_driver", "tracker", "planner")
DETECTORS = ("classifier", keys.ORACLE)
SWEEPING = ConstraintProfile(name="sweeping", max_speed=5.0, max_acceleration=1.5)
PROFILES = {SWEEPING.name: SWEEPING}


class JobManagerNode(Node):
    service = "job_manager"
    upstream = ("tracker",)
    params_type = JobManagerParams

    def setup(self) -> None:
        self.core = JobManager(self.params, self.uav)
        self.position: np.ndarray | None = None
        self.position_stamp = 0
        self.alive_services: set[str] = set()
        self.latest_tracks: Tracks | None = None
        self.command_id = 0
        self.command: MissionCommand | None = None
        self.command_sent_at = 0
        self.next_status_ns = 0
        self.silent_partners: list[str] = []
        self.command_pub = self.publisher(self.topic("command"), MissionCommand)
        self.status_pub = self.publisher(self.topic("status"), UavStatus)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        self.subscribe(self.topic("odometry"), Odometry, self.on_odometry)
        self.subscribe(self.topic("tracks"), Tracks, self.on_tracks)
        self.subscribe(keys.ALL_STATUS, UavStatus, self.on_partner_status)
        self.partner_services: dict[str, set[str]] = {}
        self.on_liveliness(keys.ALL_ALIVE, self.on_alive)

    # ---------------------------------------------------------------- inputs
    def on_world(self, msg: WorldModel, key: str) -> None:
        ground_z = next((o.center[2] for o in msg.obstacles if o.kind == "plane"), 0.0)
        if self.core.set_world(np.asarray(msg.arena, dtype=np.float64), list(msg.uavs), msg.duration, ground_z):
            area = self.core.working_area
            self.log.info("working area %d of %d: x %.1f..%.1f, %d vertices; mission %.0f s",
                          msg.uavs.index(self.uav) + 1, len(msg.uavs), area[:, 0].min(), area[:, 0].max(),
                          len(area), msg.duration)

    def on_odometry(self, msg: Odometry, key: str) -> None:
        self.position = np.asarray(msg.pose.position, dtype=np.float64)
        self.position_stamp = msg.header.stamp

    def on_tracks(self, msg: Tracks, key: str) -> None:
        self.latest_tracks = msg
        confirmed = [t.id for t in msg.tracks if t.confirmed]
        for track_id in self.core.note_confirmed_tracks(confirmed):
            track = next(t for t in msg.tracks if t.id == track_id)
            state = to_numpy(track.state)
            self.log.info("new confirmed track %d at (%.1f, %.1f, %.1f); %d confirmed now",
                          track_id, state[0], state[1], state[2], len(confirmed))

    def on_partner_status(self, msg: UavStatus, key: str) -> None:
        if msg.uav != self.uav:
            self.core.partner_status(msg.uav, msg.header.stamp, msg.flying_normally)

    def on_alive(self, key: str, alive: bool) -> None:
        parsed = keys.parse_alive(key)
        if parsed is None or parsed[0] == keys.SIM:
            return
        scope, service = parsed
        if scope == self.uav:
            (self.alive_services.add if alive else self.alive_services.discard)(service)
            return
        # A partner's service appearing or vanishing: the first sign of a fallen partner
        # (revenge mode acts on it in the full job manager).
        services = self.partner_services.setdefault(scope, set())
        if alive:
            services.add(service)
        elif service in services:
            services.discard(service)
            self.log.warning("partner %s lost %s (liveliness token gone)", scope, service)

    # ------------------------------------------------------------------ tick
    @property
    def services_ready(self) -> bool:
        return all(s in self.alive_services for s in REQUIRED_SERVICES) and \
            any(d in self.alive_services for d in DETECTORS)

    def on_tick(self, now_ns: int) -> None:
        if self.position is not None:
            previous = self.core.state
            decision = self.core.update(now_ns, self.position, self.core.is_airborne(self.position[2]),
                                        self.services_ready, position_stamp_ns=self.position_stamp)
            if self.core.state is not previous:
                step = self.core.transitions[-1]
                self.log.info("%s -> %s (%s)", step.source.value, step.target.value, step.reason)
            if decision is not None:
                self.send_command(now_ns, decision)
            elif self.command is not None and self.params.command_repeat > 0 and \
                    now_ns - self.command_sent_at >= int(self.params.command_repeat * NS):
                self.resend_command(now_ns)  # a restarted planner gets it (same id: no re-plan)
        self.check_partners(now_ns)
        if now_ns >= self.next_status_ns:
            self.publish_status(now_ns)
            period = int(NS / self.params.status_rate_hz)
            self.next_status_ns = (now_ns // period + 1) * period

    # --------------------------------------------------------------- outputs
    def send_command(self, now_ns: int, decision: MissionDecision) -> None:
        self.command_id += 1
        self.command = MissionCommand(
            header=Header(stamp=now_ns),
            command_id=self.command_id,
            action=decision.action,
            target=decision.target,
            area=list(decision.area),
            height=decision.height,
            spacing=decision.spacing,
            profile=PROFILES[decision.profile],
        )
        self.command_sent_at = now_ns
        self.command_pub.put(self.command)
        self.log.info("command %d: %s", self.command_id, decision.action)

    def resend_command(self, now_ns: int) -> None:
        self.command.header = Header(stamp=now_ns)
        self.command_sent_at = now_ns
        self.command_pub.put(self.command)

    def check_partners(self, now_ns: int) -> None:
        silent = self.core.partners_silent(now_ns)
        if silent != self.silent_partners:
            gone = sorted(set(silent) - set(self.silent_partners))
            back = sorted(set(self.silent_partners) - set(silent))
            if gone:
                self.log.warning("partners silent for %.0f s: %s (revenge mode comes later)",
                                 self.params.partner_timeout, ", ".join(gone))
            if back:
                self.log.info("partners heard again: %s", ", ".join(back))
            self.silent_partners = silent

    def publish_status(self, now_ns: int) -> None:
        position = self.position if self.position is not None else np.zeros(3)
        area = self.core.working_area
        self.status_pub.put(UavStatus(
            header=Header(stamp=now_ns),
            uav=self.uav,
            state=self.core.state.value,
            flying_normally=self.core.flying_normally,
            airborne=self.position is not None and self.core.is_airborne(position[2]),
            position=(float(position[0]), float(position[1]), float(position[2])),
            working_area=[] if area is None else [(float(x), float(y)) for x, y in area],
            target=None,
        ))


NODE = JobManagerNode
