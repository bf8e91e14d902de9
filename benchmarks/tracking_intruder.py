"""Tracks against the raw detections on `intruder` with the LiDAR classifier (issue 12), over seeds.

Flies `falconry sim intruder --uavs 2 --lockstep --detector classifier --seed S --record R.mcap`
per seed (benchmarks/mission.py's runner), scores each recording with `falconry evaluate tracking
--json` and deletes it (about 3.6 GB each). Prints per seed and UAV the detections' recall (per
scan) against the confirmed tracks' (per truth tick) and that of every track the UAV keeps,
tentative ones too (the gap to the confirmed tracks' is mostly the wait for confirmation), and
the like-for-like mean error (the (scan, target) pairs both matched); then the same pooled over
the seeds: recalls as matched over counted (target, step) pairs, mean errors weighted by their
pairs. Goals: tracks' recall at least the detections', tracks' mean error below the detections'.

    .venv/bin/python benchmarks/tracking_intruder.py                 # seeds 1-5: about 10 min
    .venv/bin/python benchmarks/tracking_intruder.py --seeds 2
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # mission.py beside this file

from mission import run  # noqa: E402


@dataclass
class Tally:
    """One UAV's (or the fleet's) figures, summed so that seeds pool."""

    detected: int = 0  # (target, scan) pairs a detection matched
    scans: int = 0  # (target, scan) pairs that counted
    tracked: int = 0  # (target, tick) pairs a confirmed track matched
    ticks: int = 0  # (target, tick) pairs that counted
    kept: int = 0  # (target, tick) pairs any track the UAV keeps matched, tentative ones too (of `ticks`)
    pairs: int = 0  # like-for-like (scan, target) pairs
    detection_error: float = 0.0  # sum over those pairs, m
    track_error: float = 0.0

    def __add__(self, other: Tally) -> Tally:
        return Tally(*(a + b for a, b in zip(vars(self).values(), vars(other).values())))

    def cells(self) -> list[str]:
        def share(a: int, b: int) -> str:
            return "-" if not b else f"{a / b:.3f}"

        def mean(total: float) -> str:
            return "-" if not self.pairs else f"{total / self.pairs:.3f}"
        return [share(self.detected, self.scans), share(self.tracked, self.ticks), share(self.kept, self.ticks),
                str(self.pairs), mean(self.detection_error), mean(self.track_error)]

    def verdict(self) -> str:
        recall = self.ticks and self.scans and self.tracked / self.ticks >= self.detected / self.scans
        error = self.pairs and self.track_error < self.detection_error
        return f"recall {'met' if recall else 'NOT met'}, error {'met' if error else 'NOT met'}"


def tallies(figures: dict) -> dict[str, Tally]:
    """Per UAV and "fleet", from `falconry evaluate tracking --json`."""
    out = {}
    for name in [*figures["uavs"], "fleet"]:
        fleet = name == "fleet"
        tracks = figures["fleet"] if fleet else figures["uavs"][name]
        detections = figures["detections"]["fleet"] if fleet else figures["detections"]["uavs"][name]
        alike = figures["alike"].get(name, {"pairs": 0, "detections": {}, "tracks": {}})
        pairs, kept = alike["pairs"], figures["comparison"][name]["kept_tracks"]
        # the same steps and counted targets as the confirmed tracks': only the matches differ
        assert kept["counted_truth_steps"] == tracks["counted_truth_steps"], (name, kept, tracks)
        out[name] = Tally(detections["matched_pairs"], detections["counted_truth_steps"], tracks["matched_pairs"],
                          tracks["counted_truth_steps"], kept["matched_pairs"], pairs,
                          pairs * (alike["detections"].get("mean_error_m") or 0.0),
                          pairs * (alike["tracks"].get("mean_error_m") or 0.0))
    return out


def evaluate(recording: Path) -> dict:
    argv = [sys.executable, "-m", "services.tools.launcher", "evaluate", "tracking", str(recording), "--json"]
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"evaluate tracking {recording} failed ({result.returncode}): {result.stderr[-2000:]}")
    return json.loads(result.stdout)


HEADER = (f"{'seed':>5} {'UAV':<6} {'det recall':>10} {'track recall':>12} {'w/ tentative':>12} {'pairs':>6} "
          f"{'det err':>8} {'track err':>9}")


def row(seed: str, name: str, tally: Tally) -> str:
    recall_d, recall_t, recall_k, pairs, error_d, error_t = tally.cells()
    return f"{seed:>5} {name:<6} {recall_d:>10} {recall_t:>12} {recall_k:>12} {pairs:>6} {error_d:>8} {error_t:>9}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="seeds (default 1-5)")
    parser.add_argument("--duration", type=float, default=120.0, help="mission time per run, s (default 120)")
    args = parser.parse_args()
    started, pooled, lines = time.time(), {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            recording = Path(tmp) / f"intruder-{seed}.mcap"
            run("intruder", 2, seed, args.duration, Path(tmp), "classifier", ("--record", str(recording)))
            figures = tallies(evaluate(recording))
            recording.unlink()
            for name, tally in figures.items():
                pooled[name] = pooled.get(name, Tally()) + tally
                lines.append(row(str(seed), name, tally))
            print(f"[{time.time() - started:5.0f} s] seed {seed}: "
                  + "; ".join(f"{name} {tally.verdict()}" for name, tally in figures.items()), flush=True)
    print("\nintruder, 2 UAVs, classifier: detections (per scan) against confirmed tracks (per truth tick);"
          "\nw/ tentative: every track the UAV keeps, tentative ones too (the gap to the track recall is mostly"
          "\nthe wait for confirmation); errors like for like, m (the (scan, target) pairs both matched)")
    print(HEADER)
    print("\n".join(lines))
    for name, tally in pooled.items():
        print(row("all", name, tally))
    print("pooled: " + "; ".join(f"{name} {tally.verdict()}" for name, tally in pooled.items()))
    print(f"wall time {time.time() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
