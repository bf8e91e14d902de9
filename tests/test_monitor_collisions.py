"""The run monitor's collisions and clearance, from synthetic world, truth, command and event
messages, and how the summary prints them."""
from __future__ import annotations

import msgspec
import pytest

from schemas import keys
from schemas.messages import (GroundTruth, Header, MissionCommand, Obstacle, SimEvent, TargetTruth, VehicleTruth,
                              WorldModel)
from services.tools.launcher.monitor import RunMonitor
from services.tools.launcher.sim_cmd import WATCHED, clearance_line, collisions_line

S = 1_000_000_000
encode = msgspec.msgpack.encode
TREE = Obstacle(kind="cylinder", center=(10.0, 30.0, 0.0), radius=1.2, height=6.0, name="tree2")
POLE = Obstacle(kind="cylinder", center=(50.0, 30.0, 0.0), radius=0.05, height=4.0, name="balloon2_pole")
OTHER_POLE = Obstacle(kind="cylinder", center=(52.0, 30.0, 0.0), radius=0.05, height=3.0, name="balloon9_pole")
SHED = Obstacle(kind="box", center=(80.0, 0.0, 2.0), size=(4.0, 4.0, 4.0), name="shed")  # unsurveyed


def world(monitor: RunMonitor, radius=None) -> None:
    monitor.handle(keys.WORLD, encode(WorldModel(
        header=Header(), scenario="test", arena=[(0, 0), (100, 0), (0, 60)], min_height=0.0, max_height=20.0,
        uavs=["uav1", "uav2"], uav_radius={"uav1": 0.4, "uav2": 0.5} if radius is None else radius,
        obstacles=[Obstacle(kind="plane", center=(0.0, 0.0, 0.0), name="ground"), TREE, POLE, OTHER_POLE])))


BALLOONS = [TargetTruth(id=name, kind="balloon", position=(x, 30.0, 4.5), velocity=(0, 0, 0), radius=0.3)
            for name, x in (("balloon2", 50.0), ("balloon9", 52.0))]


def truth(monitor: RunMonitor, t: float, uav1, uav2=(0.0, 0.0, 0.0), airborne2=False, alive1=True) -> None:
    monitor.handle(keys.TRUTH, encode(GroundTruth(
        header=Header(stamp=round(t * S)), step=round(t * 20), obstacles=[SHED], targets=BALLOONS,
        uavs=[VehicleTruth(name="uav1", position=uav1, velocity=(0, 0, 0), heading=0, airborne=True, alive=alive1),
              VehicleTruth(name="uav2", position=uav2, velocity=(0, 0, 0), heading=0, airborne=airborne2)])))


def command(monitor: RunMonitor, t: float, action: str, target=None) -> None:
    monitor.handle("falconry/uav1/command", encode(MissionCommand(header=Header(stamp=round(t * S)), command_id=1,
                                                                 action=action, target=target)))


def test_clearance_is_the_bodys_closest_approach_to_any_obstacle_and_an_attacked_pole_counts_apart():
    monitor = RunMonitor()
    world(monitor)

    def closest(uav: str = "uav1") -> tuple:
        c = monitor.summary()["clearance"][uav]
        return (c["m"], c["to"], c["t"]), c["attack_pole"]

    truth(monitor, 1.0, (10.0, 33.0, 3.0))  # 3 m from the tree's axis: 1.8 m from its bark, less the 0.4 m body
    assert closest() == ((1.4, "tree2", 1.0), None)
    truth(monitor, 2.0, (10.0, 32.0, 3.0))
    truth(monitor, 3.0, (10.0, 40.0, 3.0))
    assert closest() == ((0.4, "tree2", 2.0), None)
    command(monitor, 3.5, "attack", (50.3, 30.0, 4.5))  # balloon2, 0.3 m off its pole's axis
    truth(monitor, 4.0, (50.0, 30.0, 4.5))  # 0.5 m over balloon2's pole top: 0.1 m, apart: it attacks it
    assert closest() == ((0.4, "tree2", 2.0), {"m": 0.1, "to": "balloon2_pole", "t": 4.0})
    truth(monitor, 4.5, (51.3, 30.0, 2.5))  # balloon9's pole is no exception: 0.65 m from it, 0.25 m
    assert closest()[0] == (0.25, "balloon9_pole", 4.5)
    command(monitor, 5.0, "scan")  # the balloon is down: the UAV leaves its pole's top under another command
    truth(monitor, 5.1, (50.0, 30.0, 4.45))  # still over it: the attack's pass, not yet 1 m clear
    assert closest() == ((0.25, "balloon9_pole", 4.5), {"m": 0.05, "to": "balloon2_pole", "t": 5.1})
    truth(monitor, 5.2, (50.0, 30.0, 6.0))  # 1.6 m over the pole's top: the pass is over
    truth(monitor, 5.5, (50.0, 30.0, 4.5))  # over balloon2's pole again, no longer attacking it
    assert closest() == ((0.1, "balloon2_pole", 5.5), {"m": 0.05, "to": "balloon2_pole", "t": 5.1})
    truth(monitor, 6.0, (80.0, 2.45, 2.0), uav2=(10.0, 31.0, 3.0), airborne2=True)  # the shed: the truth's only
    truth(monitor, 7.0, (10.0, 30.0, 3.0), alive1=False)  # dead (it crashed): no longer measured
    assert closest() == ((0.05, "shed", 6.0), {"m": 0.05, "to": "balloon2_pole", "t": 5.1})
    # uav2 flew at one tick only, 1 m from the tree's axis: 0.2 m inside its bark, less its 0.5 m body
    assert closest("uav2") == ((-0.7, "tree2", 6.0), None)
    summary = monitor.summary()
    assert summary["collisions"] == []
    assert clearance_line(summary["clearance"]["uav1"]) == ("0.05 m to shed at t=6.0 s; in attacks 0.05 m to "
                                                            "balloon2_pole at t=5.1 s")
    assert clearance_line(summary["clearance"]["uav2"]) == "-0.70 m to tree2 at t=6.0 s"


def test_without_a_world_model_or_a_flight_there_is_no_clearance():
    monitor = RunMonitor()
    truth(monitor, 1.0, (10.0, 33.0, 3.0))  # no world model yet: the surveyed obstacles are unknown
    world(monitor, radius={})  # one that names no radius: the default body
    summary = monitor.summary()["clearance"]
    assert summary["uav1"] == {"m": None, "to": None, "t": None, "attack_pole": None}
    assert clearance_line(summary["uav1"]) == "none measured"
    assert clearance_line(None) == "not measured"
    truth(monitor, 2.0, (10.0, 33.0, 3.0))
    assert monitor.summary()["clearance"]["uav1"] == {"m": 1.4, "to": "tree2", "t": 2.0, "attack_pole": None}


def test_collision_events_are_listed_with_the_other_party():
    monitor = RunMonitor()
    for t, uav, detail in ((55.9, "uav1", "tree2 at 4.1 m/s (10.3, 29.1, 5.0)"),
                           (60.0, "uav2", "unnamed box (3.0, 4.0) at 2.0 m/s (1.0, 4.0, 2.0)"),
                           (61.5, "uav1", "ground at 3.2 m/s (4.0, 5.0, 0.0)")):
        monitor.handle(keys.EVENTS, encode(SimEvent(header=Header(stamp=round(t * S)), kind="collision", subject=uav,
                                                    detail=detail)))
    collisions = monitor.summary()["collisions"]
    assert [(c["t"], c["uav"], c["with"]) for c in collisions] == [
        (55.9, "uav1", "tree2"), (60.0, "uav2", "unnamed box (3.0, 4.0)"), (61.5, "uav1", "ground")]
    assert collisions[0]["detail"] == "tree2 at 4.1 m/s (10.3, 29.1, 5.0)"
    assert collisions_line([]) == "collisions: none"
    assert collisions_line(collisions[:1]) == "COLLISIONS: 1\n  t=55.9 s uav1 hit tree2 at 4.1 m/s (10.3, 29.1, 5.0)"


def test_the_launcher_hands_the_world_model_to_the_monitor():
    assert keys.WORLD in WATCHED


def test_a_run_begun_short_of_a_service_says_so_in_its_summary():
    monitor = RunMonitor()
    assert monitor.summary()["started_without"] == []
    monitor.handle(keys.EVENTS, encode(SimEvent(header=Header(), kind="started_without", subject="sim",
                                                detail="uav2/classifier, uav2/job_manager")))
    assert monitor.summary()["started_without"] == ["uav2/classifier", "uav2/job_manager"]


def test_a_uav_braking_along_its_attack_towards_the_pole_is_still_attacking_until_its_momentum_is_spent():
    """Giving way to a partner mid-attack (street, 3 UAVs, seed 5), the UAV brakes along the attack's
    line: the pole stays the attack's while the UAV closes on it; an approach after it came to rest
    and left is an obstacle's."""
    monitor = RunMonitor()
    world(monitor)

    def closest() -> tuple:
        c = monitor.summary()["clearance"]["uav1"]
        pole = c["attack_pole"]
        return (c["m"], c["to"]), None if pole is None else (pole["m"], pole["t"])

    command(monitor, 10.0, "attack", (50.0, 30.0, 4.5))
    truth(monitor, 10.5, (48.0, 30.0, 3.0))  # beside balloon2's pole, 1.55 m from it (body and pole radii off)
    command(monitor, 10.55, "stop")  # giving way: braking to a hover, 1.55 m from the pole
    truth(monitor, 10.6, (48.3, 30.0, 3.0))  # 1.25 m, still closing at 3 m/s: the attack's momentum
    truth(monitor, 10.8, (48.75, 30.0, 3.0))
    truth(monitor, 11.0, (48.8, 30.0, 3.0))
    truth(monitor, 11.5, (48.8, 30.0, 3.0))  # at rest, within 1 m: the pass goes on
    assert closest() == ((2.75, "balloon9_pole"), (0.75, 11.0))  # the other pole, an obstacle throughout
    truth(monitor, 12.0, (47.0, 30.0, 3.0))  # 2.55 m and leaving: the pass is over
    truth(monitor, 13.0, (48.9, 30.0, 3.0))  # back under the stop, no attack: the pole is an obstacle
    assert closest() == ((0.65, "balloon2_pole"), (0.75, 11.0))


def test_a_uav_out_of_the_arena_or_above_its_ceiling_is_a_geofence_breach():
    from services.tools.launcher.monitor import RunMonitor

    monitor = RunMonitor()
    monitor._on_world(WorldModel(header=Header(stamp=0), scenario="fence", min_height=1.0, arena=[(0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0)],
                                 max_height=10.0, obstacles=[Obstacle(kind="plane", center=(0.0, 0.0, 1.0))]))

    def at(t: float, *positions) -> None:
        monitor._note_geofence(t, [VehicleTruth(name=f"uav{k + 1}", position=p, velocity=(0.0, 0.0, 0.0), heading=0.0,
                                                airborne=True, alive=True) for k, p in enumerate(positions)])

    at(1.0, (10.0, 10.0, 5.0), (19.8, 10.0, 10.9))  # inside (the ceiling: ground 1 m + max_height 10 m)
    at(2.0, (20.4, 10.0, 5.0), (10.0, 10.0, 11.8))  # uav1 within the 0.5 m slack; uav2 0.8 m above 10 + 1 m
    at(3.0, (21.5, 10.0, 5.0), (10.0, 10.0, 12.5))
    at(4.0, (10.0, 10.0, 5.0), (10.0, 10.0, 5.0))
    assert monitor.geofence == [{"uav": "uav2", "start": 2.0, "end": 4.0, "m": 1.5},
                                {"uav": "uav1", "start": 3.0, "end": 4.0, "m": 1.5}]
