"""Plans kept clear of what the UAV knows is occupied (services/planner/freespace.py, search.py,
avoid.py, guard.py and commands.py), on maps made the way the mapper makes its a-priori map."""
from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.messages import ConstraintProfile, Header, MissionCommand, Obstacle
from services.lib.tracks import PredictedPath
from services.lib.voxels.apriori import obstacle_voxels
from services.lib.voxels.grid import GridGeometry
from services.planner import guard
from services.planner.avoid import Airspace, Clearances, Surroundings, body_clearance, clip, lead_in, speed_barrier
from services.planner.commands import PlannerParams, VehicleState, meeting_route, plan_command
from services.planner.freespace import FreeSpace
from services.planner.search import Band, route

GRID = GridGeometry((-10.0, -10.0, -1.0), (160, 120, 52), 0.5)
CLEAR = Clearances(0.4, 1.0, 0.3)
PARAMS = PlannerParams()
SWEEP = ConstraintProfile()
ATTACK = ConstraintProfile(name="attack", max_speed=8.3, max_acceleration=3.0)
GROUND = Obstacle(kind="plane", center=(0.0, 0.0, 0.0))


def box(center, size) -> Obstacle:
    return Obstacle(kind="box", center=tuple(map(float, center)), size=tuple(map(float, size)))


def pole(x, y, height, radius=0.05) -> Obstacle:
    return Obstacle(kind="cylinder", center=(float(x), float(y), 0.0), radius=radius, height=float(height))


def space_of(*obstacles: Obstacle, seen: bool = True, grid: GridGeometry = GRID) -> FreeSpace:
    """The a-priori map of the obstacles, everything else seen free (`seen`) or never seen."""
    space = FreeSpace(CLEAR.plan)
    space.set_ground(0.0)
    pinned = obstacle_voxels([GROUND, *obstacles], grid)
    values = np.full(grid.size, -1000.0 if seen else -740.0, np.float32)
    values[pinned] = np.inf
    every = np.arange(grid.size)
    space.apply_map(True, grid.origin, grid.shape, grid.voxel_size, -740.0, every, values)
    return space


def env_of(*obstacles: Obstacle) -> Surroundings:
    return Surroundings(space_of(*obstacles), CLEAR, Airspace(0.0, 1.0, 20.0, (0.0, 0.0), (140.0, 100.0)))


def command(action: str, **fields) -> MissionCommand:
    return MissionCommand(header=Header(stamp=0), command_id=1, action=action, **fields)


def vehicle(position, velocity=(0.0, 0.0, 0.0), heading=0.0) -> VehicleState:
    return VehicleState(np.array(position, dtype=float), np.array(velocity, dtype=float), heading, 0.0)


WALL = box((50.0, 40.0, 5.0), (1.0, 30.0, 10.0))  # across y 25-55, 10 m tall


def test_the_ground_is_no_obstacle_and_the_counts_follow_every_change():
    space = space_of(WALL)
    assert space.clearance([[20.0, 40.0, 0.1]])[0] >= space.reach  # on the ground, nothing near
    reference = space.counts.copy()
    cube = np.ravel_multi_index(np.mgrid[60:64, 60:64, 10:14].reshape(3, -1), GRID.shape)  # a new 2 m cube
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, cube, np.zeros(len(cube), np.float32))
    assert (space.counts != reference).any()
    rebuilt = FreeSpace(space.clearance_kept)
    rebuilt.set_ground(0.0)
    flat = space.replica.grid.reshape(-1)
    changed = np.flatnonzero(flat != np.float32(-740.0))
    rebuilt.apply_map(True, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, changed, flat[changed])
    assert np.array_equal(rebuilt.counts, space.counts)  # voxel-by-voxel updates equal a rebuild
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, cube,
                    np.full(len(cube), -1000.0, np.float32))  # freed again
    assert np.array_equal(space.counts, reference)


def test_a_route_goes_round_a_wall_with_the_clearance_a_plan_keeps():
    env = env_of(WALL)
    start, goal = np.array([35.0, 40.0, 5.0]), np.array([65.0, 40.0, 5.0])
    assert env.conflict(np.stack([start, goal]), CLEAR.plan) is not None  # straight through the wall
    found = route(env.space, start, goal, CLEAR.plan, env.airspace.band(), vertical_weight=2.5)
    assert found is not None and found.searched and found.reached
    assert np.allclose(found.points[[0, -1]], [start, goal])
    assert env.space.path_clearance(found.points) >= CLEAR.plan - 1e-6
    ends = found.points[1:-1]
    assert ((ends[:, 1] < 25.0) | (ends[:, 1] > 55.0) | (ends[:, 2] > 10.0)).all()  # round an end or over


def test_a_route_goes_over_a_low_building_when_that_is_quicker():
    low = box((50.0, 40.0, 1.5), (6.0, 60.0, 3.0))  # a 3 m long shed across the whole way
    env = env_of(low)
    found = route(env.space, np.array([40.0, 40.0, 2.0]), np.array([60.0, 40.0, 2.0]), CLEAR.plan,
                  env.airspace.band(), vertical_weight=2.5)
    assert found is not None and found.searched
    assert found.points[:, 2].max() >= 3.0 + CLEAR.plan - 1e-6  # over its roof
    assert np.abs(found.points[:, 1] - 40.0).max() < 10.0  # not round its ends, 30 m away


def test_a_sweep_line_through_a_tree_detours_and_keeps_the_margin():
    tree = Obstacle(kind="cylinder", center=(30.0, 30.0, 0.0), radius=1.5, height=7.0)
    env = env_of(tree)
    scan = command("scan", area=[(0.0, 0.0), (60.0, 0.0), (60.0, 60.0), (0.0, 60.0)], height=5.0, spacing=20.0)
    plan = plan_command(scan, vehicle((10.0, 4.0, 5.0)), PARAMS, env)
    bare = plan_command(scan, vehicle((10.0, 4.0, 5.0)), PARAMS)
    assert body_clearance(env, bare.path[0]) < 0  # the seed's lawnmower flies through the tree
    assert plan.outcome == "detour" and body_clearance(env, plan.path[0]) >= CLEAR.margin
    assert plan.clearance == pytest.approx(body_clearance(env, plan.path[0]), abs=1e-3)


def test_an_approach_whose_line_of_sight_is_blocked_comes_from_another_side():
    building = box((20.0, 30.0, 4.0), (10.0, 8.0, 8.0))  # between the UAV (west) and the balloon
    balloon = np.array([28.0, 30.0, 4.5])
    env = env_of(building, pole(28.0, 30.0, 4.0))
    plan = plan_command(command("approach", target=tuple(balloon)), vehicle((5.0, 30.0, 5.0)), PARAMS, env)
    assert plan.outcome == "detour" and "own line of sight is blocked" in plan.note
    goal = plan.path[0][-1]
    assert abs(np.hypot(*(goal - balloon)[:2]) - PARAMS.wait_distance) < 0.6
    assert goal[2] == pytest.approx(balloon[2] + PARAMS.hit_offset, abs=0.05)  # level with the hit point
    assert body_clearance(env, plan.path[0]) >= CLEAR.margin
    attack = plan_command(command("attack", target=tuple(balloon), profile=ATTACK), vehicle(goal), PARAMS, env)
    assert attack.outcome in ("clear", "clipped")  # over its own pole (the mount exemption), through it


def test_a_balloon_in_a_walled_yard_is_blocked_and_a_wall_cuts_the_overshoot():
    yard = [box((30.0, 33.5, 1.5), (8.0, 1.0, 3.0)), box((30.0, 26.5, 1.5), (8.0, 1.0, 3.0)),
            box((26.5, 30.0, 1.5), (1.0, 6.0, 3.0)), box((33.5, 30.0, 1.5), (1.0, 6.0, 3.0))]
    env = env_of(*yard, pole(30.0, 30.0, 2.5))
    near = plan_command(command("approach", target=(30.0, 30.0, 3.0)), vehicle((30.0, 22.0, 5.0)), PARAMS, env)
    assert near.outcome == "blocked" and "every approach" in near.note and len(near.path[0]) == 1
    wall_behind = box((30.0, 37.5, 5.0), (20.0, 1.0, 10.0))  # its face 4.5 m beyond the balloon
    env = env_of(wall_behind, pole(30.0, 32.5, 4.0))
    attack = plan_command(command("attack", target=(30.0, 32.5, 4.5), profile=ATTACK), vehicle((30.0, 28.5, 4.9)),
                          PARAMS, env)
    assert attack.outcome == "clipped" and "overshoot cut" in attack.note
    assert PARAMS.min_overshoot <= attack.path[0][-1, 1] - 32.5 < PARAMS.overshoot
    assert 37.0 - attack.path[0][:, 1].max() >= CLEAR.timed  # the wall's face is at y = 37


def test_the_guard_brakes_before_an_obstacle_that_appears_in_the_map():
    space = space_of()
    reference = np.stack([np.linspace(20.0, 60.0, 81), np.full(81, 40.0), np.full(81, 5.0)], axis=1)  # 5 m/s, dt 0.1
    ahead = guard.upcoming(reference, 0, 0.1, 0, 4.0)
    here = reference[0]
    assert guard.check(space, ahead, here, 5.0, 1.5, CLEAR.accept, CLEAR.hard).action == "clear"
    far = np.ravel_multi_index(np.mgrid[98:100, 94:106, 10:22].reshape(3, -1), GRID.shape)  # a wall at x 39-40
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, far, np.zeros(len(far), np.float32))
    verdict = guard.check(space, ahead, here, 5.0, 1.5, CLEAR.accept, CLEAR.hard)
    assert verdict.action == "replan" and verdict.ahead > 10.0  # 19 m ahead: time to go round it
    near = np.ravel_multi_index(np.mgrid[64:66, 94:106, 10:22].reshape(3, -1), GRID.shape)  # at x 22-23
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, near, np.zeros(len(near), np.float32))
    verdict = guard.check(space, ahead, here, 5.0, 1.5, CLEAR.accept, CLEAR.hard)
    assert verdict.action == "brake" and verdict.ahead < 5.0 / 1.2 + 2.0 + 1e-6
    assert "closer than" in verdict.reason


def test_the_guard_brakes_for_unseen_space_ahead_but_not_for_a_drone_the_map_keeps_unknown():
    space = space_of(seen=False)
    seen = np.ravel_multi_index(np.mgrid[40:120, 80:120, 2:30].reshape(3, -1), GRID.shape)  # x 10-50, y 30-50
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, seen, np.full(len(seen), -1000.0, np.float32))
    reference = np.stack([np.linspace(20.0, 60.0, 81), np.full(81, 40.0), np.full(81, 5.0)], axis=1)
    here = np.array([40.0, 40.0, 5.0])
    ahead = guard.upcoming(reference, 0, 0.1, 4 * 10**9, 4.0)  # from x = 40: unseen from x = 50 on
    verdict = guard.check(space, ahead, here, 5.0, 1.5, CLEAR.accept, CLEAR.hard)
    assert verdict.action == "brake" and "not seen" in verdict.reason and verdict.where[0] >= 50.0
    drone = np.ravel_multi_index(([91], [100], [12]), GRID.shape)  # one voxel at (35.75, 40.25, 5.25)
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, drone, np.full(1, -740.0, np.float32))
    early = guard.upcoming(reference, 0, 0.1, 2 * 10**9, 3.0)  # x 30..45, through the drone's voxel
    assert guard.check(space, early, early[0], 5.0, 1.5, CLEAR.accept, CLEAR.hard).action == "clear"


def test_a_replan_at_speed_keeps_the_reference_velocity_continuous():
    env = env_of()
    moving = vehicle((10.0, 10.0, 5.0), velocity=(5.0, 0.0, 0.0))
    plan = plan_command(command("goto", target=(10.0, 40.0, 5.0)), moving, PARAMS, env)  # a right angle away
    positions = plan.path[0]
    first = (positions[1] - positions[0]) / PARAMS.dt
    assert np.linalg.norm(first - [5.0, 0.0, 0.0]) < 0.3  # it carries on along its velocity first
    accelerations = np.diff(positions, n=2, axis=0) / PARAMS.dt**2
    assert np.linalg.norm(accelerations, axis=1).max() <= SWEEP.max_acceleration * 1.05
    assert lead_in(np.zeros(3), np.array([5.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]), SWEEP) is None


def test_a_pursuit_round_a_mast_meets_the_drone_where_the_uav_can_fly():
    from schemas.arrays import from_numpy

    mast = pole(30.0, 30.0, 18.0, radius=0.25)
    env = env_of(mast)
    angle = 0.5 * math.pi + (0.5 / 3.5) * 0.25 * np.arange(1, 49)  # 0.5 m/s round the mast, from its north
    circle = np.stack([30.0 + 3.5 * np.cos(angle), 30.0 + 3.5 * np.sin(angle), np.full(48, 7.0)], axis=1)
    drone = command("intercept", target=(30.0, 33.5, 7.0), target_velocity=(-0.5, 0.0, 0.0), profile=ATTACK,
                    target_path=from_numpy(circle), target_path_dt=0.25)
    uav = vehicle((30.0, 20.0, 7.0))  # south of the mast: the drone is behind it
    bare = plan_command(drone, uav, PARAMS)
    assert body_clearance(env, bare.path[0]) < CLEAR.margin  # without the map it flies by the mast
    plan = plan_command(drone, uav, PARAMS, env)
    assert body_clearance(env, plan.path[0]) >= CLEAR.margin
    at = np.minimum(np.arange(len(plan.path[0])) * PARAMS.dt / 0.25, 47).astype(int)
    assert np.linalg.norm(plan.path[0] - circle[at], axis=1).min() < 1.5  # and still meets the drone


def test_a_path_that_starts_too_close_may_leave_but_not_close_in_or_stay():
    space = space_of(WALL)  # its west face at x = 49.5, the voxels' boxes from there
    near = np.array([48.3, 40.0, 5.0])  # 1.2 m from the boxes: inside the margin already
    assert space.path_conflict(np.stack([near, [40.0, 40.0, 5.0]]), CLEAR.accept) is None  # leaving
    assert space.path_conflict(np.stack([near, [49.3, 40.0, 5.0]]), CLEAR.accept) is not None  # closing in
    along = space.path_conflict(np.stack([near, [48.3, 30.0, 5.0]]), CLEAR.accept)  # along the wall, 1.2 m off
    assert along is not None and 0.2 < along < 0.5  # a conflict once ESCAPE_LENGTH (3 m) of it is flown
    ahead = guard.upcoming(np.stack([near, [49.2, 40.0, 5.0]]), 0, 1.0, 0, 4.0)
    assert guard.check(space, ahead, near, 1.0, 1.5, CLEAR.accept, CLEAR.hard).action != "clear"


def test_only_the_balloons_own_mount_is_passed_over_not_a_post_beside_it():
    balloon = np.array([30.0, 30.0, 4.5])
    post = Obstacle(kind="cylinder", center=(31.2, 30.0, 0.0), radius=0.15, height=5.0)  # 1.2 m off the pole
    env = env_of(pole(30.0, 30.0, 4.0), post)
    attack = plan_command(command("attack", target=tuple(balloon), profile=ATTACK), vehicle((26.0, 30.0, 4.9)),
                          PARAMS, env)
    assert attack.outcome == "blocked"  # the attack line runs over the post: not the balloon's to pass
    assert np.linalg.norm(attack.path[0][-1] - [26.0, 30.0, 4.9]) < 1e-9  # at rest where it was: braking is staying
    clear = plan_command(command("attack", target=tuple(balloon), profile=ATTACK), vehicle((30.0, 26.0, 4.9)),
                         PARAMS, env_of(pole(30.0, 30.0, 4.0)))
    assert clear.outcome == "clear"  # over its own pole alone


def test_a_blocked_plan_at_speed_brakes_instead_of_stopping_dead():
    yard = [box((30.0, 33.5, 1.5), (8.0, 1.0, 3.0)), box((30.0, 26.5, 1.5), (8.0, 1.0, 3.0)),
            box((26.5, 30.0, 1.5), (1.0, 6.0, 3.0)), box((33.5, 30.0, 1.5), (1.0, 6.0, 3.0))]
    env = env_of(*yard, pole(30.0, 30.0, 2.5))
    moving = vehicle((30.0, 15.0, 5.0), velocity=(0.0, 3.0, 0.0))
    plan = plan_command(command("approach", target=(30.0, 30.0, 3.0)), moving, PARAMS, env)
    assert plan.outcome == "blocked"
    first = (plan.path[0][1] - plan.path[0][0]) / PARAMS.dt
    assert np.linalg.norm(first - [0.0, 3.0, 0.0]) < 0.2  # the reference carries on at its speed ...
    assert np.linalg.norm(plan.path[0][-1] - plan.path[0][-2]) < 0.02  # ... and comes to rest


def test_a_pursuit_towards_an_obstacle_at_speed_slides_within_the_profile():
    env = env_of(WALL)
    drone = command("intercept", target=(55.0, 40.0, 5.0), target_velocity=(0.0, 0.0, 0.0), profile=ATTACK)
    plan = plan_command(drone, vehicle((30.0, 40.0, 5.0), velocity=(8.0, 0.0, 0.0)), PARAMS, env)
    positions = plan.path[0]
    accelerations = np.diff(positions, n=2, axis=0) / PARAMS.dt**2
    assert np.linalg.norm(accelerations, axis=1).max() <= ATTACK.max_acceleration * 1.02
    assert body_clearance(env, positions) >= CLEAR.margin


def test_a_clipped_path_brakes_along_its_own_bend_not_straight_on_into_a_wall():
    """street's gap: a chaser's plan bending away from a wall 1.15 m off, clipped for what lay
    beyond, braked straight ahead from the bend and came within 0.67 m of the wall."""
    env = env_of(box((47.5, 40.0, 5.0), (1.0, 30.0, 10.0)), box((45.0, 39.0, 5.0), (6.0, 1.0, 10.0)))
    turn = np.linspace(0.0, np.pi / 2, 14)[:-1]  # 6 m/s round a 5 m quarter circle towards the wall, ...
    arc = np.stack([40.0 + 5.0 * np.sin(turn), 35.0 - 5.0 * np.cos(turn), np.full(13, 5.0)], axis=1)
    line = np.stack([np.full(20, 45.0), 35.0 + 0.6 * np.arange(20), np.full(20, 5.0)], axis=1)  # ... then north, 2 m off it
    positions = np.vstack([arc, line])
    headings = np.zeros(len(positions))
    conflict = env.conflict(positions, CLEAR.timed)
    assert conflict is not None and conflict < len(arc) + 4  # the box across the way, just past the bend
    clipped, _ = clip((positions, headings), conflict, ATTACK, PARAMS.dt)
    assert body_clearance(env, clipped) >= CLEAR.margin
    along = np.min(np.linalg.norm(clipped[:, None, :2] - dense(positions)[None, :, :2], axis=2), axis=1)
    assert along.max() < 0.05  # on the path as planned
    assert np.linalg.norm(clipped[-1] - clipped[-2]) < 0.02  # and at rest


def dense(positions: np.ndarray, step: float = 0.01) -> np.ndarray:
    out = [positions[:1]]
    for a, b in zip(positions[:-1], positions[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    return np.vstack(out)


def test_the_speed_barrier_brakes_for_an_obstacle_ahead_that_is_not_the_nearest():
    """street: coming past one block's corner (the nearest obstacle, moving away from it) at the
    next block across the gap, a barrier on the nearest alone let the pursuit fly at it at 6 m/s."""
    west, east = box((49.0, 30.0, 6.0), (14.0, 8.0, 12.0)), box((68.0, 30.0, 4.0), (12.0, 8.0, 8.0))
    env = env_of(west, east)
    position, velocity = np.array([58.4, 36.3, 5.25]), np.array([4.0, -3.0, 0.0])
    barrier = speed_barrier(env, 1.5, ATTACK.max_speed)
    limited = barrier(position, velocity)
    # the first place on the ray within the plan's clearance of the east block: ~2.4 m on
    ray = position + np.linspace(0.0, 6.0, 601)[:, None] * velocity / 5.0
    room = 0.01 * int(np.argmax(env.space.clearance(ray) < CLEAR.plan))
    assert 1.5 < room < 3.5
    assert np.linalg.norm(limited) <= np.sqrt(2.0 * 1.5 * room) + 0.05
    assert limited @ velocity > 0.0  # slowed, not turned back
    # inside the clearance the barrier asks the reference out again
    near_wall = np.array([61.0, 30.0, 5.0])  # 1.0 m from the east block
    out = barrier(near_wall, np.array([0.0, -3.0, 0.0]))
    assert out[0] < -0.5


def test_a_pursuit_detour_round_a_wall_is_flown_at_speed_and_keeps_the_margin():
    """Mast's eight ran round the tower at 5 m/s while the UAV crawled its detour at 1.3-1.9 m/s,
    braking as if to stop at the carrot 4 m ahead. The route round a still obstacle is flown at the
    speed the UAV can brake from before the route's end."""
    env = env_of(box((50.0, 40.0, 5.0), (1.0, 10.0, 10.0)))  # across y 35-45
    drone = command("intercept", target=(60.0, 40.0, 5.0), target_velocity=(0.0, 1.0, 0.0), profile=ATTACK)
    plan = plan_command(drone, vehicle((40.0, 40.0, 5.0)), PARAMS, env)
    assert plan.outcome == "detour", plan.note
    positions = plan.path[0]
    speeds = np.linalg.norm(np.diff(positions, axis=0), axis=1) / PARAMS.dt
    print(f"fastest on the detour {speeds.max():.1f} m/s")
    assert speeds.max() > 4.0  # the carrot's law alone kept it under sqrt(2 * 0.59 m/s² * 4 m) = 2.2 m/s
    assert body_clearance(env, positions) >= CLEAR.margin
    accelerations = np.diff(positions, n=2, axis=0) / PARAMS.dt**2
    assert np.linalg.norm(accelerations, axis=1).max() <= ATTACK.max_acceleration * 1.02


def test_the_map_survives_repeated_voxels_and_refuses_a_message_whose_lengths_differ():
    space = space_of()
    before = space.counts.copy()
    one = np.ravel_multi_index(([60], [60], [10]), GRID.shape)
    twice = np.concatenate([one, one])
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, twice, np.zeros(2, np.float32))
    space.apply_map(False, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, twice, np.full(2, -1000.0, np.float32))
    assert np.array_equal(space.counts, before)  # counted once, freed once
    grid = space.replica.grid.copy()
    with pytest.raises(ValueError, match="indices and 1 values"):
        space.apply_map(True, GRID.origin, GRID.shape, GRID.voxel_size, -740.0, twice, np.zeros(1, np.float32))
    assert np.array_equal(space.replica.grid, grid) and np.array_equal(space.counts, before)


def test_the_guardian_replans_on_a_conflict_brakes_when_none_helps_and_retries_while_holding():
    keeper = guard.Guardian(retry_ns=10**9)
    far, near = guard.GuardVerdict("replan", "far"), guard.GuardVerdict("brake", "near")
    assert not keeper.wants_replan(0, guard.CLEAR, True)  # nothing to do
    assert keeper.wants_replan(0, far, True) and not keeper.wants_replan(0, far, False)
    keeper.tried(0)
    assert not keeper.wants_replan(5 * 10**8, near, True)  # at most once a second
    assert keeper.must_brake(near) and not keeper.must_brake(far)
    assert keeper.takes(near, far) and keeper.takes(far, guard.CLEAR) and not keeper.takes(far, far)
    keeper.hold(10**9)
    assert not keeper.must_brake(near)  # braking already
    assert not keeper.wants_replan(3 * 10**9, far, True)  # the hold point is what it is
    assert keeper.wants_replan(3 * 10**9, guard.CLEAR, True)  # the way may be clear: plan again
    keeper.release()
    assert not keeper.held


def circling(degrees: float) -> tuple[np.ndarray, np.ndarray]:
    """A drone circling a mast at (30, 30) anticlockwise, 4 m out at 3.2 m/s, now at its north: the
    tracker's 2 s of prediction; and a UAV on the same circle at `degrees`."""
    angle = 0.5 * math.pi + 0.8 * 0.25 * np.arange(1, 9)
    circle = np.stack([30.0 + 4.0 * np.cos(angle), 30.0 + 4.0 * np.sin(angle), np.full(8, 7.0)], axis=1)
    start = math.radians(degrees)
    return circle, np.array([30.0 + 4.0 * math.cos(start), 30.0 + 4.0 * math.sin(start), 7.0])


def bearing(point: np.ndarray) -> float:
    return math.degrees(math.atan2(point[1] - 30.0, point[0] - 30.0))


def test_a_pursuit_round_a_mast_goes_to_meet_the_drone_not_after_it():
    """The drone 130° ahead of the UAV round the mast. A route to where it will be by the time a
    straight flight would get there (0.9 s) went the same way round and ended behind it: the UAV
    trailed it round the mast at its own angular speed (benchmarks/pursuit.py: 55 s to a capture).
    The route's end moves along the prediction to the time the route takes (here as far as the
    prediction goes), and the UAV goes the other way round to meet it."""
    from schemas.arrays import from_numpy

    env = env_of(pole(30.0, 30.0, 18.0, radius=0.25))
    circle, start = circling(-40.0)
    predicted = PredictedPath(np.array([30.0, 34.0, 7.0]), np.array([-3.2, 0.0, 0.0]), circle, 0.25)
    way = meeting_route(env, start, predicted, ATTACK, math.inf)
    assert way is not None and np.linalg.norm(way[-1] - circle[-1]) < 0.5  # where the drone is in 2 s
    assert bearing(way[1]) < -60.0  # clockwise, towards the drone coming round
    drone = command("intercept", target=(30.0, 34.0, 7.0), target_velocity=(-3.2, 0.0, 0.0), profile=ATTACK,
                    target_path=from_numpy(circle), target_path_dt=0.25)
    plan = plan_command(drone, vehicle(start), PARAMS, env)
    assert body_clearance(env, plan.path[0]) >= CLEAR.margin
    turned = bearing(plan.path[0][round(1.0 / PARAMS.dt)]) + 40.0
    assert turned < -10.0, f"turned {turned:.0f}° round the mast in 1 s: after the drone, not towards it"


@pytest.mark.slow(53)
def test_a_drone_circling_a_mast_tighter_than_the_uav_can_turn_is_met_not_trailed(monkeypatch):
    """Mast's circler turns at 2.56 m/s², more than a pursuit may ask of the UAV at its speed: the
    pursuit law chasing it from behind or meeting it head-on at speed passed it faster than the
    net takes (2 m/s) and trailed it round the mast. A rendezvous (pursuit.py) flies to where the
    drone will be, arriving near its velocity; from every bearing round the mast the UAV then
    catches it within 20 s, where without one it did not within 25 s from three of them."""
    from services.planner import pursuit
    from tests.test_planner_core import _chase_the_circler

    env = env_of(pole(20.0, 27.0, 18.0, radius=0.25))  # mast's mast, the drone 4 m round it
    bearings = np.arange(13) * 0.5
    met = [_chase_the_circler(b, 25.0, env) for b in bearings]
    assert all(took is not None and took < 20.0 for took in met), met
    monkeypatch.setattr(pursuit, "RENDEZVOUS_TURN", math.inf)
    assert [_chase_the_circler(b, 25.0, env) for b in (1.5, 2.0, 3.5)] == [None, None, None]


# mbzirc's outline: a notch x 40-60, y 45-60 cut out of the north edge
NOTCHED = np.array([(0.0, 0.0), (100.0, 0.0), (100.0, 60.0), (60.0, 60.0), (60.0, 45.0), (40.0, 45.0), (40.0, 60.0),
                    (0.0, 60.0)])


FENCE_KEPT = 0.65  # m inside a 1 m margin the grid keeps a plan at least (freespace.py, _set_fence)
ARENA_GRID = GridGeometry((-10.0, -10.0, -1.0), (240, 160, 52), 0.5)  # the mapper's default reach, 120 x 80 m


def fenced_env(*obstacles: Obstacle) -> Surroundings:
    space = space_of(*obstacles, grid=ARENA_GRID)
    space.set_arena(NOTCHED, PARAMS.fence_margin)
    return Surroundings(space, CLEAR, Airspace(0.0, 1.0, 20.0, (0.0, 0.0), (100.0, 60.0), tuple(map(tuple, NOTCHED)),
                                               PARAMS.fence_margin))


def inside_by(points: np.ndarray) -> np.ndarray:
    """(N,) m each point lies inside NOTCHED (negative: outside)."""
    from services.lib.geometry import distance_to_edges, point_in_polygon
    gap = distance_to_edges(points[:, :2], NOTCHED)
    return np.where(point_in_polygon(points[:, :2], NOTCHED), gap, -gap)


def test_the_arenas_edge_is_a_wall_a_sweep_going_over_to_the_far_part_goes_round_the_notch():
    """A UAV that takes over the east half from the north-west (revenge mode in mbzirc) went
    straight across the notch, 10 m out of the arena."""
    east = [(50.0, 0.0), (100.0, 0.0), (100.0, 60.0), (60.0, 60.0), (60.0, 45.0), (50.0, 45.0)]
    scan = command("scan", area=east, height=5.0, spacing=20.0)
    start = vehicle((15.0, 48.0, 5.0))
    assert inside_by(plan_command(scan, start, PARAMS, env_of()).path[0]).min() < -5.0  # no edge: across
    plan = plan_command(scan, start, PARAMS, fenced_env())
    margin = inside_by(plan.path[0])
    assert plan.outcome == "detour" and margin.min() >= FENCE_KEPT - 0.5 * CLEAR.allowance, margin.min()
    assert np.linalg.norm(plan.path[0][-1, :2] - plan_command(scan, start, PARAMS, env_of()).path[0][-1, :2]) < 1.0


def test_a_balloon_near_the_arenas_edge_is_attacked_along_it_and_the_guard_brakes_before_the_edge():
    balloon = (97.0, 30.0, 4.5)  # 3 m inside the east edge: an attack from the west would end 2 m out
    env = fenced_env(pole(97.0, 30.0, 4.0))
    head_on = plan_command(command("attack", target=balloon, profile=ATTACK), vehicle((92.0, 30.0, 4.9)), PARAMS, env)
    assert head_on.outcome == "blocked"  # not even min_overshoot is left before the edge
    approach = plan_command(command("approach", target=balloon), vehicle((80.0, 30.0, 5.0)), PARAMS, env)
    goal = approach.path[0][-1]
    assert approach.outcome != "blocked" and abs(goal[1] - balloon[1]) > 2.0  # not head-on: from north or south
    attack = plan_command(command("attack", target=balloon, profile=ATTACK), vehicle(goal), PARAMS, env)
    assert attack.outcome != "blocked" and np.ptp(attack.path[0][:, 1]) > PARAMS.wait_distance  # through it
    assert min(inside_by(approach.path[0]).min(), inside_by(attack.path[0]).min()) >= FENCE_KEPT - 0.5 * CLEAR.allowance
    reference = np.stack([np.linspace(80.0, 105.0, 51), np.full(51, 20.0), np.full(51, 5.0)], axis=1)
    verdict = guard.check(env.space, reference, reference[0], 5.0, 3.0, CLEAR.accept, CLEAR.hard)
    assert verdict.action != "clear" and verdict.where[0] < 100.0  # acted on before the body reaches the edge
