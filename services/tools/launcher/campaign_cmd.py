"""`falconry campaign`: many seeded lockstep runs, each with a random fault, and one table of how
the team coped (separation kept, collisions, clearance to obstacles, targets destroyed, emergency
landings, restarts, errors)."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from services.simulator.scenario import load_scenario, scenario_path
from services.tools.launcher import netns
from services.tools.launcher.campaign import HEADER, KINDS, RunPlan, RunResult, draw_runs, row, totals
from services.tools.launcher.common import CliError

RUN_TIMEOUT_S = 900.0


def add_parser(commands) -> None:
    p = commands.add_parser(
        "campaign", help="fly many seeded runs with random faults and tabulate how the team coped",
        description="Draw N fault schedules from a seed (kind, time, UAV, duration: one fault per run by default, "
                    f"kinds {', '.join(KINDS)}), fly each as a lockstep `falconry sim` on 2- and 3-UAV teams in "
                    "turn, and print one line per run and a table: faults, minimum separation of flying UAVs, "
                    "separation violations, collisions (a UAV's body touching an obstacle, a partner or the "
                    "ground outside a landing), the smallest clearance of a UAV's body to an obstacle (the pole "
                    "of a balloon it attacks apart), engagements at no target, geofence breaches, targets destroyed, emergency landings, restarts, handler "
                    "errors, undecodable payloads, own-UAV messages not received by services that ran throughout "
                    "(what a killed or frozen service missed while gone follows wall time; each run's summary has "
                    "it). Unless told otherwise every run flies the oracle detector (--detector), not `falconry "
                    "sim`'s onboard perception, and an os0-32-512 LiDAR on every UAV (--lidar), not the scenario's "
                    "own: the table is about the faults, not the perception. link_cut needs per-UAV network namespaces, so root and iproute2: without "
                    "them it is left out of the kinds (one line says so) and every run's draw changes. The same "
                    "command gives the same table when run as root both times, or as root neither time. "
                    "Exit status 1 when a run did not finish, broke the safety distance, had a collision, "
                    "engaged no target, left the arena or had a handler error.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--runs", type=int, default=20, help="how many runs")
    p.add_argument("--seed", type=int, default=1, help="the campaign's seed (each run's schedule and seed follow)")
    p.add_argument("--scenarios", "--scenario", dest="scenarios", default="mbzirc",
                   help="scenario names or TOML files (comma-separated) the faults are added to, taken in turn")
    p.add_argument("--duration", type=float, default=90.0, help="mission time of each run, s")
    p.add_argument("--teams", default="2,3", help="team sizes taken in turn, e.g. 2,3 or 3")
    p.add_argument("--faults-per-run", type=int, default=1)
    p.add_argument("--kinds", default=",".join(KINDS), help="fault kinds to draw from (comma-separated)")
    p.add_argument("--detector", default="oracle", choices=["oracle", "classifier", "onboard"],
                   help="detector of every run (the oracle keeps a campaign about the faults, and quick; a "
                        "LiDAR fault's effect on perception shows only with the classifier or onboard)")
    p.add_argument("--lidar", default="os0-32-512", metavar="MODEL",
                   help="LiDAR model of every UAV ('' = the scenario's own); a light one keeps runs quick")
    p.add_argument("--plot", metavar="DIR", help="draw each scenario's arena from above with where every run's "
                                                 "attacks and interceptions aimed (at a target or at none) and where "
                                                 "UAVs broke the safety distance: DIR/<scenario>.png")
    p.add_argument("--out", metavar="DIR", help="keep each run's scenario, summary, log and its services' log "
                                                "lines here (default: a temporary directory, removed afterwards)")
    p.set_defaults(handler=run_campaign)


def _options(args: argparse.Namespace) -> tuple[tuple[int, ...], tuple[str, ...]]:
    try:
        teams = tuple(int(t) for t in args.teams.split(","))
    except ValueError:
        raise CliError(f"--teams: comma-separated team sizes, e.g. 2,3 (got {args.teams!r})") from None
    if not teams or any(t not in (2, 3) for t in teams):
        raise CliError(f"--teams: sizes of 2 or 3 UAVs (got {args.teams!r})")
    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds:
        raise CliError(f"--kinds: unknown {', '.join(unknown) or 'nothing given'} (choose from {', '.join(KINDS)})")
    if "link_cut" in kinds and (why := netns.available()):
        print(f"campaign: leaving link_cut out: it needs per-UAV network namespaces, but {why}", flush=True)
        kinds = tuple(k for k in kinds if k != "link_cut")
    if args.runs < 1 or args.faults_per_run < 1:
        raise CliError("--runs and --faults-per-run must be at least 1")
    return teams, kinds


def run_campaign(args: argparse.Namespace) -> int:
    teams, kinds = _options(args)
    names = tuple(s.strip() for s in args.scenarios.split(",") if s.strip())
    if not names:
        raise CliError("--scenarios: at least one scenario name or TOML file")
    if args.plot and Path(args.plot).suffix:
        raise CliError(f"--plot: a directory for one PNG per scenario, not a file ({args.plot})")
    try:
        scenarios = {name: load_scenario(name) for name in names}  # a bad scenario is one error now, not one per run
        bases = {name: scenario_path(name).read_text() for name in names}
        plans = draw_runs(args.runs, args.seed, args.duration, teams, args.faults_per_run, kinds, names)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    with tempfile.TemporaryDirectory(prefix="falconry-campaign-") as scratch:
        out = Path(args.out) if args.out else Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        config = out / "campaign.toml"
        config.write_text(f'[sensor_driver]\nmodel = "{args.lidar}"\n' if args.lidar else "")
        print(f"campaign: {len(plans)} runs of {args.duration:g} s over {', '.join(names)}, seed {args.seed}, detector "
              f"{args.detector}" + (f", LiDAR {args.lidar}" if args.lidar else ""), flush=True)
        results, summaries, safety = [], [], None
        for plan in plans:
            started = time.monotonic()
            result, summary = _fly(plan, bases[plan.scenario], config, args, out)
            wall = time.monotonic() - started
            safety = summary.get("safety_distance", safety)
            results.append(result)
            summaries.append(summary)
            print(f"[{plan.index}/{len(plans)}] " + row(result) + f" (wall {wall:.0f} s)", flush=True)
    print("\n" + HEADER)
    for result in results:
        print(row(result))
    print("\n".join(totals(results, safety or 0.0)))
    if args.plot:
        from services.tools.launcher.plot import plot_arena  # matplotlib only when a picture is asked for
        Path(args.plot).mkdir(parents=True, exist_ok=True)
        for name, scenario in scenarios.items():
            path = Path(args.plot) / f"{Path(name).stem}.png"
            runs = [(r, s) for r, s in zip(results, summaries) if r.plan.scenario == name]
            plot_arena(scenario, [s for _, s in runs], path, f"{scenario.name}: {len(runs)} runs of campaign seed {args.seed}")
            print(f"arena picture: {path}")
    return 0 if all(r.ok for r in results) else 1


def _fly(plan: RunPlan, base: str, config: Path, args: argparse.Namespace, out: Path) -> tuple[RunResult, dict]:
    stem = out / f"run{plan.index:03d}"
    scenario = stem.with_suffix(".toml")
    scenario.write_text(base + "\n" + "\n".join(f.toml() for f in plan.faults))
    summary_path = stem.with_suffix(".json")
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", str(scenario), "--uavs", str(plan.uavs), "--lockstep",
            "--seed", str(plan.seed), "--duration", f"{args.duration:g}", "--detector", args.detector, "--quiet",
            "--progress", "0", "--summary-json", str(summary_path), "--config", str(config), "--lease-ms", "1000",
            "--log-file", str(stem.with_suffix(".services.log"))]  # what a hung or failed run's services said
    with open(stem.with_suffix(".log"), "w") as log:
        try:
            code = subprocess.run(argv, stdout=log, stderr=subprocess.STDOUT, timeout=RUN_TIMEOUT_S).returncode
        except subprocess.TimeoutExpired:
            code = None
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    if code != 0 or not summary:
        summary.setdefault("outcome", "timed out" if code is None else f"exit {code}")
        if summary.get("outcome") == "finished":
            summary["outcome"] = f"finished, exit {code}"
    return RunResult.from_summary(plan, summary), summary
