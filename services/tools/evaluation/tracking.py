"""How well each UAV's tracker followed the targets, against ground truth (`falconry evaluate tracking`).

Evaluation only, pure numpy: services/tools/evaluation/tracking_input.py reads the recording. Per UAV,
one step per truth tick: its confirmed tracks then against the truth (steps, below); beside them,
the detection baseline: one step per Detections message, its detections against the truth at its
stamp.

- The truth at a stamp (`TruthTimeline.at`): the ground truth of that stamp, which a simulated
  run has (the simulator and the tracker both stamp with the tick); between two truths, the
  earlier one with every target and UAV moved linearly toward the later one.
- Which truths count (`tracking_step`): targets that stand (not destroyed), of the kinds the
  tracker is meant to follow (TRACKED_KINDS: drones; the LiDAR perception takes a balloon on its
  pole for background, and the camera's balloon detections never reach the tracker), within the
  UAV's LiDAR range (its model's datasheet max_range) of the UAV's true position. Range, not
  "in sight" (evaluation.in_sight): a sparse LiDAR puts fewer than MIN_HITS rays on a drone in
  many scans it is detected in, and a tracker rightly carries a track through such gaps.
  Occlusion is not judged: a drone in range behind a building counts, and is missed if untracked.
- A standing target that does not count (a balloon, a drone out of range) is "don't care": a
  track closer to it than c, and closer to it than to any counted target, is left out of the step
  (neither matched nor false): the oracle detector reports balloons, and a track coasts on for a
  moment after its drone left range.
- GOSPA (Rahmathullah, García-Fernández, Svensson, "Generalized optimal sub-pattern assignment
  metric", FUSION 2017, arXiv:1601.05585), alpha = 2: over the assignments γ of tracks to truths,
      d = min_γ ( Σ_(i,j)∈γ d(x_i, y_j)^p + c^p / 2 · (|X| + |Y| − 2 |γ|) )^(1/p)
  where only pairs closer than c may be assigned. Its parts, as Stone Soup reports them, are in
  m^p and add up to d^p: localisation Σ d^p over the assigned pairs, missed c^p/2 per truth left
  unassigned, false c^p/2 per track left unassigned. The assignment is scipy's
  linear_sum_assignment over min(d, c)^p (a pair at c or beyond costs what leaving both costs).
- CUTOFF c = 2.5 m: the tracker's smallest association gate (r_min, seed 000 eq. 26): a track
  farther than that from a target can no longer take its detections, so it does not follow it;
  well above the errors of a track that does (seed 000 Table III: 0.17 m per detection).
  ORDER p = 2: the localisation part is then a sum of squared errors, like the RMSE beside it;
  a missed or false target costs c²/2 = 3.1 m².
- Matched: a (track, truth) pair the GOSPA assignment makes (so closer than c); its position
  error counts in the RMSE per axis and in 3D.
- Per target: an identity switch is a step at which it is matched to another track than at the
  previous step it was matched; a fragmentation is a step at which it is matched again after at
  least one step in which it counted and was not matched (steps in which it did not count, out of
  range, neither break nor continue its tracking); its track ids are the distinct tracks ever
  matched to it.
- A false track: a confirmed track id never matched in any step that did not leave it out.
- Mean error, RMSE, recall (tracks and detections alike): the mean and the root mean square of the
  3-D error of the matched pairs; recall, the share of (counted target, step) pairs in which the
  target was matched.

Steps of the tracks are the truth ticks (the simulator sends a truth every tick), not the Tracks
messages: the tracker sends one every tick while it holds any track (tentative ones included) but
only one a second otherwise, so steps per message would weigh a time without tracks less than a
time with them. At a truth tick, the UAV's tracks are its Tracks message of that stamp; with none,
it held no track, as long as its latest message is at most TRACKER_SILENCE_NS old; after a longer
silence (not started yet, stopped, crashed) the tracker cannot be judged and the tick is no step
("tracker silent"). This takes the tracker to tick with the simulator, which a lockstep run
guarantees: a tick a lagging tracker skipped reads as a tick without tracks. A Tracks message at
a stamp without a truth is no step.

The detection baseline (what the tracker is given, scored like what it makes): per Detections
message (one per LiDAR scan, empty or not), its detections against the truths that count at its
stamp, tracks' rules throughout: detections following a target that does not count are left out,
the rest go through the same GOSPA assignment (one-to-one, only pairs closer than c; not "the
nearest within c", which would let the two halves of a split cluster both match a drone, and one
detection match two drones flying close). Each stream's figures are over its own steps: detections
over scans (10 Hz), tracks over ticks (20 Hz); a recall is a share of time either way, so the two
compare. Their errors compare only in part that way: a track's error includes the ticks it coasts
between scans and through missed ones, where no detection is scored. So the errors are also set
side by side like for like (`alike`): over the (scan, target) pairs that both a detection and a
confirmed track matched, each one's error — what tracking does to the position it is given.

The scored tracks are a UAV's confirmed ones. Scored by the same rules, every track it keeps,
tentative ones too, gives the recall without the wait for confirmation (`falconry evaluate
tracking`'s last column): the gap between the two recalls is mostly that wait, plus any tentative
track near a target that was never confirmed.
"""
from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np

from services.lib.runtime.clock import NS

CUTOFF = 2.5  # m, GOSPA's c
ORDER = 2.0  # GOSPA's p
TRACKED_KINDS = ("drone",)
MAX_TRUTH_AGE_NS = 1_000_000_000  # a Detections message this long after the latest truth has none
# a tracker whose latest Tracks message is older than this is silent, not without tracks: its empty
# message comes once per alive_period (1 s, services/tracker/core.py), and half as much again is slack
TRACKER_SILENCE_NS = 1_500_000_000
AXES = ("x", "y", "z")


def _points(points) -> np.ndarray:
    return np.asarray(points, dtype=np.float64).reshape(-1, 3)


# --------------------------------------------------------------------------------- GOSPA
@dataclass(frozen=True)
class Gospa:
    """GOSPA (alpha = 2) of one set of tracks against one set of truths."""

    distance: float  # the metric, m: (localisation + missed + false) ** (1 / p)
    localisation: float  # Σ d^p over the assigned pairs, m^p
    missed: float  # c^p / 2 per truth left unassigned, m^p
    false: float  # c^p / 2 per track left unassigned, m^p
    missed_count: int  # truths left unassigned
    false_count: int  # tracks left unassigned
    pairs: np.ndarray  # (K, 2) int: (track index, truth index) of the assigned pairs, all closer than c


def gospa(tracks: np.ndarray, truths: np.ndarray, c: float = CUTOFF, p: float = ORDER) -> Gospa:
    """GOSPA of the (N, 3) track positions against the (M, 3) true positions."""
    if not (np.isfinite(c) and c > 0 and np.isfinite(p) and p >= 1):
        raise ValueError(f"GOSPA needs c > 0 and 1 <= p < inf, not c={c}, p={p}")
    # imported when first needed: `falconry --help` reads this module's defaults, and scipy.optimize
    # alone takes longer to import than the whole command line
    from scipy.optimize import linear_sum_assignment

    x, y = _points(tracks), _points(truths)
    gaps = np.linalg.norm(x[:, None] - y[None], axis=2)  # (N, M)
    rows, cols = linear_sum_assignment(np.minimum(gaps, c) ** p)
    close = gaps[rows, cols] < c
    rows, cols = rows[close], cols[close]
    unassigned_cost = c ** p / 2
    localisation = float((gaps[rows, cols] ** p).sum())
    missed_count, false_count = len(y) - len(rows), len(x) - len(rows)
    missed, false = missed_count * unassigned_cost, false_count * unassigned_cost
    return Gospa(distance=(localisation + missed + false) ** (1 / p), localisation=localisation, missed=missed,
                 false=false, missed_count=missed_count, false_count=false_count,
                 pairs=np.stack([rows, cols], axis=1).astype(np.int64).reshape(-1, 2))


# --------------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class TruthSnapshot:
    """The ground truth of one instant: the targets and where each UAV was."""

    stamp: int  # mission time, ns
    target_ids: tuple[str, ...]
    kinds: tuple[str, ...]  # per target: "drone", "balloon"
    positions: np.ndarray  # (M, 3)
    standing: np.ndarray  # (M,) bool: not destroyed
    uavs: dict[str, np.ndarray] = field(default_factory=dict)  # UAV -> (3,) true position


def interpolated(before: TruthSnapshot, after: TruthSnapshot, stamp: int) -> TruthSnapshot:
    """`before` with each target and UAV also in `after` moved linearly toward it, to `stamp`."""
    w = (stamp - before.stamp) / (after.stamp - before.stamp)
    later = dict(zip(after.target_ids, _points(after.positions)))
    positions = [p + w * (later[tid] - p) if tid in later else p
                 for tid, p in zip(before.target_ids, _points(before.positions))]
    uavs = {name: p + w * (after.uavs[name] - p) if name in after.uavs else p for name, p in before.uavs.items()}
    return replace(before, stamp=stamp, positions=_points(positions), uavs=uavs)


class TruthTimeline:
    """A run's ground truths by stamp."""

    def __init__(self, snapshots: Iterable[TruthSnapshot]) -> None:
        self.snapshots = sorted(snapshots, key=lambda s: s.stamp)
        self._stamps = [s.stamp for s in self.snapshots]

    def __len__(self) -> int:
        return len(self.snapshots)

    def ticks(self) -> list[int]:
        """The stamps of the truths, in order, each once."""
        return list(dict.fromkeys(self._stamps))

    def at(self, stamp: int) -> TruthSnapshot | None:
        """The truth at `stamp` (see the module's text); None before the first truth or more than
        MAX_TRUTH_AGE_NS after the last."""
        i = bisect.bisect_right(self._stamps, stamp) - 1
        if i < 0:
            return None
        before = self.snapshots[i]
        if before.stamp == stamp:
            return before
        if i + 1 < len(self.snapshots):
            return interpolated(before, self.snapshots[i + 1], stamp)
        return before if stamp - before.stamp <= MAX_TRUTH_AGE_NS else None


# --------------------------------------------------------------------------------- steps
@dataclass(frozen=True)
class TrackSet:
    """A UAV's tracks of one Tracks message: its confirmed ones (what is scored), or all it keeps,
    tentative ones too (the recall without the confirmation's wait)."""

    stamp: int  # mission time, ns
    ids: np.ndarray  # (N,) int
    positions: np.ndarray  # (N, 3)


@dataclass(frozen=True)
class ScanDetections:
    """The detections of one Detections message (one LiDAR scan)."""

    stamp: int  # mission time, ns
    detector: str  # the message's: "classifier", "oracle"
    positions: np.ndarray  # (N, 3)


def tracks_at_ticks(messages: Sequence[TrackSet], ticks: Iterable[int],
                    silence_ns: int = TRACKER_SILENCE_NS) -> Iterator[tuple[int, TrackSet | None]]:
    """Per tick, in order: the UAV's scored tracks then, from its `messages` (in stamp order): the
    message of that stamp; none (an empty set) when there is no such message and the latest before
    is at most `silence_ns` old; None when the tracker was silent (see the module's text)."""
    latest, i = None, 0
    for tick in ticks:
        while i < len(messages) and messages[i].stamp <= tick:
            latest, i = messages[i], i + 1
        if latest is None or tick - latest.stamp > silence_ns:
            yield tick, None
        elif latest.stamp == tick:
            yield tick, latest
        else:  # the tracker was alive and sent nothing: it held no track, not even a tentative one
            yield tick, TrackSet(tick, np.zeros(0, dtype=np.int64), np.zeros((0, 3)))


@dataclass(frozen=True)
class TrackingStep:
    """One UAV's estimates at one step against the truth then: its scored tracks at a truth tick,
    or the detections of one scan (their ids: their rows in the message)."""

    t: float  # mission time, s
    track_ids: np.ndarray  # (N,) int: the scored tracks (or detections)
    tracks: np.ndarray  # (N, 3) their positions
    truth_ids: tuple[str, ...]  # the M targets that count
    truths: np.ndarray  # (M, 3) their true positions
    ignored: np.ndarray  # (K, 3) standing targets that do not count: tracks following them are left out


def tracking_step(t: float, track_ids: Sequence[int], tracks: np.ndarray, truth: TruthSnapshot, uav: str,
                  sensor_range: float = float("inf"), kinds: Sequence[str] = TRACKED_KINDS) -> TrackingStep:
    """The step of a UAV's scored tracks against `truth`: which targets count (see the module's text)."""
    positions = _points(truth.positions)
    standing = np.asarray(truth.standing, dtype=bool).reshape(-1)
    wanted_kind = np.array([kind in kinds for kind in truth.kinds], dtype=bool).reshape(-1)
    here = truth.uavs.get(uav)
    in_range = (np.ones(len(positions), dtype=bool) if here is None
                else np.linalg.norm(positions - np.asarray(here, dtype=np.float64), axis=1) <= sensor_range)
    counts = standing & wanted_kind & in_range
    return TrackingStep(t=t, track_ids=np.asarray(track_ids, dtype=np.int64).reshape(-1), tracks=_points(tracks),
                        truth_ids=tuple(tid for tid, ok in zip(truth.target_ids, counts.tolist()) if ok),
                        truths=positions[counts], ignored=positions[standing & ~counts])


def _nearest_gap(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(N,) distance from each point to the nearest of `others` (inf when there are none)."""
    if not len(others):
        return np.full(len(points), np.inf)
    return np.linalg.norm(points[:, None] - others[None], axis=2).min(axis=1)


def left_out(tracks: np.ndarray, truths: np.ndarray, ignored: np.ndarray, c: float) -> np.ndarray:
    """(N,) bool: tracks following a target that does not count: closer than c to one of `ignored`,
    and closer to it than to any counted truth."""
    x = _points(tracks)
    to_ignored = _nearest_gap(x, _points(ignored))
    return (to_ignored < c) & (to_ignored < _nearest_gap(x, _points(truths)))


def assign(step: TrackingStep, c: float, p: float) -> tuple[np.ndarray, Gospa]:
    """(N,) bool, the step's estimates kept (not left out), and the GOSPA of the kept ones against
    the truths that count: the one matching rule of tracks and detections."""
    keep = ~left_out(step.tracks, step.truths, step.ignored, c)
    return keep, gospa(_points(step.tracks)[keep], step.truths, c, p)


# --------------------------------------------------------------------------------- scores
def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


@dataclass
class MatchErrors:
    """A stream's matched pairs (confirmed tracks, or detections, on truths) over its steps."""

    counted: int = 0  # (truth, step) pairs in which the truth counted
    matched: int = 0  # ... and had an estimate matched to it: the matched pairs
    error_sum: float = 0.0  # Σ 3-D error of the matched pairs, m
    squared_error: np.ndarray = field(default_factory=lambda: np.zeros(3))  # Σ per axis, m²

    def add(self, estimates: np.ndarray, truths: np.ndarray, pairs: np.ndarray) -> None:
        """One step: the (N, 3) estimates, the (M, 3) truths that counted, the GOSPA's (K, 2) pairs."""
        self.counted += len(_points(truths))
        self.add_errors(_points(estimates)[pairs[:, 0]] - _points(truths)[pairs[:, 1]])

    def add_errors(self, errors: np.ndarray) -> None:
        """Matched pairs given by their (K, 3) errors (estimate − truth): no recall is kept."""
        errors = _points(errors)
        self.matched += len(errors)
        self.error_sum += float(np.linalg.norm(errors, axis=1).sum())
        self.squared_error = self.squared_error + (errors ** 2).sum(axis=0)

    def __add__(self, other: MatchErrors) -> MatchErrors:
        return MatchErrors(self.counted + other.counted, self.matched + other.matched,
                           self.error_sum + other.error_sum, self.squared_error + other.squared_error)

    def mean_error(self) -> float | None:
        """Mean 3-D error of the matched pairs, m (None: no pair)."""
        return self.error_sum / self.matched if self.matched else None

    def rmse(self) -> dict[str, float] | None:
        """Root mean square error of the matched pairs per axis and in 3D, m (None: no pair)."""
        if not self.matched:
            return None
        per_axis = np.sqrt(self.squared_error / self.matched)
        return {**dict(zip(AXES, per_axis.tolist())), "3d": float(np.sqrt(self.squared_error.sum() / self.matched))}

    def recall(self) -> float | None:
        """Share of the (truth, step) pairs that counted with a match (None: none counted)."""
        return self.matched / self.counted if self.counted else None

    def summary(self) -> dict:
        rmse = self.rmse()
        return {"matched_pairs": self.matched, "counted_truth_steps": self.counted,
                "mean_error_m": _rounded(self.mean_error()),
                "rmse_m": None if rmse is None else {axis: round(value, 4) for axis, value in rmse.items()},
                "recall": _rounded(self.recall())}


@dataclass
class TruthRecord:
    """One target as one UAV's tracker followed it."""

    counted: int = 0  # steps in which it counted
    tracked: int = 0  # ... in which a track was matched to it
    track_ids: set[int] = field(default_factory=set)  # every track ever matched to it
    switches: int = 0
    fragmentations: int = 0
    last_track: int | None = None  # the track matched at the latest step it was matched
    lost: bool = False  # counted and unmatched since it was last matched

    def add(self, track_id: int | None) -> None:
        """One step in which it counted: matched to `track_id`, or to none."""
        self.counted += 1
        if track_id is None:
            self.lost = self.last_track is not None
            return
        self.tracked += 1
        self.switches += self.last_track is not None and track_id != self.last_track
        self.fragmentations += self.lost
        self.track_ids.add(track_id)
        self.last_track, self.lost = track_id, False

    def summary(self) -> dict:
        return {"counted_steps": self.counted, "tracked_steps": self.tracked, "track_ids": sorted(self.track_ids),
                "identity_switches": self.switches, "fragmentations": self.fragmentations}


@dataclass
class GospaSums:
    """Sums of the steps' GOSPA figures (their means: divide by `steps`)."""

    steps: int = 0
    distance: float = 0.0  # m
    localisation: float = 0.0  # m^p
    missed: float = 0.0
    false: float = 0.0
    missed_count: int = 0
    false_count: int = 0

    def add(self, score: Gospa) -> None:
        self.steps += 1
        for name in ("distance", "localisation", "missed", "false", "missed_count", "false_count"):
            setattr(self, name, getattr(self, name) + getattr(score, name))

    def __add__(self, other: GospaSums) -> GospaSums:
        return GospaSums(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def means(self) -> dict[str, float]:
        n = max(self.steps, 1)
        return {"gospa_m": round(self.distance / n, 4), "localisation": round(self.localisation / n, 4),
                "missed": round(self.missed / n, 4), "false": round(self.false / n, 4),
                "missed_targets_per_step": round(self.missed_count / n, 4),
                "false_tracks_per_step": round(self.false_count / n, 4)}


@dataclass
class TrackingScore:
    """One UAV's tracking over a run (`add` each step), or the fleet's (`fleet`)."""

    c: float = CUTOFF
    p: float = ORDER
    sums: GospaSums = field(default_factory=GospaSums)  # of the steps' GOSPA
    first_t: float | None = None  # mission time of the first and last step, s
    last_t: float = 0.0
    errors: MatchErrors = field(default_factory=MatchErrors)  # of the matched (track, truth) pairs
    left_out: int = 0  # (track, step) left out as following a target that does not count
    without_truth: int = 0  # Tracks messages with no truth at their stamp: not steps
    silent: int = 0  # truth ticks at which the tracker was silent: not steps
    truths: dict[str, TruthRecord] = field(default_factory=dict)
    tracks: dict[str, bool] = field(default_factory=dict)  # confirmed track id -> ever matched

    @property
    def pairs(self) -> int:
        """Matched (track, truth) pairs over the steps."""
        return self.errors.matched

    def add(self, step: TrackingStep) -> Gospa:
        keep, score = assign(step, self.c, self.p)
        ids, tracks, truths = step.track_ids[keep], _points(step.tracks)[keep], _points(step.truths)
        self.sums.add(score)
        self.first_t = step.t if self.first_t is None else min(self.first_t, step.t)
        self.last_t = max(self.last_t, step.t)
        self.left_out += int((~keep).sum())
        track_of = {int(j): int(ids[i]) for i, j in score.pairs}
        for j, truth_id in enumerate(step.truth_ids):
            self.truths.setdefault(truth_id, TruthRecord()).add(track_of.get(j))
        matched = set(score.pairs[:, 0].tolist())
        for i, track_id in enumerate(ids.tolist()):
            self.tracks[str(track_id)] = self.tracks.get(str(track_id), False) or i in matched
        self.errors.add(tracks, truths, score.pairs)
        return score

    def rmse(self) -> dict[str, float] | None:
        """Root mean square position error of the matched pairs per axis and in 3D, m (None: no pair)."""
        return self.errors.rmse()

    def false_tracks(self) -> int:
        return sum(not ever for ever in self.tracks.values())

    def summary(self) -> dict:
        return {
            "steps": self.sums.steps,
            "t_s": None if self.first_t is None else [round(self.first_t, 3), round(self.last_t, 3)],
            **self.errors.summary(),
            **self.sums.means(),
            "identity_switches": sum(r.switches for r in self.truths.values()),
            "fragmentations": sum(r.fragmentations for r in self.truths.values()),
            "confirmed_tracks": len(self.tracks),
            "false_tracks": self.false_tracks(),
            "left_out_track_steps": self.left_out,
            "tracks_messages_without_truth": self.without_truth,
            "tracker_silent_ticks": self.silent,
            "targets": {tid: record.summary() for tid, record in sorted(self.truths.items())},
        }


def score_tracks(messages: Iterable[TrackSet], truth: TruthTimeline, uav: str,
                 sensor_range: float = float("inf"), kinds: Sequence[str] = TRACKED_KINDS,
                 c: float = CUTOFF, p: float = ORDER) -> TrackingScore:
    """One UAV's tracking at the truth ticks, from its Tracks messages (steps: see the module's text)."""
    score = TrackingScore(c=c, p=p)
    messages, ticks = sorted(messages, key=lambda m: m.stamp), truth.ticks()
    on_a_tick = set(ticks)
    score.without_truth = sum(m.stamp not in on_a_tick for m in messages)
    for tick, tracks in tracks_at_ticks(messages, ticks):
        if tracks is None:
            score.silent += 1
            continue
        score.add(tracking_step(tick / NS, tracks.ids, tracks.positions, truth.at(tick), uav, sensor_range, kinds))
    return score


def fleet(scores: dict[str, TrackingScore]) -> TrackingScore:
    """Every UAV's steps, pairs, targets and tracks together; targets and tracks are per UAV
    ("uav1/crosser", "uav1/7"): a target two UAVs follow counts once for each."""
    parts = list(scores.values())
    total = TrackingScore(c=parts[0].c, p=parts[0].p) if parts else TrackingScore()
    for uav, s in scores.items():
        total.sums = total.sums + s.sums
        if s.first_t is not None:
            total.first_t = s.first_t if total.first_t is None else min(total.first_t, s.first_t)
        total.last_t = max(total.last_t, s.last_t)
        total.errors = total.errors + s.errors
        total.left_out += s.left_out
        total.without_truth += s.without_truth
        total.silent += s.silent
        total.truths.update({f"{uav}/{tid}": record for tid, record in s.truths.items()})
        total.tracks.update({f"{uav}/{track_id}": ever for track_id, ever in s.tracks.items()})
    return total


# --------------------------------------------------------------------------------- detection baseline
@dataclass
class DetectionScore:
    """One UAV's detections over a run (`add` each scan's step), the baseline beside its tracks; or
    the fleet's (`fleet_detections`)."""

    c: float = CUTOFF
    p: float = ORDER
    steps: int = 0  # scans scored
    detections: int = 0  # in those scans, left-out ones included
    errors: MatchErrors = field(default_factory=MatchErrors)  # of the matched (detection, truth) pairs
    left_out: int = 0  # (detection, scan) left out as following a target that does not count
    without_truth: int = 0  # Detections messages with no truth at their stamp: not steps
    detectors: set[str] = field(default_factory=set)  # the messages' detector names
    paired: dict[tuple[int, str], np.ndarray] = field(default_factory=dict)  # (stamp ns, target) -> error (3,)

    def add(self, step: TrackingStep, stamp: int | None = None) -> Gospa:
        """One scan's step; with its `stamp`, each matched pair's error is kept for `alike`."""
        keep, score = assign(step, self.c, self.p)
        self.steps += 1
        self.detections += len(keep)
        self.left_out += int((~keep).sum())
        kept = _points(step.tracks)[keep]
        self.errors.add(kept, step.truths, score.pairs)
        if stamp is not None:
            for i, j in score.pairs:
                self.paired[(stamp, step.truth_ids[j])] = kept[i] - step.truths[j]
        return score

    def summary(self) -> dict:
        return {"detectors": sorted(self.detectors), "steps": self.steps, "detections": self.detections,
                **self.errors.summary(), "left_out_detection_steps": self.left_out,
                "detections_messages_without_truth": self.without_truth}


def score_detections(messages: Iterable[ScanDetections], truth: TruthTimeline, uav: str,
                     sensor_range: float = float("inf"), kinds: Sequence[str] = TRACKED_KINDS,
                     c: float = CUTOFF, p: float = ORDER) -> DetectionScore:
    """One UAV's detections, one step per Detections message, against the truth at its stamp."""
    score = DetectionScore(c=c, p=p)
    for message in messages:
        score.detectors.add(message.detector)
        at = truth.at(message.stamp)
        if at is None:
            score.without_truth += 1
            continue
        positions = _points(message.positions)
        score.add(tracking_step(message.stamp / NS, np.arange(len(positions)), positions, at, uav, sensor_range,
                                kinds), message.stamp)
    return score


@dataclass(frozen=True)
class Alike:
    """Detections' and confirmed tracks' errors over the same (scan, target) pairs: those both matched."""

    detections: MatchErrors
    tracks: MatchErrors

    def summary(self) -> dict:
        def errors(e: MatchErrors) -> dict:
            rmse = e.rmse()
            return {"mean_error_m": _rounded(e.mean_error()),
                    "rmse_3d_m": None if rmse is None else _rounded(rmse["3d"])}
        return {"pairs": self.tracks.matched, "detections": errors(self.detections), "tracks": errors(self.tracks)}


def alike(messages: Iterable[TrackSet], truth: TruthTimeline, uav: str, detections: DetectionScore,
          sensor_range: float = float("inf"), kinds: Sequence[str] = TRACKED_KINDS,
          c: float = CUTOFF, p: float = ORDER) -> Alike:
    """At the stamps of the scans whose detections matched a target (`detections`, scored with their
    stamps), the UAV's confirmed tracks then, matched by the same rules; the pairs both matched."""
    found, given = MatchErrors(), MatchErrors()
    stamps = sorted({stamp for stamp, _ in detections.paired})
    for stamp, tracks in tracks_at_ticks(sorted(messages, key=lambda m: m.stamp), stamps):
        at = truth.at(stamp)
        if tracks is None or at is None:
            continue
        step = tracking_step(stamp / NS, tracks.ids, tracks.positions, at, uav, sensor_range, kinds)
        keep, score = assign(step, c, p)
        kept = _points(step.tracks)[keep]
        for i, j in score.pairs:
            detected = detections.paired.get((stamp, step.truth_ids[j]))
            if detected is not None:
                found.add_errors((kept[i] - step.truths[j])[None])
                given.add_errors(detected[None])
    return Alike(given, found)


def fleet_alike(parts: dict[str, Alike]) -> Alike:
    """Every UAV's like-for-like pairs together."""
    detections, tracks = MatchErrors(), MatchErrors()
    for part in parts.values():
        detections, tracks = detections + part.detections, tracks + part.tracks
    return Alike(detections, tracks)


def fleet_detections(scores: dict[str, DetectionScore]) -> DetectionScore:
    """Every UAV's scans and pairs together (a target two UAVs detect counts once for each)."""
    parts = list(scores.values())
    total = DetectionScore(c=parts[0].c, p=parts[0].p) if parts else DetectionScore()
    for s in parts:
        total.steps += s.steps
        total.detections += s.detections
        total.errors = total.errors + s.errors
        total.left_out += s.left_out
        total.without_truth += s.without_truth
        total.detectors |= s.detectors
    return total
