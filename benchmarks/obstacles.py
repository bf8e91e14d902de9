"""Flying clear of obstacles (issue 34): whole lockstep missions over every obstacle scenario, seeds
1-5, with 2 and with 3 UAVs (default detector), and per run the collisions, every UAV's clearance
(its body's closest approach to a static obstacle; a balloon's pole during that balloon's attack, up
to the UAV's being 1 m clear of it and no longer closing on it, apart), the balloons and when the
last went down, each drone's capture after its first detection, and the closest two flying UAVs
came.

Goals: 0 collisions; every clearance >= obstacle_margin (1.0 m), >= 0.3 m from a pole in its
attack; mbzirc's 5 balloons within 90 s on every seed with 2 UAVs; every drone captured within 60 s
of its first detection. A goal missed is listed at the end, run by run.

    .venv/bin/python benchmarks/obstacles.py                       # 7 scenarios x 5 seeds x 2 teams: ~3 h
    .venv/bin/python benchmarks/obstacles.py --scenarios street --seeds 1 2 --teams 2
    .venv/bin/python benchmarks/obstacles.py --json runs.json      # every run's figures too
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # mission.py beside this file

from mission import balloons_done, run  # noqa: E402

SCENARIOS = ("mbzirc", "intruder", "agile", "street", "forest", "unmapped", "mast")
MARGIN = 1.0  # m: the planner's obstacle_margin
POLE_IN_ATTACK = 0.3  # m
BALLOONS_WITHIN = 90.0  # s: mbzirc with 2 UAVs
CAPTURE_WITHIN = 60.0  # s after a drone's first detection


def figures(summary: dict) -> dict:
    """The run's figures for the table."""
    clearance = summary.get("clearance", {})
    lows = [(c["m"], name, c["to"], c["t"]) for name, c in clearance.items() if c and c.get("m") is not None]
    poles = [(c["attack_pole"]["m"], name, c["attack_pole"]["to"], c["attack_pole"]["t"])
             for name, c in clearance.items() if c and c.get("attack_pole")]
    drones = sorted(t for t, kind in summary["target_kinds"].items() if kind == "drone")
    caught = {d["target"]: d for d in summary["destroyed"]}
    captures = {d: (None if d not in caught else
                    "undetected" if caught[d]["first_detected"] is None else
                    round(caught[d]["t"] - caught[d]["first_detected"], 1)) for d in drones}
    for d in drones:  # a drone never captured: was it ever seen?
        if d not in caught:
            captures[d] = "seen, not captured" if d in summary.get("first_detected", {}) else "never seen"
    done, balloons, total = balloons_done(summary)
    separation = summary.get("min_separation")
    return {"outcome": summary.get("outcome", "?"), "collisions": summary.get("collisions", []),
            "clearance": min(lows) if lows else None, "attack_pole": min(poles) if poles else None,
            "balloons": (balloons, total, done), "captures": captures,
            "separation": None if separation is None else separation["m"],
            "handler_errors": (summary.get("health") or {}).get("handler_errors", -1),
            "started_without": summary.get("started_without", [])}


def failures(scenario: str, uavs: int, seed: int, f: dict) -> list[str]:
    where = f"{scenario} {uavs} UAVs seed {seed}"
    out = [f"{where}: {c['uav']} hit {c['with']} at t={c['t']:.1f} s" for c in f["collisions"]]
    if f["clearance"] is not None and f["clearance"][0] < MARGIN:
        m, uav, to, t = f["clearance"]
        out.append(f"{where}: {uav} {m:.2f} m from {to} at t={t:.1f} s")
    if f["attack_pole"] is not None and f["attack_pole"][0] < POLE_IN_ATTACK:
        m, uav, to, t = f["attack_pole"]
        out.append(f"{where}: {uav} {m:.2f} m from {to} in its attack at t={t:.1f} s")
    balloons, total, done = f["balloons"]
    if scenario == "mbzirc" and uavs == 2 and (done is None or done > BALLOONS_WITHIN):
        out.append(f"{where}: {balloons}/{total} balloons" + ("" if done is None else f", the last at {done:.1f} s"))
    for drone, took in f["captures"].items():
        if not isinstance(took, float) or took > CAPTURE_WITHIN:
            out.append(f"{where}: {drone} " + (f"captured {took:.1f} s after its first detection"
                                              if isinstance(took, float) else str(took or "not captured")))
    if f.get("started_without"):
        out.append(f"{where}: started without {', '.join(f['started_without'])} (start-up timed out under load)")
    if f["outcome"] != "finished" or f["handler_errors"]:
        out.append(f"{where}: outcome {f['outcome']}, {f['handler_errors']} handler errors")
    return out


def row(scenario: str, uavs: int, seed: int, f: dict) -> str:
    clearance = "-" if f["clearance"] is None else f"{f['clearance'][0]:.2f} {f['clearance'][2]}"
    pole = "-" if f["attack_pole"] is None else f"{f['attack_pole'][0]:.2f}"
    balloons, total, done = f["balloons"]
    balloon = "-" if not total else f"{balloons}/{total}" + ("" if done is None else f" {done:.0f}s")
    drones = ", ".join(f"{d} {took:.1f}s" if isinstance(took, float) else f"{d} {took}"
                       for d, took in f["captures"].items()) or "-"
    separation = "-" if f["separation"] is None else f"{f['separation']:.1f}"
    return (f"| {scenario} | {uavs} | {seed} | {len(f['collisions'])} | {clearance} | {pole} | {balloon} | {drones} "
            f"| {separation} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), help=f"default: {' '.join(SCENARIOS)}")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="default 1-5")
    parser.add_argument("--teams", type=int, nargs="+", choices=[2, 3], default=[2, 3], help="default 2 3")
    parser.add_argument("--duration", type=float, default=120.0, help="mission time per run, s (default 120)")
    parser.add_argument("--json", type=Path, help="write every run's figures here")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="keep each run's summary (SCENARIO-UAVS-SEED.json) and services' log (.log) here, "
                             "to read why a goal was missed")
    args = parser.parse_args()
    started = time.time()
    lines, missed, runs = [], [], []
    print("| scenario | UAVs | seed | collisions | clearance m (to) | pole in attack m | balloons (last) "
          "| drones: capture after first detection | min separation m |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |", flush=True)
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.keep or Path(tmp)
        for scenario in args.scenarios:
            for uavs in args.teams:
                for seed in args.seeds:
                    log = ("--log-file", str(workdir / f"{scenario}-{uavs}-{seed}.log")) if args.keep else ()
                    f = figures(run(scenario, uavs, seed, args.duration, workdir, "onboard", log))
                    runs.append({"scenario": scenario, "uavs": uavs, "seed": seed, **f})
                    lines.append(row(scenario, uavs, seed, f))
                    missed += failures(scenario, uavs, seed, f)
                    print(lines[-1] + f"  [{time.time() - started:.0f} s]", flush=True)
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1))
    print(f"\n{len(runs)} runs, {sum(len(r['collisions']) for r in runs)} collisions; goals missed: "
          + ("none" if not missed else str(len(missed))))
    for line in missed:
        print(f"  {line}")
    print(f"wall time {time.time() - started:.0f} s")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
