"""The pursuit alone against a scripted drone (issue 12): the simulator's own flight controller
(services/simulator/vehicles.py) flies the planner's pursuit (services/planner/pursuit.py), re-planned
every `--period` s from a prediction made of the drone's true state `--latency` s old plus position
noise, with the tracker's manoeuvre model (services/tracker/filters/models.py). No perception, no
job manager: what the interception law can do when the target is always seen. Each start puts the
UAV 12 m from the drone at 5 m height; prints the capture time (within the scenario's capture radius and
relative speed, 1 m and 2 m/s by default), or the closest pass.

A run takes seconds where a whole mission takes two minutes, so the law's constants can be tried
here first (`--braking`, `--terminal` override pursuit.BRAKING and TERMINAL_GAIN for the run).

    .venv/bin/python benchmarks/pursuit.py                          # agile's dodger, seeds 1-5 x 10 starts
    .venv/bin/python benchmarks/pursuit.py --drone eight --latency 0.3 --period 0.3
"""
from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from schemas.arrays import from_numpy  # noqa: E402
from schemas.messages import ConstraintProfile, Header, TrajectoryReference  # noqa: E402
from services.job_manager.params import JobManagerParams  # noqa: E402
from services.lib.runtime.clock import NS  # noqa: E402
from services.lib.tracks import PredictedPath  # noqa: E402
from services.planner import pursuit as pursuit_law  # noqa: E402
from services.planner.avoid import Airspace, Clearances, Surroundings  # noqa: E402
from services.planner.commands import PlannerParams, pursuit_clear, start_state  # noqa: E402
from services.simulator import contact  # noqa: E402
from services.simulator.core import Simulation  # noqa: E402
from services.simulator.paths import DronePath  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.simulator.specs import DroneSpec  # noqa: E402
from services.simulator.vehicles import Fleet, make_reference  # noqa: E402
from services.tracker.core import TURN_MIN_SPEED, TrackerParams  # noqa: E402
from services.tracker.filters.models import turning_path  # noqa: E402
from services.tracker.filters.turning import TurnHistory  # noqa: E402

STEP = 0.01  # s, the simulator's largest sub-step
START_DISTANCE = 12.0  # m from the drone
START_HEIGHT = 5.0  # m


@dataclass(frozen=True)
class Outcome:
    seed: int
    start: float  # s of mission time the pursuit began
    captured_after: float | None  # s; None: not within the limit
    closest: float  # m
    relative_at_closest: float  # m/s
    clearance: float = np.inf  # m: the UAV body's closest approach to a static obstacle (--obstacles)
    nearest: str = ""  # ... to which


@dataclass(frozen=True)
class World:
    """The scenario's obstacles as the planner knows them (its a-priori map) and as the body meets them."""
    env: Surroundings
    solids: contact.Shapes
    body: float  # m, the UAV's radius


def world(scenario) -> World:
    from planner import apriori_space  # benchmarks/planner.py: the a-priori map as a mapper pins it
    params = PlannerParams()
    clearances = Clearances(0.4, params.obstacle_margin, params.tracking_allowance)
    arena = np.asarray(scenario.arena)
    airspace = Airspace(scenario.ground_z, scenario.ground_z + max(scenario.min_height, 1.0),
                        scenario.ground_z + scenario.max_height, tuple(arena.min(axis=0)), tuple(arena.max(axis=0)))
    solids = contact.shapes(Simulation(scenario, ["uav1"], 1).obstacles())
    return World(Surroundings(apriori_space(scenario, clearances), clearances, airspace), solids, clearances.body)


def prediction(path: DronePath, t: float, latency: float, noise: float, rng: np.random.Generator,
               tracker: TrackerParams) -> PredictedPath:
    """What the tracker would say at t: the state `latency` s old, its acceleration by a 0.1 s
    difference and its turn from the window of states before (TurnHistory), carried to t by the
    published trajectory's model (turning_path), with white position noise."""
    seen = t - latency
    p, v = path.state(seen)
    _, v_before = path.state(seen - 0.1)
    mean = np.concatenate([p + rng.normal(0.0, noise, 3), v, (v - v_before) / 0.1])
    history = TurnHistory(tracker.turn_window, TURN_MIN_SPEED, tracker.max_turn_rate)
    for earlier in seen - np.arange(round(tracker.turn_window / 0.1), -1, -1) * 0.1:  # the scans of the window
        p_then, v_then = path.state(earlier)
        history.add(earlier, p_then + rng.normal(0.0, noise, 3), v_then)
    turn = history.turn(seen) if tracker.max_turn_rate > 0 else None
    points = turning_path(mean, 0.25, 8 + int(latency / 0.25) + 1, tracker.manoeuvre_time, turn)
    return PredictedPath(mean[:3], v, points, 0.25).rebased(latency, 8, 0.25)


def start_point(target: np.ndarray, scenario, rng, obstacles: World | None) -> np.ndarray:
    """START_DISTANCE from the drone on a random bearing, START_HEIGHT up, and clear of every obstacle."""
    for _ in range(100):
        bearing = rng.uniform(0.0, 2.0 * np.pi)
        point = np.array([target[0] + START_DISTANCE * np.cos(bearing), target[1] + START_DISTANCE * np.sin(bearing),
                          scenario.ground_z + START_HEIGHT])
        if obstacles is None or len(obstacles.solids) == 0 or \
                contact.signed_distance(point, obstacles.solids).min() > obstacles.env.clearances.plan:
            return point
    raise ValueError("no start clear of the obstacles 12 m from the drone")


def pursue(spec: DroneSpec, scenario, seed: int, index: int, start: float, args, rng,
           obstacles: World | None = None) -> Outcome:
    path = DronePath(spec, scenario, seed, index)
    jm, planner = JobManagerParams(), PlannerParams()
    tracker = TrackerParams() if args.max_turn_rate is None else TrackerParams(max_turn_rate=args.max_turn_rate)
    profile = ConstraintProfile(name="attack", max_speed=jm.attack_speed, max_acceleration=jm.attack_acceleration)
    limits = np.array([profile.max_speed, profile.max_acceleration, profile.max_heading_rate, profile.max_vertical_speed])
    fleet = Fleet(scenario, ["uav1"], seed)
    target, _ = path.state(start)
    fleet.position[0] = start_point(target, scenario, rng, obstacles)
    fleet.airborne[0], fleet.hold[0] = True, fleet.position[0]
    sent, next_plan, events, t = None, start, [], start
    closest, clearance, nearest = (np.inf, 0.0), np.inf, ""
    while t < start + args.limit:
        if t >= next_plan - 1e-9:
            predicted = prediction(path, t, args.latency, args.noise, rng, tracker)
            p, v = start_state(sent, int(round(t * NS)), fleet.position[0].copy(), fleet.velocity[0].copy(),
                               planner.rejoin_distance)
            chase = dict(profile=profile, dt=planner.dt, horizon=planner.pursuit_horizon, predicted=predicted,
                         start_velocity=v, start_heading=float(fleet.heading[0]),
                         floor=scenario.ground_z + planner.pursuit_floor,
                         trust=np.inf if args.trust is None else args.trust - args.latency)
            if obstacles is None:
                plan = pursuit_law.pursuit(p, predicted.position, predicted.velocity, **chase)
            else:
                found = pursuit_clear(obstacles.env, p, predicted.position, predicted.velocity, chase)
                plan = None if found is None else found.path
            if plan is not None:
                start_ns = int(round(t * NS))
                sent = TrajectoryReference(header=Header(stamp=start_ns), command_id=0, start=start_ns, dt=planner.dt,
                                           positions=from_numpy(plan[0]), headings=from_numpy(plan[1]))
                fleet.set_reference(0, make_reference("uav1", start_ns, planner.dt, plan[0], plan[1]), limits)
            next_plan += args.period
        t += STEP
        fleet.integrate(int(round(t * NS)), STEP, events)
        target, target_velocity = path.state(t)
        gap = float(np.linalg.norm(fleet.position[0] - target))
        relative = float(np.linalg.norm(fleet.velocity[0] - target_velocity))
        if gap < closest[0]:
            closest = (gap, relative)
        if obstacles is not None and len(obstacles.solids):
            distances = contact.signed_distance(fleet.position[0], obstacles.solids) - obstacles.body
            if distances.min() < clearance:
                clearance, nearest = float(distances.min()), obstacles.solids.names[int(distances.argmin())]
        if gap <= scenario.capture_radius and relative <= scenario.capture_speed:
            return Outcome(seed, start, t - start, gap, relative, clearance, nearest)
    return Outcome(seed, start, None, *closest, clearance, nearest)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="agile", help="built-in scenario or .toml (default agile)")
    parser.add_argument("--drone", default="dodger", help="the scenario's drone to pursue (default dodger)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="drone path seeds (default 1-5)")
    parser.add_argument("--starts", type=int, default=10, help="pursuits per seed, 10 s apart from t=15 s (default 10)")
    parser.add_argument("--latency", type=float, default=0.2, help="age of the prediction's sighting, s (default 0.2)")
    parser.add_argument("--noise", type=float, default=0.1, help="position noise of a sighting, m (default 0.1)")
    parser.add_argument("--period", type=float, default=0.3, help="s between re-plans (default 0.3)")
    parser.add_argument("--limit", type=float, default=60.0, help="s a pursuit may take (default 60, the goal)")
    parser.add_argument("--braking", type=float, help=f"override pursuit.BRAKING ({pursuit_law.BRAKING})")
    parser.add_argument("--lead-speed", type=float, help=f"override pursuit.LEAD_SPEED ({pursuit_law.LEAD_SPEED} m/s)")
    parser.add_argument("--lead-max", type=float, help=f"override pursuit.LEAD_MAX ({pursuit_law.LEAD_MAX} s)")
    parser.add_argument("--max-turn-rate", type=float,
                        help="override the tracker's max_turn_rate (1.5 rad/s; 0: Singer's straight-on prediction)")
    parser.add_argument("--trust", type=float, default=None,
                        help="s past its sighting a prediction is followed, as the planner's pursuit_trust "
                             f"(the missions: {PlannerParams().pursuit_trust}); default: for ever")
    parser.add_argument("--obstacles", action="store_true",
                        help="plan as the planner does near obstacles (commands.pursuit_clear on the scenario's "
                             "a-priori map: predicted points moved to free space, the speed barrier, routes round "
                             "obstacles) and report each pursuit's clearance (the body's closest approach to one)")
    parser.add_argument("--terminal", type=float, help=f"override pursuit.TERMINAL_GAIN ({pursuit_law.TERMINAL_GAIN} 1/s)")
    args = parser.parse_args()
    if args.braking is not None:
        pursuit_law.BRAKING = args.braking
    if args.terminal is not None:
        pursuit_law.TERMINAL_GAIN = args.terminal
    if args.lead_speed is not None:
        pursuit_law.LEAD_SPEED = args.lead_speed
    if args.lead_max is not None:
        pursuit_law.LEAD_MAX = args.lead_max
    try:
        scenario = load_scenario(args.scenario)
    except (OSError, ValueError) as error:
        print(f"pursuit.py: {error}", file=sys.stderr)
        return 2
    names = [d.name for d in scenario.drones]
    if args.drone not in names:
        print(f"pursuit.py: {args.scenario} has no drone {args.drone!r} (it has: {', '.join(names) or 'none'})",
              file=sys.stderr)
        return 2
    index = names.index(args.drone)
    obstacles = world(scenario) if args.obstacles else None
    outcomes = []
    for seed in args.seeds:
        for k in range(args.starts):
            rng = np.random.default_rng([seed, k])  # each pursuit its own draws: one that changes leaves the rest
            try:
                outcome = pursue(scenario.drones[index], scenario, seed, index, 15.0 + 10.0 * k, args, rng, obstacles)
            except ValueError as error:
                print(f"pursuit.py: {error}", file=sys.stderr)
                return 2
            outcomes.append(outcome)
            result = (f"captured after {outcome.captured_after:5.1f} s" if outcome.captured_after is not None
                      else f"not captured in {args.limit:g} s")
            clear = "" if obstacles is None else f"; clearance {outcome.clearance:.2f} m to {outcome.nearest}"
            print(f"seed {seed} start t={outcome.start:5.1f} s: {result}; closest {outcome.closest:.2f} m "
                  f"at {outcome.relative_at_closest:.1f} m/s relative{clear}", flush=True)
    times = [o.captured_after for o in outcomes if o.captured_after is not None]
    summary = f"{len(times)}/{len(outcomes)} captured within {args.limit:g} s"
    if times:
        summary += f"; median {statistics.median(times):.1f} s, mean {statistics.fmean(times):.1f} s, worst {max(times):.1f} s"
    if obstacles is not None:
        summary += (f"; clearance >= {min(o.clearance for o in outcomes):.2f} m, "
                    f"{sum(o.clearance <= 0.0 for o in outcomes)} pursuits touched an obstacle")
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
