"""What the planner flies for a mission command: the choice of manoeuvre per action, where a new
plan starts, and how each manoeuvre is kept clear of what the UAV knows is occupied (avoid.py).
Pure (numpy in, numpy out); the node only hands in the vehicle's state, the current trajectory and
the map, and publishes and logs what comes back.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import msgspec
import numpy as np

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import ConstraintProfile, Header, MissionCommand, TrajectoryReference
from services.planner import core
from services.planner.avoid import (
    Polyline,
    Surroundings,
    body_clearance,
    clear_legs,
    clip,
    fmt,
    directions_around,
    free_overshoot,
    free_points,
    landing_line,
    lead_in,
    mount_exemption,
    speed_barrier,
    timed,
    vertical_weight,
    with_lead_in,
)
from services.planner.search import route
from services.lib.tracks import PredictedPath
from services.lib.runtime.clock import NS

# The route round an obstacle to a moving target (meeting_route):
ROUTE_SPEED_SHARE = 0.5  # of the profile's speed a route round an obstacle is reckoned to be flown at (it curves)
MEETING_AIM_MAX_S = 2.0  # s ahead a prediction without a path of its own is aimed along (the tracker's 8 x 0.25 s)
MEETING_SEARCHES = 3  # routes searched per plan to move the aim to where the UAV meets the target
MEETING_TOLERANCE_S = 0.25  # a route that takes at most this longer than its aim's time meets the target
# s: a direct chase that comes too close to an obstacle sooner flies a route instead (a later conflict is
# mostly the prediction's straight extrapolation, re-planned long before; routing for it slowed mast's eight)
DIRECT_LOOK_S = 3.0


class PlannerParams(msgspec.Struct, forbid_unknown_fields=True):
    """Seed 004 Table 3.1 symbols in brackets."""

    dt: float = core.DT  # s between trajectory samples
    # of the command profile's acceleration a plan uses: the rest is the flight controller's, to make up its
    # tracking error (planned at the limit, the vehicle cannot: a pursuit re-planned every tick ran 1.8 m
    # behind its reference, into a crown the reference went round, agile seed 4). The reference still
    # carries the command's profile, the vehicle's limits
    control_share: float = 0.85
    scan_offset: float = 2.0  # m kept inside the working area's inner rectangle
    corner_factor: float = 2.0  # [c_f] the scan's cross legs and corners fly at max_speed / c_f
    wait_distance: float = 4.0  # [d_b] m from the target where an approach ends
    descend_distance: float = 11.0  # [D_p] m from the target inside which the approach descends to it
    deadband: float = 0.5  # [D_f] m: line-of-sight changes smaller than this are ignored
    overshoot: float = 5.0  # [d_o] m beyond the target where an attack ends
    hit_offset: float = core.HIT_OFFSET  # [o_h] m above the target centre the attack passes through (core.py: why 0.4)
    end_offset: float = 0.15  # [o_o] m above the target height where the attack ends
    merge_acceleration: float = 1.5  # m/s² along a moving target's path when merging onto it
    follow_time: float = 4.0  # s flown alongside a moving target after the merge
    pursuit_horizon: float = 12.0  # s a pursuit flies the predicted track before braking (re-planned sooner)
    # s past the target's last sighting a pursuit follows its prediction (at most to the path's end), then waits
    pursuit_trust: float = 1.5
    pursuit_floor: float = 1.0  # m above the ground no pursuit goes below (the job manager's lowest target height)
    # m inside the arena's edge and below its ceiling every reference stays (Airspace.confine): room for
    # the tracking error (agile, 3 UAVs, seed 1: a reference on the edge, the vehicle 0.6 m beyond it)
    fence_margin: float = 1.0
    rejoin_distance: float = 1.5  # m: a re-plan starts on the current trajectory while this close to it
    republish_period: float = 2.0  # s of mission time
    repeat_scan: bool = True  # sweep again once a scan trajectory has ended
    job_manager_timeout: float = 1.0  # s without a status of our job manager: brake to a hover (watchdog.py)
    # Obstacles (avoid.py): what the UAV knows is occupied is its mapper's map, the a-priori map included
    obstacle_margin: float = 1.0  # m the body keeps from it
    tracking_allowance: float = 0.3  # m more a plan keeps: the vehicle's tracking error and rounded corners
    # m round a balloon: the map's voxels below it are its pole and itself, which its attack passes over
    # (the pole's voxels reach 0.35 m from its axis, the estimate's error at attack range is decimetres);
    # anything else that near is passed over too, so it is kept small
    mount_radius: float = 0.8
    # m more per m away from the balloon when an approach chooses its side: a far sighting is metres off
    # (the guard and the attack itself use mount_radius alone)
    mount_growth: float = 0.1
    min_overshoot: float = 2.0  # m beyond a balloon an attack cut short by an obstacle still needs to brake in
    approach_directions: int = 24  # directions round a balloon an approach tries, its own first
    search_margin: float = 15.0  # m round a blocked leg's ends that a route search may use
    # The guard (guard.py): the active reference's next guard_horizon s against the latest map
    guard_horizon: float = 4.0  # s
    guard_slack: float = 2.0  # m beyond the braking distance inside which a conflict is braked for, not re-planned round
    guard_view: float = 45.0  # degrees: unseen space ahead within this elevation (the LiDAR's half-angle) is a conflict
    guard_retry: float = 1.0  # s between re-plans of a command the guard stopped


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
    outcome: str = "clear"  # a PlanReport outcome: what obstacles made of it
    clearance: float | None = None  # m from the body to the nearest known obstacle along it (None: none near)
    direction: np.ndarray | None = None  # an approach's: the horizontal unit vector it will attack along


class ApproachMemory:
    """The side the last approach to a target took, so that the next approach to it — the job
    manager sends one whenever its estimate moves 0.3 m — keeps that side instead of swinging
    round the balloon. A target farther than `same_target` from the last is another one."""

    def __init__(self, same_target: float = 2.0) -> None:
        self.same_target = same_target
        self.target: np.ndarray | None = None
        self.direction: np.ndarray | None = None

    def prefer(self, command: MissionCommand) -> np.ndarray | None:
        if command.action != "approach" or command.target is None or self.target is None:
            return None
        return self.direction if np.linalg.norm(self.target - np.asarray(command.target)) <= self.same_target else None

    def remember(self, command: MissionCommand, plan: Plan) -> None:
        if plan.direction is not None and command.target is not None:
            self.target, self.direction = np.asarray(command.target, dtype=np.float64), plan.direction


def planning_profile(profile: ConstraintProfile, params: PlannerParams) -> ConstraintProfile:
    """The profile plans are made within: the command's, its acceleration cut to control_share."""
    return msgspec.structs.replace(profile, max_acceleration=profile.max_acceleration * params.control_share)


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


def plan_command(command: MissionCommand, vehicle: VehicleState, params: PlannerParams,
                 env: Surroundings | None = None, approach_from: np.ndarray | None = None) -> Plan:
    """The path for one command from `vehicle` (its start state), kept clear of the map in `env`
    (None: nothing known) and within its airspace. The arena's edge is a wall the plan is made
    against (FreeSpace.set_arena: routed round a notch, clipped before the edge, an attack's
    overshoot cut); a target or a mover's predicted path beyond the arena or its ceiling is aimed
    at the nearest point fence_margin inside (a meeting out there would take the UAV out); every
    reference sample is kept below the ceiling, said in the note. Samples are never moved across,
    into the arena, after timing: a path squeezed once timed is one the vehicle cannot follow.
    `approach_from`: the direction an approach tries first (the one the last approach to the same
    target took). A command that cannot be planned is a hover, with the reason as the note."""
    if env is None or (problem := unplannable(command)) is not None:
        return _plan(command, vehicle, params, env, approach_from)
    command, aimed = _confined_command(command, env.airspace)
    plan = _plan(command, vehicle, params, env, approach_from)
    inside = env.airspace.confine(plan.path[0], across=False)
    if not aimed and not inside.moved:
        return plan
    ceiling = env.airspace.high - env.airspace.fence_margin
    said = [f"target aimed {env.airspace.fence_margin:g} m inside the arena and below {ceiling:g} m"] if aimed else []
    said += [f"{inside.moved} reference samples moved below {ceiling:g} m (up to {inside.farthest:.2f} m)"] \
        if inside.moved else []
    return replace(plan, path=(inside.points, plan.path[1]), note="; ".join([*filter(None, [plan.note]), *said]))


def _confined_command(command: MissionCommand, airspace) -> tuple[MissionCommand, bool]:
    """The command with its target and target path moved inside the airspace, and whether any moved."""
    changes = {}
    if command.target is not None:
        target = airspace.confine(np.asarray(command.target, dtype=np.float64))
        if target.moved:
            changes["target"] = tuple(float(v) for v in target.points[0])
    if command.target_path is not None:
        path = airspace.confine(to_numpy(command.target_path))
        if path.moved:
            changes["target_path"] = from_numpy(path.points)
    return (msgspec.structs.replace(command, **changes), True) if changes else (command, False)


def _plan(command: MissionCommand, vehicle: VehicleState, params: PlannerParams,
          env: Surroundings | None = None, approach_from: np.ndarray | None = None) -> Plan:
    """plan_command's planning proper."""
    if (problem := unplannable(command)) is not None:
        return Plan(core.hover(vehicle.position, vehicle.heading), f"{problem}; hovering")
    p, heading = vehicle.position, vehicle.heading
    dt, profile, prm = params.dt, planning_profile(command.profile, params), params
    action, target = command.action, command.target
    if action == "takeoff":  # also the climb back to the search height in flight
        line = Polyline.of([p, [p[0], p[1], command.height]], np.zeros(2))
        return _fly(env, line, profile, dt, vehicle)
    if action in ("land", "emergency_land"):
        return _land(env, target[2] if target is not None else vehicle.ground_z, profile, dt, vehicle)
    if action == "stop":
        return _checked(env, core.stop(p, vehicle.velocity, profile, dt, heading))
    if action == "scan" and len(command.area) >= 3:
        line = Polyline.of(*core.lawnmower_line(np.asarray(command.area), command.height, command.spacing,
                                                prm.scan_offset, profile, p, heading, prm.corner_factor))
        return _fly(env, line, profile, dt, vehicle)
    if target is not None:
        target = np.asarray(target, dtype=np.float64)
        if action == "approach":
            return _approach(target, vehicle, profile, params, env, approach_from)
        if action == "attack":
            return _attack(target, vehicle, profile, params, env)
        if action == "intercept":
            return _intercept(command, target, vehicle, params, env)
        if action in ("goto", "hover"):
            return _fly(env, Polyline.of([p, target]), profile, dt, vehicle)
    note = None if action in ("idle", "hover") else f"cannot plan {action} with what it carries; hovering"
    return Plan(core.hover(p, heading), note)


def _fly(env: Surroundings | None, line: Polyline, profile, dt: float, vehicle: VehicleState, *,
         heading: float | None = None, moving: bool = True, routed: bool = True, exempt: np.ndarray | None = None,
         corner_deviation: float = np.inf) -> Plan:
    """Fly the polyline from the vehicle's state: a lead-in along its velocity where the first leg
    turns away from it, each leg routed round what is in the way (`routed`), timed and checked."""
    velocity = vehicle.velocity if moving else None
    led = with_lead_in(line, velocity, profile)
    if env is not None and routed:
        led = clear_legs(env, led, vertical_weight(profile), exempt, keep_first=len(led.points) - len(line.points))
    cleared = timed(env, led, profile, dt, start_velocity=velocity, start_heading=vehicle.heading, heading=heading,
                    corner_deviation=corner_deviation, exempt=exempt)
    return Plan(cleared.path, cleared.note or None, cleared.outcome, cleared.clearance)


def _land(env: Surroundings | None, ground: float, profile, dt: float, vehicle: VehicleState) -> Plan:
    """Down to the ground where the vehicle comes to a stop (a lead-in along its velocity first: a
    landing started at sweep speed that came straight down touched down sliding, a crash), or beside
    it where something is below (landing_line)."""
    p = vehicle.position
    lead = lead_in(p, vehicle.velocity, np.array([p[0], p[1], ground]), profile)
    line = landing_line(env, p if lead is None else lead, ground, profile)
    if lead is not None:
        line = Polyline(np.vstack([p, line.points]), np.concatenate([[np.inf], line.corner_speeds]),
                        np.concatenate([[np.inf], line.segment_speeds]), line.outcome, line.note)
    return _fly(env, line, profile, dt, vehicle)


def _halt(vehicle: VehicleState, profile, dt: float) -> core.Path:
    """Where a blocked plan leaves the vehicle: braking to a hold along its velocity (a hover where
    it is would be a reference velocity dropping to zero at speed)."""
    return core.stop(vehicle.position, vehicle.velocity, profile, dt, vehicle.heading)


def _checked(env: Surroundings | None, path: core.Path) -> Plan:
    """A path that cannot be changed (braking): only its clearance is reported."""
    if env is None or not env.space.known:
        return Plan(path)
    conflict = env.conflict(path[0], env.clearances.accept)
    return Plan(path, None if conflict is None else "braking comes closer than the margin to an obstacle",
                "clear" if conflict is None else "blocked", body_clearance(env, path[0]))


def _clipped(env: Surroundings, path: core.Path, profile, dt: float, note: str | None = None,
             outcome: str = "clear") -> Plan:
    """A path made elsewhere (a pursuit, a merge), flown as far as it stays clear (avoid.clip)."""
    conflict = env.conflict(path[0], env.clearances.timed)
    if conflict is None:
        return Plan(path, note, outcome, body_clearance(env, path[0]))
    path = clip(path, conflict, profile, dt)
    return Plan(path, "; ".join(filter(None, [note, f"clipped before an obstacle near {fmt(path[0][-1])}"])),
                "clipped", body_clearance(env, path[0]))


def approach_exemption(target: np.ndarray, position: np.ndarray, params: PlannerParams) -> np.ndarray:
    """The mount exemption an approach chooses its side with: mount_radius grown by mount_growth per
    metre between the vehicle and the balloon, horizontally (a far sighting is metres off)."""
    distance = float(np.hypot(*(np.asarray(target) - np.asarray(position))[:2]))
    return mount_exemption(target, params.mount_radius + params.mount_growth * distance)


def _approach(target: np.ndarray, vehicle: VehicleState, profile, params: PlannerParams,
              env: Surroundings | None, prefer: np.ndarray | None = None) -> Plan:
    """Alg. 1 towards the first direction round the target whose approach goal, run-in and attack
    line are clear (the attack's overshoot may be cut to min_overshoot) and whose goal a route
    reaches: `prefer` first (the direction the last approach to this target took, so a target
    estimate that moves a little does not swing the approach from side to side), then the own
    line of sight, then turning away from it. Farther than descend_distance, where a balloon's
    estimate is still metres off (the camera's range from its size), a direction with a reachable
    goal does when no attack line is clear: nearer looks will tell. Nothing: blocked, the vehicle
    holds (the job manager makes the balloon a forbidden zone if it stays so)."""
    p, prm, dt = vehicle.position, params, params.dt
    goal = core.approach_goal(p, target, prm.wait_distance, prm.deadband, vehicle.heading, prm.hit_offset)
    if env is None or not env.space.known:
        line = Polyline.of(core.approach_waypoints(p, target, goal, prm.descend_distance, prm.wait_distance))
        return _fly(env, line, profile, dt, vehicle, heading=core.facing(p, target, vehicle.heading))
    distance = float(np.hypot(*(target - p)[:2]))
    exempt = approach_exemption(target, p, prm)
    own = target - goal
    own[2] = 0.0
    first = own / max(float(np.linalg.norm(own)), 1e-9)
    directions = directions_around(first, prm.approach_directions)
    if prefer is not None:
        directions = np.vstack([prefer, directions])
    lines, fallback = [], []
    for k, direction in enumerate(directions):
        there = goal if k == int(prefer is not None) else \
            target - prm.wait_distance * direction + np.array([0.0, 0.0, prm.hit_offset])
        if not env.free(there, env.clearances.plan):
            continue
        clear = _attack_line_clear(env, target, there, direction, prm, exempt)
        (lines if clear else fallback).append((direction, there, clear))
    far = distance > prm.descend_distance
    for direction, there, clear in lines + (fallback if far else []):
        line = Polyline.of(core.approach_waypoints(p, target, there, prm.descend_distance, prm.wait_distance))
        plan = _fly(env, line, profile, dt, vehicle, heading=core.facing(there, target, vehicle.heading))
        if plan.outcome not in ("clear", "detour"):
            continue
        notes = [plan.note]
        if not np.allclose(there, goal):
            notes.insert(0, f"attacking towards {np.degrees(np.arctan2(direction[1], direction[0])):.0f}° "
                            f"(its own line of sight is blocked)")
        if not clear:
            notes.insert(0, "no attack line is clear from this far yet")
        note = "; ".join(filter(None, notes)) or None
        return Plan(plan.path, note, "detour" if note else plan.outcome, plan.clearance, direction)
    return Plan(_halt(vehicle, profile, dt), f"every approach to {fmt(target)} is blocked by obstacles "
                f"({len(lines)} of {len(directions)} directions with a clear attack line, none with a way there)",
                "blocked")


def _attack_line_clear(env: Surroundings, target: np.ndarray, goal: np.ndarray, direction: np.ndarray,
                       prm: PlannerParams, exempt: np.ndarray) -> bool:
    """The run-in from the approach goal to the hit point and min_overshoot beyond are clear."""
    hit = target + np.array([0.0, 0.0, prm.hit_offset])
    return env.conflict(np.stack([goal, hit]), env.clearances.plan, exempt) is None and \
        free_overshoot(env, target, direction, prm.hit_offset, prm.overshoot, prm.end_offset, exempt) >= prm.min_overshoot


def _attack(target: np.ndarray, vehicle: VehicleState, profile, params: PlannerParams, env: Surroundings | None) -> Plan:
    """§5.2 through the target, over its own pole (the mount exemption), with the overshoot cut
    short where an obstacle stands in it (no less than min_overshoot: else blocked)."""
    p, prm = vehicle.position, params
    direction = core.attack_waypoints(p, target, 1.0, 0.0, 0.0, vehicle.heading)[2] - target
    overshoot, note, exempt = prm.overshoot, None, None
    if env is not None and env.space.known:
        exempt = mount_exemption(target, prm.mount_radius)
        overshoot = free_overshoot(env, target, direction, prm.hit_offset, prm.overshoot, prm.end_offset, exempt)
        hit = target + np.array([0.0, 0.0, prm.hit_offset])
        if overshoot < prm.min_overshoot or env.conflict(np.stack([p, hit]), env.clearances.accept, exempt) is not None:
            return Plan(_halt(vehicle, profile, prm.dt), f"the attack on {fmt(target)} is blocked by obstacles",
                        "blocked")
        if overshoot < prm.overshoot:
            note = f"overshoot cut to {overshoot:.1f} m by an obstacle beyond the target"
    waypoints = core.attack_waypoints(p, target, overshoot, prm.hit_offset, prm.end_offset, vehicle.heading)
    plan = _fly(env, Polyline.of(waypoints), profile, prm.dt, vehicle, heading=core.facing(p, target, vehicle.heading),
                routed=False, exempt=exempt, corner_deviation=core.HIT_DEVIATION)
    return Plan(plan.path, "; ".join(filter(None, [note, plan.note])) or None,
                "clipped" if note and plan.outcome == "clear" else plan.outcome, plan.clearance)


def warm_up(params: PlannerParams) -> int:
    """Plan a detour round a small box and a pursuit behind it on a throwaway map, so the compiled
    kernels (numba, cached on disk after a machine's first run) are ready before the first real
    command (see classifier/core.py, `warm_up`, for why). Returns the samples planned."""
    from services.planner.avoid import Airspace, Clearances
    from services.planner.freespace import FreeSpace

    clearances = Clearances(0.4, params.obstacle_margin, params.tracking_allowance)
    space = FreeSpace(clearances.plan)
    space.set_ground(0.0)
    shape = (40, 40, 20)
    wall = np.ravel_multi_index(np.mgrid[20:22, 10:30, 2:14].reshape(3, -1), shape)
    space.apply_map(True, (0.0, 0.0, -1.0), shape, 0.5, -740.0, wall, np.full(len(wall), np.inf, np.float32))
    env = Surroundings(space, clearances, Airspace(0.0, 1.0, 8.0))
    vehicle = VehicleState(np.array([4.0, 10.0, 3.0]), np.zeros(3), 0.0, 0.0)
    profile = ConstraintProfile()
    samples = 0
    for command in (MissionCommand(header=Header(), command_id=1, action="goto", target=(16.0, 10.0, 3.0)),
                    MissionCommand(header=Header(), command_id=2, action="intercept", target=(16.0, 10.0, 3.0),
                                   target_velocity=(0.0, 1.0, 0.0), profile=profile)):
        samples += len(plan_command(command, vehicle, params, env).path[0])
    return samples


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


def _intercept(command: MissionCommand, target: np.ndarray, vehicle: VehicleState, params: PlannerParams,
               env: Surroundings | None = None) -> Plan:
    """Pursuit re-plans smoothly from the current state on every new prediction; the merge (wait on
    the predicted path) is the fallback when no blend fits the profile; chasing the position is
    the last resort. With a map (`pursuit_clear`) the pursuit aims where the target will be *and*
    the UAV can fly, and slides along obstacles instead of into them."""
    p, prm, profile, dt = vehicle.position, params, planning_profile(command.profile, params), params.dt
    moving = dict(start_velocity=vehicle.velocity, start_heading=vehicle.heading)
    velocity = np.asarray(command.target_velocity or (0.0, 0.0, 0.0), dtype=np.float64)
    predicted = predicted_path(command, target, velocity, vehicle.now_ns)
    trust = pursuit_trust(command, vehicle.now_ns, prm.pursuit_trust)
    chase = dict(profile=profile, dt=dt, horizon=prm.pursuit_horizon, predicted=predicted,
                 floor=vehicle.ground_z + prm.pursuit_floor, trust=trust, **moving)
    known = env is not None and env.space.known
    if known:
        plan = pursuit_clear(env, p, target, velocity, chase)
        path = None if plan is None else plan.path
    else:
        path = core.pursuit(p, target, velocity, **chase)
        plan = None if path is None else Plan(path)
    if plan is not None:
        return plan
    if path is None:
        path = core.intercept(p, target, velocity, profile=profile, dt=dt, merge_acceleration=prm.merge_acceleration,
                              follow_time=prm.follow_time, **moving)
    if path is not None:
        return _clipped(env, path, profile, dt) if known else Plan(path)
    if known:
        return _fly(env, Polyline.of(core.approach_waypoints(p, target, target, prm.descend_distance, 0.0)), profile,
                    dt, vehicle, heading=core.facing(p, target, vehicle.heading))
    return Plan(core.approach(p, target, wait_distance=0.0, descend_distance=prm.descend_distance, deadband_band=0.0,
                              profile=profile, dt=dt, **moving),
                "no merge onto the target is feasible; chasing its position")


def pursuit_clear(env: Surroundings, position: np.ndarray, target: np.ndarray, velocity: np.ndarray,
                   chase: dict) -> Plan | None:
    """The pursuit near obstacles: the predicted points the UAV could not be at move to the nearest
    free voxel (free_points), its speed towards an obstacle is held to what it can brake from
    before the clearance (speed_barrier), and when an obstacle stands between the UAV and where
    the target will be, it first follows a route round it to where it meets the target
    (meeting_route), unless the pursuit plans a rendezvous (pursuit.py: a target turning harder
    than the UAV may) clear of obstacles until it meets; what still conflicts is clipped. None:
    no pursuit fits the profile (the target is too fast)."""
    profile = chase["profile"]
    chase = dict(chase, free=lambda points: free_points(env, points),
                 barrier=speed_barrier(env, 0.5 * profile.max_acceleration, profile.max_speed))
    direct = core.pursuit(position, target, velocity, **chase)
    if direct is None:
        return None
    conflict = env.conflict(direct[0], env.clearances.timed)
    meeting = core.meeting_length(position, target, velocity, **chase)
    if meeting and (conflict is None or conflict > meeting):
        return _clipped(env, direct, profile, chase["dt"], "pursuit to meet the target where it will be")
    soon = conflict is not None and conflict * chase["dt"] <= DIRECT_LOOK_S
    if not soon and not _blocked_ahead(env, position, chase["predicted"], profile, chase["trust"]):
        return _clipped(env, direct, profile, chase["dt"])
    way = meeting_route(env, position, chase["predicted"], profile, chase["trust"])
    if way is None:
        return _clipped(env, direct, profile, chase["dt"])
    path = core.pursuit(position, target, velocity, route=way, **chase)
    if path is None:
        return None
    if len(way) > 2:
        return _clipped(env, path, profile, chase["dt"], "pursuit round an obstacle between the UAV and the target",
                        "detour")
    return _clipped(env, path, profile, chase["dt"], "pursuit straight to where it meets the target")


def _straight_time(position: np.ndarray, predicted: PredictedPath, profile: ConstraintProfile) -> float:
    """s a straight flight at the profile's speed takes to where the target is now."""
    return float(np.linalg.norm(predicted.position - position)) / max(profile.max_speed, 1e-6)


def _free_aim(env: Surroundings, predicted: PredictedPath, ahead: float) -> np.ndarray:
    """Where the target will be in `ahead` s, moved to free space if the UAV could not be there."""
    (there,), _ = predicted.state([ahead])
    return free_points(env, there[None])[0]


def _blocked_ahead(env: Surroundings, position: np.ndarray, predicted: PredictedPath, profile: ConstraintProfile,
                   trust: float) -> bool:
    """Whether an obstacle stands between the UAV and where the target will be by the time a
    straight flight gets there."""
    aim = _free_aim(env, predicted, min(_straight_time(position, predicted, profile), max(trust, 0.0)))
    return env.conflict(np.stack([position, aim]), env.clearances.plan) is not None


def meeting_route(env: Surroundings, position: np.ndarray, predicted: PredictedPath, profile: ConstraintProfile,
                  trust: float) -> np.ndarray | None:
    """The way to where the UAV meets the target (a polyline round what stands between; two points
    when nothing does), or None when no way is found. A route to where the target will be when a
    straight flight would get there ends behind it when the route is longer than the straight
    line: round a mast the UAV then trailed the circling drone at its own angular speed for a
    minute (benchmarks/pursuit.py). So the aim moves along the prediction to the time the route
    takes at ROUTE_SPEED_SHARE of the profile's speed (a few searches: each longer route moves it
    further), at most as far as the prediction is trusted and curved; there the UAV waits for the
    target, or meets it coming the other way round."""
    speed = ROUTE_SPEED_SHARE * profile.max_speed
    steps = len(np.asarray(predicted.path).reshape(-1, 3)) if predicted.dt > 0 else 0
    latest = max(min(trust, steps * predicted.dt if steps else MEETING_AIM_MAX_S), 0.0)
    ahead = min(_straight_time(position, predicted, profile), latest)
    way = None
    for _ in range(MEETING_SEARCHES):
        aim = _free_aim(env, predicted, ahead)
        found = route(env.space, position, aim, env.clearances.plan, env.airspace.band(), vertical_weight(profile),
                      env.search_margin)
        if found is None:
            return way
        way = found.points
        takes = min(float(np.linalg.norm(np.diff(way, axis=0), axis=1).sum()) / max(speed, 1e-6), latest)
        if takes <= ahead + MEETING_TOLERANCE_S:
            break
        ahead = takes
    return way
