"""What `falconry evaluate localization` reads from a recording, and the evaluation of a whole
recording (what the command and a benchmark call: `evaluate_localization`).

`read_localization_input`, one pass (a file cut short by a crash is read up to its last complete
chunk, `ReadReport`): the ground truth (falconry/sim/truth: each UAV's position and heading per
tick) and each UAV's estimate (falconry/<uav>/localization, the localizer's; without one,
falconry/<uav>/odometry, the simulator's GNSS odometry, so every recording can be evaluated).
`read_scans`, a second pass for the KISS-ICP baseline only, once the first found something to
score: the scans (falconry/<uav>/points: world-frame points, turned into the sensor frame with the
scan's `sensor_pose`) one by one as they are read: a two-minute recording's scans do not fit in
memory. The figures are services/tools/evaluation/localization.py's.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import GroundTruth, Odometry, PointCloud, WorldModel
from services.tools.evaluation.localization import (CannotScore, KissIcpOdometry, LocalizationScore, Trajectory, TruthTrack,
                                              anchored_baseline, mount_transform, pose_matrix, score_localization,
                                              sensor_frame_points)
from services.lib.lidar.models import lidar_model
from services.tools.recorder.mcap_io import ReadReport, check_recording, read_recording
from services.tools.recorder.selection import KeyFilter
from services.lib.runtime.errors import UsageError

LOCALIZATION = keys.uav("*", keys.LOCALIZATION)
ODOMETRY = keys.uav("*", keys.ODOMETRY)
POINTS = keys.uav("*", "points")
PROGRESS_EVERY = 100  # scans between two progress lines of the baseline
DEFAULT_MAX_RANGE = 100.0  # m, KISS-ICP's own, for a scan that names neither its range nor a known model


@dataclass
class Estimate:
    """One UAV's recorded pose estimate."""

    source: str  # "localization" (the localizer) or "odometry" (the simulator's GNSS odometry)
    key: str
    trajectory: Trajectory
    health: dict[str, int] = field(default_factory=dict)  # the localizer's health -> messages ("" not counted)


@dataclass(frozen=True)
class Scan:
    """One LiDAR scan in the frame of the sensor that took it."""

    uav: str
    stamp: int  # ns
    position: np.ndarray  # (3,) the sensor's position in the world (PointCloud.sensor_pose)
    orientation: np.ndarray  # (4,) its quaternion (w, x, y, z)
    points: np.ndarray  # (N, 3) float64, the finite returns in the sensor frame
    min_range: float  # m, 0: unknown
    max_range: float  # m, 0: unknown
    sensor_model: str


@dataclass
class LocalizationInput:
    """Everything the localization evaluation takes from one recording (the scans aside)."""

    truth: dict[str, TruthTrack]
    localization: dict[str, Estimate]
    odometry: dict[str, Estimate]
    positioning: dict[str, str]  # UAV -> "lidar" when the run flew it without GNSS (WorldModel.positioning)
    report: ReadReport
    undecodable: dict[str, int] = field(default_factory=dict)  # key -> payloads skipped

    def estimate(self, uav: str) -> Estimate | None:
        """The localizer's estimate, else the GNSS odometry, else None."""
        return self.localization.get(uav) or self.odometry.get(uav)

    def evaluable(self) -> list[str]:
        """The UAVs with a truth and an estimate."""
        return sorted(u for u in self.truth if u in self.localization or u in self.odometry)


def scan_of(uav: str, cloud: PointCloud) -> Scan:
    position = np.asarray(cloud.sensor_pose.position, dtype=np.float64)
    orientation = np.asarray(cloud.sensor_pose.orientation, dtype=np.float64)
    points = to_numpy(cloud.points)
    return Scan(uav=uav, stamp=cloud.header.stamp, position=position, orientation=orientation,
                points=sensor_frame_points(points, position, orientation), min_range=cloud.min_range,
                max_range=cloud.max_range, sensor_model=cloud.sensor_model)


def _estimate(source: str, uav: str, messages: list[Odometry]) -> Estimate:
    health: dict[str, int] = {}
    for m in messages:
        if m.health:
            health[m.health] = health.get(m.health, 0) + 1
    return Estimate(source, keys.uav(uav, source), Trajectory.of(
        [m.header.stamp for m in messages], [m.pose.position for m in messages],
        [m.pose.orientation for m in messages]), dict(sorted(health.items())))


def read_localization_input(path: str) -> LocalizationInput:
    """Every UAV's truth and estimates. Raises UsageError when the file is not an MCAP file."""
    wanted = KeyFilter((keys.TRUTH, keys.WORLD, LOCALIZATION, ODOMETRY))
    truth_decoder, world_decoder = msgspec.msgpack.Decoder(GroundTruth), msgspec.msgpack.Decoder(WorldModel)
    odometry_decoder = msgspec.msgpack.Decoder(Odometry)
    truth_rows: dict[str, list[tuple]] = {}
    estimates: dict[str, dict[str, list[Odometry]]] = {keys.LOCALIZATION: {}, keys.ODOMETRY: {}}
    positioning: dict[str, str] = {}
    report, undecodable = ReadReport(), {}
    for message in read_recording(path, wanted, report):
        try:
            if message.key == keys.TRUTH:
                truth = truth_decoder.decode(message.payload)
                for v in truth.uavs:
                    truth_rows.setdefault(v.name, []).append((truth.header.stamp, v.position, v.heading, v.airborne))
            elif message.key == keys.WORLD:
                positioning.update(world_decoder.decode(message.payload).positioning)
            else:
                topic = message.key.rsplit("/", 1)[1]
                estimates[topic].setdefault(keys.uav_of(message.key), []).append(
                    odometry_decoder.decode(message.payload))
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
            undecodable[message.key] = undecodable.get(message.key, 0) + 1
    truth_tracks = {}
    for uav, rows in truth_rows.items():
        stamps, positions, headings, airborne = zip(*rows)
        truth_tracks[uav] = TruthTrack.of(stamps, positions, headings, airborne)
    return LocalizationInput(
        truth=truth_tracks,
        localization={u: _estimate(keys.LOCALIZATION, u, m) for u, m in estimates[keys.LOCALIZATION].items()},
        odometry={u: _estimate(keys.ODOMETRY, u, m) for u, m in estimates[keys.ODOMETRY].items()},
        positioning=positioning, report=report, undecodable=undecodable)


def read_scans(path: str, uavs: Iterable[str] | None = None,
               undecodable: dict[str, int] | None = None) -> Iterator[Scan]:
    """The scans of `uavs` (default: every UAV) one by one, in file order, in their sensor frame;
    an undecodable one is counted in `undecodable` (key -> count) and skipped."""
    wanted = KeyFilter([keys.uav(u, "points") for u in (["*"] if uavs is None else uavs)])
    decoder = msgspec.msgpack.Decoder(PointCloud)
    for message in read_recording(path, wanted):
        try:
            yield scan_of(keys.uav_of(message.key), decoder.decode(message.payload))
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
            if undecodable is not None:
                undecodable[message.key] = undecodable.get(message.key, 0) + 1


# ----------------------------------------------------------------------------- the KISS-ICP baseline
class Baseline:
    """KISS-ICP over every UAV's scans as they are read (`add`), one odometry per UAV, started at
    its first scan with that scan's ranges; the sensor pose of each registered scan is kept (the
    LiDAR mount is measured from it and the truth)."""

    def __init__(self, voxel_size: float | None = None, threads: int = 0,
                 progress: Callable[[str], None] | None = None) -> None:
        self.voxel_size, self.threads, self.progress = voxel_size, threads, progress
        self.odometry: dict[str, KissIcpOdometry] = {}
        self.sensor_poses: dict[str, dict[int, np.ndarray]] = {}  # UAV -> stamp -> (4, 4) recorded sensor pose
        self.read = 0
        self.began = time.monotonic()

    def add(self, scan: Scan) -> None:
        odometry = self.odometry.get(scan.uav)
        if odometry is None:
            odometry = self.odometry[scan.uav] = KissIcpOdometry(
                max_range=scan_max_range(scan), min_range=max(scan.min_range, 0.0), voxel_size=self.voxel_size,
                threads=self.threads)
        if odometry.register(scan.stamp, scan.points):
            self.sensor_poses.setdefault(scan.uav, {})[scan.stamp] = pose_matrix(scan.position, scan.orientation)
        self.read += 1
        if self.progress is not None and self.read % PROGRESS_EVERY == 0:
            per_uav = ", ".join(f"{u} {len(o.stamps)}" for u, o in sorted(self.odometry.items()))
            seconds = [s for o in self.odometry.values() for s in o.seconds]
            ms = f", {1e3 * sum(seconds) / len(seconds):.0f} ms/scan" if seconds else ""
            self.progress(f"kiss-icp: {self.read} scans read, registered {per_uav}{ms}, "
                          f"{time.monotonic() - self.began:.0f} s")

    def trajectory(self, uav: str, truth: TruthTrack, start: int | None) -> tuple[Trajectory, str]:
        """The UAV's body poses from its first registered scan at or after `start` (None: the
        first), anchored at the truth there; with what was done, for a note. Raises CannotScore."""
        odometry = self.odometry.get(uav)
        if odometry is None or not odometry.stamps:
            raise CannotScore("no scan registered")
        stamps = odometry.stamps
        poses = self.sensor_poses[uav]
        mount = next((mount_transform(body, poses[s]) for s in stamps if (body := truth.pose_at(s)) is not None), None)
        if mount is None:
            raise CannotScore("no registered scan has a truth at its stamp")
        anchor = next((i for i, s in enumerate(stamps) if (start is None or s >= start)
                       and truth.pose_at(s) is not None), None)
        if anchor is None:
            raise CannotScore("no registered scan with a truth in the window")
        trajectory = anchored_baseline(stamps, odometry.poses, anchor, truth.pose_at(stamps[anchor]), mount)
        offset = ", ".join(f"{round(v, 2) + 0.0:.2f}" for v in mount[:3, 3])  # + 0.0: no "-0.00"
        return trajectory, (f"anchored at the true pose at {stamps[anchor] / 1e9:.2f} s, LiDAR mount "
                            f"({offset}) m in the body frame")


def scan_max_range(scan: Scan) -> float:
    """The scan's max_range, else its model's datasheet range, else KISS-ICP's default."""
    if scan.max_range > 0:
        return scan.max_range
    try:
        return lidar_model(scan.sensor_model).max_range
    except ValueError:
        return DEFAULT_MAX_RANGE


# ----------------------------------------------------------------------------- the whole recording
@dataclass
class LocalizationEvaluation:
    """A recording's localization scores: per UAV, the recorded estimate's row and the baseline's."""

    recording: str
    scores: dict[str, list[LocalizationScore]]  # UAV -> rows: "falconry" first, then "kiss-icp"
    notes: list[str]  # what was scored instead, left out or could not be scored, one line each
    align: bool
    airborne: bool
    baseline: bool
    report: ReadReport
    undecodable: dict[str, int]

    def summary(self) -> dict:
        return {"recording": self.recording, "complete": self.report.complete, "aligned": self.align,
                "window": "airborne" if self.airborne else "estimate", "baseline": self.baseline,
                "undecodable": self.undecodable, "notes": self.notes,
                "uavs": {uav: {s.estimator: s.summary() for s in rows} for uav, rows in self.scores.items()}}


def evaluate_localization(path: str | Path, uavs: Iterable[str] | None = None, *, baseline: bool = True,
                          align: bool = False, airborne: bool = False, voxel_size: float | None = None,
                          threads: int = 0, progress: Callable[[str], None] | None = None) -> LocalizationEvaluation:
    """Score each UAV's recorded estimate (the localizer's, else the GNSS odometry) and, with
    `baseline`, KISS-ICP over its scans, against the recording's truth (services/
    evaluation_localization.py). `uavs`: only these (default: every UAV with a truth and an
    estimate). `airborne`: only while the UAV was airborne. `voxel_size`, `threads`:
    KISS-ICP's (default: a hundredth of the LiDAR's range; all cores). `progress` is called with a
    line every PROGRESS_EVERY scans. Raises UsageError on a file that cannot be evaluated (missing,
    not MCAP, no truth, a UAV it does not hold)."""
    path = str(path)
    check_recording(path)
    only = None if uavs is None else list(dict.fromkeys(uavs))
    data = read_localization_input(path)
    if not data.truth:
        raise UsageError(f"{path} holds no ground truth ({keys.TRUTH}): record a simulated run, "
                         "e.g. `falconry sim SCENARIO --record FILE.mcap`")
    evaluable = data.evaluable()
    if only is not None:
        missing = [u for u in only if u not in evaluable]
        if missing:
            raise UsageError(f"{path} holds no truth and estimate of {', '.join(missing)}"
                             + (f" (it has those of {', '.join(evaluable)})" if evaluable else ""))
        evaluable = only
    if not evaluable:
        raise UsageError(f"{path} holds no pose estimate ({LOCALIZATION} or {ODOMETRY}) of a UAV in its truth")
    runner = None
    if baseline:
        runner = Baseline(voxel_size, threads, progress)
        if progress is not None:
            progress(f"kiss-icp: registering the scans of {', '.join(evaluable)}")
        for scan in read_scans(path, evaluable, data.undecodable):
            runner.add(scan)
        if progress is not None:
            progress(f"kiss-icp: done, {runner.read} scans read in {time.monotonic() - runner.began:.0f} s")
    notes: list[str] = []
    scores: dict[str, list[LocalizationScore]] = {}
    for uav in evaluable:
        truth = data.truth[uav]
        window = truth.airborne_window() if airborne else None
        if airborne and window is None:
            notes.append(f"{uav} was never airborne: nothing to score")
            scores[uav] = []
            continue
        rows: list[LocalizationScore] = []
        estimate = data.estimate(uav)
        if estimate is not None:
            if estimate.source == keys.ODOMETRY:
                flew = " (though the run flew it without GNSS)" if data.positioning.get(uav) == "lidar" else ""
                notes.append(f"the recording holds no localization of {uav} ({keys.uav(uav, keys.LOCALIZATION)})"
                             f"{flew}: its GNSS odometry ({estimate.key}) is scored instead")
            try:
                rows.append(score_localization(estimate.trajectory, truth, uav=uav, estimator="falconry",
                                               source=estimate.source, align=align, window=window,
                                               health=estimate.health))
            except CannotScore as exc:
                notes.append(f"{uav} falconry ({estimate.key}): not scored: {exc}")
            else:
                if rows[-1].ate_problem:
                    notes.append(f"{uav} falconry: no ATE: {rows[-1].ate_problem}")
        if runner is not None:
            rows += _baseline_row(uav, runner, truth, window, rows[0] if rows else None, align, notes)
        scores[uav] = rows
    return LocalizationEvaluation(path, scores, notes, align, airborne, baseline, data.report, data.undecodable)


def _baseline_row(uav: str, runner: Baseline, truth: TruthTrack, window: tuple[int, int] | None,
                  estimate: LocalizationScore | None, align: bool, notes: list[str]) -> list[LocalizationScore]:
    """KISS-ICP's row, over the recorded estimate's window when it has one (so both rows cover the
    same time), anchored at its start."""
    if estimate is not None:
        window = (estimate.start_ns, estimate.end_ns)
    odometry = runner.odometry.get(uav)
    try:
        trajectory, how = runner.trajectory(uav, truth, None if window is None else window[0])
        score = score_localization(trajectory, truth, uav=uav, estimator="kiss-icp", source="points", align=align,
                                   window=window, time_per_scan_ms=odometry.time_per_scan_ms(),
                                   scans=len(odometry.stamps), skipped_scans=odometry.skipped)
    except CannotScore as exc:
        notes.append(f"{uav} kiss-icp ({keys.uav(uav, 'points')}): not scored: {exc}")
        return []
    skipped = (f"; {odometry.skipped} scans skipped (fewer than {odometry.min_points} points within "
               f"{odometry.min_range:g}-{odometry.max_range:g} m, or out of stamp order)" if odometry.skipped else "")
    notes.append(f"{uav} kiss-icp: {len(odometry.stamps)} scans registered, voxel "
                 f"{odometry.config.mapping.voxel_size:g} m, {how}{skipped}")
    if score.ate_problem:
        notes.append(f"{uav} kiss-icp: no ATE: {score.ate_problem}")
    return [score]
