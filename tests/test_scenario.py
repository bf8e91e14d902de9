"""Scenario files: the built-in loads; every bad file gives a one-line error naming the field."""
from __future__ import annotations

import math

import numpy as np
import pytest

from services.geometry import point_in_polygon, signed_area
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
    assert start_poses(s, 3) == [(5.0, 5.0, 0.0), (10.0, 5.0, 0.0), (15.0, 5.0, 0.0)]


def test_clockwise_arena_is_reoriented(tmp_path):
    s = load_scenario(write(tmp_path, GOOD.replace("[[0, 0], [40, 0], [40, 30], [0, 30]]",
                                                   "[[0, 0], [0, 30], [40, 30], [40, 0], [0, 0]]")))
    assert len(s.arena) == 4 and signed_area(np.asarray(s.arena)) > 0


def test_unknown_name_lists_builtins():
    with pytest.raises(ScenarioError, match=r"unknown scenario 'foo' \(built-in: mbzirc"):
        load_scenario("foo")
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario("/nonexistent/x.toml")


def test_unknown_field(tmp_path):
    assert error_of(tmp_path, "wind = 3\n" + GOOD) == "t.toml: wind: unknown field"
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
