import numpy as np
import pytest

from schemas.messages import ConstraintProfile
from services.planner.core import (
    DT,
    hover,
    land,
    lawnmower,
    lawnmower_waypoints,
    path_duration,
    sample_path,
    scan_rectangle,
    takeoff,
    wrap_angle,
)

SWEEP = ConstraintProfile(name="sweeping", max_speed=5.0, max_acceleration=1.5)
AREA = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 56.0], [0.0, 56.0]])  # long side along y


def speeds(positions, dt=DT):
    return np.linalg.norm(np.diff(positions, axis=0), axis=1) / dt


def accelerations(positions, dt=DT):
    return np.linalg.norm(np.diff(positions, n=2, axis=0), axis=1) / dt**2


def check_profile(positions, headings, profile, dt=DT):
    assert speeds(positions, dt).max() <= profile.max_speed * 1.01
    vertical = np.abs(np.diff(positions[:, 2])) / dt
    assert vertical.max(initial=0) <= profile.max_vertical_speed * 1.01
    assert accelerations(positions, dt).max(initial=0) <= profile.max_acceleration * 1.05
    heading_rate = np.abs(wrap_angle(np.diff(headings))) / dt
    assert heading_rate.max(initial=0) <= profile.max_heading_rate * 1.01


def test_single_segment_analytic_duration():
    # 50 m at 5 m/s with 1.5 m/s²: 2·(5/1.5) s ramps covering 5²/1.5 m, the rest at 5 m/s.
    expected = 2 * 5 / 1.5 + (50 - 25 / 1.5) / 5
    waypoints = np.array([[0.0, 0.0, 5.0], [50.0, 0.0, 5.0]])
    assert path_duration(waypoints, SWEEP, start_heading=0.0) == pytest.approx(expected)
    positions, headings = sample_path(waypoints, SWEEP, DT, start_heading=0.0)
    assert (len(positions) - 1) * DT == pytest.approx(np.ceil(expected / DT) * DT)
    np.testing.assert_allclose(positions[-1], waypoints[-1])
    assert speeds(positions).max() == pytest.approx(5.0, abs=0.01)  # reaches cruise
    np.testing.assert_allclose(headings, 0.0)
    check_profile(positions, headings, SWEEP)


def test_short_segment_is_triangular():
    # 3 m never reaches 5 m/s: peak sqrt(3·1.5), duration 2·sqrt(3 / 1.5).
    waypoints = np.array([[0.0, 0.0, 5.0], [0.0, 3.0, 5.0]])
    assert path_duration(waypoints, SWEEP, np.pi / 2) == pytest.approx(2 * np.sqrt(2.0))
    positions, headings = sample_path(waypoints, SWEEP, 0.01, np.pi / 2)
    assert speeds(positions, 0.01).max() == pytest.approx(np.sqrt(4.5), rel=0.01)


def test_takeoff_and_land():
    positions, headings = takeoff(np.array([3.0, 4.0, 0.0]), 5.0, SWEEP, heading=1.0)
    np.testing.assert_allclose(positions[-1], [3.0, 4.0, 5.0])
    np.testing.assert_allclose(positions[:, :2], [[3.0, 4.0]] * len(positions))
    assert np.all(np.diff(positions[:, 2]) >= 0)
    np.testing.assert_allclose(headings, 1.0)
    # Vertical speed limit 2 m/s: 5 m takes 2·(2/1.5) + (5 − 4/1.5)/2 s.
    assert (len(positions) - 1) * DT == pytest.approx(np.ceil((8 / 3 + (5 - 8 / 3) / 2) / DT) * DT)
    check_profile(positions, headings, SWEEP)
    down, _ = land(positions[-1], 0.0, SWEEP)
    np.testing.assert_allclose(down[-1], [3.0, 4.0, 0.0])
    check_profile(down, np.zeros(len(down)), SWEEP)


def test_hover_is_one_sample():
    positions, headings = hover(np.array([1.0, 2.0, 3.0]), 0.5)
    assert positions.shape == (1, 3) and headings.shape == (1,)


def test_lawnmower_lines_and_corners():
    start = np.array([3.0, 50.0, 5.0])  # near the (x_low, y_high) corner, inside the rectangle
    corners = lawnmower_waypoints(AREA, 5.0, 10.0, 2.0, start)
    low, high = scan_rectangle(AREA, 2.0)
    np.testing.assert_allclose([low, high], [[2.0, 2.0], [38.0, 54.0]])
    # Lines run along y (the long side); their x positions are `spacing` apart, centred.
    line_x = corners[0::2, 0]
    np.testing.assert_allclose(corners[1::2, 0], line_x)
    np.testing.assert_allclose(np.diff(line_x), 10.0)
    np.testing.assert_allclose(line_x, [5.0, 15.0, 25.0, 35.0])
    np.testing.assert_allclose(corners[0, :2], [5.0, 54.0])  # nearest corner to the start
    np.testing.assert_allclose(corners[:4, 1], [54.0, 2.0, 2.0, 54.0])  # boustrophedon

    positions, headings = lawnmower(AREA, 5.0, 10.0, 2.0, SWEEP, start, DT, start_heading=0.0)
    check_profile(positions, headings, SWEEP)
    eps = 1e-9
    assert np.all(positions[:, :2] >= low - eps) and np.all(positions[:, :2] <= high + eps)
    np.testing.assert_allclose(positions[:, 2], 5.0)
    step = speeds(positions)
    for corner in corners:
        at = np.linalg.norm(positions - corner, axis=1)
        i = int(np.argmin(at))
        assert at[i] < 1e-6  # the trajectory stops exactly on each corner
        around = step[max(i - 1, 0): i + 1]
        assert around.max() <= SWEEP.max_acceleration * DT + 1e-9
    np.testing.assert_allclose(positions[-1], corners[-1])
    # Heading follows the travel direction on the long lines (±y).
    moving = step > 1.0
    travel = np.diff(positions, axis=0)[moving]
    expected = np.arctan2(travel[:, 1], travel[:, 0])
    np.testing.assert_allclose(wrap_angle(headings[1:][moving] - expected), 0.0, atol=1e-9)


def test_lawnmower_transfer_from_outside_and_wide_area():
    wide = np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 30.0], [0.0, 30.0]])
    start = np.array([70.0, -5.0, 5.0])
    corners = lawnmower_waypoints(wide, 5.0, 10.0, 2.0, start)
    np.testing.assert_allclose(corners[0, :2], [58.0, 5.0])  # lines along x now, starting near start
    np.testing.assert_allclose(np.diff(corners[0::2, 1]), 10.0)
    positions, headings = lawnmower(wide, 5.0, 10.0, 2.0, SWEEP, start)
    np.testing.assert_allclose(positions[0], start)
    check_profile(positions, headings, SWEEP)


def test_sample_path_mixed_climb_and_turns():
    waypoints = np.array([[0, 0, 0], [0, 0, 5], [10, 0, 5], [10, 10, 8], [0, 0, 2]], float)
    profile = ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0)
    positions, headings = sample_path(waypoints, profile, DT, start_heading=2.0)
    check_profile(positions, headings, profile)
    np.testing.assert_allclose(positions[-1], waypoints[-1])
