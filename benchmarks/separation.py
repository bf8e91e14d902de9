"""Never too close, never at nothing (issue 35): whole lockstep missions, seeds 1-5, with 2 and with 3
UAVs (default detector), and per run the closest two flying UAVs came and every episode closer than
the job manager's safety distance, collisions, engagements aimed at no target, geofence breaches
(a UAV out of the arena or above its ceiling), targets destroyed or captured, and when the last went
down.

Goals: separation >= the safety distance (5 m) in every run; 0 engagements at no target; 0 geofence
breaches; 0 collisions. A goal missed is listed at the end, run by run.

    .venv/bin/python benchmarks/separation.py                     # 4 scenarios x 5 seeds x 2 teams: ~2 h
    .venv/bin/python benchmarks/separation.py --scenarios agile benchmarks/arenas/squeeze.toml --teams 3
    .venv/bin/python benchmarks/separation.py --json runs.json --keep DIR   # figures, summaries and logs
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # mission.py beside this file

from mission import run, wrong_engagements  # noqa: E402

SCENARIOS = ("mbzirc", "intruder", "agile", str(Path(__file__).resolve().parent / "arenas" / "squeeze.toml"))


def figures(summary: dict) -> dict:
    """The run's figures for the table."""
    separation = summary.get("min_separation")
    last = max((d["t"] for d in summary.get("destroyed", [])), default=None)
    return {
        "min_separation": None if separation is None else separation["m"],
        "pair": None if separation is None else f"{separation['pair']} t={separation['t']:.1f} s",
        "safety_distance": summary.get("safety_distance"),
        "violations": summary.get("separation_violations", []),
        "collisions": [f"t={c['t']:.1f} s {c['uav']} hit {c['detail']}" for c in summary.get("collisions", [])],
        "no_target": wrong_engagements(summary),
        "geofence": [f"t={b['start']:.1f} s {b['uav']} {b['m']:.1f} m out" for b in summary.get("geofence_breaches", [])],
        "destroyed": len(summary.get("destroyed", [])),
        "targets": summary.get("targets", 0),
        "last_down": last,
        "emergency_landings": sum("EMERGENCY_LANDING" in [s for _, s in u.get("states", [])]
                                  for u in summary.get("uavs", {}).values()),
        "outcome": summary.get("outcome", "?"),
        "started_without": summary.get("started_without", []),
    }


def failures(where: str, f: dict) -> list[str]:
    missed = []
    if f["violations"]:
        missed.append(f"{where}: safety distance broken {len(f['violations'])} time(s), closest {f['min_separation']} m "
                      f"({f['pair']})")
    missed += [f"{where}: collision {c}" for c in f["collisions"]]
    missed += [f"{where}: engagement at no target, {e}" for e in f["no_target"]]
    missed += [f"{where}: geofence breach {g}" for g in f["geofence"]]
    if f["outcome"] != "finished":
        missed.append(f"{where}: {f['outcome']}")
    if f["started_without"]:  # a loaded machine's start-up wait ran out: not the seed's mission
        missed.append(f"{where}: started without {', '.join(f['started_without'])}")
    return missed


def row(scenario: str, uavs: int, seed: int, f: dict) -> str:
    separation = "-" if f["min_separation"] is None else f"{f['min_separation']:.1f}"
    last = "-" if f["last_down"] is None else f"{f['last_down']:.1f}"
    return (f"| {scenario} | {uavs} | {seed} | {separation} | {len(f['violations'])} | {len(f['collisions'])} | "
            f"{len(f['no_target'])} | {len(f['geofence'])} | {f['destroyed']}/{f['targets']} ({last}) | "
            f"{f['emergency_landings']} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), help="names or TOML files "
                        "(default: mbzirc intruder agile benchmarks/arenas/squeeze.toml)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="default 1-5")
    parser.add_argument("--teams", type=int, nargs="+", choices=[2, 3], default=[2, 3], help="default 2 3")
    parser.add_argument("--duration", type=float, default=120.0, help="mission time per run, s (default 120)")
    parser.add_argument("--json", type=Path, help="write every run's figures here")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="keep each run's summary and services' log here")
    args = parser.parse_args()
    header = ("| scenario | UAVs | seed | closest m | < 5 m | collisions | at no target | geofence | "
              "targets (last down, s) | e-landings |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print(header, flush=True)
    lines, runs, missed = [], [], []
    with tempfile.TemporaryDirectory(prefix="falconry-separation-") as scratch:
        workdir = Path(scratch)
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
        for scenario in args.scenarios:
            name = Path(scenario).stem
            for uavs in args.teams:
                for seed in args.seeds:
                    started = time.monotonic()
                    log = ("--log-file", str(workdir / f"{name}-{uavs}-{seed}.log")) if args.keep else ()
                    f = figures(run(scenario, uavs, seed, args.duration, workdir, "onboard", log))
                    runs.append({"scenario": name, "uavs": uavs, "seed": seed, **f})
                    lines.append(row(name, uavs, seed, f))
                    missed += failures(f"{name} {uavs} UAVs seed {seed}", f)
                    print(lines[-1] + f"  ({time.monotonic() - started:.0f} s wall)", flush=True)
                    if args.keep:
                        for path in workdir.glob(f"{name}-{uavs}-{seed}.*"):
                            shutil.copy(path, args.keep / f"{name}-{uavs}-{seed}{path.suffix}")
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1))
    print("\n" + header)
    print("\n".join(lines))
    print(f"\ngoals missed: {len(missed)}" + "".join(f"\n  {m}" for m in missed))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
