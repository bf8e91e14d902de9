"""Separation planned ahead (team.py, plans.py): each UAV's status carries the next seconds of its
reference, and a conflict between two plans is resolved by the lower-priority UAV before the safety
distance (5 m) is crossed — where the UAVs' current velocities say nothing is coming."""
from __future__ import annotations

import numpy as np
import pytest

from services.job_manager.core import State
from services.job_manager.plans import NS, PlannedPath, first_breach
from tests.test_job_manager_machine import HOME, Rig, s


def line(t0: float, start, velocity, seconds: float = 8.0, dt: float = 0.25) -> PlannedPath:
    """A plan flying from `start` at `velocity` (m/s) from mission time t0 for `seconds`."""
    steps = np.arange(int(seconds / dt) + 1)[:, None] * dt
    return PlannedPath(s(t0), dt, np.asarray(start, dtype=float) + steps * np.asarray(velocity, dtype=float))


def turn(t0: float, start, first, then, after: float, seconds: float = 8.0, dt: float = 0.25) -> PlannedPath:
    """Flying at `first` m/s for `after` s, then at `then` m/s."""
    t = np.arange(int(seconds / dt) + 1) * dt
    before = np.minimum(t, after)[:, None] * np.asarray(first, dtype=float)
    later = np.maximum(t - after, 0.0)[:, None] * np.asarray(then, dtype=float)
    return PlannedPath(s(t0), dt, np.asarray(start, dtype=float) + before + later)


def partner(rig: Rig, t: float, plan: PlannedPath, state: str = "GOING_AROUND", name: str = "uav1",
            airborne: bool = True, velocity=None) -> None:
    position = plan.at(np.array([s(t)]))[0]
    if velocity is None:
        velocity = (plan.at(np.array([s(t) + NS // 4]))[0] - position) * 4.0
    rig.jm.partner_status(name, s(t), flying_normally=True, airborne=airborne, position=tuple(position), state=state,
                          target=None, velocity=tuple(velocity), plan=plan)


def closest(a: PlannedPath, b: PlannedPath, t0: float, seconds: float) -> float:
    return first_breach(a, b, s(t0), seconds, 0.05, 0.0).closest


def test_two_sweeps_turning_into_each_other_yield_while_the_velocities_say_they_pass_apart():
    """uav1 sweeps east 12 m north of uav2 and turns south-east into uav2's line in 1 s; uav2 sweeps
    east too. Their velocities are parallel (no breach by them); their plans meet 3.7 s ahead."""
    rig = Rig(uav="uav2").airborne()
    mine = line(1.1, HOME, (5.0, 0.0, 0.0))
    rig.jm.observe_reference(mine)
    rig.tick(1.1, velocity=(5.0, 0.0, 0.0))
    theirs = turn(1.1, HOME + [0.0, 12.0, 0.0], (5.0, 0.0, 0.0), (5.0, -4.5, 0.0), after=1.0)
    assert closest(mine, theirs, 1.1, 6.0) < 2.0  # they would meet
    partner(rig, 1.1, theirs)
    rig.tick(1.2, velocity=(5.0, 0.0, 0.0))
    assert rig.last.action == "goto" and "yielding to uav1 (12.0 m apart)" in " ".join(rig.jm.notes)
    # the same without plans: parallel velocities, no yield until it is too late
    blind = Rig(uav="uav2").airborne()
    blind.tick(1.1, velocity=(5.0, 0.0, 0.0))
    blind.jm.partner_status("uav1", s(1.1), flying_normally=True, airborne=True, position=tuple(HOME + [0.0, 12.0, 0.0]),
                            state="GOING_AROUND", target=None, velocity=(5.0, 0.0, 0.0))
    blind.tick(1.2, velocity=(5.0, 0.0, 0.0))
    assert blind.last.action == "scan"


def test_plans_that_pass_apart_change_nothing_and_the_higher_priority_uav_keeps_its_plan():
    rig = Rig(uav="uav2").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))
    rig.tick(1.1)
    partner(rig, 1.1, line(1.1, HOME + [0.0, 7.0, 0.0], (5.0, 0.0, 0.0)))  # parallel, 7 m apart
    rig.tick(1.2)
    assert rig.last.action == "scan"
    top = Rig(uav="uav1").airborne()
    top.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))
    top.tick(1.1)
    partner(top, 1.1, line(1.1, HOME + [20.0, 0.0, 0.0], (-5.0, 0.0, 0.0)), name="uav2")  # head-on in 1.5 s
    top.tick(1.2)
    assert top.last.action == "scan"  # uav2 yields, not uav1


def test_a_yield_holds_where_it_is_when_the_partners_plan_passes_clear_of_it_else_climbs_above_it():
    # uav1 crosses 10 m ahead of uav2 going north: holding where it is keeps uav2 10 m off its line
    rig = Rig(uav="uav2").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))
    rig.tick(1.1)
    partner(rig, 1.1, line(1.1, HOME + [10.0, -12.0, 0.0], (0.0, 5.0, 0.0)))
    rig.tick(1.2)
    assert rig.last.action == "goto" and rig.last.target == tuple(HOME)
    # uav1's line passes over uav2's spot: it climbs vertical_separation (6 m) above that line
    over = Rig(uav="uav2").airborne()
    over.jm.observe_reference(line(1.1, HOME, (1.0, 0.0, 0.0)))  # 3 m east by the time uav1 passes
    over.tick(1.1)
    partner(over, 1.1, line(1.1, HOME + [0.0, -15.0, 1.0], (0.0, 5.0, 0.0)))
    over.tick(1.2)
    assert over.last.action == "goto" and over.last.target == (HOME[0], HOME[1], HOME[2] + 1.0 + 6.0)


def test_a_uav_taking_off_beside_a_partner_that_is_taking_off_waits_on_the_ground():
    rig = Rig(uav="uav2")
    ground = HOME - [0.0, 0.0, 5.0]
    rig.tick(0.0, position=ground)
    assert rig.jm.state is State.TAKING_OFF
    rig.jm.observe_reference(line(0.0, ground, (0.0, 0.0, 2.0), seconds=2.5))  # straight up to 5 m
    climb = line(0.0, ground + [3.0, 0.0, 0.0], (0.0, 0.0, 2.0), seconds=2.5)  # uav1, 3 m away, the same
    partner(rig, 0.0, climb, state="TAKING_OFF", airborne=False)
    rig.tick(0.1, position=ground)
    assert rig.last.action == "goto" and rig.last.target == tuple(ground)  # held on the ground
    away = turn(3.0, ground + [3.0, 0.0, 5.0], (5.0, 0.0, 0.0), (5.0, 0.0, 0.0), after=0.0)
    partner(rig, 3.0, away, state="GOING_AROUND")
    rig.tick(3.0, position=ground)
    assert rig.last.action == "goto"  # 3 m off: still too close
    partner(rig, 4.5, away, state="GOING_AROUND")
    rig.tick(4.5, position=ground)  # 8.4 m off and leaving
    assert rig.last.action == "takeoff"


def test_two_chasers_converging_on_one_target_the_lower_one_yields_before_they_meet():
    """Both engaged on the same drone from either side; their plans meet where they would catch it."""
    rig = Rig(uav="uav2").airborne()
    drone = np.array([70.0, 30.0, 6.0])  # in uav2's half of the arena
    for t in (1.0, 1.1, 1.2):
        rig.tick(t, detections=[drone])
    assert rig.jm.state is State.GOING_TO_TARGET
    meet = HOME + [15.0, 10.0, 1.0]
    mine = line(1.3, HOME, (meet - HOME) / 4.0)
    theirs = line(1.3, meet + [15.0, 0.0, 0.0], np.array([-15.0, 0.0, 0.0]) / 4.0)
    assert np.linalg.norm(mine.positions[0] - theirs.positions[0]) > 25.0
    rig.jm.observe_reference(mine)
    partner(rig, 1.3, theirs, state="GOING_TO_TARGET")
    rig.tick(1.35)
    assert rig.last.action == "goto" and "yielding to uav1" in " ".join(rig.jm.notes)


@pytest.mark.parametrize("age, yields", [(0.1, False), (1.2, True)])
def test_a_stale_partner_plan_must_keep_a_wider_distance(age, yields):
    """A partner hovering 6.5 m away by its plan: fresh, 6.5 > 5 m; heard 1.2 s ago, it may have planned
    anew since: 5 m + 1.2 s · 2 m/s = 7.4 m."""
    t = 2.0
    rig = Rig(uav="uav2").airborne()
    rig.jm.observe_reference(line(1.0, HOME, (0.0, 0.0, 0.0)))
    hover = line(t - age, HOME + [6.5, 0.0, 0.0], (0.0, 0.0, 0.0))
    partner(rig, t - age, hover)
    rig.tick(t)
    assert (rig.last.action == "goto") is yields


def test_a_yield_lasts_while_the_missions_way_is_blocked_even_when_the_hold_itself_is_clear():
    """uav1 hovers (checking a target) 9 m ahead on uav2's sweep line: holding where it is, uav2 is
    clear of it, but taking its sweep up again would fly into it: the yield lasts until uav1 leaves."""
    rig = Rig(uav="uav2").airborne()
    sweep = line(1.1, HOME, (5.0, 0.0, 0.0))
    rig.jm.observe_reference(sweep)
    rig.tick(1.1)
    hovering = line(1.1, HOME + [9.0, 0.0, 0.0], (0.0, 0.0, 0.0), seconds=30.0)
    partner(rig, 1.1, hovering, state="CHECKING_TARGET")
    rig.tick(1.2)
    hold = rig.last
    assert hold.action == "goto" and hold.target == tuple(HOME)
    rig.jm.observe_reference(line(1.2, HOME, (0.0, 0.0, 0.0)))  # the planner flies the hold
    for t in np.arange(1.3, 5.0, 0.1):
        partner(rig, round(t, 2), hovering, state="CHECKING_TARGET")
        rig.tick(round(t, 2))
        assert rig.last == hold, f"released at {t:.1f} s"
    leaving = line(5.0, HOME + [9.0, 0.0, 0.0], (0.0, 5.0, 0.0))
    partner(rig, 5.0, leaving)
    partner(rig, 7.0, leaving)
    rig.tick(7.0)  # uav1 10 m north and going on north: the sweep east is clear
    assert rig.last.action == "scan"


def test_a_yield_is_not_held_for_a_plan_the_machine_has_moved_on_from():
    """uav1, engaged (priority), hovers 9 m ahead on uav2's sweep line: uav2 holds. A balloon comes
    into view and the machine, stopped, goes on to check it: the paused sweep is no longer the
    mission's way, and the hold, clear of uav1, ends."""
    rig = Rig(uav="uav2", team=("uav1", "uav2")).airborne()
    start = np.array([60.0, 20.0, 5.0])  # in uav2's half
    rig.jm.observe_reference(line(1.1, start, (5.0, 0.0, 0.0)))
    rig.tick(1.1, position=start)
    hovering = line(1.1, start + [9.0, 0.0, 0.0], (0.0, 0.0, 0.0), seconds=30.0)
    partner(rig, 1.1, hovering, state="GOING_TO_TARGET")
    rig.tick(1.2, position=start)
    assert rig.last.action == "goto" and rig.last.target == tuple(start)
    rig.jm.observe_reference(line(1.2, start, (0.0, 0.0, 0.0)))
    balloon = start + [-5.0, 12.0, -1.0]
    for t in np.arange(1.3, 2.5, 0.1):
        partner(rig, round(t, 2), hovering, state="GOING_TO_TARGET")
        rig.tick(round(t, 2), position=start, detections=[balloon])
        if rig.jm.state is not State.GOING_AROUND:
            break
    assert rig.jm.state in (State.CHECKING_TARGET, State.GOING_TO_TARGET)
    partner(rig, round(t + 0.1, 2), hovering, state="GOING_TO_TARGET")
    rig.tick(round(t + 0.1, 2), position=start, detections=[balloon])
    assert "separation from uav1 restored" in rig.jm.notes and rig.last.action != "goto"


def test_a_hold_climbs_when_the_partners_plan_later_comes_through_it():
    """agile, 3 UAVs, seed 1: uav3 yielded to uav2's sweep 42 m away and held where it was, clear of
    the plan's first 6 s; the sweep went on through the spot, and uav2 flew into it."""
    rig = Rig(uav="uav2").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))
    rig.tick(1.1)
    partner(rig, 1.1, line(1.1, HOME + [10.0, -12.0, 0.0], (0.0, 5.0, 0.0)))  # crosses 10 m ahead
    rig.tick(1.2)
    assert rig.last.target == tuple(HOME)  # clear of the spot: held where it is
    rig.jm.observe_reference(line(1.2, HOME, (0.0, 0.0, 0.0)))
    # uav1 has planned anew: its next line runs back west along y = HOME's, through the spot
    back = turn(2.0, HOME + [10.0, 0.0, 0.0], (-5.0, 0.0, 0.0), (-5.0, 0.0, 0.0), after=0.0)
    partner(rig, 2.0, back)
    rig.tick(2.0)
    assert rig.last.action == "goto" and rig.last.target == (HOME[0], HOME[1], HOME[2] + 6.0)
    assert "comes through the hold: climbing" in rig.jm.notes[-1]


def test_a_sweeping_uav_with_priority_brakes_rather_than_fly_into_a_partner_holding_on_its_line():
    rig = Rig(uav="uav1").airborne()
    rig.tick(1.1, velocity=(4.0, 0.0, 0.0))
    partner(rig, 1.1, line(1.1, HOME + [4.5, 0.0, 0.0], (0.0, 0.0, 0.0)), name="uav2")  # 4.5 m ahead, same height
    rig.tick(1.2, velocity=(4.0, 0.0, 0.0))
    assert rig.last.action == "stop" and "giving way to uav2" in rig.jm.notes[-1]


def test_a_uav_with_priority_whose_new_plan_starts_towards_a_partner_gives_way_before_it_is_under_way():
    """agile, 3 UAVs, seed 1: uav2 took up its sweep after an interception, at rest, straight at uav3
    7 m off; by velocities the give-way came only once it was moving, 6.7 m apart (4.1 m at the closest)."""
    rig = Rig(uav="uav1").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))  # the sweep, from rest
    rig.tick(1.1, velocity=(0.0, 0.0, 0.0))
    partner(rig, 1.1, line(1.1, HOME + [9.0, 0.0, 1.0], (0.0, 0.0, 0.0)), name="uav2")  # holding ahead
    rig.tick(1.2, velocity=(0.2, 0.0, 0.0))
    assert rig.last.action == "stop" and "giving way to uav2" in rig.jm.notes[-1]


def test_giving_way_lasts_while_the_missions_way_runs_into_the_partner_not_only_while_braking_does():
    """intruder, 2 UAVs, seed 1943: uav1's chase gave way to uav2, and its braking reference, no
    longer towards uav2, ended the give-way on the next tick; the chase, taken up again, gave way
    again: 9 engagements in 1 s. The give-way now lasts while the paused mission's plan runs into
    the partner, and ends when the partner has climbed clear of it."""
    rig = Rig(uav="uav1").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (5.0, 0.0, 0.0)))  # the sweep, from rest
    rig.tick(1.1, velocity=(0.0, 0.0, 0.0))
    holding = line(1.1, HOME + [9.0, 0.0, 1.0], (0.0, 0.0, 0.0), seconds=30.0)
    partner(rig, 1.1, holding, name="uav2")
    rig.tick(1.2, velocity=(0.2, 0.0, 0.0))
    stop = rig.last
    assert stop.action == "stop" and "giving way to uav2" in rig.jm.notes[-1]
    rig.jm.observe_reference(line(1.2, HOME, (0.0, 0.0, 0.0), seconds=30.0))  # the planner flies the stop
    for t in np.arange(1.3, 4.0, 0.1):
        partner(rig, round(t, 2), holding, name="uav2")
        rig.tick(round(t, 2), velocity=(0.0, 0.0, 0.0))
        assert rig.last == stop and not any("engaging again" in note for note in rig.jm.notes), f"{t:.1f} s"
    climbed = line(4.0, HOME + [9.0, 0.0, 7.0], (0.0, 0.0, 0.0), seconds=30.0)  # 7 m above my plan
    partner(rig, 4.0, climbed, name="uav2")
    rig.tick(4.0, velocity=(0.0, 0.0, 0.0))
    assert "uav2 is clear: engaging again" in rig.jm.notes and rig.last.action == "scan"


def test_two_uavs_sent_down_together_near_each_other_land_one_after_the_other():
    """intruder, 3 UAVs, seed 5372: the mission timer sent uav1 and uav2 down at once, landing 4.6 m
    apart; nothing kept them apart while landing. uav2 (later in team order) holds, climbing above
    uav1's descent, and lands once uav1 is down."""
    rig = Rig(uav="uav2", duration=40.0).airborne()
    here = HOME + [0.0, 0.0, 0.0]
    rig.run(1.1, 24.9, position=here)
    rig.tick(25.0, position=here)  # 40 s − landing margin 15 s
    assert rig.jm.state is State.LANDING and rig.last.action == "land"
    rig.jm.observe_reference(line(25.0, here, (0.0, 0.0, -1.0), seconds=5.0))
    descending = line(25.0, here + [4.6, 0.0, 0.0], (0.0, 0.0, -1.0), seconds=5.0)  # uav1, landing beside
    partner(rig, 25.0, descending, state="LANDING")
    rig.tick(25.1, position=here)
    assert rig.jm.state is State.LANDING and rig.last.action == "goto" and rig.last.target[2] > here[2]
    assert "yielding to uav1" in rig.jm.notes[-1]
    rig.jm.observe_reference(line(25.1, here, (0.0, 0.0, 0.0), seconds=30.0))
    rig.jm.partner_status("uav1", s(31.0), flying_normally=False, airborne=False,
                          position=tuple(here + [4.6, 0.0, 0.0]), state="LANDED", target=None,
                          velocity=(0.0, 0.0, 0.0), plan=None)
    rig.tick(31.0, position=here)
    assert rig.last.action == "land" and "separation from uav1 restored" in rig.jm.notes


def test_a_uav_with_priority_landing_from_speed_gives_way_to_a_partner_ahead():
    """intruder, 3 UAVs, seed 5372: uav1, sent down by the mission timer while sweeping at 5 m/s
    towards uav2 11 m off, braked over 8 m at the sweeping profile and came within 2.6 m of uav2
    climbing clear of it. Its landing brakes at the attack profile and gives way as its sweep does."""
    rig = Rig(uav="uav1", duration=40.0).airborne()
    far = line(0.0, HOME + [40.0, 0.0, 0.0], (0.0, 0.0, 0.0), seconds=40.0)
    for t in np.arange(1.1, 24.95, 0.1):
        partner(rig, round(t, 2), far, name="uav2")  # heard all along: not fallen
        rig.tick(round(t, 2))
    decision = rig.tick(25.0, velocity=(5.0, 0.0, 0.0))
    assert rig.jm.state is State.LANDING and decision.action == "land" and decision.profile == "attack"
    rig.jm.observe_reference(line(25.0, HOME, (5.0, 0.0, -0.5), seconds=3.0))
    partner(rig, 25.0, line(25.0, HOME + [7.0, 0.0, 0.5], (0.0, 0.0, 1.0)), name="uav2", state="LANDING")
    rig.tick(25.1, velocity=(5.0, 0.0, 0.0))
    assert rig.last.action == "stop" and "giving way to uav2" in rig.jm.notes[-1] and rig.jm.state is State.LANDING


def test_a_give_way_begun_on_our_velocities_lasts_until_the_uav_no_longer_closes_on_the_partner():
    """intruder, 2 UAVs, seed 3545: uav1 gave way to uav2 16 m off, the two closing at 8 m/s; on the
    next tick uav2's plan was a braking one, no longer predicted to come near uav1's, and the
    give-way ended with uav1 still at speed towards uav2, and began again the tick after."""
    rig = Rig(uav="uav1").airborne()
    rig.jm.observe_reference(turn(1.1, HOME, (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), after=1.4))  # stops 7 m on
    rig.tick(1.1, velocity=(5.0, 0.0, 0.0))
    partner(rig, 1.1, line(1.1, HOME + [16.0, 0.0, 0.0], (-3.0, 0.0, 0.0)), name="uav2")
    rig.tick(1.2, velocity=(5.0, 0.0, 0.0))
    stop = rig.last
    assert stop.action == "stop" and "giving way to uav2" in rig.jm.notes[-1]
    braking = turn(1.3, HOME + [15.6, 0.0, 0.0], (-1.0, 0.0, 0.0), (0.0, 0.0, 0.0), after=0.2, seconds=30.0)
    partner(rig, 1.3, braking, name="uav2")  # its plan no longer comes near mine
    rig.tick(1.3, velocity=(5.0, 0.0, 0.0))  # but I am still closing on it at speed
    assert rig.last == stop and not any("engaging again" in note for note in rig.jm.notes)
    partner(rig, 1.5, braking, name="uav2")
    rig.tick(1.5, velocity=(0.0, 0.0, 0.0))  # braked
    assert "uav2 is clear: engaging again" in rig.jm.notes


def test_a_yield_holds_where_braking_ends_not_back_where_it_began():
    """intruder, 3 UAVs, seeds 3435 and 1109: uav2 yielded to uav1 and held at the spot where the
    yield began; braked past it, it flew back faster than it climbed, towards uav1 braking towards
    it, and they came within 4.4 and 4.5 m. The hold is where braking (at the attack profile's
    3 m/s²) ends."""
    rig = Rig(uav="uav2").airborne()
    rig.jm.observe_reference(line(1.1, HOME, (2.0, 0.0, 0.0)))
    rig.tick(1.1, velocity=(2.0, 0.0, 0.0))
    crossing = turn(1.1, HOME + [-2.0, -10.0, 0.0], (0.0, 8.0, 0.0), (0.0, 0.0, 0.0), after=1.25)  # stops 2 m behind
    partner(rig, 1.1, crossing, state="GOING_TO_TARGET")
    rig.tick(1.2, velocity=(2.0, 0.0, 0.0))
    assert rig.last.action == "goto" and "yielding to uav1" in " ".join(rig.jm.notes)
    assert rig.last.target[:2] == pytest.approx((HOME[0] + 4.0 / 6.0, HOME[1]))  # 2 m/s braked at 3 m/s²


@pytest.mark.parametrize("me, other", [("uav1", "uav2"), ("uav2", "uav1")])
def test_two_uavs_whose_fresh_plans_pass_apart_do_not_brake_for_each_other_on_their_velocities(me, other):
    """intruder, 2 UAVs, seed 3545 (campaign run 11): two chases 15-16 m apart closing at 10 m/s by their
    velocities, their plans turning apart (6.6 m at the closest): both braked, again and again, and
    both targets got away. Velocities are the fallback where a plan is missing or the plans say the
    distance breaks; fresh plans that keep it make neither UAV brake."""
    rig = Rig(uav=me).airborne()
    sign = 1.0 if me == "uav1" else -1.0
    start = HOME if me == "uav1" else HOME + [16.0, 0.0, 0.0]
    away = HOME + [16.0, 0.0, 0.0] if me == "uav1" else HOME
    mine = turn(1.1, start, (5.0 * sign, 0.0, 0.0), (4.0 * sign, 3.0 * sign, 0.0), after=0.5)
    theirs = turn(1.1, away, (-5.0 * sign, 0.0, 0.0), (-4.0 * sign, -3.0 * sign, 0.0), after=0.5)
    assert 5.0 < closest(mine, theirs, 1.1, 6.0) < 7.0
    rig.jm.observe_reference(mine)
    rig.tick(1.1, position=start, velocity=(5.0 * sign, 0.0, 0.0))
    partner(rig, 1.1, theirs, name=other, state="GOING_TO_TARGET")
    rig.tick(1.2, position=mine.at(np.array([s(1.2)]))[0], velocity=(5.0 * sign, 0.0, 0.0))
    assert rig.last.action == "scan" and not any("giving way" in n or "yielding" in n for n in rig.jm.notes)


def test_an_interception_is_taken_up_after_a_yield_only_on_a_fresh_sighting():
    """intruder, 3 UAVs, seed 5144 (campaign run 2): uav3 yielded mid-interception; when separation
    was restored the dodger had been unseen 1.8 s, and the interception taken up again was aimed at
    its prediction, 4.9 m from it. The UAV holds and looks until the target is seen again."""
    def drone(t: float) -> np.ndarray:
        return HOME + np.array([38.0 + 3.0 * t, 0.0, 1.0])  # in uav2's half

    def sighting(t: float) -> None:
        rig.jm.observe_tracks(s(t), np.array([7]), drone(t)[None], np.array([[3.0, 0.0, 0.0]]))
        rig.tick(t, detections=[drone(t)])

    rig = Rig(uav="uav2").airborne()
    sighting(1.1)
    sighting(1.2)
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "intercept"
    crossing = line(1.3, HOME + [0.0, 8.0, 0.0], (0.0, -3.0, 0.0), seconds=30.0)  # uav1 across my way
    for t in np.arange(1.3, 2.75, 0.1):  # scans without the drone: it is out of sight
        partner(rig, round(t, 2), crossing, state="GOING_TO_TARGET")  # engaged as well, first in team order
        rig.tick(round(t, 2))
    assert "yielding to uav1" in " ".join(rig.jm.notes) and rig.last.action == "goto"
    far = line(2.8, HOME + [0.0, 60.0, 0.0], (0.0, 0.0, 0.0), seconds=30.0)
    partner(rig, 2.8, far, state="GOING_TO_TARGET")  # gone far away: separation restored, the drone unseen for 1.6 s
    rig.tick(2.8)
    assert "separation from uav1 restored" in " ".join(rig.jm.notes)
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "stop"
    assert "target last seen 1.6 s ago: holding until it is seen again" in rig.jm.notes[-1]
    sighting(2.9)
    assert rig.last.action == "intercept" and rig.last.target_seen == s(2.9)


@pytest.mark.parametrize("token_gone", [False, True])
def test_a_partner_killed_on_its_way_is_kept_clear_of_where_it_stopped_not_where_its_plan_went(token_gone):
    """Its last plan goes north, away from my line; killed, its autopilot holds or lands where it
    was, 3 m beside my line 12 m ahead. Answering, it flies its plan and I keep mine; not answering,
    it cannot yield and may have stopped there: I yield before I get within 5 m."""
    rig = Rig(uav="uav1").airborne()
    target = HOME + [30.0, 0.0, 1.0]
    for t in (1.0, 1.1, 1.2):
        rig.tick(t, detections=[target])
    assert rig.jm.state is State.GOING_TO_TARGET
    rig.jm.observe_reference(line(1.3, HOME, (3.0, 0.0, 0.0)))
    partner(rig, 1.3, line(1.3, HOME + [12.0, 3.0, 0.0], (0.0, 3.0, 0.0)), state="GOING_TO_TARGET", name="uav2")
    if token_gone:
        rig.jm.partner_token("uav2", False, s(1.32))
    rig.tick(1.35, detections=[target])
    assert (rig.last.action == "goto") is token_gone
