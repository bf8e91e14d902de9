import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from schemas.messages import ConstraintProfile
from services.planner.core import (
    DT,
    HIT_OFFSET,
    approach,
    approach_goal,
    attack,
    deadband,
    fly,
    hover,
    inner_rectangle,
    intercept,
    land,
    lawnmower,
    lawnmower_waypoints,
    path_duration,
    plan_intercept,
    sample_path,
    scan_rectangle,
    stop,
    takeoff,
    wrap_angle,
)
from services.planner.intercept import sample_intercept
from services.lib.runtime.clock import NS

SWEEP = ConstraintProfile(name="sweeping", max_speed=5.0, max_acceleration=1.5)
ATTACK = ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0)
AREA = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 56.0], [0.0, 56.0]])  # long side along y
ARENA = np.array([[0, 0], [100, 0], [100, 60], [60, 60], [60, 45], [40, 45], [40, 60], [0, 60]], float)
HALF_ARENA = np.array([[0, 0], [50, 0], [50, 45], [40, 45], [40, 60], [0, 60]], float)


def speeds(positions, dt=DT):
    return np.linalg.norm(np.diff(positions, axis=0), axis=1) / dt


def accelerations(positions, dt=DT):
    return np.linalg.norm(np.diff(positions, n=2, axis=0), axis=1) / dt**2


def check_profile(positions, headings, profile, dt=DT):
    assert positions.shape == (len(headings), 3)
    assert speeds(positions, dt).max(initial=0) <= profile.max_speed * 1.01
    vertical = np.abs(np.diff(positions[:, 2])) / dt
    assert vertical.max(initial=0) <= profile.max_vertical_speed * 1.01
    assert accelerations(positions, dt).max(initial=0) <= profile.max_acceleration * 1.01
    heading_rate = np.abs(wrap_angle(np.diff(headings))) / dt
    assert heading_rate.max(initial=0) <= profile.max_heading_rate * 1.01


def distance_to_polyline(point, positions):
    a, b = positions[:-1], positions[1:]
    ab = b - a
    t = np.clip(((point - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - point, axis=1).min()


def assert_ends_at_rest(positions, end, profile, dt=DT):
    np.testing.assert_allclose(positions[-1], end, atol=1e-9)
    # The last step of a stop at a_max is at most a·dt² / 2 long.
    assert np.linalg.norm(positions[-1] - positions[-2]) <= 0.5 * profile.max_acceleration * dt**2 + 1e-9


# --- time parameterisation -------------------------------------------------------------

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
    down, down_headings = land(positions[-1], 0.0, SWEEP)
    np.testing.assert_allclose(down[-1], [3.0, 4.0, 0.0])
    check_profile(down, down_headings, SWEEP)


def test_hover_is_one_sample():
    positions, headings = hover(np.array([1.0, 2.0, 3.0]), 0.5)
    assert positions.shape == (1, 3) and headings.shape == (1,)


def test_sample_path_mixed_climb_and_turns():
    waypoints = np.array([[0, 0, 0], [0, 0, 5], [10, 0, 5], [10, 10, 8], [0, 0, 2]], float)
    positions, headings = sample_path(waypoints, ATTACK, DT, start_heading=2.0)
    check_profile(positions, headings, ATTACK)
    np.testing.assert_allclose(positions[-1], waypoints[-1])


@pytest.mark.parametrize("turn_deg, stops", [(30, False), (90, False), (119, False), (150, True), (180, True)])
def test_fly_rounds_corners_and_stops_at_sharp_ones(turn_deg, stops):
    turn = np.radians(turn_deg)
    waypoints = np.array([[0, 0, 5], [30, 0, 5], [30 + 30 * np.cos(turn), 30 * np.sin(turn), 5]])
    dt = 0.02
    positions, headings = fly(waypoints, SWEEP, dt, start_heading=0.0)
    check_profile(positions, headings, SWEEP, dt)
    assert_ends_at_rest(positions, waypoints[-1], SWEEP, dt)
    step = speeds(positions, dt)
    away = np.minimum(np.linalg.norm(positions[:-1] - waypoints[0], axis=1),
                      np.linalg.norm(positions[:-1] - waypoints[-1], axis=1)) > 10.0
    middle = step[away]
    if stops:
        assert middle.min() < SWEEP.max_acceleration * dt  # brakes to (sampled) rest at the vertex
        assert distance_to_polyline(waypoints[1], positions) < 1e-3
    else:
        assert middle.min() > 1.0  # never stops, so the corner is an arc at speed
        assert distance_to_polyline(waypoints[1], positions) > 0.01


def test_fly_corner_and_segment_caps_and_start_velocity():
    waypoints = np.array([[0, 0, 5], [20, 0, 5], [20, 20, 5], [40, 20, 5]], float)
    positions, headings = fly(waypoints, SWEEP, corner_speeds=[np.inf, 1.0, np.inf, np.inf],
                              segment_speeds=[np.inf, np.inf, 2.0], start_velocity=[3.0, 4.0, 0.0])
    check_profile(positions, headings, SWEEP)
    step = speeds(positions)
    assert step[0] == pytest.approx(3.0, abs=SWEEP.max_acceleration * DT)  # keeps its speed along the path
    near_first = np.linalg.norm(positions[:-1] - waypoints[1], axis=1) < 0.6
    assert near_first.any() and step[near_first].max() <= 1.0 * 1.01
    on_last = (np.abs(positions[:-1, 1] - 20.0) < 1e-9) & (positions[:-1, 0] > 25.0)
    assert step[on_last].max() <= 2.0 * 1.01


def test_fly_climbing_corner_keeps_vertical_speed():
    # Both legs are steep; the arc between them passes through vertical.
    waypoints = np.array([[0, 0, 0], [5, 0, 8.66], [0, 0, 17.32]])
    positions, headings = fly(waypoints, SWEEP, heading=0.0, stop_angle=np.pi)
    check_profile(positions, headings, SWEEP)
    assert speeds(positions)[5:-5].min() > 0.1


def test_heading_slews_while_moving_and_settles_at_the_end():
    waypoints = np.array([[0, 0, 5], [3, 0, 5]])
    positions, headings = fly(waypoints, SWEEP, heading=np.pi / 2, start_heading=-np.pi / 2)
    check_profile(positions, headings, SWEEP)
    flight = path_duration(waypoints, SWEEP)
    assert (len(positions) - 1) * DT >= np.pi / SWEEP.max_heading_rate - 1e-9  # waited only at the end
    assert np.linalg.norm(positions[int(np.ceil(flight / DT))] - waypoints[-1]) < 1e-9
    assert headings[-1] == pytest.approx(np.pi / 2)


# --- approach and attack -------------------------------------------------------------------

@pytest.mark.parametrize("reference, expected", [
    ([0.3, 1.0, 5.0], [0.0, 1.0, 5.0]),  # line-of-sight part below D_f: removed, lateral part kept
    ([-0.4, 0.0, 5.2], [0.0, 0.0, 5.2]),
    ([2.0, 1.0, 5.0], [2.0, 1.0, 5.0]),  # above D_f: left alone
    ([-0.6, 0.5, 5.0], [-0.6, 0.5, 5.0]),
])
def test_deadband(reference, expected):
    uav, target = np.array([0.0, 0.0, 5.0]), np.array([10.0, 0.0, 5.0])
    np.testing.assert_allclose(deadband(np.array(reference), uav, target, 0.5), expected, atol=1e-12)


APPROACHES = [  # position, target, start velocity, start heading
    ([-20.0, 5.0, 8.0], [10.0, 5.0, 3.0], None, None),  # far and high: level, then descend
    ([0.0, 0.0, 5.0], [5.0, 5.0, 2.0], None, 2.5),  # inside D_p: one descending leg
    ([-15.0, 0.0, 6.0], [10.0, 0.0, 2.0], [3.0, 0.0, 0.0], np.pi),  # moving towards it, facing away
    ([30.0, -30.0, 4.0], [0.0, 0.0, 6.0], [0.0, 2.0, 0.0], None),  # sideways velocity, climbing
    ([12.0, 0.0, 5.0], [0.0, 0.0, 5.0], None, 0.0),  # just outside D_p
]


@pytest.mark.parametrize("position, target, velocity, heading", APPROACHES)
def test_approach(position, target, velocity, heading):
    position, target = np.array(position), np.array(target)
    positions, headings = approach(position, target, profile=SWEEP, start_velocity=velocity, start_heading=heading)
    check_profile(positions, headings, SWEEP)
    goal = approach_goal(position, target)
    assert_ends_at_rest(positions, goal, SWEEP)
    assert np.hypot(*(goal - target)[:2]) == pytest.approx(4.0)
    assert goal[2] == pytest.approx(target[2])
    facing = np.arctan2(*(target - position)[1::-1])
    assert wrap_angle(headings[-1] - facing) == pytest.approx(0.0, abs=1e-9)
    if heading is not None:
        assert wrap_angle(headings[0] - heading) == pytest.approx(0.0, abs=1e-12)
    horizontal = np.hypot(*(positions - target)[:, :2].T)
    start_distance = horizontal[0]
    if start_distance > 11.0:
        # Level while farther than D_p, bar the rounded junction (at most half the shorter leg).
        margin = 0.5 * min(start_distance - 11.0, 11.0 - 4.0)
        assert np.all(np.abs(positions[horizontal > 11.0 + margin, 2] - position[2]) < 1e-9)
    if velocity is not None:
        along = max(0.0, np.dot(velocity, positions[-1] - position) / np.linalg.norm(positions[-1] - position))
        assert speeds(positions)[0] == pytest.approx(along, abs=SWEEP.max_acceleration * DT)


@pytest.mark.parametrize("position, velocity", [
    ([6.0, 1.0, 2.0], None),  # from the approach's waiting point
    ([-10.0, -10.0, 6.0], None),  # far and above
    ([3.0, -3.0, 2.5], [1.0, -1.0, 0.0]),  # close, drifting away
])
def test_attack_passes_through_the_hit_point(position, velocity):
    target = np.array([2.0, 1.0, 2.0])
    position = np.array(position)
    positions, headings = attack(position, target, profile=ATTACK, start_velocity=velocity, dt=DT)
    check_profile(positions, headings, ATTACK)
    assert distance_to_polyline(target + [0, 0, HIT_OFFSET], positions) < 0.05
    direction = (target - position)[:2] / np.linalg.norm((target - position)[:2])
    end = np.concatenate([target[:2] + 5.0 * direction, [target[2] + 0.15]])
    assert_ends_at_rest(positions, end, ATTACK)
    assert wrap_angle(headings[-1] - np.arctan2(direction[1], direction[0])) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("velocity", [[3.0, 0.0, 0.0], [2.0, 2.0, 1.0], [0.0, 0.0, -1.5], [-4.0, 1.0, 0.0]])
def test_stop_brakes_within_the_braking_distance(velocity):
    position, velocity = np.array([1.0, 2.0, 5.0]), np.array(velocity)
    positions, headings = stop(position, velocity, SWEEP, heading=0.3)
    check_profile(positions, headings, SWEEP)
    speed = np.linalg.norm(velocity)
    travel = positions[-1] - position
    assert np.linalg.norm(travel) <= speed**2 / (2 * SWEEP.max_acceleration) + 1e-6
    np.testing.assert_allclose(np.cross(travel, velocity), 0.0, atol=1e-9)
    assert speeds(positions)[0] == pytest.approx(speed, abs=SWEEP.max_acceleration * DT)
    assert np.linalg.norm(positions[-1] - positions[-2]) <= 0.5 * SWEEP.max_acceleration * DT**2 + 1e-9
    np.testing.assert_allclose(headings, 0.3)


# --- scan ------------------------------------------------------------------------------------

@pytest.mark.parametrize("area, low, high", [
    (AREA, [0, 0], [40, 56]),
    (ARENA, [0, 0], [100, 45]),
    (ARENA[::-1], [0, 0], [100, 45]),  # clockwise
    (HALF_ARENA, [0, 0], [40, 60]),
])
def test_inner_rectangle_of_rectilinear_polygons(area, low, high):
    np.testing.assert_allclose(inner_rectangle(area), [low, high])


@pytest.mark.parametrize("area, best", [
    (np.array([[0, 0], [10, 0], [0, 10]], float), 25.0),
    (np.array([[0, 0], [8, -8], [16, 0], [8, 8]], float), 64.0),  # a square turned 45°: an 8 × 8 square
])
def test_inner_rectangle_of_slanted_polygons_is_inside_and_near_best(area, best):
    from services.lib.geometry import point_in_polygon

    low, high = inner_rectangle(area)
    corners = np.array([[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]]])
    shrunk = corners + 1e-6 * np.sign(0.5 * (low + high) - corners)
    assert point_in_polygon(shrunk, area).all()
    assert np.prod(high - low) >= 0.9 * best


def test_lawnmower_waypoints_layout():
    start = np.array([3.0, 50.0, 5.0])
    corners = lawnmower_waypoints(AREA, 5.0, 10.0, 2.0, start)
    np.testing.assert_allclose(scan_rectangle(AREA, 2.0), [[2.0, 2.0], [38.0, 54.0]])
    line_x = corners[0::2, 0]  # lines along y (the long side), `spacing` apart, centred
    np.testing.assert_allclose(corners[1::2, 0], line_x)
    np.testing.assert_allclose(line_x, [5.0, 15.0, 25.0, 35.0])
    np.testing.assert_allclose(corners[0, :2], [5.0, 54.0])  # nearest corner to the start
    np.testing.assert_allclose(corners[:4, 1], [54.0, 2.0, 2.0, 54.0])  # boustrophedon
    wide = np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 30.0], [0.0, 30.0]])
    corners = lawnmower_waypoints(wide, 5.0, 10.0, 2.0, np.array([70.0, -5.0, 5.0]))
    np.testing.assert_allclose(corners[0, :2], [58.0, 5.0])  # lines along x, starting near the start
    np.testing.assert_allclose(np.diff(corners[0::2, 1]), 10.0)


SCANS = [  # area, start, spacing
    (AREA, [3.0, 50.0, 5.0], 10.0),  # start inside: flows straight into the sweep
    (ARENA, [-5.0, -5.0, 0.0], 10.0),  # outside and on the ground
    (ARENA, [50.0, 20.0, 5.0], 8.0),
    (HALF_ARENA, [45.0, 5.0, 3.0], 6.0),
]


@pytest.mark.parametrize("area, start, spacing", SCANS)
def test_lawnmower_sweep(area, start, spacing):
    start, height, factor = np.array(start), 5.0, 2.0
    positions, headings = lawnmower(area, height, spacing, profile=SWEEP, start=start, start_heading=0.0,
                                    corner_factor=factor)
    check_profile(positions, headings, SWEEP)
    np.testing.assert_allclose(positions[0], start)
    corners = lawnmower_waypoints(area, height, spacing, 2.0, start)
    low, high = scan_rectangle(area, 2.0)
    assert_ends_at_rest(positions, corners[-1], SWEEP)
    sweep = positions[int(np.argmin(np.linalg.norm(positions - corners[0], axis=1))) + 1:]
    assert np.all(sweep[:, :2] >= low - 1e-9) and np.all(sweep[:, :2] <= high + 1e-9)
    np.testing.assert_allclose(sweep[:, 2], height)

    across = 0 if corners[0, 0] == corners[1, 0] else 1
    lines = corners[0::2, across]
    assert np.all(np.abs(np.diff(lines)) == pytest.approx(spacing))
    # Alg. 3: from the vehicle's line to the furthest side; the next sweep (from where this one
    # ends) comes back over the rest, so two sweeps cover every point within spacing/2 of a leg.
    far = high[across] if lines[-1] > lines[0] or len(lines) == 1 and lines[0] > start[across] else low[across]
    assert abs(far - lines[-1]) <= spacing / 2 + 1e-9
    assert abs(start[across] - lines[0]) <= spacing / 2 + 1e-9 or not low[across] <= start[across] <= high[across]
    back = lawnmower_waypoints(area, height, spacing, 2.0, corners[-1])[0::2, across]
    grid = np.stack(np.meshgrid(np.linspace(low[0], high[0], 41), np.linspace(low[1], high[1], 41)), -1).reshape(-1, 2)
    both = np.concatenate([lines, back])
    assert np.abs(grid[:, across, None] - both[None, :]).min(axis=1).max() <= spacing / 2 + 1e-9
    assert back.min() - low[across] <= spacing / 2 + 1e-9 and high[across] - back.max() <= spacing / 2 + 1e-9

    on_line = np.abs(sweep[:, across, None] - lines[None, :]).min(axis=1) < 1e-9
    step = speeds(sweep)
    both_on = on_line[:-1] & on_line[1:]
    both_off = ~on_line[:-1] & ~on_line[1:]
    assert step[both_on].max() == pytest.approx(SWEEP.max_speed, rel=0.01)  # long legs at full speed
    assert step[both_off].max() <= SWEEP.max_speed / factor * 1.01  # corners and cross legs slowed
    # The sweep itself never stops, and faces its travel on the long legs.
    assert step[5:-5].min() > 0.5
    fast = both_on & (step > 0.9 * SWEEP.max_speed)
    fast[:30] = False  # the first 3 s: the heading may still be slewing from start_heading
    assert fast.sum() > 10
    travel = np.diff(sweep, axis=0)[fast]
    np.testing.assert_allclose(wrap_angle(headings[-len(sweep):][1:][fast] - np.arctan2(travel[:, 1], travel[:, 0])),
                               0.0, atol=1e-6)


def test_lawnmower_keeps_the_positional_signature_node_uses():
    a = lawnmower(AREA, 5.0, 10.0, 2.0, SWEEP, np.array([3.0, 50.0, 5.0]), DT, 0.0)
    b = lawnmower(AREA, 5.0, 10.0, offset=2.0, profile=SWEEP, start=np.array([3.0, 50.0, 5.0]), start_heading=0.0)
    np.testing.assert_array_equal(a[0], b[0])


# --- interception ----------------------------------------------------------------------------

INTERCEPTS = [  # position, target position, target velocity, start velocity
    ([0.0, 0.0, 5.0], [30.0, 0.0, 5.0], [-2.0, 1.0, 0.0], None),  # crossing towards us
    ([0.0, 0.0, 5.0], [10.0, 0.0, 6.0], [3.0, 0.0, 0.0], [1.0, 0.0, 0.0]),  # receding, slower than us
    ([5.0, 5.0, 4.0], [-20.0, 10.0, 8.0], [1.0, -1.0, -0.3], None),  # descending
    ([0.0, 0.0, 5.0], [8.0, 3.0, 5.0], [0.0, 0.0, 0.0], None),  # still
]


@pytest.mark.parametrize("position, target, velocity, start_velocity", INTERCEPTS)
def test_intercept_merges_with_the_target(position, target, velocity, start_velocity):
    position, target, velocity = np.array(position), np.array(target), np.array(velocity)
    plan = plan_intercept(position, target, velocity, profile=SWEEP, start_velocity=start_velocity)
    assert plan is not None
    np.testing.assert_allclose(plan.merge_point, target + plan.passing * velocity)
    assert plan.arrival <= plan.merge_start - 1.0 + 1e-9  # at W with the lead margin, before the target
    assert plan.merge_start - 1.0 - plan.arrival < 0.05  # and no later than needed (smallest τ)
    positions, headings = sample_intercept(plan, SWEEP, DT)
    expected = intercept(position, target, velocity, profile=SWEEP, start_velocity=start_velocity)
    np.testing.assert_array_equal(positions, expected[0])
    check_profile(positions, headings, SWEEP)
    t = np.arange(len(positions)) * DT
    following = (t >= plan.merge_end) & (t <= plan.follow_end)
    assert following.sum() >= 30
    predicted = target + t[following, None] * velocity
    np.testing.assert_allclose(positions[following], predicted, atol=0.03)
    i = np.flatnonzero(following)[0]
    np.testing.assert_allclose((positions[i + 1] - positions[i]) / DT, velocity, atol=1e-6)
    assert_ends_at_rest(positions, positions[-1], SWEEP)
    if np.linalg.norm(velocity[:2]) > 0:
        assert wrap_angle(headings[i] - np.arctan2(velocity[1], velocity[0])) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("velocity", [[6.0, 0.0, 0.0], [0.0, 0.0, 2.5], [4.99, 0.0, 0.0]])
def test_intercept_gives_up_on_targets_it_cannot_catch(velocity):
    # Faster than max_speed (or max_vertical_speed); or receding so nearly as fast that 30 s is not enough.
    assert intercept(np.zeros(3), np.array([20.0, 0.0, 0.0]), np.array(velocity), profile=SWEEP) is None


PURSUITS = [  # UAV position, UAV velocity, target position, target velocity
    ([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [20.0, 10.0, 6.0], [4.0, 0.0, 0.0]),  # from rest, target crossing
    ([0.0, 0.0, 5.0], [5.0, 0.0, 0.0], [10.0, -15.0, 7.0], [0.0, 4.0, 0.5]),  # moving across its path
    ([30.0, 0.0, 8.0], [-3.0, 1.0, 0.0], [10.0, 0.0, 6.0], [-4.0, 0.0, 0.0]),  # target running away
    ([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [3.0, 0.0, 5.0], [0.0, 2.0, 0.0]),  # close and slow (a circling drone)
]


@pytest.mark.parametrize("uav, velocity, target, target_velocity", PURSUITS)
def test_pursuit_closes_onto_the_predicted_track_within_the_profile(uav, velocity, target, target_velocity):
    from services.planner.core import pursuit
    uav, velocity, target, target_velocity = map(np.array, (uav, velocity, target, target_velocity))
    # the closing speed plans to brake at BRAKING·a_max (0.59 m/s²): the farthest start, 22 m, takes 10.6 s
    positions, headings = pursuit(uav, target, target_velocity, profile=ATTACK, start_velocity=velocity,
                                  start_heading=0.0, horizon=16.0)
    check_profile(positions, headings, ATTACK)
    np.testing.assert_allclose(positions[0], uav)
    np.testing.assert_allclose((positions[1] - positions[0]) / DT, velocity, atol=ATTACK.max_acceleration * DT)
    horizon = int(round(16.0 / DT))
    predicted = target + target_velocity * np.arange(horizon + 1)[:, None] * DT
    gap = np.linalg.norm(positions[:horizon + 1] - predicted, axis=1)
    reached = int(np.argmax(gap < 0.1))
    assert gap[reached] < 0.1 and reached * DT < 13.0, f"never on the track: closest {gap.min():.2f} m"
    assert gap[reached:].max() < 0.2  # no more than a small overshoot once there
    settled = horizon + 1 - int(np.argmax(gap[::-1] >= 0.05))
    assert settled * DT < 13.0
    velocities = np.diff(positions[settled + 10:horizon + 1], axis=0) / DT  # a second later: at its velocity
    np.testing.assert_allclose(velocities, np.tile(target_velocity, (len(velocities), 1)), atol=0.15)
    assert_ends_at_rest(positions, positions[-1], ATTACK)


def test_pursuit_refuses_a_target_faster_than_the_profile():
    from services.planner.core import pursuit
    assert pursuit(np.zeros(3), np.array([10.0, 0, 5]), np.array([9.0, 0, 0]), profile=ATTACK) is None


def test_trajectories_longer_than_an_hour_are_refused():
    """Found by tests/test_fuzz_messages.py: a target 10,000 km away cost the planner 70 s and 20 million
    samples; limits near zero would have cost it all its memory."""
    with pytest.raises(ValueError, match="longer than"):
        approach(np.zeros(3), np.array([1e7, 0.0, 5.0]), profile=SWEEP)
    slow_turns = ConstraintProfile(max_speed=5.0, max_acceleration=1.5, max_heading_rate=1e-9)
    with pytest.raises(ValueError, match="turn"):
        fly(np.array([[0.0, 0.0, 5.0], [0.0, 10.0, 5.0]]), slow_turns, start_heading=0.0)
    with pytest.raises(ValueError, match="lines"):
        lawnmower(AREA, 5.0, 1e-6, profile=SWEEP)


def test_a_sweep_interrupted_mid_line_resumes_where_the_vehicle_is_the_way_it_was_going():
    wide = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 45.0], [0.0, 45.0]])
    fresh = lawnmower_waypoints(wide, 5.0, 20.0, 2.0, np.array([2.0, 43.0, 5.0]))
    line = fresh[0, 1]  # the first line, along x
    on_line = np.array([50.0, line + 0.3, 5.0])  # stopped halfway along it (a false alarm)
    resumed = lawnmower_waypoints(wide, 5.0, 20.0, 2.0, on_line, heading=0.0)  # it was flying +x
    np.testing.assert_allclose(resumed[0, :2], [50.0, line])
    np.testing.assert_allclose(resumed[1, :2], [98.0, line])
    assert fresh[1, 0] == 98.0  # the fresh sweep flew this line +x too: the rest is the same
    np.testing.assert_allclose(resumed[2:], fresh[2:])
    backwards = lawnmower_waypoints(wide, 5.0, 20.0, 2.0, on_line, heading=np.pi)
    np.testing.assert_allclose(backwards[:2, 0], [50.0, 2.0])
    # without a heading along the line, off it, or at its very end: from the nearest corner, as before
    for start, heading in ((on_line, None), (on_line, np.pi / 2), (on_line + [0, 5.0, 0], 0.0),
                           (np.array([97.0, line, 5.0]), 0.0)):
        again = lawnmower_waypoints(wide, 5.0, 20.0, 2.0, start, heading=heading)
        assert again[0, 0] in (2.0, 98.0), (start, heading, again[0])
    # the whole sweep from there: no flying back along the line already covered
    positions, _ = lawnmower(wide, 5.0, 20.0, profile=SWEEP, start=on_line, start_heading=0.0)
    first_leg = positions[: int(np.argmin(np.abs(positions[:, 0] - 98.0)))]
    assert np.all(np.diff(first_leg[:, 0]) >= -1e-9)


def test_pursuit_never_follows_a_prediction_below_its_floor():
    """Agile seed 4: a drone braking out of a dive, unseen behind a tree, was predicted on into the
    ground, and the pursuing UAV hit it at 3 m/s. The reference holds the floor under such a prediction."""
    from services.planner.core import pursuit
    uav, target = np.array([0.0, 0.0, 4.0]), np.array([6.0, 0.0, 3.0])
    diving = np.array([2.0, 0.0, -1.5])
    positions, headings = pursuit(uav, target, diving, profile=ATTACK, start_velocity=np.array([3.0, 0.0, -1.0]),
                                  start_heading=0.0, horizon=12.0, floor=1.0)
    check_profile(positions, headings, ATTACK)
    assert positions[:, 2].min() >= 1.0 - 1e-9
    late = positions[int(round(6.0 / DT)):int(round(12.0 / DT))]
    np.testing.assert_allclose(late[:, 2], 1.0, atol=0.05)  # under the prediction, at the floor's height
    unfloored, _ = pursuit(uav, target, diving, profile=ATTACK, start_velocity=np.array([3.0, 0.0, -1.0]),
                           start_heading=0.0, horizon=12.0)
    assert unfloored[:, 2].min() < 0.0  # the case is real: without the floor it goes underground



def _chase_the_circler(start_bearing: float, limit: float = 20.0, env=None) -> float | None:
    """The pursuit flown by the simulator's vehicle against mast's circler (4 m round the mast at
    3.2 m/s), re-planned every 0.3 s from its true state 0.2 s old, turned on by the tracker's
    turn model (TurnHistory over the same window); round the mast as `env` (Surroundings) has it
    when given (commands.pursuit_clear). Seconds to a capture (1 m, 2 m/s), or None."""
    from schemas.messages import Header, TrajectoryReference
    from schemas.arrays import from_numpy
    from services.planner.commands import PlannerParams, pursuit_clear, start_state
    from services.planner.pursuit import pursuit
    from services.simulator.paths import DronePath
    from services.simulator.scenario import load_scenario
    from services.simulator.vehicles import Fleet, make_reference
    from services.tracker.core import TURN_MIN_SPEED, TrackerParams
    from services.tracker.filters.models import turning_path
    from services.tracker.filters.turning import TurnHistory
    from services.lib.tracks import PredictedPath

    scenario = load_scenario("mast")
    [spec] = [d for d in scenario.drones if d.name == "circler"]
    path, planner, tracker = DronePath(spec, scenario, 1, 0), PlannerParams(), TrackerParams()
    limits = np.array([ATTACK.max_speed, ATTACK.max_acceleration, ATTACK.max_heading_rate, ATTACK.max_vertical_speed])
    fleet = Fleet(scenario, ["uav1"], 1)
    t = start = 20.0
    target, _ = path.state(start)
    fleet.position[0] = target + [10.0 * np.cos(start_bearing), 10.0 * np.sin(start_bearing), -2.0]
    fleet.airborne[0], fleet.hold[0] = True, fleet.position[0]
    sent, next_plan = None, start
    while t < start + limit:
        if t >= next_plan - 1e-9:
            seen = t - 0.2
            history = TurnHistory(tracker.turn_window, TURN_MIN_SPEED, tracker.max_turn_rate)
            for then in seen - 0.1 * np.arange(10, -1, -1):
                history.add(then, *path.state(then))
            (p, v), (_, before) = path.state(seen), path.state(seen - 0.1)
            mean = np.concatenate([p, v, (v - before) / 0.1])
            ahead = PredictedPath(p, v, turning_path(mean, 0.25, 9, tracker.manoeuvre_time, history.turn(seen)), 0.25)
            predicted = ahead.rebased(0.2, 8, 0.25)
            now = int(round(t * NS))
            p0, v0 = start_state(sent, now, fleet.position[0].copy(), fleet.velocity[0].copy(), planner.rejoin_distance)
            chase = dict(profile=ATTACK, dt=planner.dt, horizon=planner.pursuit_horizon, predicted=predicted,
                         start_velocity=v0, start_heading=float(fleet.heading[0]))
            if env is None:
                positions, headings = pursuit(p0, predicted.position, predicted.velocity, **chase)
            else:
                trust = planner.pursuit_trust - 0.2  # the missions': past a sighting 0.2 s old
                plan = pursuit_clear(env, p0, predicted.position, predicted.velocity, dict(chase, trust=trust))
                positions, headings = plan.path
            sent = TrajectoryReference(header=Header(stamp=now), command_id=0, start=now, dt=planner.dt,
                                       positions=from_numpy(positions), headings=from_numpy(headings))
            fleet.set_reference(0, make_reference("uav1", now, planner.dt, positions, headings), limits)
            next_plan += 0.3
        t += 0.01
        fleet.integrate(int(round(t * NS)), 0.01, [])
        target, target_velocity = path.state(t)
        if (np.linalg.norm(fleet.position[0] - target) <= scenario.capture_radius
                and np.linalg.norm(fleet.velocity[0] - target_velocity) <= scenario.capture_speed):
            return t - start
    return None


def test_a_pursuit_trailing_a_circling_drone_cuts_inside_its_turn_and_catches_it(monkeypatch):
    """Chasing the drone's predicted position from behind, the UAV needs more than the drone's
    speed on the drone's own circle, more centripetal acceleration than it has (2.6 of 3 m/s² at
    the drone's speed alone), and swings outside; aiming ahead of it along its predicted path by
    the gap it trails by (LEAD_SPEED, up to LEAD_MAX) cuts inside the turn."""
    from services.planner import pursuit
    bearings = (0.0, 2.0, 4.0)
    led = [_chase_the_circler(b) for b in bearings]
    monkeypatch.setattr(pursuit, "LEAD_MAX", 0.0)
    unled = [_chase_the_circler(b) for b in bearings]
    print(f"captured after {led} s with the lead, {unled} without")
    assert all(took is not None and took < 15.0 for took in led)
    assert any(took is None for took in unled)


def test_a_turning_prediction_is_carried_on_round_its_turn_not_along_its_last_step():
    """A rendezvous may meet the target past the tracker's 2 s path: carried straight on from
    there, a circling drone's meeting was planned where it never goes and moved on with every
    update, and the UAV trailed it (mast's circler from bearing 4 rad, 40 s uncaught)."""
    from services.lib.tracks import PredictedPath

    angle = 0.8 * 0.25 * np.arange(0, 9)  # 3.2 m/s on a 4 m circle, sampled every 0.25 s
    circle = np.stack([4.0 * np.cos(angle), 4.0 * np.sin(angle), 6.0 + 0.1 * np.arange(0, 9)], axis=1)
    predicted = PredictedPath(circle[0], np.array([0.0, 3.2, 0.4]), circle[1:], 0.25)
    carried = predicted.turning_on(4.0)
    positions, velocities = carried.state(np.arange(0, 4.01, 0.25))
    assert np.allclose(positions[:9], circle)
    assert np.allclose(np.linalg.norm(positions[:, :2], axis=1), 4.0, atol=0.01)  # round the same circle
    assert np.allclose(positions[:, 2], 6.0 + 0.1 * np.arange(17))  # climbing on as it did
    assert np.allclose(np.linalg.norm(velocities[:, :2], axis=1), np.linalg.norm(velocities[0, :2]))
    assert predicted.turning_on(2.0) is predicted  # nothing to carry on
    straight = PredictedPath(circle[0], np.zeros(3), circle[0] + np.outer(np.arange(1, 9), [0.5, 0.0, 0.0]), 0.25)
    assert np.allclose(straight.turning_on(4.0).state([3.5])[0], straight.state([3.5])[0])


@settings(max_examples=300, deadline=None)
@given(radius=st.floats(2.0, 8.0), speed=st.floats(1.0, 6.0), bearing=st.floats(0.0, 2 * np.pi),
       distance=st.floats(1.0, 15.0), velocity=st.tuples(*[st.floats(-5.0, 5.0)] * 2, st.floats(-1.5, 1.5)),
       climb=st.floats(-1.0, 1.0))
@example(radius=6.0, speed=4.0, bearing=5.0, distance=4.0, velocity=(1.0, 1.0, 1.0), climb=-1.0)  # a turn starved
@example(radius=8.0, speed=3.546875, bearing=4.1875, distance=13.5, velocity=(1.0, 0.0, 0.0), climb=-1.0)  # a descent starved
def test_a_rendezvous_with_a_turning_target_stays_within_the_profile_and_meets_it(radius, speed, bearing, distance,
                                                                                  velocity, climb):
    from services.planner import pursuit as law
    from services.lib.tracks import PredictedPath

    rate = speed / radius  # anticlockwise round (0, 0, 6), climbing or sinking
    angle = bearing + rate * 0.25 * np.arange(1, 9)
    path = np.stack([radius * np.cos(angle), radius * np.sin(angle), 6.0 + climb * 0.25 * np.arange(1, 9)], axis=1)
    here = np.array([radius * np.cos(bearing), radius * np.sin(bearing), 6.0])
    heading = np.array([-np.sin(bearing), np.cos(bearing), 0.0]) * speed + [0.0, 0.0, climb]
    predicted = PredictedPath(here, heading, path, 0.25)
    uav = here + distance * np.array([np.cos(bearing + 2.0), np.sin(bearing + 2.0), -0.1])
    chase = dict(profile=ATTACK, start_velocity=np.array(velocity), start_heading=0.0, predicted=predicted, floor=1.0)
    positions, headings = law.pursuit(uav, here, heading, **chase)
    check_profile(positions, headings, ATTACK)
    assert positions[:, 2].min() >= min(1.0, uav[2]) - 1e-9
    meeting = law.meeting_length(uav, here, heading, **chase)
    if meeting:
        (there,), (moving,) = predicted.turning_on(law.RENDEZVOUS_MAX_S).state([meeting * DT])  # turning on past its 2 s
        assert np.linalg.norm(positions[meeting] - there) < 1e-6
        arriving = (positions[meeting] - positions[meeting - 1]) / DT
        assert np.linalg.norm(arriving - moving) <= law.RENDEZVOUS_SLACK + 0.15  # a backward difference: ½·a·dt off
