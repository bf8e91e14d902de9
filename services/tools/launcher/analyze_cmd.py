"""`falconry analyze`: figures of the theory behind the perception.

`falconry analyze hit-probability` (seed 000 sec. IV-A/B, Fig. 5): the probability that the voxel a
LiDAR point falls in is the voxel the true point lies in, over the point's distance, for sensors
with different pose and range noise. The point's covariance comes from the Jacobian of eq. 42;
p_hit is eq. 46, the Gaussian's mass in the measured voxel (scipy's multivariate normal CDF),
averaged over where in its voxel the point falls and over the ray's direction.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import numpy as np

from services.lib.lidar.uncertainty import mean_hit_probability
from services.tools.launcher.common import CliError

DEFAULT_NOISE = ("ideal=0,0,0.02", "rtk=0.02,0.1,0.02", "gnss=0.1,0.5,0.03", "poor=0.3,1.0,0.05")


@dataclass(frozen=True)
class Noise:
    name: str
    position: float  # m, σ per axis
    attitude: float  # rad, σ of roll, pitch and yaw
    range: float  # m, σ of a range

    def pose_covariance(self) -> np.ndarray:
        return np.diag([self.position ** 2] * 3 + [self.attitude ** 2] * 3)

    def label(self) -> str:
        return (f"{self.name}: σ position {self.position:g} m, attitude {math.degrees(self.attitude):g}°, "
                f"range {self.range:g} m")


def parse_noise(text: str) -> Noise:
    """NAME=POSITION_M,ATTITUDE_DEG,RANGE_M."""
    try:
        name, values = text.split("=", 1)
        position, attitude, rng = (float(v) for v in values.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give NAME=POSITION_M,ATTITUDE_DEG,RANGE_M, e.g. rtk=0.02,0.1,0.02")
    if min(position, attitude, rng) < 0 or not all(map(math.isfinite, (position, attitude, rng))):
        raise argparse.ArgumentTypeError(f"{text!r}: noise must be finite and not negative")
    return Noise(name.strip() or "sensor", position, math.radians(attitude), rng)


def add_parser(commands) -> None:
    p = commands.add_parser("analyze", help="figures of the perception's theory (seed 000 sec. IV)",
                            description="Analyses that need no run. `falconry analyze hit-probability --help`.")
    analyses = p.add_subparsers(dest="analysis", metavar="ANALYSIS", required=True)
    hit = analyses.add_parser(
        "hit-probability", help="p_hit over distance for given pose and range noise (seed 000 Fig. 5)",
        description="Print (and plot) the probability that a LiDAR point lands in the voxel of the true point, "
                    "over distance, for sensors with the given noise (seed 000 eq. 41-46): the covariance of a "
                    "point from the Jacobian of eq. 42, its mass in the measured voxel by scipy's multivariate "
                    "normal CDF, averaged over where the point falls in its voxel and the ray's direction.")
    hit.add_argument("--noise", type=parse_noise, action="append", metavar="NAME=POS,ATT,RANGE",
                     help="a sensor's noise: position σ (m), attitude σ (degrees), range σ (m); repeatable "
                          f"(default: {' '.join(DEFAULT_NOISE)})")
    hit.add_argument("--voxel", type=float, default=0.5, metavar="M", help="voxel edge, m (default 0.5, the map's)")
    hit.add_argument("--max-distance", type=float, default=50.0, metavar="M",
                     help="farthest distance, m (default 50, the OS0's range)")
    hit.add_argument("--step", type=float, default=2.5, metavar="M", help="distance step, m (default 2.5)")
    hit.add_argument("--samples", type=int, default=80, metavar="N",
                     help="points averaged per distance (default 80; more is smoother and slower)")
    hit.add_argument("--seed", type=int, default=0, help="random seed of the samples (default 0)")
    hit.add_argument("--plot", metavar="FILE.png", help="also draw the curves to a PNG")
    p.set_defaults(handler=run_analyze)


def run_analyze(args: argparse.Namespace) -> int:
    noises = args.noise or [parse_noise(n) for n in DEFAULT_NOISE]
    if not (args.voxel > 0 and args.max_distance > 0 and args.step > 0 and args.samples > 0):
        raise CliError("--voxel, --max-distance, --step and --samples must be positive")
    if args.plot and not args.plot.lower().endswith(".png"):
        raise CliError("--plot writes a PNG: give a FILE.png")
    distances = np.arange(args.step, args.max_distance + 1e-9, args.step)
    rng = np.random.default_rng(args.seed)
    started, last_report = time.monotonic(), time.monotonic()
    curves = []
    for k, noise in enumerate(noises):
        curve = []
        for d in distances:
            curve.append(mean_hit_probability(float(d), noise.pose_covariance(), noise.range, args.voxel,
                                              args.samples, rng))
            if time.monotonic() - last_report > 5.0:
                last_report = time.monotonic()
                print(f"... {noise.name}: {d:g} m ({k + 1} of {len(noises)})", flush=True)
        curves.append(curve)
    print(f"p_hit: probability that a point lands in its true {args.voxel:g} m voxel (seed 000 eq. 46), "
          f"{args.samples} samples per distance")
    for noise in noises:
        print(f"  {noise.label()}")
    print("distance m | " + " | ".join(f"{n.name:>8}" for n in noises))
    for i, d in enumerate(distances):
        print(f"{d:10.1f} | " + " | ".join(f"{curves[k][i]:8.3f}" for k in range(len(noises))))
    if args.plot:
        from services.tools.launcher.plot import plot_curves  # matplotlib only when a plot is asked for

        plot_curves(args.plot, distances, {n.label(): c for n, c in zip(noises, curves)}, "distance (m)",
                    "p_hit", f"Voxel hit probability over distance ({args.voxel:g} m voxels), seed 000 Fig. 5")
        print(f"plot: {args.plot}")
    print(f"({time.monotonic() - started:.1f} s)")
    return 0
