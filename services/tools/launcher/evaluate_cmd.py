"""`falconry evaluate`: a recorded simulated run scored against its ground truth.

`falconry evaluate tracking RUN.mcap`: each UAV's confirmed tracks against the true targets, beside
its raw detections (services/tools/evaluation/tracking.py, which defines every figure).
`falconry evaluate localization RUN.mcap`: each UAV's pose estimate against its true pose, beside
KISS-ICP over its scans (services/tools/evaluation/localization.py, which defines every figure;
services/tools/evaluation/localization_input.py reads the recording).
`falconry evaluate ages RUN.mcap`: how old the sensor data was as it left each stage, as a run's
summary says it (services/tools/evaluation/__init__.py PipelineAges), from the recording's receive times. An
evaluation is a subcommand of the group: `add_parser` lists them.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import typing
from pathlib import Path

import msgspec

from schemas import keys
from schemas.messages import SimClock, TargetTruth
from services.tools.evaluation.localization import MAX_DIFF_S, LocalizationScore
from services.tools.evaluation.tracking import (CUTOFF, NS, ORDER, TRACKED_KINDS, TRACKER_SILENCE_NS, Alike, DetectionScore,
                                          MatchErrors, TrackingScore, alike, fleet, fleet_alike, fleet_detections,
                                          score_detections, score_tracks)
from services.tools.launcher.common import CliError
from services.tools.launcher.monitor import RunMonitor
from services.tools.launcher.sim_cmd import data_age_lines
from services.tools.evaluation.localization_input import PROGRESS_EVERY, LocalizationEvaluation, evaluate_localization
from services.tools.recorder.mcap_io import check_recording, read_recording
from services.tools.evaluation.tracking_input import TRACKS, TrackingInput, read_tracking_input

TARGET_KINDS = next(typing.get_args(f.type) for f in msgspec.structs.fields(TargetTruth) if f.name == "kind")

TRACKING_DESCRIPTION = f"""\
Score each UAV's tracker in a recording of a simulated run (`falconry sim ... --record RUN.mcap`)
against the ground truth it holds, beside the detections it was given. One step per truth tick
(falconry/sim/truth): the UAV's confirmed tracks then (falconry/<uav>/tracks) against the truth, the
ones its own tracker keeps (fused with a partner's where both see a target): the fleet tracks it only
passes on from partners are scored under the partner that keeps them.

Which targets count in a step: standing (not destroyed), of the --kinds the tracker follows (default
drones: the LiDAR perception takes a balloon on its pole for background), within the UAV's LiDAR range
(its model's datasheet range) of the UAV's true position; occlusion is not judged. A track following a
standing target that does not count (closer than C to it, and than to any target that counts) is left
out: neither matched nor false.

GOSPA (alpha = 2, Rahmathullah, Garcia-Fernandez, Svensson 2017), per step, over the best assignment
of tracks to targets, only pairs closer than C assigned:
  GOSPA^P = localisation + missed + false, in m^P:
  localisation = sum of d^P over the assigned pairs; missed = C^P/2 per target left unassigned;
  false = C^P/2 per track left unassigned. Means over the steps are printed.
Matched: a pair the GOSPA assignment makes; its error counts in the RMSE per axis and in 3D.
Identity switch: a target matched to another track than at the last step it was matched.
Fragmentation: a target matched again after a step in which it counted and was unmatched.
Track ids per target: distinct tracks ever matched to it. False track: a confirmed track never matched.
The fleet line pools every UAV's steps (a target two UAVs follow counts for each).

Steps: the tracker sends a Tracks message every tick while it holds any track (tentative included),
one a second otherwise; so at a truth tick without a message of that stamp the UAV held no track,
unless its latest message is more than {TRACKER_SILENCE_NS / NS:g} s old: then the tracker was
silent (not started, stopped, crashed) and the tick is skipped ("tracker silent"). This takes the
tracker to tick with the simulator, as in a lockstep run: a tick a lagging tracker skipped reads as
no tracks. A Tracks message at a stamp without a truth is no step.

Detection baseline: each Detections message (falconry/<uav>/detections, one per LiDAR scan, 10 Hz)
against the same targets that count at its stamp, by the same rules: detections following a target
that does not count are left out, the rest matched by the same GOSPA assignment (one-to-one, pairs
closer than C). For detections and tracks alike: mean err and RMSE = mean and root mean square 3-D
error of the matched; recall = share of (counted target, step) pairs with a match. Each stream's
figures are over its own steps: detections per scan (10 Hz), tracks per truth tick (20 Hz); a recall
is then a share of time for both, so "tracks' recall at least the detections'" reads straight off the
comparison table. Its errors do not compare as plainly: a track's include the ticks it coasts between
scans and through missed ones. The last table sets them like for like: over the (scan, target) pairs
that both a detection and a confirmed track matched, each one's mean err and RMSE, so "tracks' mean
err below the detections'" reads off it. The comparison's last column is the recall of every track a
UAV publishes as its own, tentative ones too: what its tracking would give without the wait for
confirmation (a target is confirmed at its third detection, or when a partner's confirmed track
corroborates it); the gap to the confirmed tracks' recall is mostly that wait, plus any tentative
track near a target that was never confirmed."""


def add_parser(commands) -> None:
    p = commands.add_parser("evaluate", help="score a recorded simulated run against its ground truth: tracking, "
                                             "localization; the age of its data at each stage",
                            description="Evaluations of a recording against the ground truth it holds. "
                                        "`falconry evaluate tracking --help`, `falconry evaluate localization "
                                        "--help`, `falconry evaluate ages --help`.")
    evaluations = p.add_subparsers(dest="evaluation", metavar="EVALUATION", required=True)
    add_tracking_parser(evaluations)
    add_localization_parser(evaluations)
    add_ages_parser(evaluations)


def add_tracking_parser(evaluations) -> None:
    t = evaluations.add_parser(
        "tracking", help="each UAV's tracks against the true targets: GOSPA, RMSE, identity switches, "
                         "fragmentations, false tracks; its detections beside them", description=TRACKING_DESCRIPTION)
    t.add_argument("recording", metavar="RECORDING.mcap",
                   help="an MCAP recording of a simulated run, which holds the ground truth")
    t.add_argument("--cutoff", type=float, default=CUTOFF, metavar="C",
                   help=f"GOSPA cut-off, m: pairs at C or farther are not assigned (default {CUTOFF:g}, the "
                        "tracker's smallest association gate)")
    t.add_argument("--order", type=float, default=ORDER, metavar="P",
                   help=f"GOSPA order p >= 1 (default {ORDER:g}: localisation as squared errors, like the RMSE)")
    t.add_argument("--uav", metavar="UAV", help="only this UAV (default: every UAV with tracks)")
    t.add_argument("--kinds", default=",".join(TRACKED_KINDS), metavar="KIND,...",
                   help=f"the target kinds that count: {', '.join(TARGET_KINDS)} (default "
                        f"{','.join(TRACKED_KINDS)})")
    t.add_argument("--json", action="store_true", help="print the figures as JSON instead of tables")
    t.set_defaults(handler=run_tracking)


def parse_kinds(text: str) -> tuple[str, ...]:
    kinds = tuple(dict.fromkeys(k.strip() for k in text.split(",") if k.strip()))
    unknown = [k for k in kinds if k not in TARGET_KINDS]
    if not kinds or unknown:
        raise CliError(f"--kinds takes {' or '.join(TARGET_KINDS)}, comma-separated, not {text!r}")
    return kinds


def check_options(args: argparse.Namespace) -> tuple[str, ...]:
    """The kinds that count, once the recording and every number are checked."""
    check_recording(Path(args.recording))
    if not (math.isfinite(args.cutoff) and args.cutoff > 0):
        raise CliError(f"--cutoff must be a positive distance in m, not {args.cutoff:g}")
    if not (math.isfinite(args.order) and args.order >= 1):
        raise CliError(f"--order must be 1 or more, not {args.order:g}")
    return parse_kinds(args.kinds)


def uavs_to_score(path: Path, run: TrackingInput, uav: str | None) -> list[str]:
    if not len(run.truth):
        raise CliError(f"{path} holds no ground truth ({keys.TRUTH}): record a simulated run, "
                       "e.g. `falconry sim SCENARIO --record FILE.mcap`")
    if not run.tracks:
        raise CliError(f"{path} holds no tracks ({TRACKS}): was the tracker running?")
    if uav is not None and uav not in run.tracks:
        raise CliError(f"{path} holds no tracks of {uav} (it has those of {', '.join(sorted(run.tracks))})")
    return [uav] if uav is not None else sorted(run.tracks)


def run_tracking(args: argparse.Namespace) -> int:
    kinds, path = check_options(args), Path(args.recording)
    run = read_tracking_input(str(path))
    ranges = {uav: run.sensor_range(uav) for uav in uavs_to_score(path, run, args.uav)}
    reach = {uav: math.inf if r is None else r for uav, r in ranges.items()}
    scores = {uav: score_tracks(run.tracks[uav], run.truth, uav, reach[uav], kinds, args.cutoff, args.order)
              for uav in ranges}
    baseline = {uav: score_detections(run.detections.get(uav, []), run.truth, uav, reach[uav], kinds, args.cutoff,
                                      args.order) for uav in ranges}
    fleet_score, fleet_baseline = fleet(scores), fleet_detections(baseline)
    kept = {uav: score_tracks(run.kept_tracks.get(uav, []), run.truth, uav, reach[uav], kinds, args.cutoff, args.order)
            for uav in ranges}
    kept["fleet"] = fleet(kept)
    alikes = {uav: alike(run.tracks[uav], run.truth, uav, baseline[uav], reach[uav], kinds, args.cutoff, args.order)
              for uav in ranges}
    alikes["fleet"] = fleet_alike(alikes)
    if args.json:
        print(json.dumps({
            "recording": str(path), "complete": run.report.complete, "cutoff_m": args.cutoff, "order": args.order,
            "kinds": list(kinds), "sensor_range_m": ranges, "tracker_silence_s": TRACKER_SILENCE_NS / NS,
            "undecodable": run.undecodable,
            "uavs": {uav: score.summary() for uav, score in scores.items()},
            "fleet": fleet_score.summary(),
            "detections": {"uavs": {uav: score.summary() for uav, score in baseline.items()},
                           "fleet": fleet_baseline.summary()},
            "comparison": comparison(scores, baseline, fleet_score, fleet_baseline, kept),
            "alike": {name: a.summary() for name, a in alikes.items()}}, indent=2))
    else:
        print("\n".join(report_lines(path, run, kinds, ranges, args.cutoff, args.order, scores, fleet_score)
                        + ["", *comparison_lines(scores, baseline, fleet_score, fleet_baseline, kept),
                           "", *alike_lines(alikes, len(scores) > 1)]))
    return 0


def alike_lines(alikes: dict[str, Alike], with_fleet: bool) -> list[str]:
    """Detections against tracks over the same (scan, target) pairs: what tracking does to the
    position it is given (services/tools/evaluation/tracking.py, `alike`)."""
    lines = ["like for like: the (scan, target) pairs both a detection and a confirmed track matched",
             f"{'UAV':<6} {'pairs':>6} {'detections mean err':>20} {'RMSE':>7} | {'tracks mean err':>16} {'RMSE':>7}"]
    for name, a in alikes.items():
        if name == "fleet" and not with_fleet:
            continue
        summary = a.summary()
        cells = [_number(summary[side][figure]) for side in ("detections", "tracks")
                 for figure in ("mean_error_m", "rmse_3d_m")]
        lines.append(f"{name:<6} {a.tracks.matched:>6} {cells[0]:>20} {cells[1]:>7} | {cells[2]:>16} {cells[3]:>7}")
    return lines


def _number(value: float | None, digits: int = 3) -> str:
    """A figure of a table, "-" where there is none."""
    return "-" if value is None else f"{value:.{digits}f}"


def comparison(scores: dict[str, TrackingScore], baseline: dict[str, DetectionScore], fleet_score: TrackingScore,
               fleet_baseline: DetectionScore, kept: dict[str, TrackingScore]) -> dict:
    """Per UAV and for the fleet, the comparison table's figures: detections' against tracks'; and
    the recall of every track kept, tentative ones too (`kept`, by UAV and "fleet")."""
    sides = {**{uav: (baseline[uav], scores[uav]) for uav in scores}, "fleet": (fleet_baseline, fleet_score)}
    return {name: {"detections": compared(d.steps, d.errors), "tracks": compared(t.sums.steps, t.errors),
                   "kept_tracks": kept_recall(kept[name])}
            for name, (d, t) in sides.items()}


def kept_recall(kept: TrackingScore) -> dict:
    """The --json figures of every track kept, tentative ones too: steps, pairs and recall."""
    s = kept.errors.summary()
    return {"steps": kept.sums.steps, "matched_pairs": s["matched_pairs"],
            "counted_truth_steps": s["counted_truth_steps"], "recall": s["recall"]}


def compared(steps: int, errors: MatchErrors) -> dict:
    s = errors.summary()
    return {"steps": steps, "mean_error_m": s["mean_error_m"],
            "rmse_3d_m": None if s["rmse_m"] is None else s["rmse_m"]["3d"], "recall": s["recall"]}


# ----------------------------------------------------------------------------- the tables
def report_lines(path: Path, run: TrackingInput, kinds: tuple[str, ...], ranges: dict[str, float | None], c: float,
                 p: float, scores: dict[str, TrackingScore], fleet_score: TrackingScore) -> list[str]:
    lines = [f"tracking against ground truth: {path}",
             f"GOSPA c = {c:g} m, p = {p:g} (parts in m^{p:g}, a missed target or false track costs "
             f"c^p/2 = {c ** p / 2:.3g}); counted: standing {' and '.join(k + 's' for k in kinds)} within "
             f"each UAV's LiDAR range"]
    if not run.report.complete:
        lines.append(f"warning: {run.report.describe(str(path))}")
    lines += [f"warning: {count} undecodable payloads on {key} skipped" for key, count in sorted(run.undecodable.items())]
    for uav, reach in ranges.items():
        if reach is None:
            lines.append(f"note: the recording names no LiDAR model of {uav}: every standing target counts")
        if scores[uav].without_truth:
            lines.append(f"note: {scores[uav].without_truth} Tracks messages of {uav} have no truth at their "
                         "stamp and are left out")
        if scores[uav].silent:
            lines.append(f"note: the tracker of {uav} was silent (no Tracks message for over "
                         f"{TRACKER_SILENCE_NS / NS:g} s) at {scores[uav].silent} truth ticks: not steps")
        if not run.detections.get(uav):
            lines.append(f"note: the recording holds no detections of {uav} ({keys.uav(uav, 'detections')}): "
                         "no baseline")
    lines += ["", *uav_table(scores, fleet_score if len(scores) > 1 else None), "", *target_table(scores)]
    return lines


UAV_COLUMNS = (("UAV", "{:<6}"), ("steps", "{:>6}"), ("pairs", "{:>6}"), ("RMSE x", "{:>7}"), ("y", "{:>6}"),
               ("z", "{:>6}"), ("3D m", "{:>6}"), ("GOSPA m", "{:>8}"), ("loc", "{:>7}"), ("missed", "{:>7}"),
               ("false", "{:>7}"), ("switches", "{:>9}"), ("fragments", "{:>10}"), ("false tracks", "{:>13}"))


def uav_table(scores: dict[str, TrackingScore], fleet_score: TrackingScore | None) -> list[str]:
    rows = [[uav, *uav_row(score)] for uav, score in scores.items()]
    if fleet_score is not None:
        rows.append(["fleet", *uav_row(fleet_score)])
    return [_row([name for name, _ in UAV_COLUMNS])] + [_row(row) for row in rows]


def uav_row(score: TrackingScore) -> list:
    s = score.summary()
    rmse = s["rmse_m"]
    errors = ["-"] * 4 if rmse is None else [f"{rmse[axis]:.3f}" for axis in ("x", "y", "z", "3d")]
    return [s["steps"], s["matched_pairs"], *errors, f"{s['gospa_m']:.3f}", f"{s['localisation']:.3f}",
            f"{s['missed']:.3f}", f"{s['false']:.3f}", s["identity_switches"], s["fragmentations"],
            f"{s['false_tracks']} of {s['confirmed_tracks']}"]


def _row(cells: list) -> str:
    return " ".join(fmt.format(str(cell)) for cell, (_, fmt) in zip(cells, UAV_COLUMNS)).rstrip()


def target_table(scores: dict[str, TrackingScore]) -> list[str]:
    lines = [f"{'UAV':<6} {'target':<12} {'counted':>8} {'tracked':>8} {'track ids':>10} {'switches':>9} "
             f"{'fragments':>10}"]
    for uav, score in scores.items():
        for tid, t in score.summary()["targets"].items():
            lines.append(f"{uav:<6} {tid:<12} {t['counted_steps']:>8} {t['tracked_steps']:>8} "
                         f"{len(t['track_ids']):>10} {t['identity_switches']:>9} {t['fragmentations']:>10}")
    if len(lines) == 1:
        lines.append("(no target counted in any step)")
    return lines


COMPARISON_COLUMNS = (("UAV", "{:<6}"), ("scans", "{:>6}"), ("mean err", "{:>9}"), ("RMSE", "{:>7}"),
                      ("recall", "{:>7}"), ("|", "{}"), ("ticks", "{:>6}"), ("mean err", "{:>9}"), ("RMSE", "{:>7}"),
                      ("recall", "{:>7}"), ("|", "{}"), ("recall", "{:>7}"))


def comparison_lines(scores: dict[str, TrackingScore], baseline: dict[str, DetectionScore],
                     fleet_score: TrackingScore, fleet_baseline: DetectionScore,
                     kept: dict[str, TrackingScore]) -> list[str]:
    """Detections against tracks, per UAV (and the fleet), each over its own steps: mean and RMSE 3-D
    error of the matched, m, and recall; last, the recall of every track kept, tentative ones too."""
    detectors = ", ".join(sorted(fleet_baseline.detectors)) or "none recorded"
    rows = [[uav, *comparison_row(baseline[uav], scores[uav], kept[uav])] for uav in scores]
    if len(scores) > 1:
        rows.append(["fleet", *comparison_row(fleet_baseline, fleet_score, kept["fleet"])])
    header = _comparison_row([name for name, _ in COMPARISON_COLUMNS])
    bar, last_bar = header.index("|"), header.rindex("|")
    return [f"detections ({detectors}) against confirmed tracks, matched alike; each over its own steps",
            f"{'':<7}{'detections, per scan':<{bar - 7}}| {'tracks, per truth tick':<{last_bar - bar - 2}}"
            "| with tentative", header, *(_comparison_row(row) for row in rows)]


def comparison_row(detections: DetectionScore, tracks: TrackingScore, kept: TrackingScore) -> list:
    return [detections.steps, *_figures(detections.errors), "|", tracks.sums.steps, *_figures(tracks.errors),
            "|", _number(kept.errors.recall())]


def _figures(errors: MatchErrors) -> list[str]:
    mean, rmse, recall = errors.mean_error(), errors.rmse(), errors.recall()
    return [_number(mean), _number(None if rmse is None else rmse["3d"]), _number(recall)]


def _comparison_row(cells: list) -> str:
    return " ".join(fmt.format(str(cell)) for cell, (_, fmt) in zip(cells, COMPARISON_COLUMNS)).rstrip()


# ============================================================================= localization
LOCALIZATION_DESCRIPTION = f"""\
Score each UAV's pose estimate in a recording of a simulated run (`falconry sim ... --record RUN.mcap`)
against its true pose (falconry/sim/truth: the body's position and heading at every tick), seed 003's
Table 2 (Grape, LiDAR-inertial SLAM) and the absolute trajectory error, beside a baseline: KISS-ICP
(Vizzo et al. 2023) over the UAV's own LiDAR scans. One row per UAV and estimate:
  falconry  the recorded estimate: the localizer's (falconry/<uav>/localization, source "localization");
            a UAV without one is scored on the simulator's GNSS odometry (falconry/<uav>/odometry, source
            "odometry", said in a note), so every recording can be evaluated.
  kiss-icp  KISS-ICP over the UAV's scans (falconry/<uav>/points, source "points") in the sensor frame,
            deskew off, ranges from the scans; anchored like the localizer at the true pose, at the
            first scan of the falconry row's window, and turned from the LiDAR's poses into the body's
            through the LiDAR mount measured at the first scan. The slow part: --no-baseline skips it
            (progress on stderr every {PROGRESS_EVERY} scans).

Each estimated pose is paired with the truth at its stamp (interpolated between ticks; a pose without a
truth tick within {MAX_DIFF_S:g} s is left out). Window: from the estimate's first pose to its last (its
drift on the ground before take-off counts); the kiss-icp row covers the falconry row's window;
--airborne narrows both to the time the UAV was airborne. Figures:
  poses       the matched poses; from s, to s: the window, mission time
  distance m  length of the TRUE path over the window
  pos err m   start-end position error |(e1 - e0) - (t1 - t0)|, e the estimated and t the true position
              at the window's first (0) and last (1) pose: where the estimate ends relative to where it
              started, against the truth (seed 003 measured |e1 - e0| on loops that end where they start);
              %: of the distance travelled
  yaw turned  sum of |change of the true heading| between ticks, deg (seed 003 counted 45 deg steps)
  yaw err     the same start-end error on the yaw, wrapped to +-180 deg; %: of the yaw turned
  ATE m       RMSE of the 3-D distance between matched estimated and true positions (evo's APE,
              translation part); not aligned: the map frame is the start frame, so an offset is an error;
              --align first fits the estimate to the truth by the best rigid SE(3) transform (Umeyama)
  ms/scan     mean compute time of the baseline per scan, on this machine ("-" for the recording)
A percentage is "-" without distance (or turn); the ATE is "-" when --align cannot align (a path on one
line: a note says so). Definitions: services/tools/evaluation/localization.py."""


def add_localization_parser(evaluations) -> None:
    t = evaluations.add_parser(
        "localization", help="each UAV's pose estimate against its true pose: seed 003's Table 2 (start-end "
                             "position and yaw error over distance and yaw turned) and the ATE; KISS-ICP beside it",
        description=LOCALIZATION_DESCRIPTION)
    t.add_argument("recording", metavar="RECORDING.mcap",
                   help="an MCAP recording of a simulated run, which holds the ground truth")
    t.add_argument("--uav", action="append", metavar="UAV",
                   help="only this UAV (repeatable; default: every UAV with a truth and an estimate)")
    t.add_argument("--no-baseline", dest="baseline", action="store_false",
                   help="skip KISS-ICP (which registers every scan: minutes for a two-minute recording)")
    t.add_argument("--align", action="store_true",
                   help="align each estimate to the truth by the best rigid (SE(3), Umeyama) transform before "
                        "the ATE (default: none; the start-end errors never need it)")
    t.add_argument("--airborne", action="store_true",
                   help="score only from the UAV's first airborne truth to its last (default: the estimate's "
                        "whole time)")
    t.add_argument("--voxel", type=float, metavar="M",
                   help="KISS-ICP's voxel size, m (default: its own, a hundredth of the LiDAR's range)")
    t.add_argument("--json", action="store_true", help="print the figures as JSON instead of a table")
    t.set_defaults(handler=run_localization)


def run_localization(args: argparse.Namespace) -> int:
    path = Path(args.recording)
    check_recording(path)
    if args.voxel is not None and not (math.isfinite(args.voxel) and args.voxel > 0):
        raise CliError(f"--voxel must be a positive size in m, not {args.voxel:g}")
    evaluation = evaluate_localization(path, args.uav, baseline=args.baseline, align=args.align,
                                       airborne=args.airborne, voxel_size=args.voxel, progress=_progress)
    if args.json:
        print(json.dumps(evaluation.summary(), indent=2))
    else:
        print("\n".join(localization_lines(evaluation)))
    return 0


def _progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


LOCALIZATION_COLUMNS = (("UAV", "{:<6}"), ("estimate", "{:<9}"), ("source", "{:<13}"), ("poses", "{:>6}"),
                        ("from s", "{:>7}"), ("to s", "{:>7}"), ("distance m", "{:>11}"), ("pos err m", "{:>10}"),
                        ("%", "{:>6}"), ("yaw turned", "{:>11}"), ("yaw err", "{:>8}"), ("%", "{:>6}"),
                        ("ATE m", "{:>7}"), ("ms/scan", "{:>8}"))


def localization_lines(evaluation: LocalizationEvaluation) -> list[str]:
    lines = [f"localization against ground truth: {evaluation.recording}",
             f"window: {'the time each UAV was airborne, within ' if evaluation.airborne else ''}each estimate's "
             f"first to last pose matched to the truth; ATE "
             + ("after rigid (SE(3)) alignment" if evaluation.align else "without alignment (the map frame is the "
                                                                          "start frame)")
             + ("" if evaluation.baseline else "; no baseline (--no-baseline)")]
    if not evaluation.report.complete:
        lines.append(f"warning: {evaluation.report.describe(evaluation.recording)}")
    lines += [f"warning: {count} undecodable payloads on {key} skipped"
              for key, count in sorted(evaluation.undecodable.items())]
    lines += [f"note: {note}" for note in evaluation.notes]
    for uav, rows in evaluation.scores.items():
        for score in rows:
            if score.health:
                total = sum(score.health.values())
                shares = ", ".join(f"{name} {100 * n / total:.1f} %" for name, n in score.health.items())
                lines.append(f"note: {uav} localizer health over {total} messages: {shares}")
    table = [_localization_row([name for name, _ in LOCALIZATION_COLUMNS])]
    table += [_localization_row([uav, *localization_row(score)])
              for uav, rows in evaluation.scores.items() for score in rows]
    if len(table) == 1:
        table.append("(nothing scored)")
    return lines + ["", *table]


def localization_row(score: LocalizationScore) -> list[str]:
    return [score.estimator, score.source, str(score.poses), f"{score.start_ns / NS:.1f}", f"{score.end_ns / NS:.1f}",
            _number(score.distance_m, 2), _number(score.position_error_m, 3), _number(score.position_error_pct, 2),
            _number(score.yaw_turned_deg, 1), _number(score.yaw_error_deg, 2), _number(score.yaw_error_pct, 3),
            _number(score.ate.rmse if score.ate else None, 3), _number(score.time_per_scan_ms, 1)]


def _localization_row(cells: list) -> str:
    return " ".join(fmt.format(str(cell)) for cell, (_, fmt) in zip(cells, LOCALIZATION_COLUMNS)).rstrip()


AGE_KEYS = ("detections", "camera_detections", "tracks", "command", "trajectory")


def add_ages_parser(evaluations) -> None:
    a = evaluations.add_parser(
        "ages", help="how old the sensor data was as it left each stage (p50 / p95 / max), from a recording",
        description="The age of the sensor data at each stage of a recorded run: scan -> detections, frame -> "
                    "camera detections, sensor -> tracks, sighting -> command, sighting -> reference (docs/"
                    "architecture.md, RunMonitor). Arrivals are the recorder's receive times, put on the mission "
                    "clock by the recorded clock ticks; a lockstep recording gives ages in whole ticks.")
    a.add_argument("recording", metavar="RECORDING.mcap", help="an MCAP recording of a run (`falconry sim ... "
                                                               "--record RUN.mcap`, or `falconry record`)")
    a.add_argument("--json", action="store_true", help="print the figures as JSON instead of lines")
    a.set_defaults(handler=run_ages)


def run_ages(args: argparse.Namespace) -> int:
    check_recording(args.recording)

    def wanted(key: str) -> bool:
        return key == keys.CLOCK or key.rsplit("/", 1)[-1] in AGE_KEYS

    clock = msgspec.msgpack.Decoder(SimClock)
    ticks = [(m.log_time, clock.decode(m.payload)) for m in read_recording(args.recording, lambda k: k == keys.CLOCK)]
    if len(ticks) < 2:
        raise CliError(f"{args.recording} holds {len(ticks)} clock ticks: no mission clock to date arrivals by")
    (first_wall, first), (last_wall, last) = ticks[0], ticks[-1]
    monitor = RunMonitor()
    if not last.lockstep and last_wall > first_wall:  # the run's own speed, mission seconds per wall second
        monitor.speed = (last.header.stamp - first.header.stamp) / (last_wall - first_wall)
    for message in read_recording(args.recording, wanted):
        monitor.handle(message.key, message.payload, message.log_time)
    ages = monitor.summary()["data_age"]
    if args.json:
        print(json.dumps(ages, indent=2))
    else:
        print("\n".join(data_age_lines(ages) or ["no message in the recording carries the stamp of its sensor data"]))
    return 0
