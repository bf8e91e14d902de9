"""The planner's choice of manoeuvre per command and where a re-plan starts (services/planner/commands.py)."""
from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas.arrays import from_numpy
from schemas.messages import ConstraintProfile, Header, MissionCommand, TrajectoryReference
from services.lib.geometry import point_in_polygon
from services.lib.runtime.clock import NS
from services.planner.commands import PlannerParams, VehicleState, plan_command, start_state

PARAMS = PlannerParams()


def command(action: str, **fields) -> MissionCommand:
    return MissionCommand(header=Header(stamp=0), command_id=1, action=action, **fields)


def vehicle(position=(0.0, 0.0, 5.0), velocity=(0.0, 0.0, 0.0)) -> VehicleState:
    return VehicleState(np.array(position, dtype=float), np.array(velocity, dtype=float), 0.0, 0.0)


def test_a_replan_starts_on_the_trajectory_while_the_vehicle_follows_it():
    positions = np.stack([np.linspace(0, 10, 101), np.zeros(101), np.full(101, 5.0)], axis=1)  # 1 m/s, dt 0.1
    reference = TrajectoryReference(header=Header(stamp=0), command_id=1, start=0, dt=0.1,
                                    positions=from_numpy(positions), headings=from_numpy(np.zeros(101)),
                                    profile=ConstraintProfile())
    here, velocity = start_state(reference, 5 * NS, np.array([5.3, 0.0, 5.0]), np.zeros(3), 1.5)
    assert np.allclose(here, [5.0, 0.0, 5.0]) and np.allclose(velocity, [1.0, 0.0, 0.0])
    far = np.array([9.0, 3.0, 5.0])  # pushed off it: the measured state
    assert start_state(reference, 5 * NS, far, np.ones(3), 1.5)[0] is far
    assert start_state(None, 5 * NS, far, np.ones(3), 1.5)[0] is far


def test_each_action_gets_its_manoeuvre():
    up = plan_command(command("takeoff", height=5.0), vehicle((0, 0, 0)), PARAMS)
    assert up.note is None and np.isclose(up.path[0][-1, 2], 5.0)
    down = plan_command(command("land"), vehicle(), PARAMS)
    assert np.isclose(down.path[0][-1, 2], 0.0)
    to = plan_command(command("goto", target=(10.0, 0.0, 5.0)), vehicle(), PARAMS)
    assert np.allclose(to.path[0][-1], [10.0, 0.0, 5.0])
    attack = plan_command(command("attack", target=(10.0, 0.0, 5.0)), vehicle(), PARAMS)
    assert attack.path[0][-1, 0] > 10.0 + PARAMS.overshoot - 0.5  # through the target and beyond
    chase = plan_command(command("intercept", target=(10.0, 0.0, 5.0), target_velocity=(1.0, 0.0, 0.0)), vehicle(),
                         PARAMS)
    assert chase.note is None and len(chase.path[0]) > 10


def test_what_cannot_be_planned_is_a_hover_with_the_reason():
    bad = plan_command(command("goto", target=(np.nan, 0.0, 5.0)), vehicle(), PARAMS)
    assert "not finite" in bad.note and np.allclose(bad.path[0], [[0.0, 0.0, 5.0]])
    empty = plan_command(command("attack"), vehicle(), PARAMS)
    assert "cannot plan attack" in empty.note
    too_fast = plan_command(command("intercept", target=(10.0, 0.0, 5.0), target_velocity=(20.0, 0.0, 0.0)),
                            vehicle(), PARAMS)
    assert "chasing its position" in too_fast.note


def test_an_intercept_along_a_curved_prediction_stays_on_the_turning_target():
    """The tracker's predicted path (here a 4 m/s turn of radius 20 m) is flown as curved; the
    straight line from the same position and velocity drifts off the turn."""
    def circle(t):
        angle = 0.2 * np.asarray(t, dtype=float)
        return np.stack([20.0 * np.cos(angle), 20.0 * np.sin(angle), np.full_like(angle, 6.0)], axis=-1)

    start = circle(0.0)
    velocity = (circle(0.001) - start) / 0.001
    path = circle(0.25 * np.arange(1, 49))  # 12 s of prediction
    vehicle_state = VehicleState(np.array([5.0, -5.0, 6.0]), np.zeros(3), 0.0, 0.0, now_ns=0)
    profile = ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0)
    curved = command("intercept", target=tuple(start), target_velocity=tuple(velocity), profile=profile,
                     target_path=from_numpy(path), target_path_dt=0.25)
    straight = command("intercept", target=tuple(start), target_velocity=tuple(velocity), profile=profile)
    at = int(8.0 / PARAMS.dt)
    trusting = msgspec.structs.replace(PARAMS, pursuit_trust=math.inf)  # one command followed for 8 s
    on_turn = plan_command(curved, vehicle_state, trusting).path[0][at]
    on_line = plan_command(straight, vehicle_state, trusting).path[0][at]
    assert np.linalg.norm(on_turn - circle(8.0)) < 0.5  # caught up by 5 s, on the turn since
    assert np.linalg.norm(on_line - circle(8.0)) > 5.0


def test_a_command_planned_late_is_planned_from_where_its_target_is_by_then():
    path = np.array([[1.0, 0.0, 5.0], [2.0, 0.0, 5.0]])
    late = command("intercept", target=(0.0, 0.0, 5.0), target_velocity=(1.0, 0.0, 0.0),
                   target_path=from_numpy(path), target_path_dt=1.0)
    from services.planner.commands import predicted_path

    seen = predicted_path(late, np.array([0.0, 0.0, 5.0]), np.array([1.0, 0.0, 0.0]), now_ns=NS // 2)
    assert np.allclose(seen.position, [0.5, 0.0, 5.0]) and np.allclose(seen.path[0], [1.5, 0.0, 5.0])


def test_a_target_path_that_is_not_positions_is_a_hover_with_the_reason():
    for path, dt in ((np.full((4, 3), np.nan), 0.25), (np.zeros((4, 3)), np.inf), (np.zeros(5), 0.25)):
        bad = command("intercept", target=(10.0, 0.0, 5.0), target_velocity=(1.0, 0.0, 0.0),
                      target_path=from_numpy(path), target_path_dt=dt)
        plan = plan_command(bad, vehicle(), PARAMS)
        assert "target path" in plan.note and np.isfinite(plan.path[0]).all()


def test_a_pursuit_follows_a_prediction_only_so_long_past_the_last_sighting():
    """Agile seed 4: a drone last seen at 4.5 m/s braked behind a tree; the UAV flew its straight
    prediction on for 3 s at 7 m/s. A prediction is followed pursuit_trust s past the sighting (and
    no further than the path it carries), then the reference waits where it puts the target."""
    from services.planner.commands import pursuit_trust

    line = dict(target=(20.0, 0.0, 6.0), target_velocity=(4.0, 0.0, 0.0),
                profile=ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0))
    seen_late = msgspec.structs.replace(command("intercept", **line), target_seen=NS)
    seen_late.header.stamp = 2 * NS  # decided at 2 s from a sighting at 1 s
    assert pursuit_trust(seen_late, 2 * NS, 1.5) == pytest.approx(0.5)
    assert pursuit_trust(command("intercept", **line), 0, 1.5) == pytest.approx(1.5)  # not said: the stamp
    short = command("intercept", **line, target_path=from_numpy(np.array([[21.0, 0.0, 6.0]])), target_path_dt=0.25)
    assert pursuit_trust(short, 0, 1.5) == pytest.approx(0.25)  # the path it carries ends first
    vehicle_state = VehicleState(np.array([0.0, 0.0, 6.0]), np.zeros(3), 0.0, 0.0, now_ns=2 * NS)
    positions = plan_command(seen_late, vehicle_state, PARAMS).path[0]
    waited = np.array([20.0 + 4.0 * 0.5, 0.0, 6.0])  # where the prediction puts it 1.5 s past the sighting
    assert np.linalg.norm(positions[-1] - waited) < 0.3
    assert np.abs(positions[:, 0]).max() < waited[0] + 0.5  # never beyond it



def test_targets_beyond_the_arena_are_aimed_inside_and_no_reference_rises_above_the_ceiling():
    """A target or a mover's meeting beyond the arena's edge (non-convex here) or above its ceiling
    is aimed at fence_margin (1 m) inside, and no reference sample rises above max_height - 1 m
    (13 - 1 m). That a plan does not overshoot the edge is the freespace's (the arena's edge is a
    wall to it: test_planner_obstacles.py), not this aim's."""
    from services.planner.avoid import Airspace, Clearances, Surroundings
    from services.planner.freespace import FreeSpace

    arena = ((0.0, 0.0), (40.0, 0.0), (40.0, 30.0), (25.0, 30.0), (25.0, 15.0), (15.0, 15.0), (15.0, 30.0), (0.0, 30.0))
    airspace = Airspace(0.0, 1.0, 13.0, (0.0, 0.0), (40.0, 30.0), arena, fence_margin=1.0)
    clearances = Clearances(0.4, 0.5, 0.2)
    env = Surroundings(FreeSpace(clearances.plan), clearances, airspace)
    climbing_out = command("intercept", target=(35.0, 25.0, 10.0), target_velocity=(3.0, 2.0, 2.0))
    plan = plan_command(climbing_out, vehicle((30.0, 10.0, 5.0)), PARAMS, env)
    assert plan.path[0][:, 2].max() <= 12.0 + 1e-9
    beyond = plan_command(command("intercept", target=(45.0, 25.0, 14.0), target_velocity=(3.0, 0.0, 0.0)),
                          vehicle((30.0, 10.0, 5.0)), PARAMS, env)
    assert "aimed 1 m inside the arena" in beyond.note and beyond.path[0][:, 2].max() <= 12.0 + 1e-9
    into_the_notch = command("goto", target=(20.0, 25.0, 5.0))  # the notch is outside the arena
    plan = plan_command(into_the_notch, vehicle((5.0, 5.0, 5.0)), PARAMS, env)
    assert inside_by(plan.path[0][-1:, :2], arena)[0] >= 1.0 - 1e-6  # it ends 1 m inside the notch's edge


def inside_by(points, polygon) -> np.ndarray:
    """(N,) how far inside the polygon each point is (negative: outside)."""
    from services.lib.geometry import distance_to_edges
    inside = point_in_polygon(points, np.asarray(polygon))
    return np.where(inside, 1.0, -1.0) * distance_to_edges(points, np.asarray(polygon))
