"""Can the whole fleet keep up? The lockstep real-time factor of a mission with 2 and 3 UAVs at the
seeds' sensor (Ouster OS0-128 × 1024), and where the time goes per service.

Flies `falconry sim SCENARIO --lockstep --detector DETECTOR` (default classifier: the LiDAR
perception the goal was set for; onboard adds the camera and Object Detect, as `make sim` runs;
every service of every UAV in its own process) once per fleet size, with the sensor driver's model set by a
parameter file, and reads the run's summary (`--summary-json`): the simulator's mission time over
wall time since the first tick is the real-time factor (goal: at least 1.0 with 3 UAVs: a lockstep
run then loses nothing against the real clock; the launcher's figure, which includes starting every
process, is printed beside it), and every process's CPU seconds at the end of the run (from its health answer) say
where the time went, printed per service as the share of one core it used on average per UAV.
On this 2-core machine the processes of all UAVs share the two cores: the sum of the shares times
the UAVs cannot exceed 200 %.

    .venv/bin/python benchmarks/fleet.py                          # 60 s missions, 2 and 3 UAVs: ~3 min
    .venv/bin/python benchmarks/fleet.py --sensor os0-64-512 --duration 30
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RTF_GOAL = 1.0  # with 3 UAVs: a lockstep run as fast as the real clock
SENSOR = "os0-128-1024"


def fly(scenario: str, uavs: int, sensor: str, duration: float, seed: int, work: Path,
        detector: str = "classifier") -> dict:
    config = work / "sensor.toml"
    config.write_text(f'[sensor_driver]\nmodel = "{sensor}"\n')
    summary = work / f"{scenario}-{uavs}.json"
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", scenario, "--uavs", str(uavs), "--seed", str(seed),
            "--lockstep", "--detector", detector, "--duration", str(duration), "--quiet", "--progress", "0",
            "--config", str(config), "--summary-json", str(summary)]
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0 or not summary.exists():
        raise SystemExit(f"{' '.join(argv[3:])} failed ({result.returncode}):\n{result.stdout[-2000:]}"
                         f"{result.stderr[-2000:]}")
    return json.loads(summary.read_text())


def shares_per_uav(summary: dict, uavs: int) -> dict[str, float]:
    """Percent of one core per service, averaged over the UAVs (the simulator and launcher: whole)."""
    wall = max(summary["wall_time"], 1e-9)
    totals: dict[str, float] = {}
    for process, seconds in summary["cpu"].items():
        service = process.rsplit("/", 1)[-1]
        per_uav = process.split("/", 1)[0] not in ("sim", "launcher", "forkserver")
        totals[service] = totals.get(service, 0.0) + 100.0 * seconds / wall / (uavs if per_uav else 1)
    return totals


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="mbzirc", help="scenario to fly (default mbzirc)")
    parser.add_argument("--sensor", default=SENSOR, help=f"LiDAR model of every UAV (default {SENSOR})")
    parser.add_argument("--duration", type=float, default=60.0, metavar="S", help="mission time per run (default 60)")
    parser.add_argument("--uavs", type=int, nargs="+", default=[2, 3], choices=[2, 3], help="fleet sizes (default 2 3)")
    parser.add_argument("--seed", type=int, default=1, help="scenario seed (default 1)")
    parser.add_argument("--detector", choices=["classifier", "onboard", "oracle"], default="classifier",
                        help="the runs' detector (default classifier: the LiDAR perception alone)")
    args = parser.parse_args()
    if args.duration <= 0:
        parser.error("--duration must be positive")
    started = time.time()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for uavs in args.uavs:
            print(f"[{time.time() - started:5.0f} s] {args.scenario}, {uavs} UAVs, {args.sensor}, "
                  f"{args.duration:g} s lockstep ...", flush=True)
            summary = fly(args.scenario, uavs, args.sensor, args.duration, args.seed, Path(tmp), args.detector)
            rtf = summary["real_time_factor"]
            results[uavs] = (rtf, shares_per_uav(summary, uavs), summary)
            print(f"        real-time factor {rtf:.2f}x from the first tick; mission {summary['mission_time']:.1f} s "
                  f"in {summary['wall_time']:.1f} s wall with start-up; outcome {summary['outcome']}", flush=True)

    services = sorted({s for _, shares, _ in results.values() for s in shares},
                      key=lambda s: -max(r[1].get(s, 0.0) for r in results.values()))
    print(f"\n{args.scenario}, {args.sensor}, lockstep, {args.duration:g} s of mission time")
    print("UAVs | real-time factor | " + " | ".join(services))
    for uavs, (rtf, shares, _) in results.items():
        print(f"{uavs:>4} | {rtf:15.2f}x | " + " | ".join(f"{shares.get(s, 0.0):>{max(len(s), 5)}.0f}"
                                                        for s in services))
    print("(CPU: % of one core per UAV, the simulator and the launcher for the whole fleet)")
    if 3 in results:
        rtf = results[3][0]
        print(f"goal: real-time factor >= {RTF_GOAL:.1f}x with 3 UAVs: {rtf:.2f}x "
              + ("MET" if rtf >= RTF_GOAL else "NOT MET"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
