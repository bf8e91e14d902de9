"""Command-line options the simulator takes (shared by `falconry run simulator` and `falconry sim`)."""
from __future__ import annotations

import argparse

from schemas import keys


def add_simulator_options(parser: argparse.ArgumentParser, *, positional_scenario: bool = False) -> None:
    group = parser.add_argument_group("simulator (SERVICE=simulator only)" if not positional_scenario else "mission")
    if positional_scenario:
        group.add_argument("scenario", nargs="?", default="mbzirc",
                           help="built-in scenario name or path to a scenario .toml (default: mbzirc)")
    else:
        group.add_argument("--scenario", default="mbzirc",
                           help="built-in scenario name or path to a scenario .toml (default: mbzirc)")
    group.add_argument("--uavs", type=int, choices=[2, 3], default=None,
                       help="number of UAVs (default: the scenario's)")
    group.add_argument("--seed", type=int, default=None, help="random seed (default: the scenario's)")
    group.add_argument("--lockstep", action=argparse.BooleanOptionalAction, default=False,
                       help="advance the clock only when every service has processed the previous tick: "
                            "deterministic for a seed, as fast as the machine allows (--no-lockstep: real "
                            "time at --rtf, the default; the later of the two wins)")
    group.add_argument("--duration", type=float, default=None, metavar="S",
                       help="mission time to simulate, seconds (default: the scenario's)")
    group.add_argument("--rtf", type=float, default=1.0, metavar="FACTOR",
                       help="real-time factor without --lockstep (default 1.0; 2.0 runs twice as fast)")
    group.add_argument("--detector", choices=keys.DETECTORS, default=keys.DEFAULT_DETECTOR,
                       help="onboard (default): the LiDAR perception for drones and the colour camera with "
                            "Object Detect for balloons; classifier: the LiDAR perception alone (no camera: "
                            "balloons on poles stay background); oracle: noisy detections made only from LiDAR "
                            "points that really hit a target (evaluation, simulation only)")
    group.add_argument("--positioning", choices=keys.POSITIONING, default=None,
                       help="where every UAV's position comes from (default: the scenario's [uav] positioning, "
                            "gnss unless it says otherwise): gnss = the simulator's odometry; lidar = flying "
                            "without GNSS, on the onboard localizer's LiDAR-inertial estimate (seed 003), one "
                            "localizer per UAV")
    group.add_argument("--tick", type=float, default=0.05, metavar="S",
                       help="mission clock tick, seconds (default 0.05 = 20 Hz)")
