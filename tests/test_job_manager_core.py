import numpy as np
import pytest

from services.geometry import point_in_polygon, polygon_area, signed_area
from services.job_manager.areas import clip_x, split_area
from services.job_manager.core import NS, JobManager, JobManagerParams, State

RECT = np.array([[0.0, 0.0], [90.0, 0.0], [90.0, 40.0], [0.0, 40.0]])
# An L: 100 × 60 minus the 50 × 30 upper-right block (area 4500).
L_SHAPE = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 30.0], [50.0, 30.0], [50.0, 60.0], [0.0, 60.0]])


def test_polygon_area_and_orientation():
    assert polygon_area(RECT) == pytest.approx(3600.0)
    assert signed_area(RECT[::-1]) == pytest.approx(-3600.0)
    assert polygon_area(L_SHAPE) == pytest.approx(4500.0)


@pytest.mark.parametrize("parts", [2, 3])
def test_split_rectangle_equal_areas(parts):
    pieces = split_area(RECT, parts)
    assert len(pieces) == parts
    areas = np.array([polygon_area(p) for p in pieces])
    np.testing.assert_allclose(areas, 3600.0 / parts, rtol=1e-3)
    # Vertical cuts of a rectangle: each piece is the strip between x = k·90/parts.
    for k, piece in enumerate(pieces):
        assert piece[:, 0].min() == pytest.approx(90.0 * k / parts, abs=1e-6)
        assert piece[:, 0].max() == pytest.approx(90.0 * (k + 1) / parts, abs=1e-6)
        assert signed_area(piece) > 0  # counter-clockwise


def test_split_l_shape_equal_areas():
    pieces = split_area(L_SHAPE, 2)
    areas = [polygon_area(p) for p in pieces]
    np.testing.assert_allclose(areas, 2250.0, rtol=1e-3)
    # The left 50 m column holds 3000 m², so the cut is at x = 2250 / 60 = 37.5.
    assert pieces[0][:, 0].max() == pytest.approx(37.5, abs=1e-6)
    three = split_area(L_SHAPE, 3)
    np.testing.assert_allclose([polygon_area(p) for p in three], 1500.0, rtol=1e-3)
    assert sum(polygon_area(p) for p in three) == pytest.approx(4500.0)


def test_split_non_convex_reversed_input():
    # A U open upwards, given clockwise: the middle cut crosses the notch.
    u_shape = np.array([[0, 0], [0, 40], [10, 40], [10, 10], [20, 10], [20, 40], [30, 40], [30, 0]], float)
    pieces = split_area(u_shape, 3)
    total = polygon_area(u_shape)
    np.testing.assert_allclose([polygon_area(p) for p in pieces], total / 3, rtol=1e-3)


def test_clip_x_keeps_exact_area():
    left = clip_x(L_SHAPE, 70.0, keep_left=True)
    right = clip_x(L_SHAPE, 70.0, keep_left=False)
    assert polygon_area(left) == pytest.approx(50 * 60 + 20 * 30)
    assert polygon_area(right) == pytest.approx(30 * 30)
    assert len(clip_x(L_SHAPE, -1.0)) == 0


def test_point_in_polygon():
    points = np.array([[25.0, 45.0], [75.0, 45.0], [75.0, 15.0], [-1.0, 10.0], [49.0, 59.0]])
    np.testing.assert_array_equal(point_in_polygon(points, L_SHAPE), [True, False, True, False, True])
    assert point_in_polygon(np.array([10.0, 10.0]), L_SHAPE) is True
    assert point_in_polygon(np.array([60.0, 50.0]), L_SHAPE) is False


# ----------------------------------------------------------------- job manager
def s(seconds: float) -> int:
    return int(round(seconds * NS))


def make_manager(duration: float = 120.0, uav: str = "uav2") -> JobManager:
    jm = JobManager(JobManagerParams(), uav)
    jm.set_world(RECT, ["uav1", "uav2", "uav3"], duration)
    return jm


def test_working_area_is_own_share():
    jm = make_manager()
    assert jm.working_area[:, 0].min() == pytest.approx(30.0, abs=1e-6)
    assert jm.working_area[:, 0].max() == pytest.approx(60.0, abs=1e-6)
    assert jm.set_world(RECT, ["uav1", "uav2", "uav3"], 120.0) is False  # re-sent world: no change


def test_mission_state_sequence():
    jm = make_manager(duration=120.0)
    ground = np.array([45.0, 20.0, 0.0])
    assert jm.update(0, ground, False, services_ready=False).action == "idle"
    assert jm.update(s(1), ground, False, services_ready=False) is None
    assert jm.state is State.IDLE

    decision = jm.update(s(2), ground, False, services_ready=True)
    assert jm.state is State.TAKING_OFF and decision.action == "takeoff" and decision.height == 5.0

    climbing = np.array([45.0, 20.0, 3.0])
    assert jm.update(s(3), climbing, True, True) is None and jm.state is State.TAKING_OFF
    assert not jm.flying_normally

    decision = jm.update(s(5), np.array([45.0, 20.0, 4.8]), True, True)
    assert jm.state is State.GOING_AROUND and jm.flying_normally
    assert decision.action == "scan" and decision.spacing == 10.0 and decision.profile == "sweeping"
    np.testing.assert_allclose(np.array(decision.area), jm.working_area)

    flying = np.array([50.0, 30.0, 5.0])
    assert jm.update(s(104.9), flying, True, True) is None and jm.state is State.GOING_AROUND
    decision = jm.update(s(105.0), flying, True, True)  # duration 120 − landing margin 15
    assert jm.state is State.LANDING and decision.action == "land"
    assert decision.target == (50.0, 30.0, 0.0)

    assert jm.update(s(107), np.array([50.0, 30.0, 1.0]), True, True) is None
    assert jm.update(s(109), np.array([50.0, 30.0, 0.05]), False, True) is None  # same command
    assert jm.state is State.LANDED
    assert [t.target for t in jm.transitions] == [State.TAKING_OFF, State.GOING_AROUND, State.LANDING, State.LANDED]


def test_no_takeoff_without_world_or_after_mission():
    jm = JobManager(JobManagerParams(), "uav1")
    jm.update(0, np.zeros(3), False, True)
    assert jm.state is State.IDLE  # no working area yet
    late = make_manager(duration=20.0)
    late.update(s(6), np.zeros(3), False, True)
    assert late.state is State.LANDED


def test_emergency_landing_on_silent_odometry():
    jm = make_manager()
    jm.update(0, np.zeros(3), False, True)
    jm.update(s(1), np.array([0, 0, 5.0]), True, True, position_stamp_ns=s(1))
    assert jm.state is State.GOING_AROUND
    jm.update(s(1.9), np.array([0, 0, 5.0]), True, True, position_stamp_ns=s(1))
    assert jm.state is State.GOING_AROUND
    decision = jm.update(s(2.1), np.array([0, 0, 5.0]), True, True, position_stamp_ns=s(1))
    assert jm.state is State.EMERGENCY_LANDING and decision.action == "emergency_land"
    assert jm.update(s(9), np.array([0, 0, 0.0]), False, True) is None
    assert jm.state is State.LANDED


def test_partners_silent_after_timeout():
    jm = make_manager()
    jm.partner_status("uav1", s(10), True)
    jm.partner_status("uav3", s(20), False)
    jm.partner_status("uav2", s(20), True)  # ourselves: ignored
    assert jm.partners_silent(s(24.9)) == []
    assert jm.partners_silent(s(25.1)) == ["uav1"]
    assert jm.partners_silent(s(35.1)) == ["uav1", "uav3"]
    jm.partner_status("uav1", s(30), True)
    assert jm.partners_silent(s(35.1)) == ["uav3"]
    assert jm.partners_grounded() == ["uav3"]


def test_new_confirmed_tracks_reported_once():
    jm = make_manager()
    assert jm.note_confirmed_tracks([3, 1]) == [1, 3]
    assert jm.note_confirmed_tracks([1, 3, 4]) == [4]
    assert jm.note_confirmed_tracks([1]) == []
