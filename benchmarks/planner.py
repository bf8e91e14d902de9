"""Time of the obstacle-aware planner on mbzirc's map (issue 34's goals: a plan with the obstacle
check and the search at most 20 ms median, the guard's check at most 2 ms median per cycle, on one
core). Figures, not a timed test.

The map is the planner's own FreeSpace made the way a mapper makes it: the world model's static
obstacles pinned occupied (the a-priori map), the rest of the arena up to 20 m seen free (what a
sweep at 5 m has cleared) — or, with --recording, the latest map a UAV's mapper published in a
recorded run (`falconry sim mbzirc --lockstep --record run.mcap`), what the LiDAR learnt included.

The plans are what a mission asks for, seeded: sweeps of each working area from points round it,
approaches to each balloon from eight bearings 15 m away, attacks from the approach goals,
gotos between random free points of the arena, intercepts of a drone circling behind the building,
take-offs and landings. Each is timed over its whole plan_command (routes, timing, checks); the
guard is timed on each plan's reference at ten moments along it (guard.upcoming + guard.check, as
the node runs it every tick).

    .venv/bin/python benchmarks/planner.py                 # about 30 s
    .venv/bin/python benchmarks/planner.py --recording run.mcap --uav uav1
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too

import msgspec  # noqa: E402
import numpy as np  # noqa: E402

from schemas.arrays import from_numpy, to_numpy  # noqa: E402
from schemas.messages import ConstraintProfile, Header, MissionCommand, VoxelMap  # noqa: E402
from services.job_manager.areas import split_area  # noqa: E402
from services.planner import guard  # noqa: E402
from services.planner.avoid import Airspace, Clearances, Surroundings  # noqa: E402
from services.planner.commands import PlannerParams, VehicleState, plan_command, warm_up  # noqa: E402
from services.planner.freespace import FreeSpace  # noqa: E402
from services.simulator.core import Simulation  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.lib.voxels.apriori import obstacle_voxels  # noqa: E402
from services.lib.voxels.grid import GridGeometry  # noqa: E402
from services.mapper.core import MapperParams  # noqa: E402

PLAN_GOAL_MS = 20.0
GUARD_GOAL_MS = 2.0
SWEEP = ConstraintProfile()
ATTACK = ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0)


def apriori_space(scenario, clearances: Clearances) -> FreeSpace:
    """The a-priori map of the scenario's world, the arena seen free up to 20 m."""
    p = MapperParams()
    grid = GridGeometry(tuple(p.origin), tuple(p.shape), p.voxel_size)
    sim = Simulation(scenario, ["uav1", "uav2"], 1)
    values = np.full(grid.size, p.unknown_value, np.float32)
    cells = grid.unflat(np.arange(grid.size))
    centres = grid.centres(cells)
    arena = np.asarray(scenario.arena)
    inside = ((centres[:, :2] >= arena.min(axis=0)) & (centres[:, :2] <= arena.max(axis=0))).all(axis=1)
    values[inside & (centres[:, 2] <= 20.0)] = p.free_value
    values[obstacle_voxels(sim.obstacles(), grid)] = np.inf
    space = FreeSpace(clearances.plan)
    space.set_ground(scenario.ground_z)
    space.apply_map(True, grid.origin, grid.shape, grid.voxel_size, p.unknown_value, np.arange(grid.size), values)
    return space


def recorded_space(path: str, uav: str, clearances: Clearances, ground_z: float) -> FreeSpace:
    """The map `uav`'s mapper had published by the end of a recording."""
    from services.tools.recorder.mcap_io import read_recording

    decoder = msgspec.msgpack.Decoder(VoxelMap)
    space = FreeSpace(clearances.plan)
    space.set_ground(ground_z)
    for message in read_recording(path, lambda key: key == f"falconry/{uav}/map"):
        m = decoder.decode(message.payload)
        space.apply_map(m.snapshot, m.origin, m.shape, m.voxel_size, m.default_value, to_numpy(m.indices),
                        to_numpy(m.values))
    if not space.known:
        sys.exit(f"{path} holds no map of {uav} (falconry/{uav}/map)")
    return space


def commands(scenario, space: FreeSpace, rng: np.random.Generator) -> list[tuple[str, MissionCommand, VehicleState]]:
    """(kind, command, vehicle) of the plans a mission asks for (see the module docstring)."""
    def command(action, **fields):
        return MissionCommand(header=Header(), command_id=1, action=action, **fields)

    def vehicle(p, v=(0.0, 0.0, 0.0)):
        return VehicleState(np.asarray(p, float), np.asarray(v, float), 0.0, scenario.ground_z)

    arena = np.asarray(scenario.arena)
    low, high = arena.min(axis=0), arena.max(axis=0)
    cases = []
    for area in split_area(arena, 2):
        for _ in range(8):
            start = (*rng.uniform(low, high), 5.0)
            cases.append(("scan", command("scan", area=[tuple(map(float, q)) for q in area], height=5.0,
                                          spacing=20.0), vehicle(start)))
    balloons = [np.array([b.pole[0], b.pole[1], scenario.ground_z + b.height + b.tether + b.radius])
                for b in scenario.balloons]
    for target in balloons:
        for bearing in np.linspace(0.0, 2.0 * math.pi, 8, endpoint=False):
            start = target + [15.0 * math.cos(bearing), 15.0 * math.sin(bearing), 0.0]
            start[2] = 5.0
            cases.append(("approach", command("approach", target=tuple(target)), vehicle(start)))
            goal = target - 4.0 * np.array([math.cos(bearing + math.pi), math.sin(bearing + math.pi), 0.0])
            cases.append(("attack", command("attack", target=tuple(target), profile=ATTACK),
                          vehicle(goal + [0.0, 0.0, 0.4])))
    free = []
    while len(free) < 40:
        point = np.array([*rng.uniform(low, high), rng.uniform(3.0, 9.0)])
        if space.clearance(point[None])[0] > 2.5:
            free.append(point)
    for a, b in zip(free[0::2], free[1::2]):
        cases.append(("goto", command("goto", target=tuple(b)), vehicle(a, rng.uniform(-3.0, 3.0, 3) * [1, 1, 0.3])))
    for k in range(12):  # a drone circling 4 m behind mbzirc's building, seen from round it
        angle = 2.0 * math.pi * k / 12
        drone = np.array([30.0 + 9.0 * math.cos(angle), 32.0 + 8.0 * math.sin(angle), 6.0])
        velocity = 3.0 * np.array([-math.sin(angle), math.cos(angle), 0.0])
        path = drone + np.outer(0.25 * np.arange(1, 49), velocity)
        start = np.array([30.0 - 20.0 * math.cos(angle), 32.0 - 20.0 * math.sin(angle), 5.0])
        cases.append(("intercept", command("intercept", target=tuple(drone), target_velocity=tuple(velocity),
                                           profile=ATTACK, target_path=from_numpy(path), target_path_dt=0.25),
                      vehicle(start)))
    for point in free[:10]:
        cases.append(("takeoff", command("takeoff", height=5.0), vehicle([point[0], point[1], scenario.ground_z])))
        cases.append(("land", command("land"), vehicle(point)))
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="mbzirc")
    parser.add_argument("--recording", help="an MCAP of a run of the scenario: its mapper's map instead")
    parser.add_argument("--uav", default="uav1", help="whose map to take from the recording")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    params = PlannerParams()
    clearances = Clearances(0.4, params.obstacle_margin, params.tracking_allowance)
    scenario = load_scenario(args.scenario)
    warm_up(params)
    space = (recorded_space(args.recording, args.uav, clearances, scenario.ground_z) if args.recording
             else apriori_space(scenario, clearances))
    arena = np.asarray(scenario.arena)
    env = Surroundings(space, clearances, Airspace(scenario.ground_z, scenario.ground_z + max(scenario.min_height, 1.0),
                                                   scenario.ground_z + scenario.max_height,
                                                   tuple(arena.min(axis=0)), tuple(arena.max(axis=0))))
    cases = commands(scenario, space, np.random.default_rng(args.seed))
    plan_ms: dict[str, list[float]] = {}
    outcomes: dict[str, int] = {}
    guard_ms: list[float] = []
    for kind, command, vehicle in cases:
        started = time.perf_counter()
        plan = plan_command(command, vehicle, params, env)
        plan_ms.setdefault(kind, []).append(1e3 * (time.perf_counter() - started))
        outcomes[plan.outcome] = outcomes.get(plan.outcome, 0) + 1
        positions = plan.path[0]
        for k in np.linspace(0, len(positions) - 1, 10).astype(int):
            now = int(round(k * params.dt * 1e9))
            started = time.perf_counter()
            ahead = guard.upcoming(positions, 0, params.dt, now, params.guard_horizon)
            guard.check(space, ahead, positions[k], 5.0, command.profile.max_acceleration, clearances.accept,
                        clearances.hard, view=params.guard_view, slack=params.guard_slack)
            guard_ms.append(1e3 * (time.perf_counter() - started))
    source = f"{args.recording} ({args.uav}'s mapper)" if args.recording else "the a-priori map, the arena seen free"
    print(f"{args.scenario}: {len(cases)} plans on {source}, one core; plans keep {clearances.plan:.2f} m from "
          f"occupied voxels' boxes (body {clearances.body} m + margin {clearances.margin} m + allowance "
          f"{clearances.allowance} m)")
    print(f"{'kind':<10} {'plans':>5} {'median ms':>9} {'p90 ms':>7} {'max ms':>7}")
    every = []
    for kind, times in plan_ms.items():
        every += times
        print(f"{kind:<10} {len(times):>5} {statistics.median(times):>9.2f} {np.percentile(times, 90):>7.2f} "
              f"{max(times):>7.2f}")
    median = statistics.median(every)
    print(f"{'all':<10} {len(every):>5} {median:>9.2f} {np.percentile(every, 90):>7.2f} {max(every):>7.2f}")
    print("outcomes: " + ", ".join(f"{name} {count}" for name, count in sorted(outcomes.items())))
    guard_median = statistics.median(guard_ms)
    print(f"guard: {len(guard_ms)} checks, median {guard_median:.3f} ms, p90 {np.percentile(guard_ms, 90):.3f} ms, "
          f"max {max(guard_ms):.3f} ms")
    print(f"goal: a plan <= {PLAN_GOAL_MS:.0f} ms median: {median:.2f} ms ({'met' if median <= PLAN_GOAL_MS else 'NOT met'}); "
          f"the guard <= {GUARD_GOAL_MS:.0f} ms median: {guard_median:.3f} ms "
          f"({'met' if guard_median <= GUARD_GOAL_MS else 'NOT met'})")


if __name__ == "__main__":
    main()
