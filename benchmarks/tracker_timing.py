"""Time per update of seed 000's buffered multi-target tracker (services/tracker/core.py) with ten
live tracks on OS0-128 scans (goal: median at most 5 ms).

The scans are the sensor driver's ray casts of mbzirc's static world (ground, building, trees,
poles) from a UAV hovering 5 m up in the arena, with ten drones (0.325 m radius) circling it at
8-25 m; the tracker's map holds that world pinned occupied (the mapper's a-priori map), and
every scan brings one detection per drone in sight (truth plus 5 cm noise). One update is what
the node does per scan: `new_point_cloud` for the scan, then `new_detections` for its detections.
In lockstep and in real time alike the classifier's detections of a scan reach the tracker before
the next scan, so no replay is needed (`same scan`); `one scan late` times the worst case the
buffer exists for, every detection replayed through one newer scan. Timed per filter.

    .venv/bin/python benchmarks/tracker_timing.py            # about 1 min
    .venv/bin/python benchmarks/tracker_timing.py --quick    # about 20 s
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too

import numpy as np  # noqa: E402

from schemas.messages import TargetTruth  # noqa: E402
from services.lib.lidar.models import lidar_model  # noqa: E402
from services.lib.runtime.clock import NS  # noqa: E402
from services.lib.voxels.apriori import obstacle_voxels  # noqa: E402
from services.lib.world.primitives import primitives_from_obstacles
from services.mapper.core import MapperCore  # noqa: E402
from services.sensor_driver.core import scan
from services.simulator.core import Simulation  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.tools.evaluation import in_sight  # noqa: E402
from services.tracker.core import OccupiedVoxels, TrackerCore, TrackerParams  # noqa: E402
from services.tracker.filters import FILTERS  # noqa: E402

SENSOR = "os0-128"
RATE_HZ = 10.0
TARGETS = 10
GOAL_MS = 5.0


@dataclass(frozen=True)
class Timing:
    filter: str
    detections: str  # when the scan's detections come: "same scan" or "one scan late"
    median_ms: float
    p95_ms: float
    live_tracks: float  # mean over the timed scans
    scans: int


def drone_positions(t: float, centre: np.ndarray) -> np.ndarray:
    """Ten drones on circles of 8-25 m around the observer, 2-5 m/s, at 3-9 m height."""
    k = np.arange(TARGETS)
    radius = 8.0 + 17.0 * k / (TARGETS - 1)
    speed = 2.0 + 3.0 * (k % 4) / 3
    phase = 2 * np.pi * k / TARGETS + speed / radius * t
    return np.stack([centre[0] + radius * np.cos(phase), centre[1] + radius * np.sin(phase),
                     3.0 + 6.0 * (k % 3) / 2 + 0.0 * phase], axis=1)


def scans(duration: float):
    """(stamp, points, truth positions, in sight) of every scan."""
    simulation = Simulation(load_scenario("mbzirc"), ["uav1"], 1)
    obstacles = simulation.obstacles()
    static = primitives_from_obstacles(obstacles)
    model = lidar_model(SENSOR, RATE_HZ)
    directions = model.directions(0)
    origin = np.array([30.0, 20.0, 5.0])
    rng = np.random.default_rng(5)
    out = []
    for k in range(int(duration * RATE_HZ)):
        t = k / RATE_HZ
        truth = drone_positions(t, origin)
        targets = [TargetTruth(id=f"d{i}", kind="drone", position=tuple(p), velocity=(0.0, 0.0, 0.0), radius=0.325)
                   for i, p in enumerate(truth)]
        result = scan(origin, 0.0, directions, static.with_targets(targets), rng,
                      min_range=model.min_range, max_range=model.max_range)
        out.append((int(t * NS), result.points, truth, in_sight(result.hits, len(targets))))
    return out, obstacles


def occupied_map(obstacles) -> OccupiedVoxels:
    mapper = MapperCore()
    mapper.pin(obstacle_voxels(obstacles, mapper.geometry))
    return OccupiedVoxels(mapper.states(), np.asarray(mapper.origin, dtype=np.float64), mapper.voxel_size,
                          np.asarray(mapper.shape, dtype=np.int64))


def time_filter(name: str, recorded, occupied: OccupiedVoxels, warm_up: int, late: bool) -> Timing:
    tracker = TrackerCore(TrackerParams(filter=name))
    tracker.set_occupied(occupied)
    rng = np.random.default_rng(9)
    times, live = [], []
    previous = None
    for k, (stamp, points, truth, seen) in enumerate(recorded):
        detections = (stamp, truth[seen] + rng.normal(0.0, 0.05, (int(seen.sum()), 3)))
        started = time.perf_counter()
        tracker.new_point_cloud(stamp, points)
        if late and previous is not None:
            tracker.new_detections(*previous)
        elif not late:
            tracker.new_detections(*detections)
        elapsed = time.perf_counter() - started
        previous = detections
        if k >= warm_up:
            times.append(elapsed * 1e3)
            live.append(len(tracker))
    return Timing(name, "one scan late" if late else "same scan", statistics.median(times),
                  float(np.percentile(times, 95)), float(np.mean(live)), len(times))


def run(duration: float, filters=FILTERS) -> list[Timing]:
    recorded, obstacles = scans(duration)
    occupied = occupied_map(obstacles)
    warm_up = int(2 * RATE_HZ)  # tracks start and the compiled kernels load
    return [time_filter(name, recorded, occupied, warm_up, late) for name in filters for late in (False, True)]


def print_table(timings: list[Timing]) -> None:
    print(f"\nTracker update (Alg. 2) on {SENSOR} scans with {TARGETS} drones, ms per scan:")
    print("| filter | detections | median | p95 | live tracks | scans |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for t in timings:
        print(f"| {t.filter} | {t.detections} | {t.median_ms:.2f} | {t.p95_ms:.2f} | {t.live_tracks:.1f} | {t.scans} |")
    for t in timings:
        verdict = "met" if t.median_ms <= GOAL_MS else "NOT met"
        print(f"{t.filter}, detections {t.detections}: median {t.median_ms:.2f} ms with {t.live_tracks:.1f} "
              f"live tracks (goal <= {GOAL_MS:g} ms: {verdict})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=12.0, help="s of scans (default 12)")
    parser.add_argument("--quick", action="store_true", help="6 s of scans")
    args = parser.parse_args()
    print_table(run(6.0 if args.quick else args.duration))


if __name__ == "__main__":
    main()
