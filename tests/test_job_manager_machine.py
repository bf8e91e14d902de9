"""The job manager's state machine, transition by transition, on an injected clock
(seed 004 ch. 3): every transition of §3.4, the state timers and forbidden zones of §3.5.1-2,
the abort system of §3.5.3 and automatic start / mission timer of §3.6."""
from __future__ import annotations

import numpy as np
import pytest

from services.job_manager.core import MISSION_STATES, NS, JobManager, JobManagerParams, State

ARENA = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 60.0], [0.0, 60.0]])
HOME = np.array([20.0, 20.0, 5.0])  # in uav1's half (x < 50)
BALLOON = np.array([30.0, 30.0, 4.0])


def s(seconds: float) -> int:
    return int(round(seconds * NS))


class Rig:
    """Drives one JobManager: each `tick` delivers a scan's detections (the LiDAR heartbeat)
    and odometry stamped `t`, then runs the machine at `t`."""

    def __init__(self, uav: str = "uav1", team=("uav1", "uav2"), duration: float = 300.0, **params) -> None:
        self.jm = JobManager(JobManagerParams(**params), uav)
        self.jm.set_world(ARENA, list(team), duration)
        self.t = 0.0
        self.position = HOME.copy()
        self.velocity = np.zeros(3)
        self.decisions = []

    def tick(self, t: float, detections=(), position=None, velocity=None, scan: bool = True,
             odometry: bool = True, ready: bool = True, positioning: str = ""):
        self.t = t
        if position is not None:
            self.position = np.asarray(position, dtype=float)
        if velocity is not None:
            self.velocity = np.asarray(velocity, dtype=float)
        if scan:
            self.jm.observe_detections(s(t), np.asarray(detections, dtype=float).reshape(-1, 3))
        if odometry:
            self.odometry_stamp = s(t)
        decision = self.jm.update(s(t), self.position, self.jm.is_airborne(self.position[2]), ready,
                                  position_stamp_ns=self.odometry_stamp, velocity=self.velocity,
                                  positioning=positioning)
        if decision is not None:
            self.decisions.append(decision)
        return decision

    def run(self, start: float, end: float, step: float = 0.1, **kw):
        t = start
        while t <= end + 1e-9:
            self.tick(round(t, 6), **kw)
            t += step
        return self.jm.state

    @property
    def last(self):
        return self.decisions[-1]

    def airborne(self) -> "Rig":
        """PREFLIGHT → TAKING_OFF → IDLE at t = 1."""
        self.tick(0.0, position=HOME - [0, 0, 5])
        assert self.jm.state is State.TAKING_OFF
        self.tick(1.0, position=HOME)
        assert self.jm.state is State.IDLE
        return self

    def engaged(self) -> "Rig":
        """... IDLE → CHECKING_TARGET → GOING_TO_TARGET on BALLOON, at rest."""
        self.airborne()
        self.tick(1.1, detections=[BALLOON])
        assert self.jm.state is State.CHECKING_TARGET
        self.tick(1.2, detections=[BALLOON])
        assert self.jm.state is State.GOING_TO_TARGET
        return self

    def destroying(self) -> "Rig":
        """... GOING_TO_TARGET → DESTROYING once within D_k of the balloon."""
        self.engaged()
        self.tick(1.3, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
        assert self.jm.state is State.DESTROYING
        return self


def states(rig: Rig) -> list[tuple[str, str]]:
    return [(t.source.value, t.target.value) for t in rig.jm.transitions]


# --------------------------------------------------------- automatic start (§3.6)
def test_preflight_waits_for_services_then_takes_off():
    rig = Rig()
    ground = HOME - [0, 0, 5]
    assert rig.tick(0.0, position=ground, ready=False).action == "idle"
    assert rig.tick(1.0, position=ground, ready=False) is None and rig.jm.state is State.PREFLIGHT
    decision = rig.tick(2.0, position=ground)
    assert rig.jm.state is State.TAKING_OFF and decision.action == "takeoff" and decision.height == 5.0
    assert not rig.jm.flying_normally
    rig.tick(3.0, position=HOME - [0, 0, 1.0])
    assert rig.jm.state is State.TAKING_OFF
    rig.tick(4.0, position=HOME)
    assert rig.jm.state is State.IDLE and rig.jm.flying_normally


def test_mission_timer_lands_and_late_start_stays_down():
    rig = Rig(duration=40.0).airborne()
    rig.run(1.1, 24.9)
    assert rig.jm.state is State.GOING_AROUND
    decision = rig.tick(25.0, position=[22.0, 30.0, 5.0])  # 40 s − landing margin 15 s
    assert rig.jm.state is State.LANDING and decision.action == "land" and decision.target == (22.0, 30.0, 0.0)
    assert decision.profile == "attack"  # its lead-in brakes as any stop
    rig.tick(30.0, position=[22.0, 30.0, 0.05])
    assert rig.jm.state is State.LANDED and not rig.jm.flying_normally
    late = Rig(duration=20.0)
    late.tick(0.0, position=HOME - [0, 0, 5], ready=False)
    late.tick(0.5, position=HOME - [0, 0, 5], ready=False)
    assert late.jm.state is State.PREFLIGHT
    late.jm.update(s(20.0), HOME - [0, 0, 5], False, True, position_stamp_ns=s(20.0))
    assert late.jm.state is State.LANDED


# ------------------------------------------------------------- transitions (§3.4)
TRANSITIONS = [
    # (name, setup, action on the rig, expected state, expected decision action or None)
    ("IDLE → GOING_AROUND: nothing in view", "airborne", lambda r: r.tick(1.1), State.GOING_AROUND, "scan"),
    ("IDLE → CHECKING_TARGET: target in view", "airborne", lambda r: r.tick(1.1, detections=[BALLOON]),
     State.CHECKING_TARGET, "stop"),
    ("CHECKING_TARGET → GOING_TO_TARGET: at rest, closest target locked", "airborne",
     lambda r: (r.tick(1.1, detections=[BALLOON]), r.tick(1.2, detections=[[80, 50, 4], BALLOON])),
     State.GOING_TO_TARGET, "approach"),
    ("CHECKING_TARGET → IDLE → GOING_AROUND: no target for t_m", "airborne",
     lambda r: (r.tick(1.1, detections=[BALLOON], velocity=[1.0, 0, 0]), r.run(1.2, 4.3)), State.GOING_AROUND, "scan"),
    ("CHECKING_TARGET → GOING_TO_TARGET: a target seen within t_m is locked once at rest", "airborne",
     lambda r: (r.tick(1.1, detections=[BALLOON], velocity=[1.0, 0, 0]), r.run(1.2, 2.0),
                r.tick(2.1, velocity=[0, 0, 0])), State.GOING_TO_TARGET, "approach"),
    ("GOING_TO_TARGET → DESTROYING: within D_k", "engaged",
     lambda r: r.tick(1.3, detections=[BALLOON], position=BALLOON + [5.0, 0, 1.0]), State.DESTROYING, None),
    ("GOING_TO_TARGET stays outside D_k", "engaged",
     lambda r: r.tick(1.3, detections=[BALLOON], position=BALLOON + [6.0, 0, 1.0]), State.GOING_TO_TARGET, None),
    ("GOING_TO_TARGET → CHECKING_TARGET: target unseen for t_m", "engaged",
     lambda r: r.run(1.3, 4.3), State.CHECKING_TARGET, "stop"),
    ("DESTROYING → CHECKING_TARGET: target unseen for t_m before the attack", "destroying",
     lambda r: r.run(1.4, 4.4), State.CHECKING_TARGET, "stop"),
]


@pytest.mark.parametrize("name,setup,act,state,action", TRANSITIONS, ids=[t[0] for t in TRANSITIONS])
def test_transition(name, setup, act, state, action):
    rig = getattr(Rig(), setup)()
    count = len(rig.decisions)
    act(rig)
    assert rig.jm.state is state, states(rig)
    if action is not None:
        assert rig.last.action == action and len(rig.decisions) > count
    if action == "stop":  # as hard as the vehicle may: a pursuit at attack speed planned to brake so
        assert rig.last.profile == "attack"  # (at the sweeping profile a lost chase ended in a tree)


def test_going_around_stops_before_checking():
    rig = Rig().airborne()
    rig.tick(1.1)
    assert rig.last.action == "scan" and rig.last.area and rig.last.spacing == 20.0
    rig.tick(1.2, detections=[BALLOON], velocity=[5.0, 0, 0])  # seen while sweeping at 5 m/s
    assert rig.jm.state is State.GOING_AROUND and rig.last.action == "stop" and rig.last.profile == "attack"
    rig.tick(1.3, detections=[BALLOON], velocity=[2.0, 0, 0])
    assert rig.jm.state is State.GOING_AROUND
    rig.tick(1.4, detections=[BALLOON], velocity=[0.2, 0, 0])
    assert rig.jm.state is State.CHECKING_TARGET


def test_false_alarm_while_sweeping_resumes_the_scan():
    rig = Rig().airborne()
    rig.tick(1.1)
    rig.tick(1.2, detections=[BALLOON], velocity=[5.0, 0, 0])
    assert rig.last.action == "stop"
    rig.run(1.3, 4.1, velocity=[1.0, 0, 0])  # never stops below stop_speed, target gone
    assert rig.jm.state is State.GOING_AROUND
    rig.tick(4.3)
    assert rig.last.action == "scan"


def test_going_around_climbs_to_search_height_first():
    rig = Rig().airborne()
    rig.tick(1.1, position=HOME - [0, 0, 2.0])
    assert rig.jm.state is State.GOING_AROUND and rig.last.action == "takeoff"
    rig.tick(1.2, position=HOME)
    assert rig.last.action == "scan"


def test_attack_only_after_target_confirmed_for_t_m_then_flown_through():
    rig = Rig().destroying()  # locked at t = 1.2, seen since 1.1
    assert rig.last.action == "approach" and rig.last.profile == "sweeping"
    rig.run(1.4, 4.0, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
    assert rig.last.action == "approach", "attacked before the target was confirmed for t_m"
    rig.tick(4.2, detections=[BALLOON])  # seen without a gap for 3.1 s, since t = 1.1
    attack = rig.last
    assert attack.action == "attack" and attack.profile == "attack"
    np.testing.assert_allclose(attack.target, BALLOON, atol=0.05)
    rig.tick(5.0, position=BALLOON + [-3.0, 0, 0], velocity=[-3.0, 0, 0])  # through it, still fast
    assert rig.jm.state is State.DESTROYING
    rig.tick(5.5, position=BALLOON + [-5.0, 0, 0], velocity=[-0.3, 0, 0])
    assert rig.jm.state is State.IDLE
    assert rig.jm.zones.tries_at(BALLOON) == 1 and not rig.jm.zones.zones


def test_a_gap_in_detections_restarts_the_confirmation():
    rig = Rig().destroying()
    rig.run(1.4, 2.5, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
    rig.run(2.6, 3.8, detections=[], position=BALLOON + [4.0, 0, 0])  # 1.2 s gap > streak_gap
    rig.run(3.9, 6.8, detections=[BALLOON])
    assert rig.last.action == "approach"
    rig.run(6.9, 7.0, detections=[BALLOON])
    assert rig.last.action == "attack"


def test_second_try_at_the_same_place_makes_a_forbidden_zone():
    rig = Rig().destroying()
    for attempt in (1, 2):
        rig.run(rig.t + 0.1, rig.t + 3.2, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
        assert rig.last.action == "attack"
        rig.tick(rig.t + 0.5, detections=[BALLOON], position=BALLOON + [-5.0, 0, 0], velocity=[0, 0, 0])
        assert rig.jm.state is State.IDLE
        if attempt == 1:  # the balloon survived: checked and approached again
            rig.tick(rig.t + 0.1, detections=[BALLOON])
            rig.tick(rig.t + 0.1, detections=[BALLOON])
            rig.tick(rig.t + 0.1, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
            assert rig.jm.state is State.DESTROYING
    assert [z.reason for z in rig.jm.zones.zones] == ["2 tries"]
    rig.tick(rig.t + 0.1, detections=[BALLOON])
    assert rig.jm.state is State.GOING_AROUND  # the balloon is filtered out now


# --------------------------------------------- state timers and forbidden zones (§3.5.1-2)
TIMERS = [
    ("T_c", dict(checking_timeout=2.0, stop_speed=0.1), "CHECKING_TARGET", 2.0),
    ("T_g", dict(going_timeout=5.0), "GOING_TO_TARGET", 5.0),
    ("T_d", dict(destroying_timeout=4.0, target_time=10.0), "DESTROYING", 4.0),
]


@pytest.mark.parametrize("timer,params,state,limit", TIMERS, ids=[t[0] for t in TIMERS])
def test_state_timer_forbids_the_target_and_returns_to_idle(timer, params, state, limit):
    rig = Rig(**params).airborne()
    rig.tick(1.1, detections=[BALLOON], velocity=[0.5, 0, 0])  # CHECKING, not yet at rest
    if state != "CHECKING_TARGET":
        rig.tick(1.2, detections=[BALLOON], velocity=[0, 0, 0])
    if state == "DESTROYING":
        rig.tick(1.3, detections=[BALLOON], position=BALLOON + [4.0, 0, 0])
    assert rig.jm.state.value == state
    entered = rig.jm.transitions[-1].stamp / NS
    near = BALLOON + [4.0, 0, 0] if state == "DESTROYING" else HOME
    rig.run(rig.t + 0.1, entered + limit - 0.05, detections=[BALLOON], position=near)
    assert rig.jm.state.value == state and not rig.jm.zones.zones
    rig.run(rig.t + 0.1, entered + limit + 0.1, detections=[BALLOON], position=near)
    rig.tick(rig.t + 0.1, detections=[BALLOON], position=near)
    assert f"state timer {limit:g} s" in [t.reason for t in rig.jm.transitions]
    (zone,) = rig.jm.zones.zones
    assert np.linalg.norm(np.array(zone.center) - BALLOON) < 0.3 and zone.reason.startswith(state)
    assert rig.jm.state is State.GOING_AROUND  # the forbidden balloon is not in view any more


def test_a_balloon_every_approach_to_which_stays_blocked_becomes_a_forbidden_zone():
    """The planner reports each plan (PlanReport); an approach it finds blocked by obstacles for
    blocked_time makes the balloon a forbidden zone, and a clear plan in between starts that over."""
    rig = Rig(blocked_time=2.0).engaged()
    rig.jm.plan_report(s(1.3), "approach", "blocked", "every approach to (30.0, 30.0, 4.0) is blocked")
    rig.run(1.3, 2.5, detections=[BALLOON])
    rig.jm.plan_report(s(2.5), "approach", "detour", "")  # a better estimate, a way found
    rig.run(2.6, 4.0, detections=[BALLOON])
    assert rig.jm.state is State.GOING_TO_TARGET and not rig.jm.zones.zones
    rig.jm.plan_report(s(4.0), "approach", "blocked", "every approach to (30.0, 30.0, 4.0) is blocked")
    rig.run(4.1, 5.9, detections=[BALLOON])
    assert rig.jm.state is State.GOING_TO_TARGET
    rig.run(6.0, 6.2, detections=[BALLOON])
    (zone,) = rig.jm.zones.zones
    assert zone.reason == "every approach blocked by obstacles"
    assert np.linalg.norm(np.array(zone.center) - BALLOON) < 0.3
    assert "every approach to the target blocked for 2 s" in [t.reason for t in rig.jm.transitions]
    assert rig.jm.state is State.GOING_AROUND  # the forbidden balloon is no target any more


def test_a_blocked_interception_forbids_nothing():
    """A zone cannot hold a mover; a blocked intercept report (the pursuit clipped to a stop) is no
    reason to forbid the static target the UAV is engaged with either."""
    rig = Rig(blocked_time=2.0).engaged()
    rig.jm.plan_report(s(1.3), "intercept", "blocked", "")
    rig.run(1.3, 4.0, detections=[BALLOON])
    assert rig.jm.state is State.GOING_TO_TARGET and not rig.jm.zones.zones


def test_an_attack_starts_only_once_the_vehicle_is_level():
    """Still sinking onto the hit height, the vehicle would pass under its run-in's reference."""
    rig = Rig(target_time=0.5).destroying()
    rig.run(1.4, 2.5, detections=[BALLOON], velocity=[0.0, 0.0, -0.8])
    assert not rig.jm.engagement.attacking
    rig.tick(2.6, detections=[BALLOON], velocity=[0.0, 0.0, -0.2])
    assert rig.jm.engagement.attacking and rig.last.action == "attack"


def test_forbidden_zone_expires_after_t_f():
    rig = Rig(going_timeout=2.0).engaged()
    rig.run(1.3, 3.3, detections=[BALLOON])
    (zone,) = rig.jm.zones.zones
    created = zone.created / NS
    rig.run(rig.t + 0.1, created + 14.9, detections=[BALLOON])
    assert rig.jm.state is State.GOING_AROUND and rig.jm.zones.zones
    rig.tick(created + 15.0, detections=[BALLOON])
    assert not rig.jm.zones.zones and any("expired" in n for n in rig.jm.notes)
    assert rig.jm.state is State.CHECKING_TARGET  # the balloon counts again


def test_detections_outside_the_working_area_or_on_the_ground_are_ignored():
    rig = Rig().airborne()
    rig.tick(1.1, detections=[[80.0, 30.0, 4.0], [25.0, 25.0, 0.3]])  # uav2's half; a drone on the ground
    assert rig.jm.state is State.GOING_AROUND


# --------------------------------------------------------------- abort system (§3.5.3)
@pytest.mark.parametrize("silent", ["scan", "odometry"])
def test_silent_sensor_for_more_than_1_s_is_an_emergency_landing(silent):
    rig = Rig().airborne()
    rig.run(1.1, 5.0)
    quiet = {silent: False}
    rig.run(5.1, 6.0, **quiet)
    assert rig.jm.state is State.GOING_AROUND
    decision = rig.tick(6.1, **quiet)
    assert rig.jm.state is State.EMERGENCY_LANDING and decision.action == "emergency_land"
    assert ("LiDAR silent" if silent == "scan" else "odometry silent") in rig.jm.transitions[-1].reason
    rig.tick(9.0, position=HOME - [0, 0, 5], **quiet)
    assert rig.jm.state is State.LANDED


def test_no_take_off_before_the_lidar_is_heard():
    """Every service alive is not enough: the UAV waits on the ground for its first fresh scan
    (a stale one does not count), so slow perception at start never becomes an abort in the air."""
    rig = Rig()
    for t in (0.0, 0.5, 3.0):
        rig.tick(t, position=HOME - [0, 0, 5], scan=False)
        assert rig.jm.state is State.PREFLIGHT
    assert all(decision.action != "takeoff" for decision in rig.decisions)
    rig.jm.observe_detections(s(1.0), np.zeros((0, 3)))  # heard, but 2 s ago by 3.0
    rig.tick(3.0, position=HOME - [0, 0, 5], scan=False)
    assert rig.jm.state is State.PREFLIGHT
    decision = rig.tick(3.1, position=HOME - [0, 0, 5])
    assert rig.jm.state is State.TAKING_OFF and decision.action == "takeoff"


def test_lidar_that_stops_at_take_off_aborts_one_second_later():
    rig = Rig()
    rig.tick(0.0, position=HOME - [0, 0, 5])
    assert rig.jm.state is State.TAKING_OFF
    rig.tick(0.9, position=HOME - [0, 0, 4], scan=False)
    assert rig.jm.state is State.TAKING_OFF
    rig.tick(1.1, position=HOME - [0, 0, 3], scan=False)
    assert rig.jm.state is State.EMERGENCY_LANDING


# ----------------------------------------------------------------- moving targets
def test_moving_target_is_intercepted_static_preferred():
    rig = Rig().airborne()
    drone = np.array([25.0, 25.0, 6.0])
    rig.jm.observe_tracks(s(1.1), np.array([7]), drone[None], np.array([[4.0, 0.0, 0.0]]))
    rig.tick(1.1, detections=[drone, BALLOON])
    rig.tick(1.2, detections=[drone, BALLOON])
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "approach"  # the static one first
    rig2 = Rig().airborne()
    rig2.jm.observe_tracks(s(1.1), np.array([7]), drone[None], np.array([[4.0, 0.0, 0.0]]))
    rig2.tick(1.1, detections=[drone])
    rig2.jm.observe_tracks(s(1.2), np.array([7]), (drone + [0.4, 0, 0])[None], np.array([[4.0, 0.0, 0.0]]))
    rig2.tick(1.2, detections=[drone + [0.4, 0, 0]])
    assert rig2.jm.state is State.GOING_TO_TARGET
    assert rig2.last.action == "intercept" and rig2.last.profile == "attack"
    assert rig2.last.target_velocity == (4.0, 0.0, 0.0)


def test_a_mover_is_intercepted_along_its_tracks_predicted_path_by_the_tracks_identity():
    """The intercept command carries the tracker's prediction (curved here), re-based to the
    command's time; a new identity for the same target is followed; a prediction that still holds
    sends nothing new."""
    def turning(t: float) -> np.ndarray:  # a 4 m/s turn of radius 8 m around (25, 33)
        angle = -np.pi / 2 + 0.5 * t
        return np.array([25.0 + 8.0 * np.cos(angle), 33.0 + 8.0 * np.sin(angle), 6.0])

    def tracks(rig, t: float, track_id: int) -> None:
        path = [turning(t + 0.25 * (i + 1)) for i in range(8)]
        velocity = (turning(t + 0.01) - turning(t)) / 0.01
        rig.jm.observe_tracks(s(t), np.array([track_id]), turning(t)[None], velocity[None], [np.array(path)], 0.25)

    rig = Rig().airborne()
    tracks(rig, 1.1, 7)
    rig.tick(1.1, detections=[turning(1.1)])
    tracks(rig, 1.2, 7)
    decision = rig.tick(1.2, detections=[turning(1.2)])
    assert rig.jm.state is State.GOING_TO_TARGET and decision.action == "intercept"
    assert rig.jm.engagement.track_id == 7
    assert np.allclose(decision.target, turning(1.2)) and decision.target_path_dt == 0.25
    assert np.allclose(decision.target_path, [turning(1.2 + 0.25 * (i + 1)) for i in range(8)], atol=0.05)
    tracks(rig, 1.3, 7)
    assert rig.tick(1.3, detections=[turning(1.3)]) is None  # the sent prediction still holds: nothing new
    tracks(rig, 1.4, 12)  # the tracker lost 7 and started 12 on the same drone
    assert rig.tick(1.4, detections=[turning(1.4)]) is None and rig.jm.engagement.track_id == 12
    straight = Rig().airborne()  # the same drone, but its tracks predict a straight line: re-planned on the turn
    for t in (1.1, 1.2, 1.3, 1.4, 1.5, 1.6):
        velocity = (turning(t + 0.01) - turning(t)) / 0.01
        straight.jm.observe_tracks(s(t), np.array([7]), turning(t)[None], velocity[None])
        straight.tick(t, detections=[turning(t)])
    assert sum(d.action == "intercept" for d in straight.decisions) > 1


def test_a_drone_in_our_area_that_only_a_partner_sees_is_engaged_from_the_fleet_picture():
    """uav2 sees nothing itself; its tracker's fleet picture holds uav1's confirmed track of a drone
    in uav2's half. uav2 locks it and intercepts along it; the same track marked as uav2's own
    (not the fleet's) is not a detection, so without the fleet picture nothing happens."""
    def drone(t: float) -> np.ndarray:
        return np.array([80.0 + 3.0 * t, 40.0, 6.0])

    def run(fleet: bool):
        rig = Rig(uav="uav2")
        rig.tick(0.0, position=[70.0, 20.0, 0.0])
        rig.tick(1.0, position=[70.0, 20.0, 5.0])
        assert rig.jm.state is State.IDLE
        for t in (1.1, 1.2, 1.3):
            rig.jm.observe_tracks(s(t), np.array([2_000_005]), drone(t)[None], np.array([[3.0, 0.0, 0.0]]),
                                  fleet=np.array([fleet]), covariances=np.eye(3)[None] * 0.04)
            rig.tick(t)  # its own scans are empty
        return rig

    rig = run(fleet=True)
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "intercept"
    assert rig.jm.engagement.track_id == 2_000_005
    assert np.allclose(rig.last.target, drone(1.2), atol=0.01)  # sent at the lock; the prediction still holds
    assert run(fleet=False).jm.state is State.GOING_AROUND  # sweeping its area, nothing seen


def test_a_mover_the_detector_loses_stays_in_sight_while_its_track_takes_scan_updates():
    """Beside a tree the classifier calls the drone background; the tracker still corrects its
    track from the scans. Fresh corrections of the followed track keep the target seen; a track
    that only coasts does not, and the target is unseen after t_m."""
    def drone(t: float) -> np.ndarray:
        return np.array([25.0 + 3.0 * t, 25.0, 6.0])

    def run(corrected_by_scans: bool):
        rig = Rig().airborne()
        for t in np.arange(1.1, 6.05, 0.1):
            t = round(float(t), 2)
            seen = [drone(t)] if t <= 1.3 else []  # the detector loses it at 1.4 s
            correction = s(t) if corrected_by_scans or t <= 1.3 else s(1.3)
            rig.jm.observe_tracks(s(t), np.array([7]), drone(t)[None], np.array([[3.0, 0.0, 0.0]]),
                                  covariances=np.eye(3)[None] * 0.04, corrected=np.array([correction]))
            rig.tick(t, detections=seen)
        return rig.jm.state

    assert run(corrected_by_scans=True) is State.GOING_TO_TARGET
    assert run(corrected_by_scans=False) is State.CHECKING_TARGET  # unseen for 3 s: checked again


def test_a_mover_that_turns_out_of_sight_is_followed_on_its_track_when_seen_again():
    """The detector loses the drone at 1.4 s and the tracker's scans at 1.6 s; out of sight it turns
    north. When the tracker's scans find it again (2.6 s), the line the target filter fitted has run
    on east and the track's fresh positions fall outside its gate. They are scans of the same
    drone, so the filter starts again from them and the target stays in sight; the same track
    coasting on without scans still ends the engagement."""
    def drone(t: float) -> np.ndarray:
        return np.array([25.0 + 3.0 * t, 25.0, 6.0]) if t <= 1.6 else np.array([29.8, 25.0 + 3.0 * (t - 1.6), 6.0])

    def run(scanned_again: bool):
        rig = Rig().airborne()
        for t in np.arange(1.1, 6.05, 0.1):
            t = round(float(t), 2)
            velocity = np.array([[3.0, 0.0, 0.0] if t <= 1.6 else [0.0, 3.0, 0.0]])
            seen = [drone(t)] if t <= 1.3 else []
            scanned = t <= 1.5 or (scanned_again and t >= 2.6)
            rig.jm.observe_tracks(s(t), np.array([7]), drone(t)[None], velocity, covariances=np.eye(3)[None] * 0.04,
                                  corrected=np.array([s(t) if scanned else s(min(t, 1.5))]))
            rig.tick(t, detections=seen)
        return rig

    followed = run(scanned_again=True)
    assert followed.jm.state is State.GOING_TO_TARGET
    assert np.linalg.norm(followed.jm.engagement.position(s(6.0)) - drone(6.0)) < 0.5
    assert run(scanned_again=False).jm.state is State.CHECKING_TARGET


def test_a_far_target_is_not_lost_while_out_of_reliable_range():
    rig = Rig().engaged()  # locked at 1.2 from HOME, 14 m away
    far = BALLOON + [25.0, 0.0, 1.0]
    rig.run(1.3, 8.0, position=far)  # 25 m away: unseen does not count
    assert rig.jm.state is State.GOING_TO_TARGET
    rig.run(8.1, 11.0, position=BALLOON + [8.0, 0, 0])
    assert rig.jm.state is State.GOING_TO_TARGET
    rig.run(11.1, 11.3, position=BALLOON + [8.0, 0, 0])
    assert rig.jm.state is State.CHECKING_TARGET  # 3 s within range without a detection


def drone_at(t: float, start=(25.0, 25.0, 6.0), velocity=(3.0, 0.0, 0.0)) -> np.ndarray:
    return np.asarray(start) + np.asarray(velocity) * t


def test_target_filter_measures_velocity_and_follows_a_mover():
    from services.job_manager.targets import TargetFilter
    rng = np.random.default_rng(1)
    mover = TargetFilter(drone_at(0.0), 0, gate=3.0, measurement_sigma=0.15, process_sigma=0.05, max_gap_ns=s(1.0))
    still = TargetFilter(BALLOON, 0, gate=3.0, measurement_sigma=0.15, process_sigma=0.05, max_gap_ns=s(1.0))
    for k in range(1, 21):
        t = 0.1 * k
        assert mover.update((drone_at(t) + rng.normal(0, 0.1, 3))[None], s(t))
        assert still.update((BALLOON + rng.normal(0, 0.1, 3))[None], s(t))
    np.testing.assert_allclose(mover.velocity, [3.0, 0.0, 0.0], atol=0.3)
    np.testing.assert_allclose(mover.predict(s(2.5)), drone_at(2.5), atol=0.3)
    assert still.speed() < 0.3
    np.testing.assert_allclose(still.estimate, BALLOON, atol=0.1)


def along_ray_covariance(observer: np.ndarray, target: np.ndarray, along: float, across: float) -> np.ndarray:
    """A camera detection's covariance: `along` m σ on the line of sight, `across` m σ across it."""
    ray = (target - observer) / np.linalg.norm(target - observer)
    return across**2 * np.eye(3) + (along**2 - across**2) * np.outer(ray, ray)


def camera_sightings(observer, target, along, across, rng, count):
    """`count` detections of a still target, scattered as their covariance says."""
    cov = along_ray_covariance(observer, target, along, across)
    return rng.multivariate_normal(target, cov, size=count), cov


def test_a_far_balloon_seen_by_the_camera_does_not_move_though_its_unweighted_fit_says_so():
    """30 m away a camera's range from the balloon's size is ~3 m off along the ray: ten frames
    of it fit "speeds" of metres per second. Weighed by their covariances they are noise."""
    from services.job_manager.targets import TargetFilter
    rng = np.random.default_rng(4)
    observer = BALLOON + [-30.0, 0.0, 1.0]
    noisy_speeds, moved = [], []
    for trial in range(20):
        seen, cov = camera_sightings(observer, BALLOON, 3.0, 0.05, rng, 11)
        weighed = TargetFilter(seen[0], 0, gate=3.0, measurement_sigma=0.15, process_sigma=0.05,
                               max_gap_ns=s(1.0), history_ns=s(1.0), covariance=cov)
        blind = TargetFilter(seen[0], 0, gate=50.0, measurement_sigma=0.15, process_sigma=0.05,
                             max_gap_ns=s(1.0), history_ns=s(1.0))
        for k in range(1, 11):
            assert weighed.update(seen[k][None], s(0.1 * k), cov[None])
            blind.update(seen[k][None], s(0.1 * k))
        noisy_speeds.append(blind.speed())
        moved.append(weighed.moves(1.0, 3.0))
    assert np.median(noisy_speeds) > 2.0  # what the fixed-noise fit believed
    assert not any(moved)


def test_covariances_weigh_the_balloon_estimate_and_shape_the_gate():
    from services.job_manager.targets import TargetFilter
    rng = np.random.default_rng(5)
    observer = BALLOON + [-30.0, 0.0, 1.0]
    seen, cov = camera_sightings(observer, BALLOON, 3.0, 0.05, rng, 30)
    target = TargetFilter(seen[0], 0, gate=3.0, measurement_sigma=0.15, process_sigma=0.05,
                          max_gap_ns=s(1.0), covariance=cov)
    for k in range(1, 30):
        assert target.update(seen[k][None], s(0.1 * k), cov[None])
    assert np.linalg.norm(target.estimate - BALLOON) < 1.5  # 3 m per frame along the ray, averaged
    assert abs(target.estimate[1] - BALLOON[1]) < 0.1  # across the ray it was precise all along
    # a detection 8 m along the ray fits the camera's ellipsoid; one 4 m across it does not
    assert target.update((target.estimate + [-8.0, 0.0, 0.0])[None], s(3.0), cov[None])
    assert not target.update((target.estimate + [0.0, 4.0, 0.0])[None], s(3.1), cov[None])
    # a near, precise detection outweighs the far ones
    close = np.eye(3) * 0.02**2
    target.update(BALLOON[None], s(3.2), close[None])
    assert np.linalg.norm(target.estimate - BALLOON) < 0.2


def test_a_drone_seen_by_the_lidar_still_moves_and_bad_covariances_fall_back_to_the_default():
    from services.job_manager.targets import TargetFilter
    rng = np.random.default_rng(6)
    lidar = np.eye(3) * 0.2**2
    mover = TargetFilter(drone_at(0.0), 0, gate=3.0, measurement_sigma=0.15, process_sigma=0.05,
                         max_gap_ns=s(1.0), history_ns=s(1.0), covariance=lidar)
    broken = np.full((3, 3), np.nan)
    for k in range(1, 11):
        t = 0.1 * k
        cov = broken if k % 3 == 0 else lidar  # every third one unusable: weighed by the default
        assert mover.update((drone_at(t) + rng.normal(0, 0.2, 3))[None], s(t), cov[None])
    assert mover.moves(1.0, 3.0)
    np.testing.assert_allclose(mover.velocity, [3.0, 0.0, 0.0], atol=0.6)
    assert np.isfinite(mover.estimate).all()


def test_a_balloon_the_camera_sees_is_attacked_though_its_range_jumps_when_depth_takes_over():
    """The camera's range from a balloon's size is biased (here 3 m long, a tight colour pick)
    until the depth image reaches it, then it jumps to the truth: a velocity fit reads 5 m/s.
    A target the balloon detector saw is tethered: approached and attacked, never intercepted."""
    rig = Rig().airborne()
    observer = HOME.copy()
    biased = BALLOON + 3.0 * (BALLOON - observer) / np.linalg.norm(BALLOON - observer)
    far = along_ray_covariance(observer, BALLOON, 1.5, 0.05)
    near = np.eye(3) * 0.05**2
    for k in range(40):
        t = round(1.1 + 0.05 * k, 3)
        seen, cov = (biased, far) if k < 20 else (BALLOON, near)
        if k % 2:  # frames between the scans; the LiDAR sees nothing of a balloon on its pole
            rig.jm.observe_camera(s(t), seen[None], cov[None])
        rig.tick(t)
    assert rig.jm.engagement is not None and rig.jm.engagement.filter.tethered
    assert all(d.action != "intercept" for d in rig.decisions), [d.action for d in rig.decisions]
    assert not any("intercepting" in n for n in rig.jm.notes)
    np.testing.assert_allclose(rig.jm.engagement.position(s(3.1)), BALLOON, atol=0.3)


def test_a_target_that_turns_out_to_move_is_intercepted():
    rig = Rig().airborne()
    rig.tick(1.1, detections=[drone_at(0.0)])
    rig.tick(1.2, detections=[drone_at(0.1)])
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "approach"
    for k in range(2, 12):
        rig.tick(round(1.1 + 0.1 * k, 3), detections=[drone_at(0.1 * k)])
    assert rig.last.action == "intercept" and rig.last.profile == "attack"
    np.testing.assert_allclose(rig.last.target_velocity, [3.0, 0.0, 0.0], atol=0.2)
    assert any("intercepting" in n for n in rig.jm.notes)


def test_a_target_locked_as_static_moves_when_a_fast_track_went_through_its_sighting():
    """Locked on one far sighting, a drone seen now and then leaves the filter's gate between
    sightings and its fit never learns that it moves; the tracker's confirmed track through the
    sighting tells, and the UAV intercepts along it."""
    rig = Rig().airborne()
    rig.tick(1.1, detections=[drone_at(0.0)])
    rig.tick(1.2, detections=[drone_at(0.0)])  # the same place twice: static to the filter
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "approach"
    rig.tick(1.3)
    assert rig.last.action == "approach"  # no track yet: still the place it was seen at
    rig.jm.observe_tracks(s(1.4), np.array([5]), drone_at(0.2)[None], np.array([[3.0, 0.0, 0.0]]),
                          [np.array([drone_at(0.2 + 0.25 * (i + 1)) for i in range(8)])], 0.25)
    rig.tick(1.4)
    assert rig.last.action == "intercept" and rig.jm.engagement.track_id == 5
    assert any("(track 5): intercepting" in n for n in rig.jm.notes)


def test_static_targets_come_first_even_while_intercepting():
    rig = Rig().airborne()
    far_balloon = np.array([40.0, 40.0, 4.0])  # not in view until t = 2.0
    for k in range(0, 9):
        rig.tick(round(1.1 + 0.1 * k, 3), detections=[drone_at(0.1 * k)])
    assert rig.last.action == "intercept"
    t = 2.0
    while rig.jm.state is not State.IDLE:  # the balloon in view: only once it has held still for 1 s
        rig.tick(round(t, 3), detections=[drone_at(t - 1.1), far_balloon])
        t += 0.1
        assert t < 3.2
    assert t > 2.95 and "static targets first" in rig.jm.transitions[-1].reason
    for _ in range(2):
        rig.tick(round(t, 3), detections=[drone_at(t - 1.1), far_balloon])
        t += 0.1
    assert rig.jm.state is State.GOING_TO_TARGET and rig.last.action == "approach"  # the drone was closer
    np.testing.assert_allclose(rig.last.target, far_balloon, atol=0.2)


def test_a_mover_that_runs_out_a_timer_is_skipped_for_t_f():
    rig = Rig(going_timeout=3.0).airborne()
    mover = lambda t: drone_at(t - 1.1, velocity=(1.5, 0, 0))  # noqa: E731
    t = 1.1
    while rig.jm.state is not State.IDLE or t < 2.0:
        rig.tick(round(t, 3), detections=[mover(t)], position=mover(t) + [0, 12.0, 0])  # never gets close
        t += 0.1
        assert t < 10
    timer = t - 0.1
    assert "state timer 3 s" in rig.jm.transitions[-1].reason and not rig.jm.zones.zones
    count = len(rig.jm.transitions)
    while t < timer + 14.9:  # the mover stays in view, but it is not chased: the sweep goes on
        rig.tick(round(t, 3), detections=[mover(t)])
        t += 0.1
    engaged = [x for x in rig.jm.transitions[count:] if x.target is State.GOING_TO_TARGET]
    assert not engaged, engaged
    assert rig.jm.state is State.GOING_AROUND and rig.last.action == "scan"
    while t < timer + 16.5:  # t_f later, movers count again
        rig.tick(round(t, 3), detections=[mover(t)])
        t += 0.1
    assert rig.last.action in ("stop", "intercept") and rig.jm.state is not State.GOING_AROUND


def test_a_partners_track_coasting_unseen_is_no_sighting():
    """Agile seed 4: a partner's track of a drone that had braked out of sight behind a tree coasted
    on, and counted as a sighting it kept the UAV chasing the empty prediction. A partner's track
    counts while its partner corrected it within FLEET_SEEN_WITHIN (last_correction 0: not said, counts)."""
    def drone(t: float) -> np.ndarray:
        return np.array([80.0 + 3.0 * t, 40.0, 6.0])

    def run(corrected_at):
        rig = Rig(uav="uav2")
        rig.tick(0.0, position=[70.0, 20.0, 0.0])
        rig.tick(1.0, position=[70.0, 20.0, 5.0])
        for t in (1.1, 1.2, 1.3):
            rig.jm.observe_tracks(s(t), np.array([2_000_005]), drone(t)[None], np.array([[3.0, 0.0, 0.0]]),
                                  fleet=np.array([True]), covariances=np.eye(3)[None] * 0.04,
                                  corrected=np.array([corrected_at(t)], dtype=np.int64))
            rig.tick(t)
        return rig.jm.state

    assert run(lambda t: s(t - 0.1)) is State.GOING_TO_TARGET  # corrected 0.1 s before: seen
    assert run(lambda t: 0) is State.GOING_TO_TARGET  # not said (an older partner): as before
    assert run(lambda t: s(0.5)) is State.GOING_AROUND  # coasting since 0.5 s: nothing seen


def test_a_lock_on_a_partners_track_counts_its_age_from_the_partners_last_scan_of_it():
    """agile, 2 UAVs, seed 1852 (campaign run 27): uav2, braking to a stop, locked the dodger on a
    partner's track 0.5 s past its last correction, and took the interception up 0.65 s later: the
    sighting was 1.15 s old, its prediction 2.9 m from the drone. A partner's track counts as seen
    when its partner last scanned it, so the UAV holds and looks instead."""
    def drone(t: float) -> np.ndarray:
        return np.array([80.0 + 1.0 * t, 40.0, 6.0])

    def run(corrected_at):
        rig, rig.said = Rig(uav="uav2"), []
        rig.tick(0.0, position=[70.0, 30.0, 0.0])
        rig.tick(1.0, position=[70.0, 30.0, 5.0])
        t = 1.1
        while t < 2.25:
            rig.jm.observe_tracks(s(t), np.array([2_000_005]), drone(t)[None], np.array([[1.0, 0.0, 0.0]]),
                                  fleet=np.array([True]), covariances=np.eye(3)[None] * 0.04,
                                  corrected=np.array([corrected_at(t)], dtype=np.int64))
            rig.jm.partner_status("uav1", s(t), flying_normally=True, position=(20.0, 20.0, 5.0))  # far off
            rig.tick(t, velocity=[3.0, 0.0, 0.0] if t < 2.15 else [0.0, 0.0, 0.0])  # braking until 2.15
            rig.said += rig.jm.notes
            t = round(t + 0.05, 2)
        return rig

    stale = run(lambda t: s(min(t, 1.05)))  # the partner lost it at 1.05 s: sightings until 1.55 s
    assert stale.jm.state is State.GOING_TO_TARGET and stale.last.action == "stop"
    assert "target last seen 1.1 s ago: holding until it is seen again" in " ".join(stale.said)
    fresh = run(lambda t: s(t - 0.05))  # still scanned by the partner
    assert fresh.jm.state is State.GOING_TO_TARGET and fresh.last.action == "intercept"
    assert fresh.last.target_seen == s(2.1)  # the partner's scan the lock was made on


def test_an_intercept_is_renewed_at_least_every_intercept_refresh_and_says_when_its_target_was_seen():
    """The planner follows a prediction pursuit_trust s past the sighting only; a mover that keeps
    to its prediction would otherwise get no new command, and the UAV would stop following it."""
    def drone(t: float) -> np.ndarray:
        return np.array([30.0 + 3.0 * t, 40.0, 6.0])

    rig = Rig().airborne()
    t = 1.1
    while t < 4.0:
        rig.jm.observe_tracks(s(t), np.array([7]), drone(t)[None], np.array([[3.0, 0.0, 0.0]]))
        rig.tick(t, detections=[drone(t)])
        t = round(t + 0.1, 2)
    sent = [d for d in rig.decisions if d.action == "intercept"]
    assert len(sent) >= 3  # the prediction never moved: renewed by time
    assert all(0 < d.target_seen for d in sent)
    assert sent[-1].target_seen >= s(3.0)


def test_a_mover_passed_close_keeps_its_pursuit_past_t_d_and_one_never_reached_does_not():
    """T_d counts for a mover from its latest close pass (a just-seen sighting within
    close_pass_distance): agile's dodger brakes harder than the UAV and took several passes, and a
    pursuit given up at 20 s left every mover skipped for t_f while the UAV swept an empty area."""
    def run(offset: float):
        rig = Rig(destroying_timeout=3.0, filter_switch_distance=20.0).airborne()
        mover = lambda t: drone_at(t - 1.1, velocity=(1.5, 0, 0))  # noqa: E731
        t = 1.1
        while t < 12.0:
            rig.tick(round(t, 3), detections=[mover(t)], position=mover(t) + [0, offset, 0])
            t += 0.1
        return [x.reason for x in rig.jm.transitions if x.source is State.DESTROYING]

    assert run(offset=1.5) == []  # alongside it the whole time: still DESTROYING after 9 s
    assert any("state timer 3 s" in reason for reason in run(offset=12.0))  # never close: given up


def test_a_descending_mover_lost_for_a_moment_is_not_down_but_one_seen_low_is():
    """"Moving target down" (a captured drone drops) needs the last sighting near the lowest
    target height, not only the prediction below it: a drone last seen descending at 1 m/s at
    2.5 m and then unseen for 2 s is predicted in the ground, yet it is still chased; one last
    seen at 1.5 m is down."""
    def run(last_seen_height: float):
        rig = Rig(filter_switch_distance=20.0).airborne()
        mover = lambda t: drone_at(t - 1.1, start=(25.0, 25.0, last_seen_height + 1.0),  # noqa: E731
                                   velocity=(1.5, 0.0, -1.0))
        t = 1.1
        while t < 2.15:  # seen for 1 s, down to last_seen_height
            rig.tick(round(t, 3), detections=[mover(t)], position=mover(t) + [3.0, 0, 0])
            t += 0.1
        assert rig.jm.state is State.DESTROYING and rig.jm.engagement.moving
        while t < 4.15:  # unseen for 2 s (t_m is 3 s)
            rig.tick(round(t, 3), position=mover(t) + [3.0, 0, 0])
            t += 0.1
        return rig

    chased = run(last_seen_height=2.5)
    assert chased.jm.engagement.position(s(chased.t))[2] < 1.0  # the prediction is in the ground
    assert chased.jm.state is State.DESTROYING and chased.last.action == "intercept"
    dropped = run(last_seen_height=1.5)
    assert ("DESTROYING", "IDLE") in states(dropped)
    assert any(x.reason == "moving target down" for x in dropped.jm.transitions)


# ------------------------------------------------------------------ flying without GNSS
def localized_rig() -> Rig:
    rig = Rig()
    rig.jm.positioning_by_localizer = True
    return rig


def test_without_gnss_pre_flight_waits_for_the_localizer_to_track():
    rig = localized_rig()
    rig.tick(0.0, position=HOME - [0, 0, 5], positioning="")
    rig.tick(0.1, position=HOME - [0, 0, 5], positioning="degraded")
    assert rig.jm.state is State.PREFLIGHT
    rig.tick(0.2, position=HOME - [0, 0, 5], positioning="tracking")
    assert rig.jm.state is State.TAKING_OFF


def test_with_gnss_the_odometry_health_is_not_asked():
    rig = Rig()
    rig.tick(0.0, position=HOME - [0, 0, 5], positioning="lost")
    assert rig.jm.state is State.TAKING_OFF
    rig.tick(1.0, position=HOME, positioning="lost")
    assert rig.jm.state is State.IDLE and rig.last.action != "stop"


def test_degraded_positioning_flies_every_command_but_a_stop_slower_and_tracking_again_restores_it():
    rig = localized_rig()
    rig.tick(0.0, position=HOME - [0, 0, 5], positioning="tracking")
    rig.tick(1.0, position=HOME, positioning="tracking")
    rig.tick(1.1, positioning="tracking")
    assert rig.last.action == "scan" and rig.last.profile == "sweeping"
    rig.tick(1.2, positioning="degraded")
    assert rig.last.action == "scan" and rig.last.profile == "degraded"
    assert any("positioning degraded" in note for note in rig.jm.notes)
    rig.tick(1.3, positioning="tracking")
    assert rig.last.action == "scan" and rig.last.profile == "sweeping"
    rig.tick(1.4, detections=[BALLOON], velocity=[5.0, 0, 0], positioning="degraded")
    assert rig.last.action == "stop" and rig.last.profile == "attack"  # braking never speeds up


def test_lost_positioning_holds_then_lands_as_a_silent_lidar_does():
    rig = localized_rig()
    rig.tick(0.0, position=HOME - [0, 0, 5], positioning="tracking")
    rig.tick(1.0, position=HOME, positioning="tracking")
    rig.tick(1.1, positioning="lost")
    assert rig.last.action == "stop" and rig.jm.state in MISSION_STATES  # hold
    rig.run(1.2, 2.0, positioning="lost")  # within sensor_timeout (1 s): still holding
    assert rig.jm.state in MISSION_STATES and rig.last.action == "stop"
    rig.tick(2.2, positioning="lost")
    assert rig.jm.state is State.EMERGENCY_LANDING
    assert rig.jm.transitions[-1].reason.startswith("positioning lost")


def test_positioning_found_again_within_the_timeout_resumes_the_mission():
    rig = localized_rig()
    rig.tick(0.0, position=HOME - [0, 0, 5], positioning="tracking")
    rig.tick(1.0, position=HOME, positioning="tracking")
    rig.run(1.1, 1.8, positioning="lost")
    rig.run(1.9, 3.5, positioning="tracking")
    assert rig.jm.state in MISSION_STATES and rig.last.action == "scan"


def test_the_job_manager_node_takes_a_vanished_localizer_for_lost_positioning():
    """Its liveliness token gone, a localizer sends nothing, and the flight controller carries its last
    estimate on unchecked: the node hands the machine "lost" (hold, then land) whatever the odometry says."""
    from schemas import keys
    from schemas.messages import Header, WorldModel
    from tests.tools.fuzz import UAV, encode, wire

    wired = wire("job_manager")
    world = WorldModel(header=Header(stamp=0), scenario="t", arena=[tuple(p) for p in ARENA], min_height=0.0,
                       max_height=20.0, uavs=[UAV, "uav2"], duration=300.0, positioning={UAV: "lidar"})
    wired.deliver(keys.WORLD, encode(world))
    node = wired.node
    assert node.core.positioning_by_localizer
    node.positioning = "tracking"
    wired.token(keys.alive(UAV, keys.LOCALIZER), True)
    node.core.state = State.IDLE  # in flight
    assert node.positioning_health() == "tracking"
    wired.token(keys.alive(UAV, keys.LOCALIZER), False)
    assert node.positioning_health() == "lost"
    node.core.state = State.PREFLIGHT  # on the ground it only waits
    assert node.positioning_health() == "tracking"


def test_a_single_camera_blob_or_blobs_that_disagree_in_3d_start_no_engagement():
    """lock_sightings: a target is locked only once three scans or frames of the last t_m agree on
    it in 3D (within their covariances); blobs that come and go elsewhere are never locked."""
    rig = Rig().airborne()
    along_x = np.diag([4.0, 0.01, 0.01])  # a camera's range is metres off along its ray (x here)
    rig.jm.observe_camera(s(1.05), BALLOON[None], along_x[None])
    rig.run(1.1, 4.5)  # the blob never comes back
    assert State.GOING_TO_TARGET not in [t.target for t in rig.jm.transitions]
    rig2 = Rig().airborne()
    for k, t in enumerate((1.05, 1.15, 1.25, 1.35)):  # four frames, each blob 2 m across the ray from the last
        rig2.jm.observe_camera(s(t), (BALLOON + [0.0, 2.0 * k, 0.0])[None], along_x[None])
        rig2.tick(t + 0.05)
    assert rig2.jm.state is not State.GOING_TO_TARGET
    rig3 = Rig().airborne()
    for k, t in enumerate((1.05, 1.15, 1.25)):  # three frames, the range 1.5 m apart along the ray: one balloon
        rig3.jm.observe_camera(s(t), (BALLOON + [1.5 * (k - 1), 0.0, 0.0])[None], along_x[None])
        rig3.tick(t + 0.05)
    assert rig3.jm.state is State.GOING_TO_TARGET


def test_the_preflight_check_wants_every_mission_service_and_one_detector():
    jm = Rig().jm
    base = {"sensor_driver", "tracker", "planner"}
    assert not jm.services_ready(base)  # no detector
    assert jm.services_ready(base | {"classifier"}) and jm.services_ready(base | {"oracle"})
    assert not jm.services_ready({"sensor_driver", "planner", "classifier"})  # no tracker
    jm.positioning_by_localizer = True  # without GNSS the localizer is needed too
    assert not jm.services_ready(base | {"classifier"}) and jm.services_ready(base | {"classifier", "localizer"})

