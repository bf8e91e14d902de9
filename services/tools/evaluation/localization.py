"""How well a UAV localized itself, against ground truth (`falconry evaluate localization`).

Evaluation only, pure numpy (evo and KISS-ICP imported when first needed: `falconry --help` imports
this module, and evo alone takes longer to import than the whole command line);
services/tools/evaluation/localization_input.py reads a recording. One estimate of one UAV (a `Trajectory`
of body poses in the world frame) is scored against that UAV's truth (`TruthTrack`, the
simulator's pose of the body at every tick), over the estimate's time (below): seed 003's Table 2
(the Grape LiDAR-inertial SLAM, §2.1) and the absolute trajectory error.

- Matching: each estimated pose is paired with the truth at its stamp, the truth interpolated
  between its ticks (evo.core.sync.associate_trajectories, SyncMethod.interpolation: positions
  linearly, orientations by slerp; a pose with no truth tick within MAX_DIFF_S, one simulator
  tick, is left out). Should the estimate have more poses than the truth over its time, the truth
  ticks are the pairs' stamps and the estimate is interpolated instead. In a simulated run every
  stamp is a tick, so the pairs are exact.
- Window: from the first matched pose to the last one (the estimate's whole time: for a localizer
  started before take-off its drift on the ground counts too);
  `window` narrows it (the command's --airborne: from the UAV's first airborne truth to its last).
- Distance travelled, m: the length of the TRUE path over the window (every truth tick inside it,
  and the interpolated truths at its ends).
- Position error, m: the start–end error. With e the estimated and t the true positions at the
  window's first (0) and last (1) pose,
      |(e1 − e0) − (t1 − t0)|,
  the error of the estimated displacement: where the estimate ends relative to where it started,
  against where the UAV really ended relative to where it started. It equals the final position
  error when the estimate starts at the true pose, and ignores a constant offset. Position error,
  % = 100 · that / distance travelled. Seed 003 recorded runs that end where they start (to about
  5 cm) and took the distance between the estimated start and end poses divided by the ESTIMATED
  total distance; on such a run the error above is exactly that distance (t1 − t0 = 0), and the
  true distance replaces the estimated one (they differ by the estimate's error).
- Yaw turned, deg: Σ |Δ yaw| of the truth over the window's ticks, each Δ wrapped to [−180°, 180°)
  (seed 003 counted the rotation in ticks of 45°, leaving out smaller turns made by the walking
  carrier; a flying UAV's yaw is commanded, so every turn counts here).
- Yaw error, deg: the same start–end idea on the heading, |wrap((ψe1 − ψe0) − (ψt1 − ψt0))|, the
  estimated yaw from the pose's quaternion (roll and pitch ignored), the true one the simulator's
  heading. Wrapped: a drift of a whole turn reads as none. Yaw error, % = 100 · that / yaw turned.
- ATE (absolute trajectory error, Sturm et al. 2012), m: the root mean square (and mean, max) of the
  3-D distance between matched estimated and true positions (evo.core.metrics.APE, translation
  part). Not aligned by default: the localizer's map frame is the world frame it was started in (at
  the known launch pose), so a constant offset is an error; `align=True` first applies the rigid
  SE(3) transform (Umeyama, no scale) that fits the estimate best to the truth, which leaves only
  the shape of the error (the usual ATE of odometry benchmarks).

The KISS-ICP baseline (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP", RA-L 2023;
PyPI kiss-icp): `KissIcpOdometry` registers a UAV's scans, in the sensor frame, in stamp order,
motion compensation (deskew) off (the simulated LiDAR takes a scan at one instant); its poses are
the sensor's relative to the first scan. `anchored_baseline` turns them into body poses in the
world: anchored, like the localizer, at the known true pose of the body at the first scan of the
window, and through the fixed LiDAR mount (sensor pose in the body frame, measured at the UAV's
first scan: `mount_transform`): B_k = B_a · M · T_a⁻¹ · T_k · M⁻¹, with B_a the true body pose at the
anchor scan a, T the KISS-ICP poses and M the mount. The body trajectory is scored like the
localizer's, against the same truth. Seen from a few metres up, a simulated scan is mostly flat,
featureless ground (2 cm of range noise) whose rings move with the sensor; KISS-ICP's point-to-point registration then
takes much of a horizontal motion for none (on the intruder scenario it keeps within 0.4 m over
23 m of flight once the ground points are left out, and loses most of it with them): the
baseline is KISS-ICP as its authors configure it, its failure there is part of the comparison.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from services.lib.geometry import heading_quaternions, quaternion, rotation_matrix, wrap_angle, yaw_of
from services.lib.runtime.clock import NS

MAX_DIFF_S = 0.05  # s: a pose is matched to the truth only with a truth tick this close (the simulator's tick)
MIN_SCAN_POINTS = 100  # a scan with fewer finite returns in range is not registered (silent or NaN LiDAR)


def _positions(points) -> np.ndarray:
    return np.asarray(points, dtype=np.float64).reshape(-1, 3)


# --------------------------------------------------------------------------------- trajectories
@dataclass(frozen=True)
class Trajectory:
    """Body poses over time in the world frame: the estimate (or the truth) of one UAV."""

    stamps: np.ndarray  # (N,) int64 mission time, ns, increasing
    positions: np.ndarray  # (N, 3) m
    orientations: np.ndarray  # (N, 4) quaternions (w, x, y, z), schemas' Pose order

    @staticmethod
    def of(stamps, positions, orientations) -> Trajectory:
        """Sorted by stamp, one pose per stamp (the last given), poses with a non-finite value dropped."""
        stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
        positions = _positions(positions)
        orientations = np.asarray(orientations, dtype=np.float64).reshape(-1, 4)
        if not len(stamps) == len(positions) == len(orientations):
            raise ValueError(f"{len(stamps)} stamps, {len(positions)} positions and {len(orientations)} "
                             "orientations do not make a trajectory")
        finite = (np.isfinite(positions).all(axis=1) & np.isfinite(orientations).all(axis=1)
                  & (np.linalg.norm(orientations, axis=1) > 0))
        stamps, positions, orientations = stamps[finite], positions[finite], orientations[finite]
        order = np.argsort(stamps, kind="stable")
        stamps, positions, orientations = stamps[order], positions[order], orientations[order]
        last = np.append(stamps[1:] != stamps[:-1], True)  # of several poses at one stamp, the last given
        return Trajectory(stamps[last], positions[last], orientations[last])

    @staticmethod
    def from_headings(stamps, positions, headings) -> Trajectory:
        """A level body's poses from its heading (yaw, rad), as the simulator's truth gives them."""
        return Trajectory.of(stamps, positions, heading_quaternions(headings))

    def __len__(self) -> int:
        return len(self.stamps)

    def yaw(self) -> np.ndarray:
        return yaw_of(self.orientations.reshape(-1, 4))

    def between(self, start: int, end: int) -> Trajectory:
        """The poses with start <= stamp <= end."""
        keep = (self.stamps >= start) & (self.stamps <= end)
        return Trajectory(self.stamps[keep], self.positions[keep], self.orientations[keep])

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) homogeneous poses (body to world)."""
        out = np.tile(np.eye(4), (len(self), 1, 1))
        out[:, :3, :3] = [rotation_matrix(q) for q in self.orientations]
        out[:, :3, 3] = self.positions
        return out

    def to_evo(self, name: str = ""):
        """This trajectory as evo's PoseTrajectory3D (stamps in s)."""
        from evo.core.trajectory import PoseTrajectory3D

        return PoseTrajectory3D(positions_xyz=self.positions.copy(), orientations_quat_wxyz=self.orientations.copy(),
                                timestamps=self.stamps / NS, meta={"name": name} if name else None)


@dataclass(frozen=True)
class TruthTrack:
    """One UAV's true body poses at the truth ticks: the simulator's position and heading."""

    stamps: np.ndarray  # (N,) int64 ns, increasing
    positions: np.ndarray  # (N, 3) m
    headings: np.ndarray  # (N,) yaw, rad
    airborne: np.ndarray  # (N,) bool

    @staticmethod
    def of(stamps, positions, headings, airborne=None) -> TruthTrack:
        stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
        airborne = np.ones(len(stamps), dtype=bool) if airborne is None else np.asarray(airborne, dtype=bool)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        unique = np.append(stamps[1:] != stamps[:-1], True)
        return TruthTrack(stamps[unique], _positions(positions)[order][unique],
                          np.asarray(headings, dtype=np.float64).reshape(-1)[order][unique],
                          airborne.reshape(-1)[order][unique])

    def __len__(self) -> int:
        return len(self.stamps)

    def trajectory(self) -> Trajectory:
        return Trajectory.from_headings(self.stamps, self.positions, self.headings)

    def pose_at(self, stamp: int) -> np.ndarray | None:
        """(4, 4) true body pose at `stamp`, interpolated between ticks (position linearly, heading
        along the shorter turn); None outside the truth or more than MAX_DIFF_S from a tick."""
        if not len(self) or stamp < self.stamps[0] or stamp > self.stamps[-1]:
            return None
        i = int(np.searchsorted(self.stamps, stamp, side="left"))
        if self.stamps[i] == stamp:
            position, heading = self.positions[i], self.headings[i]
        else:
            before, after = self.stamps[i - 1], self.stamps[i]
            if min(stamp - before, after - stamp) > MAX_DIFF_S * NS:
                return None
            w = (stamp - before) / (after - before)
            position = self.positions[i - 1] + w * (self.positions[i] - self.positions[i - 1])
            heading = self.headings[i - 1] + w * float(wrap_angle(self.headings[i] - self.headings[i - 1]))
        return pose_matrix(position, heading_quaternions([heading])[0])

    def airborne_window(self) -> tuple[int, int] | None:
        """(first, last) stamp at which the UAV was airborne; None: never."""
        flying = self.stamps[self.airborne]
        return (int(flying[0]), int(flying[-1])) if len(flying) else None


def pose_matrix(position, orientation) -> np.ndarray:
    """(4, 4) homogeneous pose of a position and a quaternion (w, x, y, z)."""
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(orientation)
    out[:3, 3] = np.asarray(position, dtype=np.float64).reshape(3)
    return out


# --------------------------------------------------------------------------------- seed 003's Table 2
def path_length(positions) -> float:
    """Length of the polyline through the (N, 3) positions, m."""
    return float(np.linalg.norm(np.diff(_positions(positions), axis=0), axis=1).sum())


def yaw_turned(headings) -> float:
    """Σ |Δ yaw| over the (N,) headings, each step wrapped to [−π, π), rad."""
    return float(np.abs(wrap_angle(np.diff(np.asarray(headings, dtype=np.float64).reshape(-1)))).sum())


def start_end_position_error(estimated, true) -> float:
    """|(e_last − e_first) − (t_last − t_first)| of matched (N, 3) estimated and true positions, m."""
    e, t = _positions(estimated), _positions(true)
    return float(np.linalg.norm((e[-1] - e[0]) - (t[-1] - t[0])))


def start_end_yaw_error(estimated, true) -> float:
    """|wrap((ψe_last − ψe_first) − (ψt_last − ψt_first))| of matched (N,) estimated and true yaws, rad."""
    e, t = np.asarray(estimated, dtype=np.float64).reshape(-1), np.asarray(true, dtype=np.float64).reshape(-1)
    return float(abs(wrap_angle((e[-1] - e[0]) - (t[-1] - t[0]))))


# --------------------------------------------------------------------------------- ATE (evo)
class CannotScore(ValueError):
    """The estimate has no pose matched to the truth (in the window), or cannot be aligned to it."""


@dataclass(frozen=True)
class Matched:
    """An estimate and the truth at its stamps, pose for pose."""

    truth: Trajectory
    estimate: Trajectory

    def __len__(self) -> int:
        return len(self.estimate)


def match(truth: Trajectory, estimate: Trajectory, max_diff: float = MAX_DIFF_S) -> Matched:
    """The estimate's poses that have a truth tick within `max_diff` s, each with the truth
    interpolated at its stamp (evo's associate_trajectories by interpolation: the trajectory with
    fewer poses keeps them, the other is interpolated at their stamps); only estimated poses within
    the truth's time (interpolation never extrapolates). Empty when none."""
    empty = Matched(truth.between(1, 0), estimate.between(1, 0))
    if len(truth) < 2 or not len(estimate):
        return empty
    inside = estimate.between(int(truth.stamps[0]), int(truth.stamps[-1]))
    if not len(inside):
        return empty
    from evo.core import sync

    ref, est = truth.to_evo("truth"), inside.to_evo("estimate")
    try:
        ref, est = sync.associate_trajectories(ref, est, sync_method=sync.SyncMethod.interpolation,
                                               max_diff=max_diff)
    except sync.SyncException:
        return empty
    # the sparser of the two keeps its poses, the other is interpolated at its stamps
    stamps = np.rint(est.timestamps * NS).astype(np.int64)
    return Matched(truth=Trajectory(stamps, np.asarray(ref.positions_xyz), np.asarray(ref.orientations_quat_wxyz)),
                   estimate=Trajectory(stamps, np.asarray(est.positions_xyz), np.asarray(est.orientations_quat_wxyz)))


@dataclass(frozen=True)
class Ate:
    """Absolute trajectory error (translation part) of matched poses, m."""

    rmse: float
    mean: float
    max: float
    aligned: bool  # the estimate was first aligned to the truth by the best rigid (SE(3)) transform


def absolute_trajectory_error(matched: Matched, align: bool = False) -> Ate:
    """evo's APE, translation part, of matched poses (at least one; `align` needs three not on one
    line: raises CannotScore otherwise)."""
    if align and len(matched) < 3:
        raise CannotScore(f"cannot align {len(matched)} poses to the truth (it takes 3 not on one line)")
    from evo.core import metrics

    from evo.core.geometry import GeometryException

    ref, est = matched.truth.to_evo("truth"), matched.estimate.to_evo("estimate")
    if align:
        try:
            est.align(ref, correct_scale=False)
        except GeometryException as exc:  # e.g. every position on one line: the rotation is undetermined
            raise CannotScore(f"cannot align the estimate to the truth ({exc})") from None
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stat = ape.get_statistic
    return Ate(rmse=float(stat(metrics.StatisticsType.rmse)), mean=float(stat(metrics.StatisticsType.mean)),
               max=float(stat(metrics.StatisticsType.max)), aligned=align)


# --------------------------------------------------------------------------------- the score
@dataclass(frozen=True)
class LocalizationScore:
    """One estimate of one UAV against its truth: seed 003's Table 2 and the ATE (the module's text)."""

    uav: str
    estimator: str  # "falconry", "kiss-icp"
    source: str  # where the poses came from: "localization", "odometry" (GNSS), "points" (the baseline)
    poses: int  # matched poses in the window
    start_ns: int  # the window: the first and last matched pose, mission time
    end_ns: int
    distance_m: float  # true path length
    position_error_m: float  # start-end position error
    position_error_pct: float | None  # of distance_m (None: no distance travelled)
    yaw_turned_deg: float  # Σ |Δ yaw| of the truth
    yaw_error_deg: float  # start-end yaw error
    yaw_error_pct: float | None  # of yaw_turned_deg (None: no turn)
    ate: Ate | None  # None: `align` asked for and the poses cannot be aligned (see ate_problem)
    time_per_scan_ms: float | None = None  # the estimator's mean compute time per scan, when known
    scans: int | None = None  # scans registered (the baseline)
    skipped_scans: int = 0  # scans not registered: too few points in range, or out of stamp order
    health: dict[str, int] = field(default_factory=dict)  # the localizer's health -> messages
    ate_problem: str = ""  # why there is no ATE

    def summary(self) -> dict:
        r = _rounded
        ate = self.ate
        return {"estimator": self.estimator, "source": self.source, "poses": self.poses,
                "start_s": r(self.start_ns / NS), "end_s": r(self.end_ns / NS), "distance_m": r(self.distance_m),
                "position_error_m": r(self.position_error_m), "position_error_pct": r(self.position_error_pct),
                "yaw_turned_deg": r(self.yaw_turned_deg), "yaw_error_deg": r(self.yaw_error_deg),
                "yaw_error_pct": r(self.yaw_error_pct), "ate_rmse_m": r(ate.rmse) if ate else None,
                "ate_mean_m": r(ate.mean) if ate else None, "ate_max_m": r(ate.max) if ate else None,
                "aligned": ate.aligned if ate else None, "ate_problem": self.ate_problem or None,
                "time_per_scan_ms": r(self.time_per_scan_ms), "scans": self.scans,
                "skipped_scans": self.skipped_scans, "health": dict(self.health)}


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)


def _percent(part: float, whole: float) -> float | None:
    return 100.0 * part / whole if whole > 1e-9 else None


def score_localization(estimate: Trajectory, truth: TruthTrack, *, uav: str = "", estimator: str = "falconry",
                       source: str = "localization", align: bool = False, window: tuple[int, int] | None = None,
                       max_diff: float = MAX_DIFF_S, time_per_scan_ms: float | None = None,
                       scans: int | None = None, skipped_scans: int = 0,
                       health: dict[str, int] | None = None) -> LocalizationScore:
    """`estimate` against `truth` over the estimate's time (within `window`, (start, end) stamps in
    ns, when given): see the module's text. Raises CannotScore when no pose is matched; when
    `align` is asked for and the poses cannot be aligned (fewer than three, all on one line), the
    score has no ATE and says why (ate_problem)."""
    if window is not None:
        estimate = estimate.between(*window)
    matched = match(truth.trajectory(), estimate, max_diff)
    if not len(matched):
        raise CannotScore(f"no pose of the estimate has a truth within {max_diff:g} s")
    start, end = int(matched.estimate.stamps[0]), int(matched.estimate.stamps[-1])
    inside = (truth.stamps > start) & (truth.stamps < end)
    true_path = np.concatenate([matched.truth.positions[:1], truth.positions[inside], matched.truth.positions[-1:]])
    true_yaws = matched.truth.yaw()
    true_headings = np.concatenate([true_yaws[:1], truth.headings[inside], true_yaws[-1:]])
    distance, turned = path_length(true_path), np.degrees(yaw_turned(true_headings))
    position_error = start_end_position_error(matched.estimate.positions, matched.truth.positions)
    yaw_error = np.degrees(start_end_yaw_error(matched.estimate.yaw(), true_yaws))
    try:
        ate, ate_problem = absolute_trajectory_error(matched, align), ""
    except CannotScore as exc:
        ate, ate_problem = None, str(exc)
    return LocalizationScore(
        uav=uav, estimator=estimator, source=source, poses=len(matched), start_ns=start, end_ns=end,
        distance_m=distance, position_error_m=position_error, position_error_pct=_percent(position_error, distance),
        yaw_turned_deg=float(turned), yaw_error_deg=float(yaw_error), yaw_error_pct=_percent(yaw_error, turned),
        ate=ate, time_per_scan_ms=time_per_scan_ms, scans=scans, skipped_scans=skipped_scans,
        health=dict(health or {}), ate_problem=ate_problem)


# --------------------------------------------------------------------------------- the KISS-ICP baseline
def sensor_frame_points(points, position, orientation) -> np.ndarray:
    """(N, 3) float64: the finite world-frame points of an organised scan ((H, W, 3), NaN for no
    return) in the frame of the sensor at `position` with `orientation` (w, x, y, z): Rᵀ (p − position)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    return (p - np.asarray(position, dtype=np.float64).reshape(3)) @ rotation_matrix(orientation)


def mount_transform(body_pose: np.ndarray, sensor_pose: np.ndarray) -> np.ndarray:
    """(4, 4) the sensor's pose in the body frame, M = B⁻¹ S, from the body's and the sensor's
    (4, 4) world poses at one instant."""
    return np.linalg.inv(body_pose) @ sensor_pose


class KissIcpOdometry:
    """KISS-ICP over one sensor's scans, in stamp order: `register` each (sensor-frame points);
    `stamps` and `poses` (4 × 4, the sensor's pose relative to the first registered scan) grow by
    one per registered scan; `seconds` is the compute time of each."""

    def __init__(self, max_range: float, min_range: float = 0.0, voxel_size: float | None = None,
                 threads: int = 0, min_points: int = MIN_SCAN_POINTS) -> None:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        if not (np.isfinite(max_range) and max_range > min_range >= 0):
            raise ValueError(f"KISS-ICP needs 0 <= min_range < max_range, not {min_range:g} and {max_range:g}")
        config = KISSConfig()
        config.data.max_range, config.data.min_range, config.data.deskew = float(max_range), float(min_range), False
        # KISS-ICP's own default (its load_config): a hundredth of the range
        config.mapping.voxel_size = float(voxel_size) if voxel_size else float(max_range) / 100.0
        config.registration.max_num_threads = int(threads)
        self.config = config
        self.min_range, self.max_range, self.min_points = float(min_range), float(max_range), min_points
        self._icp = KissICP(config)
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []
        self.seconds: list[float] = []
        self.skipped = 0  # scans not registered: too few points in range, or a stamp not after the last

    def register(self, stamp: int, points) -> bool:
        """One scan's (N, 3) sensor-frame points; False (and counted in `skipped`) when it has
        fewer than `min_points` within the ranges or is not newer than the last one registered."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        distance = np.linalg.norm(p, axis=1)
        p = p[(distance >= self.min_range) & (distance <= self.max_range)]
        if len(p) < self.min_points or (self.stamps and stamp <= self.stamps[-1]):
            self.skipped += 1
            return False
        began = time.perf_counter()
        self._icp.register_frame(np.ascontiguousarray(p), np.zeros(len(p)))
        self.seconds.append(time.perf_counter() - began)
        self.stamps.append(int(stamp))
        self.poses.append(np.array(self._icp.last_pose, dtype=np.float64))
        return True

    def time_per_scan_ms(self) -> float | None:
        return 1e3 * float(np.mean(self.seconds)) if self.seconds else None


def anchored_baseline(stamps: Sequence[int], poses, anchor: int, body_at_anchor: np.ndarray,
                      mount: np.ndarray) -> Trajectory:
    """The body's world poses from sensor poses relative to the first scan ((N, 4, 4) `poses` at
    `stamps`), anchored at scan index `anchor` where the body's true pose is `body_at_anchor`, the
    sensor mounted at `mount` (its pose in the body frame): B_k = B_a · M · T_a⁻¹ · T_k · M⁻¹.
    Only the poses from the anchor on."""
    t = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[anchor:]
    world = body_at_anchor @ mount @ np.linalg.inv(t[0]) @ t @ np.linalg.inv(mount)
    return Trajectory.of(np.asarray(stamps, dtype=np.int64)[anchor:], world[:, :3, 3],
                         [quaternion(m[:3, :3]) for m in world])
