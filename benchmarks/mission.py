"""Mission figures (seed 004): how fast the team clears the arena, run after run.

Runs whole `falconry sim` missions in lockstep (deterministic for a seed) and prints, per seed,
when all balloons of `mbzirc` were destroyed with 2 and with 3 UAVs, how many attacks or
interceptions went for no target (the run's evaluation: aimed more than 2 m from every target),
and for `intruder`, how long after its first detection each intruder was captured. The detector
is `falconry sim`'s default, onboard (LiDAR perception and the colour camera); `--detector oracle`
gives the evaluation detector's figures.

    .venv/bin/python benchmarks/mission.py                  # 5 seeds, 2 and 3 UAVs, intruder: ~35 min
    .venv/bin/python benchmarks/mission.py --seeds 1 2 --skip-intruder --detector oracle
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BALLOON_GOAL_S = 90.0  # issues 4 and 11: all 5 balloons of mbzirc with 2 UAVs (oracle, then onboard)
INTRUDER_GOAL_S = 60.0  # issue 4: an intruder at 4 m/s captured within 60 s of first detection


def run(scenario: str, uavs: int, seed: int, duration: float, workdir: Path, detector: str,
        extra: tuple[str, ...] = ()) -> dict:
    """One lockstep `falconry sim` run (`extra`: more of its options); its summary."""
    summary = workdir / f"{Path(scenario).stem}-{uavs}-{seed}.json"  # a scenario may be a TOML file's path
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", scenario, "--uavs", str(uavs), "--seed", str(seed),
            "--lockstep", "--detector", detector, "--duration", str(duration), "--quiet", "--progress", "0",
            "--summary-json", str(summary), *extra]
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[2:])} failed ({result.returncode}):\n{result.stdout[-2000:]}{result.stderr[-2000:]}")
    return json.loads(summary.read_text())


def balloons_done(summary: dict) -> tuple[float | None, int, int]:
    kinds = summary["target_kinds"]
    balloons = [d["t"] for d in summary["destroyed"] if kinds.get(d["target"]) == "balloon"]
    total = sum(1 for k in kinds.values() if k == "balloon")
    return (max(balloons) if balloons and len(balloons) == total else None), len(balloons), total


def wrong_engagements(summary: dict) -> list[str]:
    """Attacks and interceptions aimed at no target, as 'uav1 t=12.3 s attack'."""
    return [f"{name} t={e['t']:.1f} s {e['action']}" for name, uav in summary["uavs"].items()
            for e in uav.get("engagements", []) if e["target"] is None]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="seeds to run (default 1-5)")
    parser.add_argument("--duration", type=float, default=120.0, help="mission time per run, s (default 120)")
    parser.add_argument("--skip-intruder", action="store_true", help="only the mbzirc balloon runs")
    parser.add_argument("--detector", choices=["onboard", "classifier", "oracle"], default="onboard",
                        help="the runs' detector (default onboard, falconry sim's)")
    args = parser.parse_args()
    started = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for seed in args.seeds:
            row = {"seed": seed}
            for uavs in (2, 3):
                summary = run("mbzirc", uavs, seed, args.duration, work, args.detector)
                done, got, total = balloons_done(summary)
                row[uavs] = done
                wrong = wrong_engagements(summary)
                row.setdefault("wrong", []).extend(wrong)
                print(f"[{time.time() - started:6.0f} s] mbzirc seed {seed}, {uavs} UAVs: "
                      + (f"all {total} balloons at t={done:.1f} s" if done is not None else f"{got}/{total} balloons")
                      + f"; {len(wrong)} attacks at no target" + (f" ({', '.join(wrong)})" if wrong else ""),
                      flush=True)
            rows.append(row)
        intruders = []
        if not args.skip_intruder:
            for seed in args.seeds:
                s = run("intruder", 2, seed, args.duration, work, args.detector)
                for d in s["destroyed"]:
                    if d["first_detected"] is not None:
                        intruders.append((seed, d["target"], d["t"] - d["first_detected"]))
                caught = {d["target"] for d in s["destroyed"]}
                missed = sorted(set(s["target_kinds"]) - caught)
                print(f"[{time.time() - started:6.0f} s] intruder seed {seed}: "
                      + ", ".join(f"{d['target']} captured {d['t'] - d['first_detected']:.1f} s after first detection"
                                  for d in s["destroyed"] if d["first_detected"] is not None)
                      + (f"; not captured: {', '.join(missed)}" if missed else ""), flush=True)

    print(f"\nmbzirc, detector {args.detector}, all 5 balloons destroyed (mission time, s; goal with 2 UAVs <= 90 s)")
    print("seed | 2 UAVs | 3 UAVs")
    for row in rows:
        cells = [f"{row[n]:.1f}" if row[n] is not None else "not all" for n in (2, 3)]
        print(f"{row['seed']:>4} | {cells[0]:>6} | {cells[1]:>6}")
    for n in (2, 3):
        done = [row[n] for row in rows if row[n] is not None]
        if done:
            print(f"{n} UAVs: {len(done)}/{len(rows)} seeds cleared, mean {statistics.mean(done):.1f} s, "
                  f"worst {max(done):.1f} s")
    wrong = sum(len(row.get("wrong", [])) for row in rows)
    print(f"attacks or interceptions at no target, all runs: {wrong} (goal 0: {'met' if wrong == 0 else 'NOT met'})")
    two = [row[2] for row in rows]
    if all(t is not None for t in two):
        print(f"2-UAV goal (<= {BALLOON_GOAL_S:g} s on every seed): {'met' if max(two) <= BALLOON_GOAL_S else 'NOT met'}")
    if intruders:
        worst = max(t for _, _, t in intruders)
        print(f"intruder captures: {len(intruders)}, worst {worst:.1f} s after first detection "
              f"(goal <= {INTRUDER_GOAL_S:g} s: {'met' if worst <= INTRUDER_GOAL_S else 'NOT met'})")
    print(f"wall time {time.time() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
