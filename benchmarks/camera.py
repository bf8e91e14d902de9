"""The camera and Object Detect (seed 004 §2.3, §4.1): time per frame on one core, and how well the
balloons of mbzirc are found over distance.

Renders frames of the `mbzirc` world with the camera's default parameters from poses a searching
UAV takes (search height 5 m, headings all round, positions over the arena), drifting exposure and
white balance included, and runs Object Detect on each with the built-in colour file of the
balloons' colour. Prints:
- the median and 95th percentile time per rendered frame and per Object Detect frame, each on one
  core, and of both together per frame (goal, issue 39: at most 5 ms median together at the
  default 640 × 360);
- per 5 m of distance: balloons in view (at least `--min-pixels` of the balloon's pixels in the
  frame, from the renderer's per-pixel truth), the share found (recall: a detection within 1 m
  of the balloon's centre, or within 10 % of its distance when farther than 10 m: beyond the
  depth image's reach the range comes from the balloon's size, whose error grows with the
  square of the distance), false detections (matching no balloon) and the precision, and the
  detected position's error, mean and 95th percentile; with `--plot`, recall and error over
  distance as a PNG.

    .venv/bin/python benchmarks/camera.py                 # 400 frames: about 20 s
    .venv/bin/python benchmarks/camera.py --frames 100 --plot camera.png
"""
from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too

import numpy as np  # noqa: E402

from schemas.messages import Appearance  # noqa: E402
from services.camera.core import Camera, CameraParams, Gains  # noqa: E402
from services.lib.geometry import point_in_polygon, quaternion  # noqa: E402
from services.lib.world.primitives import pack, primitives_from_obstacles
from services.object_detect.colors import load_color_file  # noqa: E402
from services.object_detect.core import CameraView, ObjectDetectParams, detect  # noqa: E402
from services.object_detect.node import color_file_path  # noqa: E402
from services.simulator.core import Simulation  # noqa: E402
from services.simulator.scenario import load_scenario  # noqa: E402
from services.tools import evaluation  # noqa: E402

GOAL_MS = 5.0  # render + detect, median per frame
BIN_M = 5.0
MATCH_M = evaluation.MATCH_DISTANCE
MATCH_SHARE = evaluation.CAMERA_RANGE_SHARE  # of the distance, when that is larger (the run summary's match)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400, help="frames to render (default 400)")
    parser.add_argument("--colors", default="red", help="colour file or built-in name (default red: mbzirc's)")
    parser.add_argument("--min-pixels", type=int, default=12, help="a balloon is in view with this many pixels")
    parser.add_argument("--seed", type=int, default=1, help="poses and noise (default 1)")
    parser.add_argument("--plot", metavar="PNG", help="write recall and error over distance here")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    scenario = load_scenario("mbzirc")
    sim = Simulation(scenario, ["uav1", "uav2"], args.seed)
    truths = [t.truth() for t in sim.targets()]
    balloons = [(k, t) for k, t in enumerate(truths, start=1) if t.kind == "balloon"]
    world = pack(primitives_from_obstacles(sim.obstacles()).with_targets(truths))
    look = Appearance(sky=tuple(scenario.appearance.sky), ground=tuple(scenario.appearance.ground),
                      obstacle=tuple(scenario.appearance.obstacle), sun_elevation=scenario.appearance.sun_elevation,
                      sun_azimuth=scenario.appearance.sun_azimuth, ambient=scenario.appearance.ambient)
    colors = load_color_file(color_file_path(args.colors))
    rng = np.random.default_rng(args.seed)
    camera, gains, params = Camera(CameraParams(), rng), Gains(), ObjectDetectParams()
    arena = np.asarray(scenario.arena)
    low, high = arena.min(axis=0), arena.max(axis=0)
    render_ms, detect_ms, rows = [], [], []
    camera.render(world, look, np.array([5.0, 5.0, 5.0]), np.eye(3), np.ones(3), rng)  # compiled before timing
    while len(render_ms) < args.frames:
        xy = rng.uniform(low, high)
        if not point_in_polygon(xy[None], arena)[0]:
            continue
        position, rotation = camera.pose(np.array([xy[0], xy[1], 5.0]), rng.uniform(-math.pi, math.pi))
        gains.step(rng, camera.params)
        started = time.perf_counter()
        frame = camera.render(world, look, position, rotation, gains.factors(), rng)
        rendered = time.perf_counter()
        k = camera.intrinsics
        found = detect(frame.rgb, frame.depth_mm, CameraView(k, position, quaternion(rotation)),
                       colors, params)
        done = time.perf_counter()
        render_ms.append((rendered - started) * 1e3)
        detect_ms.append((done - rendered) * 1e3)
        ids = world.ids[np.maximum(frame.hits, 0)] * (frame.hits >= 0)
        matched = np.zeros(len(found.positions), dtype=bool)
        for k_id, balloon in balloons:
            centre = np.asarray(balloon.position)
            distance = float(np.linalg.norm(centre - position))
            if np.count_nonzero(ids == k_id) < args.min_pixels:
                continue
            gaps = np.linalg.norm(found.positions - centre, axis=1) if len(found.positions) else np.zeros(0)
            hit = bool(len(gaps)) and gaps.min() <= max(MATCH_M, MATCH_SHARE * distance)
            if hit:
                matched[int(np.argmin(gaps))] = True
            rows.append((distance, hit, float(gaps.min()) if hit else math.nan, 0))
        for p in found.positions[~matched]:
            rows.append((float(np.linalg.norm(p - position)), False, math.nan, 1))
    report(render_ms, detect_ms, rows, args)
    return 0


def report(render_ms, detect_ms, rows, args) -> None:
    print(f"{len(render_ms)} frames of mbzirc, 640 × 360, colours {args.colors!r}, one core")
    both = np.asarray(render_ms) + np.asarray(detect_ms)
    for name, values in (("render", render_ms), ("detect", detect_ms), ("both", both)):
        median = float(np.median(values))
        goal = f"   (goal <= {GOAL_MS:g} ms median: {'met' if median <= GOAL_MS else 'NOT met'})" if name == "both" else ""
        print(f"  {name:<7} median {median:5.1f} ms   p95 {np.percentile(values, 95):5.1f} ms{goal}")
    data = np.array(rows, dtype=float).reshape(-1, 4)
    print(f"\nballoons in view (>= {args.min_pixels} pixels) by distance; found = a detection within "
          f"{MATCH_M:g} m or {100 * MATCH_SHARE:g} % of the distance")
    print("  distance m  | in view | recall | false | error mean | error p95")
    edges = np.arange(0.0, max(float(data[:, 0].max(initial=0.0)), BIN_M) + BIN_M, BIN_M)
    centres, recalls, errors = [], [], []
    for a, b in zip(edges[:-1], edges[1:]):
        band = (data[:, 0] >= a) & (data[:, 0] < b)
        seen = band & (data[:, 3] == 0)
        false = int(np.count_nonzero(band & (data[:, 3] == 1)))
        if not seen.any() and not false:
            continue
        hits = seen & (data[:, 1] == 1)
        recall = hits.sum() / max(seen.sum(), 1)
        err = data[hits, 2]
        mean = float(err.mean()) if len(err) else math.nan
        p95 = float(np.percentile(err, 95)) if len(err) else math.nan
        print(f"  {a:4.0f} - {b:4.0f}  | {int(seen.sum()):7d} | {100 * recall:5.0f}% | {false:5d} | "
              f"{mean:8.3f} m | {p95:7.3f} m")
        centres.append((a + b) / 2)
        recalls.append(100 * recall)
        errors.append(mean)
    total_false = int(np.count_nonzero(data[:, 3] == 1))
    seen = data[:, 3] == 0
    found = int(np.count_nonzero(data[seen, 1] == 1))
    print(f"  all         | {int(seen.sum()):7d} | {100 * found / max(seen.sum(), 1):5.0f}% | {total_false:5d} |")
    print(f"  precision {100 * found / max(found + total_false, 1):.0f} % ({found} detections matched a balloon, "
          f"{total_false} matched none)")
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
        left.plot(centres, recalls, "o-")
        left.set(xlabel="distance to the balloon, m", ylabel="recall, %", title="balloons found", ylim=(0, 105))
        right.plot(centres, errors, "o-")
        right.set(xlabel="distance to the balloon, m", ylabel="position error, m", title="mean error of those found")
        for ax in (left, right):
            ax.grid(True, alpha=0.3)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=100)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    sys.exit(main())
