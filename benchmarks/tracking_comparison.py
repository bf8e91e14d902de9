"""Single-target LiDAR tracking, three filters compared (seed 002 sec. 5.2 and its results table).

The `sparse` scenario (services/simulator/scenarios/sparse.toml): uav1 is the observer, held at
its start (3, 2) at 5 m with its Livox Mid-360 (services/lib/lidar/models.py, the sensor driver's
default 2 cm range noise, 10 Hz); the scenario's target drone (0.65 m, a flat disc 0.3 m thick)
manoeuvres on its seeded random path 10-35 m away at up to 5 m/s and 3 m/s², and returns 1-4
points per scan. The scans come from the sensor driver's caster (services.sensor_driver.core.scan)
of the scenario's world (services.simulator.core.Simulation: its ground, and the target at its
true position at each scan's stamp: the simulator's own closed-form path). Each scan goes once
through seed 002's front end (services/tracker/frontend.py), and the same candidates through the
single-target loop (services/tracker/single.py) with each filter:

  kf        fixed-noise constant-acceleration Kalman filter, no recovery (seed 002's Fixed CA-KF)
  particle  2000-particle filter, systematic resampling, no recovery
  adaptive  seed 002's adaptive EKF (adaptive Q and R), with recovery after N missed steps

Options for what the scene lacks: `--clutter` adds a building, two trees and a pole around the
target's box (walls, crowns and a pole in the cloud, and occlusions); `--observer-height 2` brings
the ground into view (at 5 m the Mid-360's lowest beam, 7° down, meets the ground 44 m away, beyond
its 40 m range, so the sparse scene's cloud holds the target alone); `--single-returns` lets one
return make a candidate (DBSCAN min_samples 1, no lower eigenvalue bound) instead of seed 002's
rule that rejects single-point returns.

Errors are taken at every scan after the track's first estimate, against the target's true
position at the scan's stamp, coasting included. Prints per seed and pooled: RMSE of X, Y, Z and
3-D, the largest 3-D error, the share of scans whose candidate went into the estimate (an update
or a (re)initialisation) and the median time of one loop step with an update (predict, gate,
update; the front end, the same for every filter, is timed apart). Then seed 002's goal ratios of
the pooled 3-D RMSE: adaptive / particle at most 0.5, adaptive / kf at most 0.25. Last, the same
scans with recovery for every filter: what the recovery alone does, apart from the adaptation.
Then seed 000's multi-target tracker's time per update with ten live tracks on OS0-128 scans
(benchmarks/tracker_timing.py; `--skip-timing` leaves it out).

    .venv/bin/python benchmarks/tracking_comparison.py                 # seeds 1-5, 120 s: about 1.5 min
    .venv/bin/python benchmarks/tracking_comparison.py --quick         # seeds 1-2, 40 s: about 15 s
    .venv/bin/python benchmarks/tracking_comparison.py --seeds 3 7 --duration 60 --clutter
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too
sys.path.insert(0, str(Path(__file__).resolve().parent))  # tracker_timing.py beside it

import msgspec  # noqa: E402
import numpy as np  # noqa: E402

from schemas.messages import Obstacle, TargetTruth  # noqa: E402
from services.lib.lidar.models import lidar_model  # noqa: E402
from services.lib.runtime.clock import NS  # noqa: E402
from services.lib.geometry import yaw_rotation
from services.lib.lidar.models import DEFAULT_MOUNT
from services.lib.world.primitives import primitives_from_obstacles
from services.sensor_driver.core import scan, SensorDriverParams
from services.simulator.core import Simulation  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.tracker.filters import FilterParams, make_filter  # noqa: E402
from services.tracker.frontend import Candidates, FrontEndParams, front_end  # noqa: E402
from services.tracker.single import Outcome, SingleTargetParams, single_target_tracker  # noqa: E402

import tracker_timing  # noqa: E402  (beside this file: the multi-target tracker's time per update)

SCENARIO = "sparse"
OBSERVER = "uav1"
OBSERVER_HEIGHT = 5.0  # m: where the planner holds uav1 in this scenario (sparse.toml)
RATE_HZ = 10.0
FILTERS = (("kf", False), ("particle", False), ("adaptive", True))  # (filter, recovery), seed 002 sec. 5.2
GOAL_VS_PARTICLE = 0.5  # adaptive / particle 3-D RMSE: seed 002's 2.8 / 5.5 m
GOAL_VS_KF = 0.25  # adaptive / fixed KF: 2.8 / 13.0 m
MATCH_DISTANCE = 1.0  # m: a candidate farther than this from the target is clutter


@dataclass(frozen=True)
class Observation:
    """One seed's scans as the front end saw them, with the truth at each scan's stamp."""

    stamps: np.ndarray  # (K,) ns
    truth: np.ndarray  # (K, 3) target position
    candidates: list[Candidates]
    target_returns: np.ndarray  # (K,) rays that hit the target
    other_returns: int  # rays that hit anything else (ground, obstacles)
    clutter_candidates: int  # candidates farther than MATCH_DISTANCE from the target
    frontend_seconds: np.ndarray  # (K,)
    distance: np.ndarray  # (K,) observer to target, m


@dataclass(frozen=True)
class Run:
    """One filter on one seed's scans."""

    errors: np.ndarray  # (M, 3) estimate - truth at every scan after initialisation
    measured: int  # of those scans, how many used a candidate
    reinitiated: int
    update_seconds: np.ndarray  # time of each loop step that updated

    def rmse(self) -> np.ndarray:
        """RMSE of X, Y, Z and 3-D."""
        squared = self.errors**2
        return np.sqrt(np.append(squared.mean(axis=0), squared.sum(axis=1).mean()))


def clutter() -> list[Obstacle]:
    """Static clutter around the target's box (x -8..16, y 12..30, z 3..12), in the Mid-360's range
    from the observer at (3, 2): a building behind it, a tree on either side and a lamp pole."""
    return [Obstacle(kind="box", center=(4.0, 36.0, 5.0), size=(20.0, 6.0, 10.0), name="building"),
            Obstacle(kind="cylinder", center=(-9.5, 20.0, 0.0), radius=0.25, height=3.0, name="tree1_trunk"),
            Obstacle(kind="cone", center=(-9.5, 20.0, 3.0), radius=2.0, height=6.0, name="tree1"),
            Obstacle(kind="cylinder", center=(17.5, 25.0, 0.0), radius=0.25, height=3.0, name="tree2_trunk"),
            Obstacle(kind="cone", center=(17.5, 25.0, 3.0), radius=2.5, height=7.0, name="tree2"),
            Obstacle(kind="cylinder", center=(12.0, 12.0, 0.0), radius=0.1, height=10.0, name="pole")]


def observe(seed: int, duration: float, frontend: FrontEndParams, height: float = OBSERVER_HEIGHT,
            obstacles: Sequence[Obstacle] = ()) -> Observation:
    scenario = load_scenario(SCENARIO)
    sim = Simulation(scenario, [f"uav{k + 1}" for k in range(scenario.uavs)], seed)
    x, y, heading = scenario.starts[sim.index(OBSERVER)]
    origin = np.array([x, y, height]) + yaw_rotation(heading) @ np.asarray(DEFAULT_MOUNT)
    driver = SensorDriverParams()
    model = lidar_model(scenario.uav.sensor, RATE_HZ)
    static = primitives_from_obstacles(sim.obstacles() + list(obstacles))
    rng = np.random.default_rng([seed, sim.index(OBSERVER)])
    count = int(round(duration * RATE_HZ))
    stamps = np.arange(count, dtype=np.int64) * int(NS / RATE_HZ)
    positions, velocities = sim.drones.kinematics(stamps / NS)  # (K, drones, 3): the target is drone 0
    truth = positions[:, 0]
    candidates, target_returns, seconds = [], np.zeros(count, dtype=np.int64), np.zeros(count)
    other_returns = off_target = 0
    for k in range(count):
        target = TargetTruth(id=sim.drones.ids[0], kind="drone", position=tuple(truth[k]),
                             velocity=tuple(velocities[k, 0]), radius=float(sim.drones.radii[0]))
        result = scan(origin, heading, model.directions(k), static.with_targets([target]), rng,
                      min_range=model.min_range, max_range=model.max_range, range_noise=driver.range_noise,
                      body_box=driver.body_box)
        started = time.perf_counter()
        found = front_end(result.points, origin, frontend)
        seconds[k] = time.perf_counter() - started
        candidates.append(found)
        target_returns[k] = int((result.hits == 1).sum())
        other_returns += int((result.hits == 0).sum())
        off_target += int((np.linalg.norm(found.positions - truth[k], axis=1) > MATCH_DISTANCE).sum())
    return Observation(stamps, truth, candidates, target_returns, other_returns, off_target, seconds,
                       np.linalg.norm(truth - origin, axis=1))


def run_filter(observation: Observation, name: str, recovery: bool, filters: FilterParams,
               loop: SingleTargetParams) -> Run:
    tracker = single_target_tracker(make_filter(name, filters), msgspec.structs.replace(loop, recovery=recovery))
    errors, measured, reinitiated, update_seconds = [], 0, 0, []
    for stamp, truth, found in zip(observation.stamps, observation.truth, observation.candidates):
        started = time.perf_counter()
        record = tracker.step(int(stamp), found)
        elapsed = time.perf_counter() - started
        if record.estimate is None:
            continue
        errors.append(record.estimate.position - truth)
        measured += record.updated
        reinitiated += record.outcome is Outcome.REINITIATED
        if record.outcome is Outcome.UPDATED:
            update_seconds.append(elapsed)
    return Run(np.array(errors).reshape(-1, 3), measured, reinitiated, np.array(update_seconds))


def pooled(runs: list[Run]) -> Run:
    return Run(np.concatenate([r.errors for r in runs]), sum(r.measured for r in runs),
               sum(r.reinitiated for r in runs), np.concatenate([r.update_seconds for r in runs]))


def row(run: Run) -> str:
    rmse = run.rmse()
    biggest = float(np.linalg.norm(run.errors, axis=1).max()) if len(run.errors) else math.nan
    share = 100.0 * run.measured / max(len(run.errors), 1)
    per_update = 1e3 * float(np.median(run.update_seconds)) if len(run.update_seconds) else math.nan
    return (f"{rmse[0]:7.2f} {rmse[1]:7.2f} {rmse[2]:7.2f} {rmse[3]:7.2f} {biggest:8.2f} {share:7.1f} "
            f"{per_update:8.3f} {run.reinitiated:6d}")


HEADER = "RMSE X       Y       Z      3D    max 3D  valid %  ms/upd  reinit"


def print_observation(seed: int, o: Observation) -> None:
    scans = len(o.stamps)
    hist = np.bincount(np.minimum(o.target_returns, 5), minlength=6) * 100.0 / scans
    with_candidate = np.mean([len(c) > 0 for c in o.candidates]) * 100.0
    print(f"seed {seed}: {scans} scans, target {o.distance.min():.1f}-{o.distance.max():.1f} m away; target "
          f"returns per scan 0/1/2/3/4/5+: " + "/".join(f"{h:.0f}" for h in hist) + " %; "
          f"{with_candidate:.0f} % of scans with a valid candidate; {o.other_returns} returns from the "
          f"ground or obstacles, {o.clutter_candidates} candidates off the target; front end "
          f"{1e3 * np.median(o.frontend_seconds):.2f} ms median", flush=True)


def print_table(total: dict[str, Run]) -> None:
    print(f"  {'metric':<24}{'Fixed CA-KF':>14}{'Particle':>14}{'Adaptive':>14}")
    theirs = {"RMSE X (m)": (15.0, 6.0, 3.0), "RMSE Y (m)": (20.0, 8.0, 4.0), "RMSE Z (m)": (4.0, 2.5, 1.5),
              "RMSE 3D (m)": (13.0, 5.5, 2.8)}
    names = ("kf", "particle", "adaptive")
    for k, metric in enumerate(theirs):
        cells = [f"{total[n].rmse()[k]:6.2f} ({t:4.1f})" for n, t in zip(names, theirs[metric])]
        print(f"  {metric:<24}" + "".join(f"{c:>14}" for c in cells))
    rows = {
        "max 3D error (m)": lambda r: f"{np.linalg.norm(r.errors, axis=1).max():6.2f}",
        "valid measurements (%)": lambda r: f"{100.0 * r.measured / len(r.errors):6.1f}",
        "time per update (ms)": lambda r: f"{1e3 * np.median(r.update_seconds):6.3f}",
        "re-initialisations": lambda r: f"{r.reinitiated:6d}",
    }
    seed_figures = {"valid measurements (%)": (14.7, 15.8, 8.5), "time per update (ms)": (108.5, 101.3, 103.8)}
    for metric, cell in rows.items():
        cells = [cell(total[n]) + (f" ({seed_figures[metric][i]:4.1f})" if metric in seed_figures else "")
                 for i, n in enumerate(names)]
        print(f"  {metric:<24}" + "".join(f"{c:>14}" for c in cells))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--duration", type=float, default=None, help="s of mission per seed (default 120)")
    parser.add_argument("--quick", action="store_true", help="seeds 1-2 for 40 s each (a smoke run)")
    parser.add_argument("--clutter", action="store_true", help="a building, two trees and a pole in the scene")
    parser.add_argument("--observer-height", type=float, default=OBSERVER_HEIGHT, metavar="M",
                        help=f"the observer's height (default {OBSERVER_HEIGHT:g} m; below ~5 m the ground is in view)")
    parser.add_argument("--single-returns", action="store_true",
                        help="one return makes a candidate (DBSCAN min_samples 1, no lower eigenvalue bound)")
    parser.add_argument("--skip-timing", action="store_true",
                        help="leave out the multi-target tracker's time per update (benchmarks/tracker_timing.py)")
    args = parser.parse_args()
    seeds = args.seeds[:2] if args.quick else args.seeds
    duration = args.duration or (40.0 if args.quick else 120.0)
    frontend, filters = FrontEndParams(), FilterParams()
    if args.single_returns:
        frontend = msgspec.structs.replace(frontend, cluster_min_points=1, min_spread=0.0)
    # one R for every filter: the one the filters floor theirs at
    loop = SingleTargetParams(measurement_variance=filters.measurement_variance)
    print(f"{SCENARIO}{' + clutter' if args.clutter else ''}: observer {OBSERVER} still at "
          f"{args.observer_height:g} m, Mid-360 at {RATE_HZ:g} Hz, {duration:g} s per seed; front end {frontend}; "
          f"recovery after {loop.max_missed} missed steps, gate {loop.gate_probability:g}, "
          f"R = {loop.measurement_variance:g} m² I", flush=True)
    runs: dict[str, list[Run]] = {name: [] for name, _ in FILTERS}
    recovered: dict[str, list[Run]] = {name: [] for name, recovery in FILTERS if not recovery}
    for seed in seeds:
        observation = observe(seed, duration, frontend, args.observer_height, clutter() if args.clutter else [])
        print_observation(seed, observation)
        print(f"  {'filter':<10}{HEADER}")
        for name, recovery in FILTERS:
            run = run_filter(observation, name, recovery, filters, loop)
            runs[name].append(run)
            print(f"  {name:<10}{row(run)}", flush=True)
        for name in recovered:
            recovered[name].append(run_filter(observation, name, True, filters, loop))

    total = {name: pooled(r) for name, r in runs.items()}
    print(f"\nPooled over seeds {', '.join(map(str, seeds))} (seed 002's table, their figures in brackets):")
    print_table(total)
    adaptive = total["adaptive"].rmse()[3]
    print("\nGoals (pooled 3-D RMSE):")
    for other, goal in (("particle", GOAL_VS_PARTICLE), ("kf", GOAL_VS_KF)):
        ratio = adaptive / total[other].rmse()[3]
        print(f"  adaptive / {other:<9}{ratio:7.3f}   goal <= {goal:g}: {'met' if ratio <= goal else 'NOT met'}")
    print("\nRecovery alone: every filter with it (pooled 3-D RMSE, max 3-D error, per-seed 3-D RMSE):")
    for name, r in [*((n, pooled(v)) for n, v in recovered.items()), ("adaptive", total["adaptive"])]:
        per_seed = " ".join(f"{x.rmse()[3]:.2f}" for x in (recovered.get(name) or runs[name]))
        print(f"  {name:<10}{r.rmse()[3]:6.2f} m   max {np.linalg.norm(r.errors, axis=1).max():6.2f} m   "
              f"seeds: {per_seed}")
    if not args.skip_timing:
        tracker_timing.print_table(tracker_timing.run(6.0 if args.quick else 12.0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
