"""Scripted drone paths: limits hold (finite differences), bounds hold, determinism, take-off."""
from __future__ import annotations

import math

import numpy as np
import pytest

from services.lib.geometry import point_in_polygon
from services.simulator.paths import DronePath
from services.simulator.scenario import ScenarioError, parse_scenario

DT = 0.01
ARENA = [[-60, -60], [60, -60], [60, 60], [-60, 60]]


def world(drone: dict, **extra):
    data = {"name": "paths", "arena": ARENA, "duration": 300.0, "drones": [drone]}
    data.update(extra)
    return parse_scenario(data, "paths.toml")


def sampled(drone: dict, seconds: float = 120.0, seed: int = 5, **extra):
    s = world(drone, **extra)
    t = np.arange(0.0, seconds, DT)
    p, v = DronePath(s.drones[0], s, seed, 0).state(t)
    return s.drones[0], t, p, v


def assert_within_limits(spec, p: np.ndarray, v: np.ndarray, speed: float) -> None:
    assert np.linalg.norm(v, axis=1).max() <= speed + 1e-9
    # Mean acceleration over a sample can only be smaller than the peak.
    assert (np.linalg.norm(np.diff(v, axis=0), axis=1) / DT).max() <= spec.max_acceleration + 1e-6
    # The reported velocity is the derivative of the position (trapezoid rule over each sample).
    assert np.abs(np.diff(p, axis=0) - 0.5 * DT * (v[1:] + v[:-1])).max() < 1e-4


def test_circle_keeps_speed_and_acceleration():
    spec, _, p, v = sampled({"path": "circle", "center": [0, 0, 6], "radius": 5.0, "speed": -3.0,
                             "max_acceleration": 2.0})
    assert_within_limits(spec, p, v, 3.0)
    assert np.allclose(np.linalg.norm(v, axis=1), 3.0)
    assert np.allclose(np.linalg.norm(p[:, :2], axis=1), 5.0) and np.allclose(p[:, 2], 6.0)
    assert p[0, 0] * v[0, 1] - p[0, 1] * v[0, 0] < 0  # negative speed flies clockwise


def test_figure8_extents_peak_speed_and_limits():
    spec, _, p, v = sampled({"path": "figure8", "center": [5, -5, 7], "size": [30.0, 12.0], "speed": 4.0,
                             "max_acceleration": 1.5})
    assert_within_limits(spec, p, v, 4.0)
    assert np.linalg.norm(v, axis=1).max() > 3.99  # the peak speed is reached (at the crossing)
    assert np.allclose(np.ptp(p, axis=0), [30.0, 12.0, 0.0], atol=0.05)
    assert np.allclose(p.min(axis=0)[:2] + np.ptp(p, axis=0)[:2] / 2, [5, -5], atol=0.05)


def test_waypoints_stop_at_each_point_and_loop():
    points = np.array([[0, 0, 5], [20, 0, 5], [20, 10, 8]], float)
    spec, t, p, v = sampled({"path": "waypoints", "waypoints": points.tolist(), "speed": 4.0,
                             "max_acceleration": 2.0, "loop": True})
    assert_within_limits(spec, p, v, 4.0)
    assert np.linalg.norm(v, axis=1).max() > 3.99  # cruises at the set speed on the long legs
    for point in points:  # passes every waypoint, at rest there
        nearest = np.linalg.norm(p - point, axis=1)
        assert nearest.min() < 0.05 and np.linalg.norm(v[np.argmin(nearest)]) < 0.1
    laps = t[np.linalg.norm(p - points[0], axis=1) < 0.01]
    assert laps.max() > 100 and np.unique(np.round(laps)).size >= 5  # back at the start, lap after lap


def test_waypoints_without_loop_hover_at_the_end():
    _, _, p, v = sampled({"path": "waypoints", "waypoints": [[0, 0, 5], [10, 0, 5]], "speed": 2.0})
    assert np.allclose(p[-1], [10, 0, 5]) and np.allclose(v[-1], 0.0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_stays_in_its_box_within_limits(seed):
    box = [[-20.0, 10.0, 3.0], [10.0, 30.0, 12.0]]
    spec, _, p, v = sampled({"path": "random", "box": box, "speed": 6.0, "max_acceleration": 4.0},
                            seconds=150.0, seed=seed)
    assert_within_limits(spec, p, v, 6.0)
    assert (p >= np.array(box[0]) + 0.49).all() and (p <= np.array(box[1]) - 0.49).all()
    assert np.ptp(p, axis=0).min() > 5.0  # it really roams the box
    assert np.linalg.norm(v, axis=1).mean() > 1.5  # and keeps moving


def test_random_is_deterministic_whatever_the_query_order():
    s = world({"path": "random", "box": [[0, 0, 2], [20, 20, 8]], "speed": 4.0})
    t = np.arange(0.0, 60.0, 0.05)
    at_once = DronePath(s.drones[0], s, 9, 0).state(t)
    stepwise = DronePath(s.drones[0], s, 9, 0)
    one_by_one = np.array([stepwise.state(float(x))[0] for x in t])
    assert np.array_equal(at_once[0], one_by_one)
    other_seed = DronePath(s.drones[0], s, 10, 0).state(t)[0]
    other_index = DronePath(s.drones[0], s, 9, 1).state(t)[0]
    assert not np.allclose(at_once[0], other_seed) and not np.allclose(at_once[0], other_index)


def test_random_without_box_stays_in_non_convex_airspace():
    notched = [[0, 0], [40, 0], [40, 40], [25, 40], [25, 15], [15, 15], [15, 40], [0, 40]]
    _, _, p, v = sampled({"path": "random", "speed": 5.0, "center": [5, 5, 4]}, seconds=200.0,
                         arena=notched, min_height=2.0, max_height=9.0)
    assert point_in_polygon(p[:, :2], np.array(notched, float)).all()
    assert p[:, 2].min() >= 2.0 and p[:, 2].max() <= 9.0
    assert p[:, 0].max() > 28  # it found its way round the notch


def test_takeoff_waits_on_the_ground_then_climbs():
    spec, t, p, v = sampled({"path": "waypoints", "waypoints": [[3, 4, 5], [10, 4, 5]], "speed": 2.0,
                             "takeoff_time": 10.0, "climb_speed": 0.5, "max_acceleration": 1.0}, seconds=40.0)
    assert_within_limits(spec, p, v, 2.0)
    waiting = t < 10.0
    assert np.allclose(p[waiting], [3, 4, 0.325]) and np.allclose(v[waiting], 0.0)
    assert np.abs(v[:, 2]).max() <= 0.5 + 1e-9
    climb_end = t[np.argmax(p[:, 2] >= 5.0 - 1e-9)]
    assert 10.0 + (5.0 - 0.325) / 0.5 <= climb_end < 10.0 + (5.0 - 0.325) / 0.5 + 1.0
    assert np.allclose(p[-1], [10, 4, 5])


def test_circle_after_takeoff_speeds_up_within_the_limit():
    spec, t, p, v = sampled({"path": "circle", "center": [0, 0, 4], "radius": 8.0, "speed": 4.0, "phase": 1.0,
                             "takeoff_time": 2.0, "max_acceleration": 3.0}, seconds=40.0)
    assert_within_limits(spec, p, v, 4.0)
    assert np.allclose(p[0], [8 * math.cos(1.0), 8 * math.sin(1.0), 0.325])
    assert np.allclose(np.linalg.norm(v[-100:], axis=1), 4.0)  # at speed on the circle in the end


def test_paths_are_validated(tmp_path):
    def error(drone: dict, **extra) -> str:
        with pytest.raises(ScenarioError) as info:
            world(drone, **extra)
        return str(info.value)

    assert error({"path": "circle", "center": [0, 0, 5], "radius": 2.0, "speed": 4.0}) == (
        "paths.toml: drones[0].speed: 4.0 m/s on this circle needs 8.01 m/s², more than 100% of "
        "max_acceleration 3.0")
    assert "drones[0].radius: the circle leaves the arena at (" in error(
        {"path": "circle", "center": [55, 0, 5], "radius": 8.0, "speed": 1.0})
    assert error({"path": "waypoints", "waypoints": [[0, 0, 5], [70, 0, 5]], "speed": 1.0}) == (
        "paths.toml: drones[0].waypoints[1]: the leg to it leaves the arena")
    assert error({"path": "waypoints", "waypoints": [[0, 0, 5], [5, 0, 0.1]], "speed": 1.0}) == (
        "paths.toml: drones[0].waypoints[1]: height 0.1 puts the drone below the ground")
    assert "drones[0].box: reaches outside the arena" in error(
        {"path": "random", "box": [[50, 0, 2], [70, 10, 8]], "speed": 1.0})
    assert error({"path": "waypoints", "waypoints": [[0, 0, 5], [5, 0, 5]], "radius": 3.0, "speed": 1.0}) == (
        "paths.toml: drones[0].radius: not used by a waypoints path")
    assert error({"path": "figure8", "center": [0, 0, 5], "speed": 1.0}) == (
        "paths.toml: drones[0].size: required for a figure8 path")
    assert error({"path": "random", "speed": 0.0}) == "paths.toml: drones[0].speed: must be > 0, got 0.0"
    assert error({"path": "spiral", "speed": 1.0}).startswith("paths.toml: drones[0].path: invalid enum value")
    # A target may fly outside the team's arena when an airspace says so.
    outside = {"path": "circle", "center": [0, 0, 5], "radius": 8.0, "speed": 1.0}
    assert "is outside the arena" in error(outside, arena=[[20, 20], [50, 20], [50, 40]])
    world(outside, arena=[[20, 20], [50, 20], [50, 40]], airspace=[[-20, -20], [60, -20], [60, 60], [-20, 60]])
