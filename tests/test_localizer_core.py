"""The localizer as one pipeline (services/localizer/core.py) and what GNSS-denied flight adds around
it: pole features (poles.py) on scans cast by the sensor driver's own caster, the scan registration by
the estimate (sensor_driver/core.py), the flight controller's relay of the estimate
(simulator/positioning.py), and whole flights of the simulator's vehicle and IMU through a scenario's
world, scan by scan, without Zenoh. Fixed seeds: deterministic."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from schemas.messages import Obstacle
from services.lib.lidar.models import lidar_model
from services.localizer.core import Localizer, LocalizerParams, restart_frame_covariance, sensor_frame
from services.localizer.features import FeatureParams, extract_features
from services.lib.geometry import yaw_rotation
from services.lib.lidar.models import DEFAULT_MOUNT
from services.lib.world.primitives import primitives_from_obstacles
from services.sensor_driver.core import reregistered, scan, SensorDriverParams
from services.lib.runtime.clock import to_ns
from services.simulator.core import Simulation
from services.simulator.positioning import EstimateRelay
from services.simulator.scenario import load_scenario
from services.simulator.specs import NS

TICK = 0.05
MODEL = lidar_model("os0-128", 10.0)


def cast(origin, heading: float, obstacles: list[Obstacle], seed: int = 0, frame: int = 0):
    world = primitives_from_obstacles(obstacles)
    return scan(np.asarray(origin, dtype=float), heading, MODEL.directions(frame), world, np.random.default_rng(seed),
                min_range=MODEL.min_range, max_range=MODEL.max_range)


# ------------------------------------------------------------------ frames
def test_sensor_frame_undoes_the_registration_and_keeps_no_returns():
    rng = np.random.default_rng(1)
    local = rng.normal(size=(4, 5, 3)) * 10
    local[1, 2] = np.nan
    origin, heading = np.array([3.0, -2.0, 5.0]), 0.7
    world = local @ yaw_rotation(heading).T + origin
    back = sensor_frame(world, origin, yaw_rotation(heading))
    np.testing.assert_allclose(back, local, atol=1e-12)
    assert np.isnan(back[1, 2]).all()
    with pytest.raises(ValueError, match="organised scan"):
        sensor_frame(np.zeros((10, 3)), origin, np.eye(3))


def test_a_scan_registered_by_a_wrong_pose_keeps_every_point_where_it_is_from_the_sensor():
    rng = np.random.default_rng(2)
    origin, heading = np.array([10.0, 5.0, 4.0]), 0.3
    believed_origin, believed_heading = origin + [0.5, -0.3, 0.1], heading + 0.05
    points = (origin + rng.normal(size=(3, 7, 3)) * 8).astype(np.float32)
    points[0, 0] = np.nan
    moved = reregistered(points, origin, heading, believed_origin, believed_heading)
    assert moved.dtype == np.float32 and np.isnan(moved[0, 0]).all()
    seen_from_truth = sensor_frame(points, origin, yaw_rotation(heading))
    seen_from_belief = sensor_frame(moved, believed_origin, yaw_rotation(believed_heading))
    np.testing.assert_allclose(seen_from_belief, seen_from_truth, atol=1e-4)


def test_the_flight_controller_holds_the_estimates_error_at_its_own_stamp():
    relay = EstimateRelay(timeout=1_000)
    for k in range(5):
        relay.record_truth("uav1", k * 50, np.array([k, 0.0, 5.0]), 0.1 * k)
    error = relay.take_estimate("uav1", 100, (2.3, 0.1, 5.0), 0.25, np.eye(6), "degraded")
    np.testing.assert_allclose(error.position, [0.3, 0.1, 0.0])
    assert error.heading == pytest.approx(0.05) and error.health == "degraded"
    assert relay.take_estimate("uav1", 75, (2.0, 0.0, 5.0), 0.0, None, "tracking") is None  # no truth then
    assert relay.take_estimate("uav1", 50, (1.0, 0.0, 5.0), 0.1, None, "tracking") is None  # older than held
    assert relay.take_estimate("uav1", 150, (math.nan, 0.0, 5.0), 0.3, None, "tracking") is None
    assert relay.errors["uav1"].stamp == 100
    wrapped = relay.take_estimate("uav1", 200, (4.0, 0.0, 5.0), -math.pi + 0.01 + 0.4 - 2 * math.pi, None, "tracking")
    assert abs(wrapped.heading) < math.pi


def test_the_simulator_publishes_the_belief_and_calls_it_lost_once_the_estimates_stop():
    """The simulator node as the flight controller of a UAV without GNSS: its odometry is the belief
    (truth + the estimate's error, the localizer's covariance and health) until the estimates stop
    for estimate_timeout, then "lost"; a UAV with GNSS is untouched."""
    from schemas import keys
    from schemas.arrays import from_numpy, to_numpy
    from schemas.messages import Header, Odometry, Pose
    from services.lib.geometry import heading_quaternion
    from tests.tools.fuzz import encode, wire

    wired = wire("simulator", positioning="lidar")
    node = wired.node
    node.publish_state(0, 0)
    first = wired.published(Odometry, keys.uav("uav1", keys.ODOMETRY))
    assert first.health == ""  # the launch pose: no estimate yet
    truth = node.sim.vehicles()[0]
    covariance = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    wired.deliver(keys.uav("uav1", keys.LOCALIZATION), encode(Odometry(
        header=Header(stamp=0), pose=Pose(position=tuple(truth.position + [0.2, 0.0, 0.0]),
                                          orientation=heading_quaternion(truth.heading)),
        covariance=from_numpy(covariance), health="tracking")))
    timeout = to_ns(node.params.estimate_timeout)
    for now, health in ((timeout, "tracking"), (timeout + 50_000_000, "lost")):
        node.publish_state(1, now)
        odometry = wired.published(Odometry, keys.uav("uav1", keys.ODOMETRY))
        assert odometry.health == health
        np.testing.assert_allclose(odometry.pose.position, node.sim.vehicles()[0].position + [0.2, 0.0, 0.0])
        np.testing.assert_allclose(to_numpy(odometry.covariance).reshape(6, 6), covariance)
    assert node.positioning == {"uav1": "lidar", "uav2": "lidar"}


def test_an_estimate_stream_that_stops_makes_the_flight_controllers_position_lost():
    """A localizer alive but silent (frozen, starved of IMU samples) must not leave the UAV flying on
    a frozen belief still called "tracking": past the timeout the belief's health is "lost"."""
    relay = EstimateRelay(timeout=1_000)
    assert relay.belief("uav1", 0) is None  # no estimate yet: the launch pose, no health
    for k in range(3):
        relay.record_truth("uav1", k * 100, np.array([k, 0.0, 5.0]), 0.0)
    relay.take_estimate("uav1", 100, (1.2, 0.0, 5.0), 0.02, np.eye(6), "tracking")
    fresh, last = relay.belief("uav1", 1_100), relay.belief("uav1", 1_101)
    assert (fresh.health, last.health) == ("tracking", "lost")
    assert last.heading_error == pytest.approx(0.02) and np.array_equal(last.covariance, np.eye(6))
    relay.take_estimate("uav1", 200, (2.1, 0.0, 5.0), 0.0, None, "degraded")  # the stream is back
    assert relay.belief("uav1", 1_101).health == "degraded"
    with pytest.raises(ValueError, match="positive"):
        EstimateRelay(timeout=0)


# ------------------------------------------------------------------ poles
GROUND = Obstacle(kind="plane", center=(0.0, 0.0, 0.0))
TRUNK = Obstacle(kind="cylinder", center=(12.0, 5.0, 0.0), radius=1.5, height=7.0)
POLE = Obstacle(kind="cylinder", center=(-4.0, -6.0, 0.0), radius=0.05, height=4.0)
CONE = Obstacle(kind="cone", center=(-15.0, 10.0, 0.0), radius=2.0, height=8.0)
BALLOON = Obstacle(kind="sphere", center=(3.0, 9.0, 5.0), radius=0.3)


def axis_offset(edge, obstacle: Obstacle, origin: np.ndarray) -> tuple[float, float]:
    """Horizontal distance (m) of the feature's line from the obstacle's axis at the feature's height,
    and the angle (°) between the line and the vertical."""
    centre = edge.centre + origin  # sensor frame is level and unrotated here
    return float(np.hypot(*(centre[:2] - np.array(obstacle.center[:2])))), \
        math.degrees(math.acos(min(1.0, abs(edge.direction[2]))))


def test_trunks_poles_and_cones_give_vertical_lines_through_their_axes_and_a_balloon_does_not():
    origin = np.array([0.0, 0.0, 4.0])
    cloud = cast(origin, 0.0, [GROUND, TRUNK, POLE, CONE, BALLOON])
    local = sensor_frame(cloud.points, origin, np.eye(3))
    poles = [e for e in extract_features(local).edges if e.pole]
    found = {}
    for obstacle, name in ((TRUNK, "trunk"), (POLE, "pole"), (CONE, "cone")):
        offsets = [axis_offset(e, obstacle, origin) for e in poles]
        distance, tilt = min(offsets)
        found[name] = (distance, tilt)
    assert found["trunk"][0] < 0.05 and found["trunk"][1] < 1.0
    assert found["pole"][0] < 0.06 and found["pole"][1] < 1.0  # the returns' mean: off by up to the radius
    assert found["cone"][0] < 0.1 and found["cone"][1] < 2.0
    assert len(poles) == 3  # not the balloon: it spans 0.6 m
    assert all(axis_offset(e, BALLOON, origin)[0] > 1.0 for e in poles)


def test_poles_can_be_turned_off_and_a_wall_is_no_pole():
    origin = np.array([0.0, 0.0, 4.0])
    wall = Obstacle(kind="box", center=(10.0, -4.0, 3.0), size=(1.0, 12.0, 6.0))
    cloud = cast(origin, 0.0, [GROUND, wall, TRUNK])
    local = sensor_frame(cloud.points, origin, np.eye(3))
    assert not [e for e in extract_features(local, FeatureParams(poles_per_sector=0)).edges if e.pole]
    poles = [e for e in extract_features(local).edges if e.pole]
    assert len(poles) == 1 and axis_offset(poles[0], TRUNK, origin)[0] < 0.05


# ------------------------------------------------------------------ whole flights
RANGE_NOISE = SensorDriverParams().range_noise  # m, σ of every range in a flown scan


def fly(scenario: str, waypoints: list, seconds: float, uav_index: int = 0):
    """The simulator's vehicle (with its IMU) along waypoints relative to its start, at 3 m/s; a scan
    every other tick into a Localizer started at the launch pose, with the sensor driver's range noise
    (as flown). Returns per scan: (error m, health, estimate, true position)."""
    sc = load_scenario(scenario)
    names = [f"uav{i + 1}" for i in range(sc.uavs)]
    uav = names[uav_index]
    sim = Simulation(sc, names, seed=1)
    world = primitives_from_obstacles(sim.obstacles())
    rng = np.random.default_rng(0)
    me = sim.vehicles()[uav_index]
    start, heading = me.position.copy(), me.heading
    corners = [start + np.asarray(w, dtype=float) for w in waypoints]
    path = np.concatenate([a + (b - a) * np.linspace(0, 1, max(2, int(np.linalg.norm(b - a) / 0.3)))[:, None]
                           for a, b in zip(corners[:-1], corners[1:])])
    localizer = Localizer(LocalizerParams())
    localizer.start(0, yaw_rotation(heading), start, np.zeros(3))
    mount = np.asarray(DEFAULT_MOUNT)
    results = []
    for k in range(1, int(round(seconds / TICK)) + 1):
        if k % 10 == 1:  # a fresh reference, as the planner sends (the flight controller's failsafe)
            sim.set_reference(uav, 0, 0.1, path, np.full(len(path), heading), 3.0, 1.5, 1.0, 2.0)
        sim.step(TICK)
        samples = sim.imu(uav)
        localizer.add_imu(samples.stamps_ns, samples.accelerometer, samples.gyroscope)
        if k % 2:
            continue
        me = sim.vehicles()[uav_index]
        origin = me.position + yaw_rotation(me.heading) @ mount
        cloud = scan(origin, me.heading, MODEL.directions(k // 2), world, rng, min_range=MODEL.min_range,
                     max_range=MODEL.max_range, range_noise=RANGE_NOISE)
        result = localizer.add_scan(sim.time_ns, sensor_frame(cloud.points, origin, yaw_rotation(me.heading)))
        estimate = result.estimate
        assert estimate.stamp_ns == sim.time_ns
        results.append((float(np.linalg.norm(estimate.translation - me.position)), estimate.health, estimate,
                        me.position.copy()))
    return results


def test_a_flight_over_the_mbzirc_field_is_tracked_by_its_building_trees_and_poles():
    results = fly("mbzirc", [[0, 0, 0], [0, 0, 5], [10, 10, 5], [30, 10, 5]], seconds=12.0)
    errors = np.array([r[0] for r in results])
    assert {r[1] for r in results} == {"tracking"}
    # 0.08 m after 30 m (0.7 m before the level-plane prior: a degree of tilt left by the start)
    assert errors.max() < 0.2, f"max {errors.max():.2f} m, last {errors[-1]:.2f} m"
    for error, _, estimate, _ in results[::10]:  # the reported σ covers the error
        assert error < 4 * max(estimate.position_sigma, 0.05)


def test_an_open_field_gives_the_floor_alone_and_positioning_degrades_then_is_lost():
    results = fly("open", [[0, 0, 0], [0, 0, 5], [30, 0, 5]], seconds=8.0)  # degraded at 2.1 s, lost at 4.4 s
    health = [r[1] for r in results]
    assert health[0] == "tracking"
    first_degraded, first_lost = health.index("degraded"), health.index("lost")
    assert first_degraded < first_lost
    assert set(health[first_lost:]) == {"lost"}
    sigmas = [r[2].position_sigma for r in results]
    assert sigmas[first_lost] > LocalizerParams().graph.lost_position_sigma


# ------------------------------------------------------------------ the node
def hover_through_the_node(first_odometry: dict, ticks: int = 8, fail_at: int | None = None, monkeypatch=None,
                           mount=DEFAULT_MOUNT, warnings: list[str] | None = None):
    """The localizer node on a fake session (tests/tools/fuzz.py's harness): the first odometry (its
    pose the UAV's true one, plus `first_odometry`'s fields), IMU batches, then scans of a hovering
    UAV over mbzirc every other tick, registered with the LiDAR at `mount`; the graph made to give up
    at tick `fail_at`; the node's warnings appended to `warnings`. Returns the node,
    the answers on falconry/<uav>/localization and the true position."""
    from schemas import keys
    from schemas.arrays import from_numpy
    from schemas.messages import Header, ImuBatch, Odometry, PointCloud, Pose
    from services.lib.geometry import heading_quaternion
    from tests.tools.fuzz import UAV, encode, wire

    wired = wire("localizer")  # the node logs to a logger of its own (the harness's), at ERROR
    if warnings is not None:
        collect = logging.Handler(logging.WARNING)
        collect.emit = lambda record: warnings.append(record.getMessage())
        wired.node.log.logger.setLevel(logging.WARNING)
        wired.node.log.logger.addHandler(collect)
    sc = load_scenario("mbzirc")
    sim = Simulation(sc, ["uav1", "uav2"], seed=1)
    world = primitives_from_obstacles(sim.obstacles())
    me = sim.vehicles()[0]
    wired.deliver(keys.uav(UAV, keys.ODOMETRY), encode(Odometry(
        header=Header(stamp=0), pose=Pose(position=tuple(me.position), orientation=heading_quaternion(me.heading)),
        **first_odometry)))
    out = keys.uav(UAV, keys.LOCALIZATION)
    answers = []
    for k in range(1, ticks + 1):
        sim.step(TICK)
        samples = sim.imu("uav1")
        wired.deliver(keys.uav(UAV, keys.IMU), encode(ImuBatch(
            header=Header(stamp=sim.time_ns), stamps=from_numpy(samples.stamps_ns),
            accelerometer=from_numpy(samples.accelerometer), gyroscope=from_numpy(samples.gyroscope), rate_hz=200)))
        if k % 2:
            continue
        if k == fail_at:  # the graph gives up on this scan
            monkeypatch.setattr(wired.node.core, "add_scan",
                                lambda *a: (_ for _ in ()).throw(RuntimeError("Indeterminate")))
        origin = me.position + yaw_rotation(me.heading) @ np.asarray(mount)
        cloud = scan(origin, me.heading, MODEL.directions(k // 2), world, np.random.default_rng(k),
                     min_range=MODEL.min_range, max_range=MODEL.max_range)
        wired.deliver(keys.uav(UAV, "points"), encode(PointCloud(
            header=Header(stamp=sim.time_ns), width=cloud.points.shape[1], height=cloud.points.shape[0],
            sensor_pose=Pose(position=tuple(origin), orientation=heading_quaternion(me.heading)),
            points=from_numpy(cloud.points))))
        answers.append(wired.published(Odometry, out))
    return wired.node, answers, me.position


def test_the_node_publishes_an_estimate_per_scan_and_lost_for_good_once_the_graph_fails(monkeypatch):
    """The launch pose from the first odometry (no health: not a belief), then each scan answered; a
    gtsam failure turns every later answer into "lost" at the last pose."""
    warnings = []
    node, answers, truth = hover_through_the_node({}, fail_at=6, monkeypatch=monkeypatch, warnings=warnings)
    assert [a.header.stamp for a in answers] == [k * 50_000_000 for k in (2, 4, 6, 8)]
    assert [a.health for a in answers] == ["tracking", "tracking", "lost", "lost"]
    assert np.linalg.norm(np.asarray(answers[1].pose.position) - truth) < 0.05
    assert answers[3].pose == answers[1].pose  # the last estimate, held
    assert node.counters.handler_errors == 0
    np.testing.assert_allclose(node.mount_seen, DEFAULT_MOUNT, atol=1e-6)  # the driver's mount, as lidar_mount
    assert not [w for w in warnings if "lidar_mount" in w]


def test_the_node_sees_the_lidar_mount_the_scans_were_registered_with():
    """The first scan at the launch point shows where the sensor driver mounts the LiDAR: a
    lidar_mount that differs (two services, two parameters) is warned about (MOUNT_TOLERANCE)."""
    from services.localizer.node import MOUNT_TOLERANCE

    elsewhere = np.asarray(DEFAULT_MOUNT) + [0.1, 0.0, -0.05]
    warnings = []
    node, _, _ = hover_through_the_node({}, ticks=4, mount=elsewhere, warnings=warnings)
    np.testing.assert_allclose(node.mount_seen, elsewhere, atol=1e-6)
    assert np.linalg.norm(elsewhere - DEFAULT_MOUNT) > MOUNT_TOLERANCE
    assert sum("lidar_mount says" in w for w in warnings) == 1  # once, not per scan


def test_a_localizer_restarted_in_flight_carries_the_beliefs_covariance_on():
    """Restarted in flight, the first odometry is the flight controller's belief (it has a health):
    the map frame starts there, and the estimates keep its uncertainty rather than claiming the
    launch point's millimetre; a belief 0.6 m uncertain is not "tracking" (0.5 m) however well the
    new map frame holds. A belief with no usable covariance starts the map frame all the same."""
    from schemas.arrays import from_numpy, to_numpy

    belief = np.diag([0.36, 0.36, 0.04, 1e-4, 1e-4, 1e-4])
    node, answers, _ = hover_through_the_node({"health": "tracking", "covariance": from_numpy(belief)}, ticks=4)
    assert [a.health for a in answers] == ["degraded", "degraded"]
    for answer in answers:
        covariance = to_numpy(answer.covariance).reshape(6, 6)
        assert np.all(np.diag(covariance) >= np.diag(belief) - 1e-12)
        assert np.diag(covariance)[0] < 0.36 + 0.01  # plus the new frame's own, small
    unusable = from_numpy(np.full((6, 6), np.nan))
    node, answers, _ = hover_through_the_node({"health": "degraded", "covariance": unusable}, ticks=4)
    assert [a.health for a in answers] == ["lost", "lost"] and node.counters.handler_errors == 0


def test_a_restart_from_a_belief_of_unknown_worth_starts_lost():
    lost_sigma = LocalizerParams().graph.lost_position_sigma
    belief = np.diag([0.04, 0.04, 0.01, 1e-4, 1e-4, 1e-4])
    belief[0, 1] = 0.01  # not symmetric as received (a float32 bridge): made so
    frame = restart_frame_covariance(belief, lost_sigma)
    np.testing.assert_allclose(frame, frame.T)
    np.testing.assert_allclose(frame[0, 1], 0.005)
    assert frame[0, 0] == 0.04
    for covariance in (None, np.full(36, np.nan), -np.eye(6), np.eye(3)):
        frame = restart_frame_covariance(covariance, lost_sigma)
        assert np.all(np.diag(frame)[:3] == lost_sigma ** 2), covariance
        assert np.linalg.eigvalsh(frame)[0] >= 0
