"""`falconry evaluate localization`: a UAV's pose estimate against its true pose (seed 003's Table 2,
evo's ATE), beside KISS-ICP over its scans.

The Table-2 figures on synthetic trajectories with a known drift; the ATE (evo itself, not mocked)
on a known offset; matching, windows and the baseline's anchoring on hand-built cases; the command
on a small recording written with the project's MCAP writer (truth, localization, odometry and
scans of a rigid scene seen from a UAV flying straight), KISS-ICP included; and bad input.
"""
from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import GroundTruth, Header, Odometry, PointCloud, Pose, VehicleTruth
from services.tools.evaluation.localization import (CannotScore, KissIcpOdometry, Trajectory, TruthTrack,
                                              absolute_trajectory_error, anchored_baseline, heading_quaternions, match,
                                              mount_transform, path_length, pose_matrix, score_localization,
                                              sensor_frame_points, wrap_angle, yaw_of, yaw_turned)
from services.tools.launcher.cli import main
from services.tools.evaluation import localization_input
from services.tools.evaluation.localization_input import evaluate_localization
from services.tools.recorder.mcap_io import McapRecordWriter
from services.lib.runtime.clock import NS
from tests.conftest import REPO, falconry_argv

TICK = NS // 20  # the simulator's 50 ms tick
encode = msgspec.msgpack.encode


# --------------------------------------------------------------------------- seed 003's Table 2
def straight_run(samples: int = 1001, length: float = 100.0):
    """100 m along x at 5 m height in 50 s (20 Hz), the heading turning one full turn on the way
    (given wrapped to [-pi, pi), as the simulator gives it)."""
    stamps = np.arange(samples) * TICK
    s = np.linspace(0.0, length, samples)
    positions = np.c_[s, np.zeros(samples), np.full(samples, 5.0)]
    headings = np.linspace(0.0, 2 * np.pi, samples)
    return stamps, s, positions, headings, TruthTrack.of(stamps, positions, wrap_angle(headings))


def test_a_linear_drift_gives_the_table_2_figures():
    """1 m of sideways drift over 100 m travelled is 1 %; 1 deg of yaw drift over a full turn is 1/360."""
    stamps, s, positions, headings, truth = straight_run()
    drifting = Trajectory.from_headings(stamps, positions + np.c_[np.zeros_like(s), s / 100.0, np.zeros_like(s)],
                                        headings + np.radians(s / 100.0))
    score = score_localization(drifting, truth, uav="uav1")
    assert score.poses == 1001 and (score.start_ns, score.end_ns) == (0, 50 * NS)
    assert score.distance_m == pytest.approx(100.0, abs=1e-9)
    assert score.position_error_m == pytest.approx(1.0, abs=1e-9)
    assert score.position_error_pct == pytest.approx(1.0, abs=1e-9)
    assert score.yaw_turned_deg == pytest.approx(360.0, abs=1e-6)
    assert score.yaw_error_deg == pytest.approx(1.0, abs=1e-6)
    assert score.yaw_error_pct == pytest.approx(100.0 / 360.0, abs=1e-6)
    # the ATE of a drift growing linearly from 0 to 1 m: mean 0.5, RMS sqrt(1/3) (the samples' own)
    offsets = s / 100.0
    assert score.ate.rmse == pytest.approx(float(np.sqrt(np.mean(offsets ** 2))), abs=1e-9)
    assert (score.ate.mean, score.ate.max) == (pytest.approx(0.5, abs=1e-9), pytest.approx(1.0, abs=1e-9))
    summary = score.summary()
    assert (summary["position_error_pct"], summary["yaw_error_pct"], summary["aligned"]) == (1.0, 0.2778, False)


def test_the_start_end_error_is_the_seed_papers_on_a_loop_and_ignores_a_constant_offset():
    """A square loop of 40 m that ends where it started: the error is |e_end - e_start| (seed 003's);
    an estimate off by a constant offset has none, while its ATE is the offset."""
    corners = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]], dtype=float)
    xy = np.concatenate([np.linspace(a, b, 100, endpoint=False) for a, b in zip(corners[:-1], corners[1:])]
                        + [corners[-1:]])
    stamps = np.arange(len(xy)) * TICK
    positions = np.c_[xy, np.full(len(xy), 3.0)]
    truth = TruthTrack.of(stamps, positions, np.zeros(len(xy)))
    late = np.arange(len(xy)) / (len(xy) - 1)  # the estimate ends 0.3 m east, 0.4 m north of its start
    ending_off = Trajectory.from_headings(stamps, positions + np.c_[0.3 * late, 0.4 * late, 0 * late],
                                          np.zeros(len(xy)))
    score = score_localization(ending_off, truth)
    assert score.distance_m == pytest.approx(40.0) and score.position_error_m == pytest.approx(0.5)
    assert score.position_error_pct == pytest.approx(1.25) and score.yaw_turned_deg == 0.0
    assert score.yaw_error_pct is None  # no turn: no percentage
    shifted = Trajectory.from_headings(stamps, positions + [0.3, 0.4, 0.0], np.zeros(len(xy)))
    offset = score_localization(shifted, truth)
    assert offset.position_error_m == pytest.approx(0.0, abs=1e-9)
    assert (offset.ate.rmse, offset.ate.mean, offset.ate.max) == (pytest.approx(0.5), pytest.approx(0.5),
                                                                   pytest.approx(0.5))
    aligned = score_localization(shifted, truth, align=True)  # Umeyama takes the offset out
    assert aligned.ate.aligned and aligned.ate.rmse == pytest.approx(0.0, abs=1e-9)


def test_the_yaw_error_is_wrapped_and_the_yaw_turned_counts_every_turn():
    assert yaw_turned(wrap_angle(np.linspace(0, 4 * np.pi, 81))) == pytest.approx(4 * np.pi)
    assert yaw_turned([0.0, 0.5, 0.0, 0.5]) == pytest.approx(1.5)  # back and forth counts each way
    stamps, _, positions, headings, truth = straight_run()
    turned_back = Trajectory.from_headings(stamps, positions, headings + np.radians(np.linspace(0, 359, len(stamps))))
    assert score_localization(turned_back, truth).yaw_error_deg == pytest.approx(1.0, abs=1e-6)  # 359 deg: -1 deg
    assert yaw_of(heading_quaternions([3.0, -3.0])) == pytest.approx([3.0, -3.0])
    assert path_length([[0, 0, 0], [3, 4, 0], [3, 4, 12]]) == pytest.approx(17.0)


def test_ate_comes_from_evo_on_matched_poses():
    stamps, _, positions, headings, truth = straight_run(101, 10.0)
    estimate = Trajectory.from_headings(stamps, positions + [0.0, 0.0, 2.0], headings)
    ate = absolute_trajectory_error(match(truth.trajectory(), estimate))
    assert (ate.rmse, ate.mean, ate.max, ate.aligned) == (pytest.approx(2.0), pytest.approx(2.0),
                                                          pytest.approx(2.0), False)
    unaligned = score_localization(estimate, truth, align=True)  # a straight line leaves the rotation undetermined
    assert unaligned.ate is None and "cannot align" in unaligned.ate_problem
    assert unaligned.distance_m == pytest.approx(10.0) and unaligned.summary()["ate_rmse_m"] is None


def test_poses_between_ticks_meet_the_interpolated_truth_and_poses_without_truth_are_left_out():
    stamps, _, positions, headings, truth = straight_run(101, 10.0)  # 5 s at 2 m/s
    between = stamps[:-1] + TICK // 2
    midway = (positions[:-1] + positions[1:]) / 2
    # and three poses past the truth's end: not matched (never extrapolated)
    late = stamps[-1] + np.array([1, 2, 3]) * TICK
    estimate = Trajectory.from_headings(np.r_[between, late], np.r_[midway, np.zeros((3, 3))],
                                        np.r_[headings[:-1] + np.diff(headings) / 2, np.zeros(3)])
    score = score_localization(estimate, truth)
    assert score.poses == 100 and score.ate.rmse == pytest.approx(0.0, abs=1e-9)
    assert score.distance_m == pytest.approx(10.0 - 0.1)  # half a tick at 2 m/s lost at either end
    window = score_localization(estimate, truth, window=(1 * NS, 2 * NS))
    assert window.poses == 20 and window.distance_m == pytest.approx(1.9)  # 1.025 s to 1.975 s
    with pytest.raises(CannotScore, match="no pose of the estimate has a truth"):
        score_localization(estimate, truth, window=(100 * NS, 200 * NS))
    far = Trajectory.from_headings(stamps[:3] + TICK // 2, positions[:3], headings[:3])
    assert len(match(truth.trajectory(), far, max_diff=0.01)) == 0  # 25 ms from the nearest tick


def test_an_estimate_denser_than_the_truth_is_interpolated_at_the_truth_ticks():
    stamps, _, positions, headings, truth = straight_run(11, 1.0)
    fine = np.arange(0, stamps[-1] + 1, TICK // 5)
    s = fine / stamps[-1]
    estimate = Trajectory.from_headings(fine, np.c_[s, np.zeros_like(s), np.full_like(s, 5.0)], np.zeros_like(s))
    matched = match(truth.trajectory(), estimate)
    assert matched.estimate.stamps.tolist() == stamps.tolist()


def test_an_unsorted_estimate_is_sorted_and_non_finite_poses_dropped():
    trajectory = Trajectory.of([2, 1, 3, 3], [[2, 0, 0], [1, 0, 0], [math.nan, 0, 0], [3, 0, 0]],
                               heading_quaternions([0, 0, 0, 0]))
    assert trajectory.stamps.tolist() == [1, 2, 3] and trajectory.positions[:, 0].tolist() == [1, 2, 3]


# --------------------------------------------------------------------------- the baseline's frames
def test_the_baseline_is_anchored_at_the_true_pose_through_the_mount():
    """Sensor poses relative to the first scan, from a body turning and moving with the LiDAR
    mounted off its origin, come back as the body's true poses once anchored at any scan."""
    headings = np.radians([30.0, 40.0, 55.0, 70.0])
    bodies = [pose_matrix([2.0 * k, 1.0 * k, 5.0 + 0.1 * k], heading_quaternions([h])[0])
              for k, h in enumerate(headings)]
    mount = pose_matrix([0.1, 0.0, 0.3], (1.0, 0.0, 0.0, 0.0))
    sensors = [b @ mount for b in bodies]
    relative = [np.linalg.inv(sensors[0]) @ s for s in sensors]  # what KISS-ICP reports
    assert mount_transform(bodies[0], sensors[0]) == pytest.approx(mount)
    for anchor in (0, 2):
        trajectory = anchored_baseline([10, 20, 30, 40], relative, anchor, bodies[anchor], mount)
        assert trajectory.stamps.tolist() == [10, 20, 30, 40][anchor:]
        assert trajectory.matrices() == pytest.approx(np.array(bodies[anchor:]), abs=1e-9)


def test_sensor_frame_points_drop_no_returns_and_undo_the_sensor_pose():
    heading = np.radians(30.0)
    orientation = heading_quaternions([heading])[0]
    local = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, -1.0]])
    world = (pose_matrix([5.0, 6.0, 7.0], orientation) @ np.c_[local, np.ones(2)].T).T[:, :3]
    organised = np.full((2, 2, 3), np.nan)
    organised[0, 1], organised[1, 0] = world
    assert sensor_frame_points(organised, (5.0, 6.0, 7.0), orientation) == pytest.approx(local)


# --------------------------------------------------------------------------- a recording
RNG = np.random.default_rng(7)


def box_surface(lo, hi, count: int) -> np.ndarray:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    points = RNG.uniform(lo, hi, size=(count, 3))
    axis, side = RNG.integers(0, 3, count), RNG.integers(0, 2, count)
    points[np.arange(count), axis] = np.where(side, hi[axis], lo[axis])
    return points


# a ground and five boxes around the path, at random points on their surfaces (a regular grid
# would alias ICP): every direction of motion and rotation is constrained
SCENE = np.vstack([np.c_[RNG.uniform(-25, 25, (12000, 2)), np.zeros(12000)],
                   box_surface([-3, 5, 0], [2, 9, 5], 3000), box_surface([6, -8, 0], [9, -3, 3], 3000),
                   box_surface([-10, -9, 0], [-7, -4, 8], 3000), box_surface([10, 6, 0], [13, 12, 4], 3000),
                   box_surface([2, -2, 0], [3, -1, 2], 1000)])
HEADING = math.radians(30.0)
SPEED = 2.0  # m/s along the heading
MOUNT = np.array([0.1, 0.0, 0.3])  # the LiDAR in the body frame (the sensor driver's `mount`)
MAX_RANGE = 20.0


def body_position(t: float) -> np.ndarray:
    return np.array([SPEED * t * math.cos(HEADING), SPEED * t * math.sin(HEADING), 4.0])


def vehicle(uav: str, t: float, airborne: bool = True) -> VehicleTruth:
    return VehicleTruth(name=uav, position=tuple((body_position(t) + (0 if uav == "uav1" else 10.0)).tolist()),
                        velocity=(SPEED * math.cos(HEADING), SPEED * math.sin(HEADING), 0.0), heading=HEADING,
                        airborne=airborne)


def scan(stamp: int) -> PointCloud:
    """The scene as the LiDAR of uav1 sees it at `stamp`: world-frame points within range, NaN for
    the rest, organised as 8 rows."""
    origin = body_position(stamp / NS) + np.array([[math.cos(HEADING), -math.sin(HEADING), 0],
                                                   [math.sin(HEADING), math.cos(HEADING), 0], [0, 0, 1]]) @ MOUNT
    points = np.where((np.linalg.norm(SCENE - origin, axis=1) <= MAX_RANGE)[:, None], SCENE, np.nan)
    organised = points.reshape(8, -1, 3).astype(np.float32)
    return PointCloud(header=Header(stamp=stamp), width=organised.shape[1], height=8,
                      sensor_pose=Pose(tuple(origin.tolist()), tuple(heading_quaternions([HEADING])[0].tolist())),
                      points=from_numpy(organised), sensor_model="os0-32", min_range=0.3, max_range=MAX_RANGE)


def odometry(uav: str, stamp: int, offset=(0.0, 0.0, 0.0), health: str = "") -> Odometry:
    position = body_position(stamp / NS) + (0 if uav == "uav1" else 10.0) + np.asarray(offset)
    return Odometry(header=Header(stamp=stamp), health=health,
                    pose=Pose(tuple(position.tolist()), tuple(heading_quaternions([HEADING])[0].tolist())))


def write(path: Path, messages: list[tuple[str, object]]) -> Path:
    writer = McapRecordWriter(str(path))
    for n, (key, message) in enumerate(messages):
        writer.write(key, encode(message), 1_750_000_000 * NS + n)
    writer.close()
    return path


def synthetic_run(path: Path, seconds: float = 2.0, scans: bool = True) -> Path:
    """uav1 flies straight at 2 m/s for `seconds` (airborne from 0.5 s), its localizer's estimate
    drifting sideways to 0.2 m at the end (health degraded for the last quarter), its LiDAR
    scanning the scene at 10 Hz; uav2 flies alongside with GNSS odometry 0.3 m off in x, no scans."""
    ticks = int(round(seconds * 20))
    side = np.array([-math.sin(HEADING), math.cos(HEADING), 0.0])
    messages: list[tuple[str, object]] = []
    for k in range(ticks + 1):
        stamp, t = k * TICK, k * TICK / NS
        messages.append((keys.TRUTH, GroundTruth(header=Header(stamp=stamp), step=k, uavs=[
            vehicle("uav1", t, airborne=t >= 0.5), vehicle("uav2", t)])))
        messages.append(("falconry/uav1/odometry", odometry("uav1", stamp, (5.0, 0.0, 0.0))))  # ignored: localization
        messages.append(("falconry/uav2/odometry", odometry("uav2", stamp, (0.3, 0.0, 0.0))))
        if k % 2 == 0:
            health = "degraded" if k > 0.75 * ticks else "tracking"
            messages.append(("falconry/uav1/localization", odometry("uav1", stamp, side * 0.2 * k / ticks, health)))
            if scans:
                messages.append(("falconry/uav1/points", scan(stamp)))
    return write(path, messages)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return synthetic_run(tmp_path_factory.mktemp("localization") / "run.mcap")


def rows(out: str) -> dict[tuple[str, str], list[str]]:
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("UAV") and "ATE m" in line)
    return {tuple(line.split()[:2]): line.split() for line in lines[start + 1:] if line.strip()}


def test_the_command_scores_the_estimates_and_kiss_icp_recovers_the_straight_flight(recording, capsys,
                                                                                    monkeypatch):
    monkeypatch.setattr(localization_input, "PROGRESS_EVERY", 5)
    assert main(["evaluate", "localization", str(recording), "--json"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert "kiss-icp: 5 scans read, registered uav1 5" in captured.err  # progress on stderr
    uav1, uav2 = result["uavs"]["uav1"], result["uavs"]["uav2"]
    falconry = uav1["falconry"]
    assert (falconry["source"], falconry["poses"], falconry["start_s"], falconry["end_s"]) == \
        ("localization", 21, 0.0, 2.0)
    assert falconry["distance_m"] == pytest.approx(4.0, abs=1e-6)
    assert falconry["position_error_m"] == pytest.approx(0.2, abs=1e-6)
    assert falconry["position_error_pct"] == pytest.approx(5.0, abs=1e-3)
    assert falconry["health"] == {"degraded": 5, "tracking": 16}
    kiss = uav1["kiss-icp"]
    assert (kiss["source"], kiss["scans"], kiss["skipped_scans"], kiss["poses"]) == ("points", 21, 0, 21)
    assert kiss["distance_m"] == pytest.approx(4.0, abs=1e-6)  # the same window as falconry's
    assert kiss["position_error_m"] < 0.03 and kiss["ate_rmse_m"] < 0.03, kiss  # within a few cm
    assert kiss["yaw_error_deg"] < 0.5 and kiss["time_per_scan_ms"] > 0
    assert uav2["falconry"]["source"] == "odometry" and "kiss-icp" not in uav2
    assert uav2["falconry"]["ate_rmse_m"] == pytest.approx(0.3, abs=1e-6)
    assert uav2["falconry"]["position_error_m"] == pytest.approx(0.0, abs=1e-6)
    notes = "\n".join(result["notes"])
    assert "holds no localization of uav2 (falconry/uav2/localization): its GNSS odometry" in notes
    assert "uav2 kiss-icp (falconry/uav2/points): not scored: no scan registered" in notes
    assert "uav1 kiss-icp: 21 scans registered, voxel 0.2 m, anchored at the true pose at 0.00 s, LiDAR mount " \
           "(0.10, 0.00, 0.30) m in the body frame" in notes


def test_the_table_has_a_row_per_uav_and_estimate(recording, capsys):
    assert main(["evaluate", "localization", str(recording), "--airborne", "--align"]) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.startswith("UAV"))
    for column in ("estimate", "source", "poses", "from s", "to s", "distance m", "pos err m", "%", "yaw turned",
                   "yaw err", "ATE m", "ms/scan"):
        assert column in header
    table = rows(out)
    assert set(table) == {("uav1", "falconry"), ("uav1", "kiss-icp"), ("uav2", "falconry")}
    assert table[("uav1", "falconry")][2:7] == ["localization", "16", "0.5", "2.0", "3.00"]  # airborne from 0.5 s
    assert table[("uav1", "kiss-icp")][2:7] == ["points", "16", "0.5", "2.0", "3.00"]
    assert table[("uav1", "falconry")][-1] == "-" and float(table[("uav1", "kiss-icp")][-1]) > 0
    assert "ATE after rigid (SE(3)) alignment" in out and "the time each UAV was airborne" in out
    assert "note: uav1 localizer health over 21 messages: degraded 23.8 %, tracking 76.2 %" in out
    # a straight flight leaves the alignment undetermined: no ATE, said in a note, the rest scored
    assert table[("uav1", "falconry")][-2] == "-" and table[("uav2", "falconry")][-2] == "-"
    assert "note: uav2 falconry: no ATE: cannot align the estimate to the truth" in out


def test_no_baseline_and_one_uav(recording, capsys):
    assert main(["evaluate", "localization", str(recording), "--no-baseline", "--uav", "uav2"]) == 0
    captured = capsys.readouterr()
    assert set(rows(captured.out)) == {("uav2", "falconry")} and "no baseline (--no-baseline)" in captured.out
    assert captured.err == ""


def test_the_library_call_a_benchmark_makes(recording):
    evaluation = evaluate_localization(recording, ["uav1"], threads=1)
    falconry, kiss = evaluation.scores["uav1"]
    assert (falconry.estimator, kiss.estimator) == ("falconry", "kiss-icp")
    assert falconry.position_error_pct == pytest.approx(5.0, abs=1e-3) and kiss.ate.rmse < 0.03
    assert evaluation.summary()["uavs"]["uav1"]["kiss-icp"]["scans"] == 21


def test_kiss_icp_skips_scans_without_enough_returns_and_old_stamps():
    odometry = KissIcpOdometry(max_range=20.0, min_range=0.3, threads=1)
    assert not odometry.register(0, np.zeros((0, 3)))
    assert not odometry.register(0, np.full((500, 3), 50.0))  # all beyond the range
    assert odometry.register(1, SCENE[:20000] - [0.0, 0.0, 4.0]) and not odometry.register(1, SCENE[:20000])
    assert odometry.skipped == 3 and odometry.stamps == [1] and odometry.poses[0] == pytest.approx(np.eye(4))
    with pytest.raises(ValueError):
        KissIcpOdometry(max_range=0.0)


def test_help_explains_every_figure_and_option():
    result = subprocess.run(falconry_argv("evaluate", "localization", "--help"), cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 0
    for term in ("Table 2", "falconry", "kiss-icp", "GNSS odometry", "distance m", "pos err m", "yaw turned",
                 "yaw err", "ATE m", "ms/scan", "start-end", "(e1 - e0) - (t1 - t0)", "evo", "Umeyama", "mount",
                 "--uav", "--no-baseline", "--align", "--airborne", "--voxel", "--json"):
        assert term in result.stdout, term


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("case, args, expected", [
    ("missing", (), "no such recording"),
    ("not_mcap", (), "is not an MCAP file"),
    ("directory", (), "no such recording"),
    ("no_truth", (), "holds no ground truth (falconry/sim/truth)"),
    ("run", ("--uav", "uav9"), "holds no truth and estimate of uav9 (it has those of uav1, uav2)"),
    ("run", ("--voxel", "0"), "--voxel must be a positive size"),
    ("run", ("--voxel", "wide"), "invalid float value: 'wide'"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, case, args, expected):
    path = {"missing": lambda: tmp_path / "missing.mcap", "not_mcap": lambda: REPO / "README.md",
            "directory": lambda: tmp_path,
            "no_truth": lambda: write(tmp_path / "n.mcap", [("falconry/uav1/odometry", odometry("uav1", 0))]),
            "run": lambda: synthetic_run(tmp_path / "run.mcap", seconds=0.5, scans=False)}[case]()
    try:
        code = main(["evaluate", "localization", str(path), "--no-baseline", *args])
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    assert code == 2
    captured = capsys.readouterr()
    assert expected in captured.err and captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert captured.out == ""


def test_a_recording_without_estimates_is_one_line(tmp_path, capsys):
    path = write(tmp_path / "t.mcap", [(keys.TRUTH, GroundTruth(header=Header(stamp=0), step=0,
                                                                uavs=[vehicle("uav1", 0.0)]))])
    assert main(["evaluate", "localization", str(path)]) == 2
    err = capsys.readouterr().err
    assert "holds no pose estimate (falconry/*/localization or falconry/*/odometry)" in err and err.count("\n") == 1
