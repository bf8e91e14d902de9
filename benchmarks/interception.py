"""Interception of agile intruders (issue 12): how long after its first detection each drone of
`agile` (a figure-eight at up to 6 m/s, a random manoeuvrer at 5 m/s among trees) and `intruder`
(4 m/s straight legs, 3 m/s random) is captured, with the onboard LiDAR classifier and tracker.

Runs whole `falconry sim` missions in lockstep (deterministic for a seed; benchmarks/mission.py's
runner) and prints, per scenario and seed, each drone's capture time after its first detection,
then per scenario the median and the worst. Goals: every drone within 60 s of its first
detection on every seed, median at most 30 s.

    .venv/bin/python benchmarks/interception.py                      # 5 seeds x 2 scenarios: ~14 min
    .venv/bin/python benchmarks/interception.py --seeds 1 2 --scenarios agile
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # mission.py beside this file

from mission import run  # noqa: E402

WORST_GOAL_S = 60.0
MEDIAN_GOAL_S = 30.0


def captures(summary: dict) -> tuple[dict[str, float | None], list[str]]:
    """Per drone, its capture time after its first detection (None: never detected first), and
    the drones not captured."""
    drones = sorted(t for t, kind in summary["target_kinds"].items() if kind == "drone")
    caught = {d["target"]: (None if d["first_detected"] is None else d["t"] - d["first_detected"])
              for d in summary["destroyed"]}
    return {d: caught[d] for d in drones if d in caught}, [d for d in drones if d not in caught]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="seeds (default 1-5)")
    parser.add_argument("--scenarios", nargs="+", default=["agile", "intruder"], help="default: agile intruder")
    parser.add_argument("--detector", choices=["classifier", "oracle", "onboard"], default="classifier",
                        help="the runs' detector (default classifier: the LiDAR perception)")
    parser.add_argument("--duration", type=float, default=120.0, help="mission time per run, s (default 120)")
    args = parser.parse_args()
    started = time.time()
    times: dict[str, list[float]] = {s: [] for s in args.scenarios}
    failures: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        for scenario in args.scenarios:
            for seed in args.seeds:
                summary = run(scenario, 2, seed, args.duration, Path(tmp), args.detector)
                caught, missed = captures(summary)
                times[scenario] += [t for t in caught.values() if t is not None]
                failures += [f"{scenario} seed {seed}: {d} not captured" for d in missed]
                failures += [f"{scenario} seed {seed}: {d} captured {t:.1f} s after first detection"
                             for d, t in caught.items() if t is not None and t > WORST_GOAL_S]
                print(f"[{time.time() - started:6.0f} s] {scenario} seed {seed}: "
                      + ", ".join(f"{d} {'captured %.1f s after first detection' % t if t is not None else 'captured'}"
                                  for d, t in caught.items())
                      + (f"; not captured: {', '.join(missed)}" if missed else ""), flush=True)
    print(f"\ncapture time after first detection, detector {args.detector} (goal: all <= {WORST_GOAL_S:g} s, "
          f"median <= {MEDIAN_GOAL_S:g} s)")
    for scenario, values in times.items():
        if values:
            median = statistics.median(values)
            print(f"{scenario}: {len(values)} captures, median {median:.1f} s "
                  f"({'met' if median <= MEDIAN_GOAL_S else 'NOT met'}), worst {max(values):.1f} s")
    print("every drone within the goal on every seed: " + ("met" if not failures else "NOT met: " + "; ".join(failures)))
    print(f"wall time {time.time() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
