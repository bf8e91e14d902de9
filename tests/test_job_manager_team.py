"""Team rules of the job manager (seed 004 §3.5.4 and docs/architecture.md "Mission"):
revenge mode for 2 and 3 UAVs, the explicit come-back rule, one chaser per target, separation."""
from __future__ import annotations

import numpy as np
import pytest

from services.job_manager.core import State
from services.job_manager.team import breach_time
from services.lib.geometry import polygon_area
from tests.test_job_manager_machine import BALLOON, HOME, Rig, s


def flying(rig: Rig, name: str, t: float, position=(70.0, 30.0, 5.0), state: str = "GOING_AROUND", target=None,
           normally: bool = True, velocity=(0.0, 0.0, 0.0)) -> None:
    rig.jm.partner_status(name, s(t), flying_normally=normally, airborne=True, position=position, state=state,
                          target=target, velocity=velocity)


def x_range(area: np.ndarray) -> tuple[float, float]:
    return round(float(area[:, 0].min()), 3), round(float(area[:, 0].max()), 3)


REVENGE = [
    # (why the partner falls, what the rig sees, seconds after the partner was last fine)
    ("reports not flying normally", lambda r, t: flying(r, "uav2", t, state="EMERGENCY_LANDING", normally=False), 0.0),
    ("silent for t_s", lambda r, t: None, 15.0),
    # a lost token alone could be a cut radio with the partner still flying: it falls after t_s of silence too
    ("job manager token gone", lambda r, t: r.jm.partner_token("uav2", False, s(t)), 15.0),
]


@pytest.mark.parametrize("why,event,delay", REVENGE, ids=[r[0] for r in REVENGE])
def test_revenge_mode_takes_over_the_whole_arena(why, event, delay):
    rig = Rig().airborne()
    rig.jm.partner_token("uav2", True, s(1.0))
    flying(rig, "uav2", 1.0)
    rig.tick(1.1)
    assert x_range(rig.jm.working_area) == (0.0, 50.0) and rig.last.action == "scan"
    for t in np.arange(1.2, 10.01, 0.1):
        flying(rig, "uav2", round(t, 3))
        rig.tick(round(t, 3))
    event(rig, 10.0)
    if delay > 0:  # silence: nothing changes until t_s has passed
        rig.run(10.1, 10.0 + delay - 0.1)
        assert x_range(rig.jm.working_area) == (0.0, 50.0), "fell too early"
    rig.run(10.0 + delay + 0.1, 10.0 + delay + 0.2)
    assert x_range(rig.jm.working_area) == (0.0, 100.0)
    assert rig.jm.team.fallen == ["uav2"]
    # re-planned: the partner's half first, for one sweep of it (3000 m² / (20 m · 5 m/s) · 1.5 = 45 s)
    assert rig.last.action == "scan" and x_range(np.array(rig.last.area)) == (50.0, 100.0)
    assert any(n.startswith("partner uav2 fell") for n in rig.jm.notes)
    assert any(n.startswith("sweeping the part taken over first (x 50.0..100.0, 45 s)") for n in rig.jm.notes)
    fell = rig.t
    rig.tick(rig.t + 0.1, detections=[[80.0, 30.0, 4.0]])  # the partner's half counts now
    assert rig.jm.state is State.CHECKING_TARGET
    rig.run(rig.t + 0.1, fell + 44.8)  # nothing more in view: back to the sweep of the part taken over
    assert rig.jm.state is State.GOING_AROUND and x_range(np.array(rig.last.area)) == (50.0, 100.0)
    rig.run(fell + 45.0, fell + 45.2)
    assert rig.last.action == "scan" and x_range(np.array(rig.last.area)) == (0.0, 100.0)  # then the whole arena


@pytest.mark.parametrize("fall", ["token gone", "silent for t_s"])
def test_partner_heard_again_gets_its_area_back_only_after_rejoin_time(fall):
    rig = Rig().airborne()
    rig.jm.partner_token("uav2", True, s(1.0))
    flying(rig, "uav2", 1.0)
    rig.tick(1.1)
    if fall == "token gone":
        rig.jm.partner_token("uav2", False, s(2.0))
    rig.run(1.2, 16.2)  # last heard at 1.0: fallen after 15 s of silence
    back_from = 16.3
    if fall == "token gone":
        rig.jm.partner_token("uav2", True, s(back_from))
    assert x_range(rig.jm.working_area) == (0.0, 100.0)
    for t in np.arange(back_from, back_from + 2.95, 0.2):
        flying(rig, "uav2", round(t, 3))
        rig.tick(round(t, 3))
    assert x_range(rig.jm.working_area) == (0.0, 100.0), "back before rejoin_time"
    flying(rig, "uav2", back_from + 3.1)
    rig.tick(back_from + 3.1)
    assert x_range(rig.jm.working_area) == (0.0, 50.0) and rig.jm.team.fallen == []
    assert any(n.startswith("partner uav2 is back") for n in rig.jm.notes)


def test_a_partner_never_heard_falls_t_s_after_take_off():
    rig = Rig().airborne()  # took off at t = 0
    rig.run(1.1, 14.9)
    assert rig.jm.team.fallen == []
    rig.run(15.0, 15.2)
    assert rig.jm.team.fallen == ["uav2"] and "never heard" in rig.jm.team.partners["uav2"].fallen_reason


THIRD = 100.0 / 3
FALLS = [  # the fallen UAV; each survivor's new area, and the part of it it sweeps first (its growth)
    ("uav1", {"uav2": ((0.0, 50.0), (0.0, THIRD)), "uav3": ((50.0, 100.0), (50.0, 2 * THIRD))}),
    ("uav2", {"uav1": ((0.0, 50.0), (THIRD, 50.0)), "uav3": ((50.0, 100.0), (50.0, 2 * THIRD))}),
    ("uav3", {"uav1": ((0.0, 50.0), (THIRD, 50.0)), "uav2": ((50.0, 100.0), (2 * THIRD, 100.0))})]


@pytest.mark.parametrize("fallen,expected", FALLS)
def test_three_uavs_survivors_share_the_fallen_area(fallen, expected):
    for me, (area, first) in expected.items():
        rig = Rig(uav=me, team=("uav1", "uav2", "uav3")).airborne()
        jm = rig.jm
        before = x_range(jm.working_area)
        assert before[1] - before[0] == pytest.approx(100.0 / 3, abs=1e-3)
        jm.partner_status(fallen, s(1.0), flying_normally=True, position=(50.0, 30.0, 5.0), state="GOING_AROUND")
        jm.partner_status(fallen, s(2.0), flying_normally=False, position=(50.0, 30.0, 1.0),
                          state="EMERGENCY_LANDING")
        rig.tick(2.0)
        assert x_range(jm.working_area) == area
        assert polygon_area(jm.working_area) == pytest.approx(3000.0, rel=1e-3)
        assert rig.last.action == "scan" and x_range(np.array(rig.last.area)) == pytest.approx(first, abs=1e-3)


def test_a_target_claimed_by_a_partner_is_left_to_it_unless_i_am_closer():
    rig = Rig().airborne()
    near_border = np.array([49.0, 30.0, 4.0])  # in uav1's half
    flying(rig, "uav2", 1.0, position=(52.0, 30.0, 5.0), state="GOING_TO_TARGET", target=near_border + [0.2, 0, 0])
    rig.tick(1.1, detections=[near_border])
    assert rig.jm.state is State.GOING_AROUND, "chased a target the partner had claimed"
    # both claim it: the one closer keeps it
    rig2 = Rig().airborne()
    rig2.tick(1.1, detections=[near_border], position=[46.0, 30.0, 5.0])
    rig2.tick(1.2, detections=[near_border])
    assert rig2.jm.state is State.GOING_TO_TARGET
    flying(rig2, "uav2", 1.2, position=(60.0, 30.0, 5.0), state="GOING_TO_TARGET", target=near_border)
    assert len(rig2.jm.candidates(s(1.3), np.array([46.0, 30.0, 5.0]))) == 1  # uav1 is closer: keeps it
    flying(rig2, "uav2", 1.3, position=(48.0, 30.0, 5.0), state="GOING_TO_TARGET", target=near_border)
    assert len(rig2.jm.candidates(s(1.3), np.array([46.0, 30.0, 5.0]))) == 0  # uav2 closer: uav1 yields it


def test_the_lower_priority_uav_yields_by_climbing_above_the_partner():
    rig = Rig(uav="uav2").airborne()  # uav2 ranks below uav1
    rig.tick(1.1)
    flying(rig, "uav1", 1.2, position=HOME + [3.0, 0, 0])
    rig.tick(1.2)
    hold = rig.last
    assert hold.action == "goto" and hold.target == (HOME[0], HOME[1], HOME[2] + 6.0)  # vertical_separation
    flying(rig, "uav1", 1.3, position=HOME + [6.0, 0, 0])  # 6 m: beyond 5 m but inside the hysteresis
    rig.tick(1.3)
    assert rig.last == hold
    flying(rig, "uav1", 1.4, position=HOME + [7.5, 0, 0])
    rig.tick(1.4)
    assert rig.last.action == "scan"  # separation restored: back to the mission
    # the higher-priority UAV does not yield
    top = Rig(uav="uav1").airborne()
    top.tick(1.1)
    flying(top, "uav2", 1.2, position=HOME + [3.0, 0, 0])
    top.tick(1.2)
    assert top.last.action == "scan"


def test_an_engaged_uav_has_priority_over_a_sweeping_one():
    rig = Rig(uav="uav1").airborne()
    rig.tick(1.1)
    flying(rig, "uav2", 1.2, position=HOME + [3.0, 0, 0], state="DESTROYING")
    rig.tick(1.2)
    assert rig.last.action == "goto"  # uav1 outranks by order, but uav2 is attacking


def test_a_partner_that_does_not_answer_outranks_an_engaged_uav():
    """Killed while engaging, a partner comes down in its emergency landing where its last status
    left it; its rank there (below this engaged UAV by team order) must not make it the one to
    yield: its job manager's token gone, or silent for lost_link_time, it outranks everyone."""
    def engaged_near(token_gone: bool, silent_for: float):
        rig = Rig(uav="uav1").airborne()
        rig.tick(1.1, detections=[HOME + [12.0, 0.0, 1.0]])
        rig.tick(1.2, detections=[HOME + [12.0, 0.0, 1.0]])
        assert rig.jm.state is State.GOING_TO_TARGET
        flying(rig, "uav2", 1.25, position=HOME + [4.0, 0.0, 0.0], state="GOING_TO_TARGET")
        if token_gone:
            rig.jm.partner_token("uav2", False, s(1.26))
        rig.tick(1.3 + silent_for, detections=[HOME + [12.0, 0.0, 1.0]])
        return rig

    assert engaged_near(token_gone=False, silent_for=0.0).last.action != "goto"  # uav1 ranks first: uav2 yields
    assert engaged_near(token_gone=True, silent_for=0.0).last.action == "goto"  # uav2 cannot: uav1 gives way
    assert engaged_near(token_gone=False, silent_for=1.6).last.action == "goto"  # stale (lost_link_time 1.5 s)


def test_an_engaged_uav_brakes_rather_than_fly_into_the_partner_yielding_to_it():
    """unmapped, every seed: the circler's interceptor, with priority, flew at 3 m/s into the
    partner that had yielded to it and was still braking, before it could climb."""
    rig = Rig().engaged()  # uav1 on BALLOON, at HOME
    toward = (BALLOON - HOME) * [1.0, 1.0, 0.0]
    toward = 4.0 * toward / np.linalg.norm(toward)
    partner = HOME + toward  # 4 m ahead, on the way to the balloon, at the same height
    flying(rig, "uav2", 1.25, position=partner)
    rig.tick(1.3, detections=[BALLOON], velocity=0.5 * toward)  # 2 m/s towards it
    assert rig.last.action == "stop" and rig.last.profile == "attack"
    assert "giving way to uav2" in rig.jm.notes[-1]
    rig.tick(1.4, detections=[BALLOON], velocity=np.zeros(3))  # stopped: still held, not released
    assert rig.last.action == "stop"
    flying(rig, "uav2", 1.45, position=partner + [0.0, 0.0, 5.6])  # it climbed out of the way
    rig.tick(1.5, detections=[BALLOON])
    assert rig.last.action == "approach" and "clear: engaging again" in " ".join(rig.jm.notes[-3:])
    # moving away from a partner, or a sweeping UAV: nothing to give way to
    away = Rig().engaged()
    flying(away, "uav2", 1.25, position=HOME + toward)
    away.tick(1.3, detections=[BALLOON], velocity=-0.5 * toward)
    assert away.last.action == "approach"


def test_breach_time_is_when_a_partner_first_comes_within_the_radius():
    assert breach_time(np.array([20.0, 0, 0]), np.array([-5.0, 0, 0]), 5.0) == pytest.approx(3.0)
    assert breach_time(np.array([3.0, 0, 0]), np.array([5.0, 0, 0]), 5.0) == 0.0  # inside already
    assert breach_time(np.array([20.0, 0, 0]), np.array([5.0, 0, 0]), 5.0) == np.inf  # going away
    assert breach_time(np.array([20.0, 6.0, 0]), np.array([-5.0, 0, 0]), 5.0) == np.inf  # passes 6 m aside
    assert breach_time(np.array([20.0, 0, 0]), np.zeros(3), 5.0) == np.inf
    # passing 3 m aside: the 5 m circle is entered 4 m before the closest point
    assert breach_time(np.array([20.0, 3.0, 0]), np.array([-4.0, 0, 0]), 5.0) == pytest.approx(4.0)


def test_a_head_on_meeting_is_resolved_before_the_safety_distance_is_broken():
    """street seed 4: uav2 sweeping south at 4.5 m/s and uav1 intercepting north at 3 m/s met
    head-on; both acted only at 5 m, with about 6 m of braking between them."""
    south, north = np.array([0.0, -4.5, 0.0]), np.array([0.0, 3.0, 0.0])
    far = Rig(uav="uav2").airborne()  # sweeping, uav1 engaged 25 m ahead: (25 - 5) / 7.5 = 2.7 s to the breach
    far.tick(1.1, velocity=south)
    flying(far, "uav1", 1.1, position=HOME + [0.0, -25.0, 0.0], state="GOING_TO_TARGET", velocity=north)
    far.tick(1.2)
    assert far.last.action == "goto"  # held where braking at 3 m/s² ends, 6 m above uav1's way
    assert far.last.target == pytest.approx((HOME[0], HOME[1] - 4.5**2 / 6.0, HOME[2] + 6.0))
    assert "yielding to uav1 (24.7 m apart)" in " ".join(far.jm.notes)  # carried on 0.1 s at 3 m/s
    early = Rig(uav="uav2").airborne()  # 30 m: 3.3 s to the breach, later than the 3 s lookahead
    early.tick(1.1, velocity=south)
    flying(early, "uav1", 1.2, position=HOME + [0.0, -30.0, 0.0], state="GOING_TO_TARGET", velocity=north)
    early.tick(1.2)
    assert early.last.action == "scan"
    aside = Rig(uav="uav2").airborne()  # the same speeds on lines 6 m apart: no conflict
    aside.tick(1.1, velocity=south)
    flying(aside, "uav1", 1.2, position=HOME + [6.0, -15.0, 0.0], state="GOING_TO_TARGET", velocity=north)
    aside.tick(1.2)
    assert aside.last.action == "scan"


def test_an_engaged_uav_gives_way_to_a_partner_it_will_meet_and_a_yield_lasts_until_it_has_passed():
    rig = Rig().engaged()  # uav1 on BALLOON, at HOME
    toward = (BALLOON - HOME) * [1.0, 1.0, 0.0]
    toward = toward / np.linalg.norm(toward)
    flying(rig, "uav2", 1.25, position=HOME + 15.0 * toward, velocity=-4.5 * toward)  # sweeping at it
    rig.tick(1.3, detections=[BALLOON], velocity=3.0 * toward)  # (15 - 0.2·4.5 - 5) / 7.5 = 1.2 s
    assert rig.last.action == "stop" and "giving way to uav2" in rig.jm.notes[-1]
    # the partner (yielding) hovers 4 m above the way: still held; 5.6 m above: clear
    flying(rig, "uav2", 1.35, position=HOME + 6.0 * toward + [0.0, 0.0, 4.0])
    rig.tick(1.4, detections=[BALLOON], velocity=1.0 * toward)
    assert rig.last.action == "stop"
    flying(rig, "uav2", 1.45, position=HOME + 6.0 * toward + [0.0, 0.0, 5.6])
    rig.tick(1.5, detections=[BALLOON])
    assert rig.last.action == "approach"
    # the yielding side: held (above the way) while the engaged partner passes below, released once it is past
    low = Rig(uav="uav2").airborne()
    low.tick(1.1)
    flying(low, "uav1", 1.1, position=HOME + [0.0, -12.0, 0.0], state="GOING_TO_TARGET", velocity=(0.0, 3.0, 0.0))
    low.tick(1.2)
    hold = low.last
    assert hold.action == "goto"
    for t, y in ((2.0, -6.0), (3.0, -3.0), (4.0, 0.0), (5.0, 3.0), (6.0, 6.0)):
        flying(low, "uav1", t, position=HOME + [0.0, y, 0.0], state="GOING_TO_TARGET", velocity=(0.0, 3.0, 0.0))
        low.tick(t, position=HOME + [0.0, 0.0, 3.0])
        assert low.last == hold, f"released at t = {t}"
    flying(low, "uav1", 7.0, position=HOME + [0.0, 10.0, 0.0], state="GOING_TO_TARGET", velocity=(0.0, 3.0, 0.0))
    low.tick(7.0, position=HOME + [0.0, 0.0, 3.0])
    assert low.last.action == "scan"


def test_a_silent_partner_is_carried_on_at_its_velocity():
    rig = Rig(uav="uav2").airborne()
    rig.tick(1.1)
    # heard 1 s ago 40 m away closing at 10 m/s: 30 m now, (30 - 5) / 10 = 2.5 s to the breach
    flying(rig, "uav1", 0.2, position=HOME + [40.0, 0.0, 0.0], velocity=(-10.0, 0.0, 0.0))
    rig.tick(1.2)
    assert rig.last.action == "goto" and "yielding to uav1 (30.0 m apart)" in " ".join(rig.jm.notes)


def test_an_engaged_uav_drops_its_target_when_a_closer_partner_claims_it():
    rig = Rig().engaged()  # uav1 on BALLOON, 14 m away
    flying(rig, "uav2", 1.25, position=BALLOON + [3.0, 0, 1.0], state="GOING_TO_TARGET", target=BALLOON)
    rig.tick(1.3, detections=[BALLOON])
    assert rig.jm.state is State.IDLE and "partner" in rig.jm.transitions[-1].reason
    rig.tick(1.4, detections=[BALLOON])
    assert rig.jm.state is State.GOING_AROUND  # and leaves it alone


def test_an_isolated_uav_second_in_team_order_lands_where_it_is_and_the_first_goes_on():
    """Lost-link rule, 2 UAVs: both halves hear nothing; uav2 lands in place, uav1 keeps its area and takes
    over uav2's only t_s after uav2's last status, when uav2 is surely on the ground."""
    for me, partner, lands in (("uav2", "uav1", True), ("uav1", "uav2", False)):
        rig = Rig(uav=me).airborne()
        rig.jm.partner_token(partner, True, s(1.0))
        for t in np.arange(1.0, 5.01, 0.1):
            flying(rig, partner, round(t, 3), position=(30.0, 30.0, 5.0))
            rig.tick(round(t, 3))
        rig.jm.partner_token(partner, False, s(5.05))  # the radio goes
        rig.run(5.1, 6.4)
        assert rig.jm.state is not State.LANDING, "landed before lost_link_time"
        rig.run(6.5, 6.7)
        if lands:
            assert rig.jm.state is State.LANDING and rig.last.action == "land"
            assert rig.last.target[:2] == pytest.approx(rig.position[:2])  # where it is
            assert "lost link" in rig.jm.transitions[-1].reason
        else:
            assert rig.jm.state is not State.LANDING
            assert x_range(rig.jm.working_area) == (0.0, 50.0)  # not before t_s
            rig.run(6.8, 20.1)
            assert x_range(rig.jm.working_area) == (0.0, 100.0)


def test_in_a_team_of_three_the_isolated_uav_lands_and_the_two_that_hear_each_other_go_on():
    heard = {"uav1": ("uav2", "uav3"), "uav2": ("uav1", "uav3"), "uav3": ("uav1", "uav2")}
    for me in ("uav1", "uav3"):
        cut = "uav1" if me == "uav1" else "uav2"  # uav1 cut off (seen by itself), or uav2 (seen by uav3)
        rig = Rig(uav=me, team=("uav1", "uav2", "uav3")).airborne()
        for t in np.arange(1.0, 8.01, 0.1):
            for partner in heard[me]:
                if round(t, 3) <= 5.0 or (me != cut and partner != cut):
                    flying(rig, partner, round(t, 3), position=(50.0, 30.0, 5.0))
            rig.tick(round(t, 3))
        assert (rig.jm.state is State.LANDING) == (me == cut), (me, rig.jm.state)


def test_an_unaccounted_partner_is_a_no_fly_column_until_it_is_seen_landed():
    """Detections near its last position are no targets, and a sweep over it passes high enough above it."""
    rig = Rig().airborne()
    for t in np.arange(1.0, 3.01, 0.1):
        flying(rig, "uav2", round(t, 3), position=(45.0, 30.0, 6.0))
        rig.tick(round(t, 3))
    assert rig.last.action == "scan" and rig.last.height == rig.jm.params.search_height
    rig.run(3.1, 5.0)  # uav2 silent: stale after 1.5 s
    p = rig.jm.params
    assert rig.last.action == "scan" and rig.last.height == pytest.approx(6.0 + p.vertical_separation)
    assert p.vertical_separation > p.safety_distance
    near, far = [40.0, 30.0, 4.0], [20.0, 30.0, 4.0]  # 5 m and 25 m from its last position
    assert rig.jm.candidates(s(5.0), rig.position).shape == (0, 3)
    rig.tick(5.1, detections=[near, far])
    assert rig.jm.candidates(s(5.1), rig.position).tolist() == [far]
    rig.jm.partner_status("uav2", s(5.2), flying_normally=False, airborne=False, position=(45.0, 30.0, 0.0),
                          state="LANDED")
    rig.tick(5.2, detections=[near, far])
    assert sorted(rig.jm.candidates(s(5.2), rig.position).tolist()) == sorted([near, far])


def test_two_uavs_cut_off_from_each_other_both_yield_and_only_the_later_in_team_order_climbs():
    """A lasting link cut takes each UAV's token from the other's view: each sees a partner that
    does not answer, so both yield. Both climbing alike, two UAVs 3 m apart would stay 3 m apart;
    the later in team order climbs above the other's plan and the earlier holds at its height."""
    def cut_off(me: str, partner: str):
        rig = Rig(uav=me).airborne()
        rig.tick(1.1)
        flying(rig, partner, 1.2, position=HOME + [3.0, 0, 0])
        rig.jm.partner_token(partner, False, s(1.21))
        rig.tick(1.3)
        return rig.last

    first, second = cut_off("uav1", "uav2"), cut_off("uav2", "uav1")
    assert first.action == "goto" and first.target[2] == pytest.approx(HOME[2])
    assert second.action == "goto" and second.target[2] == pytest.approx(HOME[2] + 6.0)  # vertical_separation


def test_a_uav_on_the_ground_yields_by_staying_there_whatever_its_state():
    """cutclose (an arena written against the link-cut rule): uav2, cut off on the ground beside
    uav1, decided to land where it was (lost link) and, yielding to uav1 in LANDING, climbed 10 m
    over uav1's plan: off the ground, 4.3 m from it. A UAV not airborne holds on the ground."""
    from services.job_manager.team import Mover

    rig = Rig(uav="uav2").airborne()
    rig.tick(1.1)
    flying(rig, "uav1", 1.2, position=HOME + [3.0, 0, 0])
    team = rig.jm.team
    on_ground = HOME - [0.0, 0.0, HOME[2]]
    for state in ("LANDING", "TAKING_OFF", "IDLE"):
        me = Mover(on_ground, np.zeros(3), state, plan=None, airborne=False)
        spot = team.hold_spot(s(1.3), me, team.partners["uav1"], rig.jm._separation)
        assert np.allclose(spot, on_ground), (state, spot)
