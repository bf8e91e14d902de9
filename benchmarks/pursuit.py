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
from services.planner import pursuit as pursuit_law  # noqa: E402
from services.planner.commands import PlannerParams, start_state  # noqa: E402
from services.simulator.paths import DronePath  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.simulator.specs import DroneSpec  # noqa: E402
from services.simulator.vehicles import Fleet, make_reference  # noqa: E402
from services.tracker.core import TURN_MIN_SPEED, TrackerParams  # noqa: E402
from services.tracker.filters.models import turning_path  # noqa: E402
from services.tracker.filters.turning import TurnHistory  # noqa: E402
from services.tracker.view import PredictedPath  # noqa: E402

NS = 1_000_000_000
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


def pursue(spec: DroneSpec, scenario, seed: int, index: int, start: float, args, rng) -> Outcome:
    path = DronePath(spec, scenario, seed, index)
    jm, planner = JobManagerParams(), PlannerParams()
    tracker = TrackerParams() if args.max_turn_rate is None else TrackerParams(max_turn_rate=args.max_turn_rate)
    profile = ConstraintProfile(name="attack", max_speed=jm.attack_speed, max_acceleration=jm.attack_acceleration)
    limits = np.array([profile.max_speed, profile.max_acceleration, profile.max_heading_rate, profile.max_vertical_speed])
    fleet = Fleet(scenario, ["uav1"], seed)
    target, _ = path.state(start)
    bearing = rng.uniform(0.0, 2.0 * np.pi)
    fleet.position[0] = [target[0] + START_DISTANCE * np.cos(bearing), target[1] + START_DISTANCE * np.sin(bearing),
                         scenario.ground_z + START_HEIGHT]
    fleet.airborne[0], fleet.hold[0] = True, fleet.position[0]
    sent, next_plan, events, t = None, start, [], start
    closest = (np.inf, 0.0)
    while t < start + args.limit:
        if t >= next_plan - 1e-9:
            predicted = prediction(path, t, args.latency, args.noise, rng, tracker)
            p, v = start_state(sent, int(round(t * NS)), fleet.position[0].copy(), fleet.velocity[0].copy(),
                               planner.rejoin_distance)
            plan = pursuit_law.pursuit(p, predicted.position, predicted.velocity, profile=profile, dt=planner.dt,
                                       horizon=planner.pursuit_horizon, predicted=predicted, start_velocity=v,
                                       start_heading=float(fleet.heading[0]),
                                       floor=scenario.ground_z + planner.pursuit_floor)
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
        if gap <= scenario.capture_radius and relative <= scenario.capture_speed:
            return Outcome(seed, start, t - start, gap, relative)
    return Outcome(seed, start, None, *closest)


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
    outcomes = []
    for seed in args.seeds:
        rng = np.random.default_rng(seed)
        for k in range(args.starts):
            outcome = pursue(scenario.drones[index], scenario, seed, index, 15.0 + 10.0 * k, args, rng)
            outcomes.append(outcome)
            result = (f"captured after {outcome.captured_after:5.1f} s" if outcome.captured_after is not None
                      else f"not captured in {args.limit:g} s")
            print(f"seed {seed} start t={outcome.start:5.1f} s: {result}; closest {outcome.closest:.2f} m "
                  f"at {outcome.relative_at_closest:.1f} m/s relative", flush=True)
    times = [o.captured_after for o in outcomes if o.captured_after is not None]
    summary = f"{len(times)}/{len(outcomes)} captured within {args.limit:g} s"
    if times:
        summary += f"; median {statistics.median(times):.1f} s, mean {statistics.fmean(times):.1f} s, worst {max(times):.1f} s"
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
