"""What the fleet viewer costs a mission: the same lockstep run with and without `--rrd`.

Runs `falconry sim SCENARIO --lockstep` with a fixed seed, alternating runs without a viewer and
with `--rrd FILE` (the viewer process drawing every UAV to a rerun file), and prints the wall
time of each, the medians, the slowdown (goal: at most 10 %), the file's size per minute of
mission, and the viewer's own figures (messages drawn, scans dropped to keep up). Lockstep
makes both runs the same mission, so the wall time is the only thing the viewer may change.

    .venv/bin/python benchmarks/viz.py                       # mbzirc, 2 UAVs, 60 s, 3 pairs: ~7 min
    .venv/bin/python benchmarks/viz.py --pairs 1 --duration 30
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SLOWDOWN_GOAL = 0.10  # issue 8: a mission with the viewer at most 10 % slower


def run(args: argparse.Namespace, workdir: Path, label: str, rrd: Path | None) -> dict:
    summary = workdir / f"{label}.json"
    log = workdir / f"{label}.log"
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", args.scenario, "--uavs", str(args.uavs),
            "--seed", str(args.seed), "--lockstep", "--duration", str(args.duration), "--quiet", "--progress", "0",
            "--detector", "classifier",  # the figures in benchmarks/README.md were measured with the LiDAR alone
            "--summary-json", str(summary), "--log-file", str(log)] + (["--rrd", str(rrd)] if rrd else [])
    started = time.monotonic()
    result = subprocess.run(argv, capture_output=True, text=True)
    wall = time.monotonic() - started
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[2:])} failed ({result.returncode}):\n{result.stdout[-2000:]}")
    out = {"wall": wall, "mission": json.loads(summary.read_text())["mission_time"]}
    if rrd is not None:
        out["bytes"] = rrd.stat().st_size
        viewer = [line for line in log.read_text().splitlines() if "sim/viewer" in line]
        drew = next((line for line in viewer if "view: drew" in line), "")
        dropped = next((line for line in viewer if "dropped" in line and "scans" in line), "")
        out["drew"] = drew.split("view: ", 1)[-1]
        out["dropped"] = int(re.search(r"dropped (\d+) scans", dropped).group(1)) if dropped else 0
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="mbzirc", help="scenario (default mbzirc)")
    parser.add_argument("--uavs", type=int, default=2, help="team size (default 2)")
    parser.add_argument("--duration", type=float, default=60.0, help="mission time per run, s (default 60)")
    parser.add_argument("--seed", type=int, default=1, help="seed of every run (default 1)")
    parser.add_argument("--pairs", type=int, default=3, help="runs without and with the viewer (default 3 each)")
    args = parser.parse_args()
    plain, drawn = [], []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for i in range(args.pairs):
            # alternate, so that drift in the machine's load hits both alike
            plain.append(run(args, work, f"plain{i}", None))
            print(f"pair {i + 1}: without viewer {plain[-1]['wall']:6.1f} s wall", flush=True)
            drawn.append(run(args, work, f"drawn{i}", work / f"run{i}.rrd"))
            d = drawn[-1]
            print(f"pair {i + 1}: with --rrd     {d['wall']:6.1f} s wall, {d['bytes'] / 1e6:.1f} MB, "
                  f"{d['dropped']} scans dropped ({d['drew']})", flush=True)
    without = statistics.median(r["wall"] for r in plain)
    with_viewer = statistics.median(r["wall"] for r in drawn)
    slowdown = with_viewer / without - 1.0
    per_minute = statistics.median(r["bytes"] / 1e6 / (r["mission"] / 60) for r in drawn)
    print(f"\n{args.scenario}, {args.uavs} UAVs, lockstep, {args.duration:g} s of mission, seed {args.seed}, "
          f"{args.pairs} pairs")
    print(f"wall time median: without viewer {without:.1f} s, with --rrd {with_viewer:.1f} s "
          f"(ratio {with_viewer / without:.3f}, {100 * slowdown:+.1f} %; goal <= +{100 * SLOWDOWN_GOAL:.0f} %: "
          f"{'met' if slowdown <= SLOWDOWN_GOAL else 'NOT met'})")
    print(f"rerun file: {per_minute:.1f} MB per minute of mission (median), "
          f"scans dropped by the viewer: {sum(r['dropped'] for r in drawn)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
