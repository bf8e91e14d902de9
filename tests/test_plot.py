"""The run timeline PNG and the run monitor behind it, for a simulated run and a real flight."""
from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas.arrays import from_numpy
from schemas.messages import Detections, GroundTruth, Header, SimEvent, UavStatus, VehicleTruth
from services.lib.runtime.errors import UsageError
from services.tools.launcher.monitor import RunMonitor
from services.tools.launcher.plot import plot_timeline

S = 1_000_000_000
encode = msgspec.msgpack.encode


def feed_run(monitor: RunMonitor, start: int) -> None:
    """Two UAVs for 10 s: states, detections, a destroyed target, and their true positions."""
    for k in range(0, 101):
        stamp = start + k * S // 10
        state = "TAKING_OFF" if k < 10 else "GOING_AROUND" if k < 60 else "DESTROYING"
        for i, uav in enumerate(("uav1", "uav2")):
            monitor.handle(f"falconry/{uav}/status", encode(UavStatus(
                header=Header(stamp=stamp), uav=uav, state=state, flying_normally=True, airborne=k >= 10,
                position=(0.0, 0.0, 5.0))))
            monitor.handle(f"falconry/{uav}/detections", encode(Detections(
                header=Header(stamp=stamp), detector="classifier", positions=from_numpy(np.zeros((k % 3, 3))),
                covariances=from_numpy(np.zeros((k % 3, 3, 3))), point_counts=from_numpy(np.zeros(k % 3, np.int32)),
                extents=from_numpy(np.zeros(k % 3, np.float32)))))
        monitor.handle("falconry/sim/truth", encode(GroundTruth(header=Header(stamp=stamp), step=k, uavs=[
            VehicleTruth(name="uav1", position=(0.0, 0.0, 5.0), velocity=(0, 0, 0), heading=0, airborne=k >= 10),
            VehicleTruth(name="uav2", position=(3.0 + (k - 10) / 10, 4.0, 5.0), velocity=(0, 0, 0), heading=0,
                         airborne=k >= 10)])))
    monitor.handle("falconry/sim/events", encode(SimEvent(header=Header(stamp=start + 8 * S), kind="target_destroyed",
                                                          subject="balloon1", detail="uav2")))


@pytest.mark.parametrize("start", [0, 1_790_000_000 * S], ids=["simulated", "flight (wall-clock stamps)"])
def test_the_timeline_reads_from_mission_time_zero_and_is_drawn(tmp_path, start):
    monitor = RunMonitor()
    feed_run(monitor, start)
    uav1 = monitor.uavs["uav1"]
    assert [state for _, state in uav1.states] == ["TAKING_OFF", "GOING_AROUND", "DESTROYING"]
    assert uav1.states[1][0] == pytest.approx(1.0)
    assert uav1.nearest_partner[0].value == pytest.approx(5.0)  # 3-4-5 at take-off
    assert all(b.t - a.t >= 0.25 - 1e-9 for a, b in zip(uav1.nearest_partner, uav1.nearest_partner[1:]))
    assert monitor.destroyed[0][:2] == (pytest.approx(8.0), "balloon1")
    assert monitor.latest == pytest.approx(10.0)
    path = tmp_path / "run.png"
    plot_timeline(monitor, path, "test run")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


def test_an_unwritable_plot_is_one_clear_error(tmp_path):
    monitor = RunMonitor()
    feed_run(monitor, 0)
    with pytest.raises(UsageError, match="cannot write the plot"):
        plot_timeline(monitor, tmp_path / "missing" / "run.png", "test run")


def test_the_monitor_reports_each_episode_below_the_safety_distance():
    """uav2 passes uav1 at 2 m (t = 3..5 s below 5 m), later comes within 4 m once more; landed UAVs never count."""
    monitor = RunMonitor(safety_distance=5.0)
    gaps = [8.0, 6.0, 4.9, 2.0, 4.0, 5.5, 7.0, 4.5, 6.0, 1.0]  # the last while uav2 is on the ground
    for k, gap in enumerate(gaps):
        monitor.handle("falconry/sim/truth", encode(GroundTruth(header=Header(stamp=(k + 1) * S), step=k, uavs=[
            VehicleTruth(name="uav1", position=(0.0, 0.0, 5.0), velocity=(0, 0, 0), heading=0, airborne=True),
            VehicleTruth(name="uav2", position=(gap, 0.0, 5.0), velocity=(0, 0, 0), heading=0, airborne=k < 9)])))
    summary = monitor.summary()
    assert summary["safety_distance"] == 5.0
    assert summary["min_separation"]["m"] == 2.0
    assert summary["separation_violations"] == [
        {"start": 3.0, "end": 6.0, "pair": "uav1-uav2", "m": 2.0},
        {"start": 8.0, "end": 9.0, "pair": "uav1-uav2", "m": 4.5}]
    assert RunMonitor().summary()["separation_violations"] == []  # no safety distance given: nothing judged


def test_the_monitor_judges_engagements_by_their_aim_and_scores_the_camera():
    """Each engagement is judged once, at its first attack or intercept command (re-plans of the same
    one follow it); an aim within 2 m of a standing target went for it, one at a pole top did not.
    Camera detections count as matched or false like the LiDAR's."""
    from schemas.messages import MissionCommand, TargetTruth
    from services.tools.launcher.sim_cmd import engagement_line
    monitor = RunMonitor()
    balloon = (30.0, 30.0, 4.0)
    monitor.handle("falconry/sim/truth", encode(GroundTruth(header=Header(stamp=S), step=0, targets=[
        TargetTruth(id="balloon1", kind="balloon", position=balloon, velocity=(0, 0, 0), radius=0.3)])))

    def command(k: int, action: str, target) -> None:
        monitor.handle("falconry/uav1/command", encode(MissionCommand(
            header=Header(stamp=S), command_id=k, action=action, target=target)))

    command(1, "approach", (29.0, 30.0, 4.0))
    command(2, "attack", (30.5, 30.0, 4.0))
    command(3, "attack", (30.3, 30.0, 4.0))  # a re-plan of the same attack
    command(4, "scan", None)
    command(5, "attack", (50.0, 12.0, 3.0))  # a red pole top: no target there
    camera = Detections(header=Header(stamp=S), detector="camera",
                        positions=from_numpy(np.array([balloon, (50.0, 12.0, 3.0)])),
                        covariances=from_numpy(np.zeros((2, 3, 3))), point_counts=from_numpy(np.zeros(2, np.int32)),
                        extents=from_numpy(np.zeros(2, np.float32)))
    monitor.handle("falconry/uav1/camera_detections", encode(camera))
    uav1 = monitor.summary()["uavs"]["uav1"]
    assert [(e["action"], e["target"]) for e in uav1["engagements"]] == [("attack", "balloon1"), ("attack", None)]
    assert uav1["engagements"][1]["miss_m"] == pytest.approx(math.dist((50.0, 12.0, 3.0), balloon), abs=0.01)
    assert (uav1["camera"]["detections"], uav1["camera"]["matched"], uav1["camera"]["false"]) == (2, 1, 1)
    assert monitor.first_detected["balloon1"] == (pytest.approx(1.0), "uav1")
    line = engagement_line(uav1["engagements"])
    assert line.startswith("2 attacks, 1 at no target: t=1.0 s attack at (50.0, 12.0, 3.0), nearest target")
    assert engagement_line(uav1["engagements"][:1]) == "1 attack, all at a target (within 2 m)"


def test_a_chase_taken_up_again_just_after_the_capture_aims_at_the_captured_drone_not_at_no_target():
    """A UAV learns its drone is down only once unseen for t_m (3 s): an intercept re-sent 0.05 s after
    the capture (after giving way) aims where the drone was; 3 s later the same aim is at nothing."""
    from schemas.messages import MissionCommand, TargetTruth
    monitor = RunMonitor()
    drone = (60.0, 20.0, 6.0)

    def truth(k: int, destroyed: bool) -> None:
        monitor.handle("falconry/sim/truth", encode(GroundTruth(header=Header(stamp=k * S // 20), step=k, targets=[
            TargetTruth(id="crosser", kind="drone", position=drone, velocity=(0, 0, 0), radius=0.3,
                        destroyed=destroyed)])))

    def command(k: int, action: str, target=None) -> None:
        monitor.handle("falconry/uav1/command", encode(MissionCommand(
            header=Header(stamp=k * S // 20), command_id=k, action=action, target=target)))

    truth(20, False)
    command(20, "intercept", drone)
    truth(21, True)  # captured at t = 1.05 s
    command(21, "stop")
    command(22, "intercept", (60.1, 20.0, 6.0))  # taken up again 0.05 s after the capture
    command(23, "stop")
    command(22 + 20 * 4, "intercept", (60.1, 20.0, 6.0))  # 4 s after: nothing there
    engagements = monitor.summary()["uavs"]["uav1"]["engagements"]
    assert [e["target"] for e in engagements] == ["crosser", "crosser", None]


def test_a_camera_detection_matches_within_a_tenth_of_its_distance_a_lidar_one_within_1_m():
    from services.tools import evaluation
    target = np.array([[40.0, 0.0, 4.0]])
    off = np.array([[37.5, 0.0, 4.0], [0.5, 0.0, 4.0]])  # 2.5 m short at 37.5 m; 0.5 m from a target at 1 m
    near = np.array([[1.0, 0.0, 4.0]])
    camera = np.array([0.0, 0.0, 4.0])
    tolerance = evaluation.camera_tolerance(off, camera)
    np.testing.assert_allclose(tolerance, [3.75, 1.0])
    assert evaluation.matched(off[:1], target, tolerance[:1]).tolist() == [True]
    assert evaluation.matched(off[:1], target).tolist() == [False]  # the LiDAR's 1 m
    assert evaluation.matched(off[1:], near, tolerance[1:]).tolist() == [True]
