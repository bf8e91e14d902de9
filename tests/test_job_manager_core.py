import numpy as np
import pytest

from services.job_manager.areas import clip_x, split_area
from services.lib.geometry import point_in_polygon, polygon_area, signed_area

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


def test_distance_to_the_outline_inside_and_out():
    from services.lib.geometry import distance_to_edges
    # (75, 45) lies in the cut-out block, 15 m above its lower edge
    points = np.array([[25.0, 45.0], [75.0, 45.0], [50.0, 30.0], [-3.0, -4.0], [102.0, 15.0]])
    np.testing.assert_allclose(distance_to_edges(points, L_SHAPE), [15.0, 15.0, 0.0, 5.0, 2.0])


def test_a_target_on_the_line_between_two_areas_is_usable_from_both_but_not_outside_the_arena():
    from services.job_manager.targets import ForbiddenZones, usable_detections
    left, right = split_area(RECT, 2)
    on_line = np.array([[45.0 + dx, 20.0, 4.0] for dx in (-0.3, 0.3, 1.9, -2.5)])
    outside = np.array([[45.0, -1.0, 4.0]])  # near both areas' outline, but off the field
    zones = ForbiddenZones(radius=4.5, lifetime_ns=1, max_tries=2)
    common = dict(zones=zones, claimed=np.zeros((0, 3)), claim_radius=4.5, min_z=1.0, arena=RECT)
    points = np.vstack([on_line, outside])
    strict = [usable_detections(points, area=area, **common) for area in (left, right)]
    np.testing.assert_array_equal(strict[0] | strict[1], [True, True, True, True, False])
    assert not (strict[0] & strict[1]).any()  # without the overlap each is one UAV's alone
    both = [usable_detections(points, area=area, area_overlap=2.0, **common) for area in (left, right)]
    np.testing.assert_array_equal(both[0], [True, True, True, True, False])
    np.testing.assert_array_equal(both[1], [True, True, True, False, False])
