"""How old is the sensor data when each stage acts on it? (issue 39)

Flies `falconry sim <scenario>` in real time (not lockstep: in lockstep every stage waits for the
tick and the ages count ticks, not the machine) and prints the summary's data ages per stage,
p50 / p95 / max, from the launcher's monitor. Every message carries in header.source the stamp of
the newest scan or frame it derives from; the monitor dates each message's arrival (on Zenoh's
thread) in mission time and counts a stream's age only when its source moves on:

  scan → detections          the classifier's (or oracle's) detections of a scan
  frame → camera detections  Object Detect's of a camera frame
  sensor → tracks            the tracker's picture, by its freshest correction
  sighting → command         a job manager's command at a target, by the sighting it was decided on
  sighting → reference       the planner's first reference for such a command: scan to setpoint

Goal (issue 39): sighting → reference p50 <= 100 ms and p95 <= 150 ms on a 2-UAV `intruder` run.
Ages are in mission time, which is what a moving target's lead is made of. With `--rtf` below 1
(a machine that cannot fly the fleet in real time: its stages fall behind and queue) they are
also printed in wall time (mission ms / rtf), the figure the goal is about.

    .venv/bin/python benchmarks/latency.py                       # intruder, 2 UAVs, 60 s: ~2 min
    .venv/bin/python benchmarks/latency.py --scenario mbzirc --uavs 3 --duration 90
    .venv/bin/python benchmarks/latency.py --rtf 0.4                # slower than real time
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOALS_MS = {"sighting → reference": (100.0, 150.0)}  # p50, p95


def fly(args: argparse.Namespace, work: Path) -> dict:
    summary = work / "summary.json"
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", args.scenario, "--uavs", str(args.uavs),
            "--seed", str(args.seed), "--duration", str(args.duration), "--rtf", str(args.rtf), "--quiet",
            "--progress", "0",
            "--summary-json", str(summary)]
    result = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    if not summary.exists():
        sys.exit(f"the run left no summary (exit {result.returncode}): {result.stderr.strip()[-400:]}")
    return json.loads(summary.read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="intruder", help="scenario to fly (default intruder)")
    parser.add_argument("--uavs", type=int, default=2, choices=(2, 3), help="fleet size (default 2)")
    parser.add_argument("--duration", type=float, default=60.0, help="mission time, s (default 60)")
    parser.add_argument("--seed", type=int, default=1, help="scenario seed (default 1)")
    parser.add_argument("--rtf", type=float, default=1.0, help="mission seconds per wall second (default 1)")
    args = parser.parse_args()
    if not 0 < args.rtf <= 10:
        parser.error(f"--rtf must lie in (0, 10], got {args.rtf:g}")
    print(f"{args.scenario}, {args.uavs} UAVs, seed {args.seed}, {args.duration:g} s at {args.rtf:g}x real time ...",
          flush=True)
    with tempfile.TemporaryDirectory() as work:
        summary = fly(args, Path(work))
    rtf = summary["mission_time"] / max(summary["wall_time"], 1e-9)
    print(f"outcome {summary['outcome']}, mission {summary['mission_time']:.1f} s at {rtf:.2f}x real time")
    stages = summary.get("data_age", {}).get("stages", {})
    if not stages:
        print("no stage reported a data age")
        return 1
    wall = args.rtf != 1.0
    extra = " wall p50 / p95 ms |" if wall else ""
    print(f"\n| stage | count | p50 ms | p95 ms | max ms |{extra} goal |\n| --- | ---: | ---: | ---: | ---: |"
          + (" ---: |" if wall else "") + " --- |")
    for stage, row in stages.items():
        p50, p95 = row["p50_ms"] / args.rtf, row["p95_ms"] / args.rtf  # wall time
        goal = ""
        if stage in GOALS_MS:
            goal_p50, goal_p95 = GOALS_MS[stage]
            goal = f"p50 <= {goal_p50:g}, p95 <= {goal_p95:g} (wall): " \
                   f"{'met' if p50 <= goal_p50 and p95 <= goal_p95 else 'NOT met'}"
        walls = f" {p50:.1f} / {p95:.1f} |" if wall else ""
        print(f"| {stage} | {row['count']} | {row['p50_ms']:.1f} | {row['p95_ms']:.1f} | {row['max_ms']:.1f} |{walls}"
              f" {goal} |")
    if not any(stage in stages for stage in GOALS_MS):
        print("\nno engagement reached the planner: no sighting → reference figure")
    return 0


if __name__ == "__main__":
    sys.exit(main())
