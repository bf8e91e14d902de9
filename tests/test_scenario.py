"""Scenario files: the built-in loads; every bad file gives a one-line error naming the field."""
from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.geometry import point_in_polygon, signed_area
from services.simulator.scenario import (
    ScenarioError,
    builtin_scenarios,
    load_scenario,
    start_poses,
)

GOOD = """
name = "t"
arena = [[0, 0], [40, 0], [40, 30], [0, 30]]
starts = [[5, 5, 0.0]]

[[balloons]]
pole = [10, 10]
height = 3.0
"""


def write(tmp_path, text: str, name: str = "t.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def error_of(tmp_path, text: str) -> str:
    with pytest.raises(ScenarioError) as info:
        load_scenario(write(tmp_path, text))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("t.toml: ")
    return message


def test_builtin_mbzirc_loads():
    assert "mbzirc" in builtin_scenarios()
    s = load_scenario("mbzirc")
    assert s.name == "mbzirc" and s.duration == 120.0 and s.uavs == 2
    arena = np.asarray(s.arena)
    width, depth = np.ptp(arena, axis=0)
    assert 90 <= width <= 110 and 50 <= depth <= 70
    assert signed_area(arena) > 0  # counter-clockwise
    assert signed_area(arena) < width * depth - 1.0  # non-convex: a notch is cut out of the box
    assert len(s.balloons) == 5 and all(2.5 <= b.height <= 5.0 for b in s.balloons)
    assert len(s.drones) == 1 and s.drones[0].center[2] == 8.0
    assert {o.kind for o in s.obstacles} >= {"box", "cylinder"}
    assert len(s.starts) == 2


def test_good_file_defaults_and_automatic_starts(tmp_path):
    s = load_scenario(write(tmp_path, GOOD))
    assert s.balloons[0].radius == 0.3 and s.needle_reach == 0.3 and s.max_height == 20.0
    assert s.balloon_ids() == ["balloon1"]
    assert start_poses(s, 3) == [(5.0, 5.0, 0.0), (15.0, 5.0, 0.0), (25.0, 5.0, 0.0)]  # START_SPACING apart


def test_clockwise_arena_is_reoriented(tmp_path):
    s = load_scenario(write(tmp_path, GOOD.replace("[[0, 0], [40, 0], [40, 30], [0, 30]]",
                                                   "[[0, 0], [0, 30], [40, 30], [40, 0], [0, 0]]")))
    assert len(s.arena) == 4 and signed_area(np.asarray(s.arena)) > 0


def test_unknown_name_lists_builtins():
    with pytest.raises(ScenarioError, match=r"unknown scenario 'foo' \(built-in: agile, forest, intruder, mast, mbzirc, open, sparse, street, takeoff, unmapped;"):
        load_scenario("foo")
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario("/nonexistent/x.toml")


def test_unknown_field(tmp_path):
    assert error_of(tmp_path, "gravity = 3\n" + GOOD) == "t.toml: gravity: unknown field"
    nested = GOOD.replace("height = 3.0", "height = 3.0\ncolour = 'red'")
    assert error_of(tmp_path, nested) == "t.toml: balloons[0].colour: unknown field"


def test_wrong_type(tmp_path):
    text = GOOD + '\n[[balloons]]\npole = [12, 12]\n\n[[balloons]]\npole = [14, 14]\nheight = "tall"\n'
    assert error_of(tmp_path, text) == "t.toml: balloons[2].height: expected float, got str"


def test_missing_required_field(tmp_path):
    assert error_of(tmp_path, GOOD.replace('name = "t"', "")) == "t.toml: name: missing required field"


def test_self_intersecting_arena(tmp_path):
    bow_tie = GOOD.replace("[[0, 0], [40, 0], [40, 30], [0, 30]]", "[[0, 0], [40, 30], [40, 0], [0, 30]]")
    assert "arena: edges 0 and 2 cross" in error_of(tmp_path, bow_tie)


def test_too_few_arena_points(tmp_path):
    assert "arena: needs at least 3 points" in error_of(tmp_path, GOOD.replace(
        "[[0, 0], [40, 0], [40, 30], [0, 30]]", "[[0, 0], [40, 0]]"))


def test_balloon_outside_arena(tmp_path):
    message = error_of(tmp_path, GOOD.replace("pole = [10, 10]", "pole = [50, 10]"))
    assert message == "t.toml: balloons[0].pole: (50.0, 10.0) is outside the arena"


def test_start_outside_arena(tmp_path):
    assert "starts[0]: " in error_of(tmp_path, GOOD.replace("[[5, 5, 0.0]]", "[[-5, 5, 0.0]]"))


def test_uavs_out_of_range(tmp_path):
    assert error_of(tmp_path, "uavs = 5\n" + GOOD) == "t.toml: uavs: must be 2 or 3, got 5"


def test_heights_and_duration(tmp_path):
    assert "min_height" in error_of(tmp_path, "min_height = 30.0\n" + GOOD)
    assert "duration" in error_of(tmp_path, "duration = 0.0\n" + GOOD)


def test_obstacle_dimensions(tmp_path):
    text = GOOD + '\n[[obstacles]]\nkind = "cylinder"\ncenter = [20, 20, 0]\nradius = 1.0\n'
    assert error_of(tmp_path, text) == "t.toml: obstacles[0].height: must be > 0 for a cylinder, got 0.0"
    assert "obstacles[0].kind: invalid enum value 'pyramid'" in error_of(
        tmp_path, GOOD + '\n[[obstacles]]\nkind = "pyramid"\n')


def test_invalid_toml(tmp_path):
    assert "invalid TOML" in error_of(tmp_path, "name = \n")


def test_points_in_non_convex_polygon():
    notched = np.array([[0, 0], [10, 0], [10, 10], [6, 10], [6, 5], [4, 5], [4, 10], [0, 10]], float)
    inside = point_in_polygon(np.array([[1, 1], [5, 7], [5, 3], [9, 9], [11, 1], [-math.pi, 2]]), notched)
    assert inside.tolist() == [True, False, True, True, False, False]


# ---------------------------------------------------------------- issue 3: built-ins, UAVs, faults
def test_every_builtin_loads_and_runs_a_few_steps():
    from services.simulator.core import Simulation

    assert builtin_scenarios() == ["agile", "forest", "intruder", "mast", "mbzirc", "open", "sparse", "street", "takeoff",
                                  "unmapped"]
    for name in builtin_scenarios():
        s = load_scenario(name)
        sim = Simulation(s, [f"uav{i + 1}" for i in range(s.uavs)], s.seed)
        for _ in range(4):
            sim.step(0.05)
        assert len(sim.targets()) == len(s.balloons) + len(s.drones)
    assert load_scenario("mbzirc").wind.speed > 0
    intruder = load_scenario("intruder")
    assert any(d.path == "waypoints" and d.speed == 4.0 for d in intruder.drones)
    assert any(d.path == "random" for d in intruder.drones)
    assert sum(o.kind == "box" for o in intruder.obstacles) >= 2
    agile = load_scenario("agile")
    assert {(d.path, d.speed) for d in agile.drones} == {("figure8", 6.0), ("random", 5.0)}
    assert agile.obstacles == intruder.obstacles and agile.arena == intruder.arena


def test_sparse_target_stays_10_to_35_m_from_the_observer():
    from services.simulator.paths import MARGIN, DronePath

    s = load_scenario("sparse")
    assert s.uav_spec("uav1").sensor == "mid360" and s.airspace
    # The observer's working area shrinks to the line y = 2, x 2..4 (see the scenario's comment).
    observer = np.array([[x, 2.0, z] for x in (2.0, 3.0, 4.0) for z in (0.0, 2.5, 5.0)])
    low, high = np.array(s.drones[0].box[0]) + MARGIN, np.array(s.drones[0].box[1]) - MARGIN
    corners = np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])
    assert np.linalg.norm(corners[:, None] - observer[None], axis=2).max() <= 35.0
    assert low[1] - observer[:, 1].max() >= 10.0
    for seed in (1, 2):
        p, _ = DronePath(s.drones[0], s, seed, 0).state(np.arange(0.0, s.duration, 0.1))
        gaps = np.linalg.norm(p[:, None] - observer[None], axis=2)
        assert 10.0 <= gaps.min() and gaps.max() <= 35.0


def test_takeoff_target_rests_by_the_wall_then_climbs():
    from services.simulator.paths import DronePath

    s = load_scenario("takeoff")
    drone, building = s.drones[0], s.obstacles[0]
    wall_y = building.center[1] - building.size[1] / 2
    path = DronePath(drone, s, s.seed, 0)
    resting, _ = path.state(drone.takeoff_time - 1.0)
    assert resting[2] == s.ground_z + drone.body_radius and wall_y - resting[1] - drone.body_radius < 1.0
    assert path.state(drone.takeoff_time + 6.0)[0][2] > resting[2] + 2.0


def test_uav_table_and_overrides(tmp_path):
    s = load_scenario(write(tmp_path, GOOD + '\n[uav]\nsensor = "os1-128"\nodometry_position_sigma = 0.1\n'
                            '[uav.attack]\nmax_speed = 7.0\nmax_acceleration = 2.5\n'
                            '[uav.overrides.uav2]\nsensor = "mid360"\n'))
    one, two = s.uav_spec("uav1"), s.uav_spec("uav2")
    assert (one.sensor, two.sensor) == ("os1-128", "mid360")
    assert one.attack.max_speed == 7.0 and two.attack.max_acceleration == 2.5 and two.odometry_position_sigma == 0.1
    assert one.sweeping.max_speed == 5.0 and one.sweeping.max_acceleration == 1.5
    assert one.attack.message("attack").max_speed == 7.0
    assert error_of(tmp_path, GOOD + "\n[uav]\nodometry_attitude_sigma = -1.0\n") == (
        "t.toml: uav.odometry_attitude_sigma: must be >= 0, got -1.0")
    assert error_of(tmp_path, GOOD + "\n[uav.overrides.uav1]\nsensor = 'velodyne'\n").startswith(
        "t.toml: uav.overrides.uav1.sensor: unknown LiDAR model 'velodyne'")
    assert error_of(tmp_path, GOOD + "\n[uav.overrides.uav2]\nsensr = 'x'\n") == (
        "t.toml: uav.overrides.uav2.sensr: unknown field")
    assert error_of(tmp_path, GOOD + "\n[uav.attack]\nmax_speed = 7.0\n") == (
        "t.toml: uav.attack.max_acceleration: missing required field")


def fault(**fields) -> str:
    lines = "\n".join(f"{k} = {v!r}" if isinstance(v, str) else f"{k} = {v}" for k, v in fields.items())
    return GOOD + "\n[[faults]]\n" + lines + "\n"


def test_fault_schedule_parses_into_commands(tmp_path):
    from services.simulator.scenario import check_team

    text = fault(time=30.0, kind="lidar_silent", uav="uav2", duration=5.0) + fault(
        time=40.0, kind="odometry_jump", uav="uav1", offset=[1.0, 0.0, 0.0]).replace(GOOD, "") + fault(
        time=50.0, kind="kill", uav="uav3", service="planner").replace(GOOD, "")
    s = load_scenario(write(tmp_path, text))
    assert [(f.time, f.kind, f.uav) for f in s.faults] == [
        (30.0, "lidar_silent", "uav2"), (40.0, "odometry_jump", "uav1"), (50.0, "kill", "uav3")]
    command = s.faults[1].command()
    assert command.header.stamp == 40_000_000_000 and command.offset == (1.0, 0.0, 0.0)
    check_team(s, ["uav1", "uav2", "uav3"])
    with pytest.raises(ScenarioError, match=r"^faults\[2\]\.uav: uav3 is not in the team \(uav1, uav2\)$"):
        check_team(s, ["uav1", "uav2"])  # the command line ran a smaller team


def test_bad_faults_name_the_field(tmp_path):
    assert error_of(tmp_path, fault(time=1.0, kind="meteor", uav="uav1")) == (
        "t.toml: faults[0].kind: invalid enum value 'meteor'")
    assert error_of(tmp_path, fault(time=1.0, kind="kill", uav="uav4")) == (
        "t.toml: faults[0].uav: 'uav4' is not a UAV of a team of at most 3 (uav1..uav3)")
    assert error_of(tmp_path, fault(time=500.0, kind="freeze", uav="uav1")) == (
        "t.toml: faults[0].time: 500.0 s is outside the mission (0 to duration 120.0 s)")
    assert error_of(tmp_path, fault(time=1.0, kind="lidar_nan", uav="uav1", service="mapper")) == (
        "t.toml: faults[0].service: only kill, freeze, slow, clock_jump faults target one service")
    assert error_of(tmp_path, fault(time=1.0, kind="freeze", uav="uav1", service="mapr")).startswith(
        "t.toml: faults[0].service: unknown service 'mapr' (one of sensor_driver, ")
    assert error_of(tmp_path, fault(time=1.0, kind="odometry_jump", uav="uav1")) == (
        "t.toml: faults[0].offset: an odometry_jump needs a non-zero offset")
    assert error_of(tmp_path, fault(time=1.0, kind="kill", uav="uav1", duration=-2.0)) == (
        "t.toml: faults[0].duration: must be >= 0, got -2.0")
    assert error_of(tmp_path, fault(kind="kill", uav="uav1")) == "t.toml: faults[0].time: missing required field"
    assert error_of(tmp_path, fault(time=1.0, kind="kill")) == (
        "t.toml: faults[0].uav: '' is not a UAV of a team of at most 3 (uav1..uav3)")


def test_the_delivery_clock_and_router_faults_take_their_own_fields_only(tmp_path):
    from services.simulator.scenario import check_team
    assert error_of(tmp_path, fault(time=1.0, kind="duplicate", uav="uav1")).startswith(
        "t.toml: faults[0].topic: a duplicate fault needs one of the UAV's topics (odometry, imu, localization, points, ")
    assert error_of(tmp_path, fault(time=1.0, kind="reorder", uav="uav1", topic="radio")).endswith(", not 'radio'")
    assert error_of(tmp_path, fault(time=1.0, kind="kill", uav="uav1", topic="points")) == (
        "t.toml: faults[0].topic: only duplicate and reorder faults take a topic")
    assert error_of(tmp_path, fault(time=1.0, kind="slow", uav="uav1", delay=0.2)) == (
        "t.toml: faults[0].delay: a slow fault needs 0 < delay <= 0.1 s per message (a longer one is a freeze)")
    assert error_of(tmp_path, fault(time=1.0, kind="freeze", uav="uav1", delay=0.1)) == (
        "t.toml: faults[0].delay: only slow faults take a delay")
    assert error_of(tmp_path, fault(time=1.0, kind="clock_jump", uav="uav1")) == (
        "t.toml: faults[0].jump: a clock_jump needs a non-zero finite jump, s")
    assert error_of(tmp_path, fault(time=1.0, kind="router_restart", uav="uav1", duration=2.0)) == (
        "t.toml: faults[0].uav: a router_restart concerns the run's router, not one UAV")
    assert error_of(tmp_path, fault(time=1.0, kind="router_restart")) == (
        "t.toml: faults[0].duration: a router_restart needs the time the router stays down (> 0 s)")
    good = [fault(time=1.0, kind="duplicate", uav="uav1", topic="detections", duration=2.0),
            fault(time=2.0, kind="slow", uav="uav2", service="tracker", delay=0.05),
            fault(time=3.0, kind="clock_jump", uav="uav1", jump=-3600.0),
            fault(time=4.0, kind="router_restart", duration=1.5)]
    s = load_scenario(write(tmp_path, GOOD + "".join(g.removeprefix(GOOD) for g in good)))
    commands = [f.command() for f in s.faults]
    assert (commands[0].topic, commands[1].delay, commands[2].jump, commands[3].uav) == ("detections", 0.05, -3600.0, "")
    check_team(s, ["uav1", "uav2"])  # the router is nobody's UAV


def test_bad_wind_and_capture(tmp_path):
    assert error_of(tmp_path, GOOD + "\n[wind]\ngust_period = 0.0\n") == (
        "t.toml: wind.gust_period: must be > 0, got 0.0")
    assert error_of(tmp_path, "capture_radius = 0.0\n" + GOOD) == "t.toml: capture_radius: must be > 0, got 0.0"
    assert error_of(tmp_path, "airspace = [[0, 0], [1, 1], [1, 0], [0, 1]]\n" + GOOD).startswith(
        "t.toml: airspace: edges 0 and 2 cross")
