"""Targets: balloons sway within their tether in the wind; drones are captured only when slow enough."""
from __future__ import annotations

import math

import numpy as np

from services.simulator.core import Simulation
from services.simulator.scenario import parse_scenario
from services.simulator.targets import Balloons, Drones

ARENA = [[-50, -50], [50, -50], [50, 50], [-50, 50]]
LIMITS = dict(max_speed=5.0, max_acceleration=1.5, max_heading_rate=1.0, max_vertical_speed=2.0)


def world(**extra):
    data = {"name": "targets", "arena": ARENA, "starts": [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]]}
    data.update(extra)
    return parse_scenario(data, "targets.toml")


BALLOONS = [{"pole": [10.0, 0.0], "height": 3.0, "tether": 0.4}, {"pole": [-10.0, 5.0], "height": 4.0}]


def test_still_air_balloon_sits_above_its_pole():
    balloons = Balloons(world(balloons=BALLOONS))
    assert np.allclose(balloons.positions(np.array([0.0, 37.0])), [[10, 0, 3.7], [-10, 5, 4.5]])
    assert np.allclose(balloons.velocities(12.0), 0.0)


def test_balloons_sway_within_their_tether_and_downwind():
    wind = {"speed": 6.0, "direction": math.pi / 2, "gust": 4.0, "gust_period": 5.0}
    balloons = Balloons(world(balloons=BALLOONS, wind=wind))
    t = np.arange(0.0, 60.0, 0.05)
    centres = balloons.positions(t)  # (S, 2, 3)
    offsets = centres - balloons.anchors
    arms = np.array([0.7, 0.5])
    assert np.allclose(np.linalg.norm(offsets, axis=-1), arms)  # on the tether's sphere
    sideways = np.linalg.norm(offsets[..., :2], axis=-1)
    assert (sideways < arms).all() and (sideways.max(axis=0) > 0.3 * arms).all()
    assert (np.ptp(offsets[..., :2], axis=0) > 0.05).all()  # it moves with the gusts, in both directions
    mean = offsets[..., :2].mean(axis=0)
    assert (mean[:, 1] > 5 * np.abs(mean[:, 0])).all()  # leaning with the wind (towards +y)
    assert not np.allclose(offsets[:, 0], offsets[:, 1] * arms[0] / arms[1])  # not in unison
    # The reported velocity is the derivative of the position.
    velocity = balloons.velocities(t[1:-1])
    assert np.allclose(velocity, (centres[2:] - centres[:-2]) / 0.1, atol=2e-3)
    again = Balloons(world(balloons=BALLOONS, wind=wind)).positions(t)
    assert np.array_equal(centres, again)  # a closed form of mission time


def drone_world(**extra):
    hover = {"path": "waypoints", "waypoints": [[20.0, 0.0, 5.0], [20.0, 0.5, 5.0]], "speed": 1.0,
             "name": "hoverer"}
    return world(drones=[hover], **extra)


def test_capture_needs_a_slow_enough_approach():
    drones = Drones(drone_world(capture_radius=1.0, capture_speed=2.0), seed=1)
    at = np.array([100.0])  # long at rest at (20, 0.5, 5)
    alive, names = np.array([True]), ["uav1"]
    near = np.array([[[20.0, 1.2, 5.0]]])
    assert drones.check_captures(at, near, np.array([[[2.5, 0.0, 0.0]]]), alive, names) == []  # too fast
    assert drones.check_captures(at, near + [0, 0.4, 0], np.array([[[0.5, 0.0, 0.0]]]), alive, names) == []  # far
    assert drones.check_captures(at, near, np.array([[[0.0, 1.5, 0.0]]]), np.array([False]), names) == []  # dead
    found = drones.check_captures(at, near, np.array([[[1.5, 0.0, 0.0]]]), alive, names)
    assert found == [(0, ("target_captured", "hoverer", "uav1"))]
    assert drones.check_captures(at, near, np.zeros((1, 1, 3)), alive, names) == []  # only once


def test_fast_pass_does_not_capture_but_a_slow_approach_does():
    sim = Simulation(drone_world(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.5, 5.0]]), np.zeros(1), **LIMITS)
    for _ in range(200):
        sim.step(0.05)
    # Straight through the hovering drone at 5 m/s: no capture.
    line = np.array([[0.0, 0.5, 5.0], [40.0, 0.5, 5.0]])
    sim.set_reference("uav1", sim.time_ns, 8.0, line, np.zeros(2), **LIMITS)
    events = [e for _ in range(300) for e in sim.step(0.05)]
    assert not [e for e in events if e[0] == "target_captured"]
    assert max(np.linalg.norm(v.velocity) for v in sim.vehicles()) < 5.0 + 1e-9
    # Back, slowly, to the drone: captured, and it drops to the ground.
    back, start = np.array([[40.0, 0.5, 5.0], [20.0, 0.5, 5.0]]), sim.time_ns
    events = []
    for k in range(600):
        if k % 40 == 0:  # re-sent every 2 s, as the planner does (the offboard failsafe stops it otherwise)
            sim.set_reference("uav1", start, 20.0, back, np.zeros(2), **LIMITS)
        events += sim.step(0.05)
    assert [e for e in events if e[0] == "target_captured"] == [("target_captured", "hoverer", "uav1")]
    drone = next(t for t in sim.targets() if t.kind == "drone")
    assert drone.destroyed and np.allclose(drone.position, [20.0, 0.5, 0.325]) and np.allclose(drone.velocity, 0)
