"""What the planner flies for a mission command: the choice of manoeuvre per action and where a
new plan starts. Pure (numpy in, numpy out); the node only hands in the vehicle's state and the
current trajectory and logs the note that comes back.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np

from schemas.arrays import to_numpy
from schemas.messages import MissionCommand, TrajectoryReference
from services.planner import core
from services.runtime.clock import NS
from services.tracker.view import PredictedPath


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
    # s past the target's last sighting a pursuit follows its prediction (at most to the path's end), then waits
    pursuit_trust: float = 1.5
    pursuit_floor: float = 1.0  # m above the ground no pursuit goes below (the job manager's lowest target height)
    rejoin_distance: float = 1.5  # m: a re-plan starts on the current trajectory while this close to it
    republish_period: float = 2.0  # s of mission time
    repeat_scan: bool = True  # sweep again once a scan trajectory has ended
    job_manager_timeout: float = 1.0  # s without a status of our job manager: brake to a hover (watchdog.py)


@dataclass(frozen=True)
class VehicleState:
    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    heading: float  # rad
    ground_z: float  # where it started: the ground when no target says otherwise
    now_ns: int = 0  # mission time the plan starts at


@dataclass(frozen=True)
class Plan:
    path: core.Path
    note: str | None = None  # what the operator should read in the log (a fallback taken, a refusal)


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
    if command.target_path is not None:
        path = np.asarray(to_numpy(command.target_path), dtype=np.float64)
        if path.size % 3 or not np.isfinite(path).all() or not 0.0 < command.target_path_dt < math.inf:
            return "a target path that is not finite positions (K, 3) every finite positive target_path_dt"
    return None


def start_state(trajectory: TrajectoryReference | None, now_ns: int, position: np.ndarray, velocity: np.ndarray,
                rejoin_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a new plan starts: on the current trajectory at `now` while the vehicle follows it
    (within `rejoin_distance`), else the measured position and velocity. Starting a re-plan from
    the measured state would hand the controller a reference with no error to act on: re-planned
    every tick, a braking manoeuvre would never brake."""
    if trajectory is not None and rejoin_distance > 0:
        positions = to_numpy(trajectory.positions).reshape(-1, 3)
        u = (now_ns - trajectory.start) / NS / trajectory.dt
        if 0.0 <= u < len(positions) - 1:
            i = int(u)
            here = positions[i] + (u - i) * (positions[i + 1] - positions[i])
            if np.linalg.norm(here - position) <= rejoin_distance:
                return here, (positions[i + 1] - positions[i]) / trajectory.dt
    return position, velocity


def plan_command(command: MissionCommand, vehicle: VehicleState, params: PlannerParams) -> Plan:
    """The path for one command from `vehicle` (its start state). A command that cannot be planned
    is a hover, with the reason as the note."""
    if (problem := unplannable(command)) is not None:
        return Plan(core.hover(vehicle.position, vehicle.heading), f"{problem}; hovering")
    p, v, heading = vehicle.position, vehicle.velocity, vehicle.heading
    dt, profile, prm = params.dt, command.profile, params
    action, target = command.action, command.target
    moving = dict(start_velocity=v, start_heading=heading)
    if action == "takeoff":
        return Plan(core.takeoff(p, command.height, profile, dt, heading))
    if action in ("land", "emergency_land"):
        ground = target[2] if target is not None else vehicle.ground_z
        return Plan(core.land(p, ground, profile, dt, heading))
    if action == "stop":
        return Plan(core.stop(p, v, profile, dt, heading))
    if action == "scan" and len(command.area) >= 3:
        return Plan(core.lawnmower(np.asarray(command.area), command.height, command.spacing,
                                   offset=prm.scan_offset, corner_factor=prm.corner_factor, profile=profile,
                                   start=p, dt=dt, **moving))
    if target is not None:
        target = np.asarray(target, dtype=np.float64)
        if action == "approach":
            return Plan(core.approach(p, target, wait_distance=prm.wait_distance, descend_distance=prm.descend_distance,
                                      deadband_band=prm.deadband, profile=profile, dt=dt, **moving))
        if action == "attack":
            return Plan(core.attack(p, target, overshoot=prm.overshoot, hit_offset=prm.hit_offset,
                                    end_offset=prm.end_offset, profile=profile, dt=dt, **moving))
        if action == "intercept":
            return _intercept(command, target, vehicle, params)
        if action in ("goto", "hover"):
            return Plan(core.goto(p, target, profile, dt, heading))
    note = None if action in ("idle", "hover") else f"cannot plan {action} with what it carries; hovering"
    return Plan(core.hover(p, heading), note)


def predicted_path(command: MissionCommand, target: np.ndarray, velocity: np.ndarray, now_ns: int) -> PredictedPath:
    """The command's prediction of its target seen from `now_ns` (a command is planned a tick or so
    after it was sent): its predicted path when it carries one, else the straight line."""
    path = None if command.target_path is None else to_numpy(command.target_path).reshape(-1, 3)
    sent = PredictedPath(target, velocity, path if path is not None else np.zeros((0, 3)), command.target_path_dt)
    late = max(0.0, (now_ns - command.header.stamp) / NS)
    if path is None or not len(path) or command.target_path_dt <= 0:
        (position,), (now_velocity,) = sent.state([late])
        return PredictedPath(position, now_velocity)
    return sent.rebased(late, len(path), command.target_path_dt)


def pursuit_trust(command: MissionCommand, now_ns: int, trust_after_sighting: float) -> float:
    """How long from now a pursuit may follow the command's prediction: to the end of the path it
    carries, and no more than `trust_after_sighting` s past the target's last measurement
    (target_seen; the command's stamp when not given)."""
    stamp = command.header.stamp
    seen = command.target_seen if 0 < command.target_seen <= stamp else stamp
    end = seen / NS + trust_after_sighting
    if command.target_path is not None and command.target_path_dt > 0:
        end = min(end, stamp / NS + len(to_numpy(command.target_path).reshape(-1, 3)) * command.target_path_dt)
    return end - now_ns / NS


def _intercept(command: MissionCommand, target: np.ndarray, vehicle: VehicleState, params: PlannerParams) -> Plan:
    """Pursuit re-plans smoothly from the current state on every new prediction; the merge (wait on
    the predicted path) is the fallback when no blend fits the profile; chasing the position is
    the last resort."""
    p, prm, profile, dt = vehicle.position, params, command.profile, params.dt
    moving = dict(start_velocity=vehicle.velocity, start_heading=vehicle.heading)
    velocity = np.asarray(command.target_velocity or (0.0, 0.0, 0.0), dtype=np.float64)
    predicted = predicted_path(command, target, velocity, vehicle.now_ns)
    trust = pursuit_trust(command, vehicle.now_ns, prm.pursuit_trust)
    path = core.pursuit(p, target, velocity, profile=profile, dt=dt, horizon=prm.pursuit_horizon,
                        predicted=predicted, floor=vehicle.ground_z + prm.pursuit_floor, trust=trust, **moving)
    if path is None:
        path = core.intercept(p, target, velocity, profile=profile, dt=dt, merge_acceleration=prm.merge_acceleration,
                              follow_time=prm.follow_time, **moving)
    if path is not None:
        return Plan(path)
    return Plan(core.approach(p, target, wait_distance=0.0, descend_distance=prm.descend_distance, deadband_band=0.0,
                              profile=profile, dt=dt, **moving),
                "no merge onto the target is feasible; chasing its position")
