"""Simulator core: reference tracking within limits, events, balloon destruction, determinism, each
UAV's IMU samples."""
from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas.arrays import to_numpy
from schemas.messages import ImuBatch
from services.lib.geometry import GRAVITY
from services.lib.imu import ImuParams
from services.simulator.core import Simulation
from services.simulator.node import imu_batch
from services.simulator.scenario import parse_scenario
from services.simulator.specs import NS

DT = 0.05
LIMITS = dict(max_speed=4.0, max_acceleration=1.5, max_heading_rate=0.5, max_vertical_speed=1.0)


def scenario(**extra):
    data = {
        "name": "unit",
        "arena": [[-50, -50], [50, -50], [50, 50], [-50, 50]],
        "starts": [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]],
        # centre at z = 5.0, the pole's top 0.8 m below it: a body flying through the balloon clears the pole
        "balloons": [{"pole": [20.0, 0.0], "height": 4.2, "tether": 0.5, "name": "red"}],
        "drones": [{"center": [0.0, 0.0, 8.0], "radius": 6.0, "speed": 2.0, "phase": 0.5}],
        "obstacles": [{"kind": "box", "center": [-20.0, -20.0, 2.0], "size": [4.0, 4.0, 4.0]}],
    }
    data.update(extra)
    return parse_scenario(data, "unit.toml")


def fly(sim: Simulation, seconds: float, resend=None):
    """Step the sim; returns (positions (T, 3), velocities (T, 3), headings (T,), events) of uav1.
    `resend()` is called every 2 s, as the planner re-sends its trajectory (else the flight
    controller's offboard failsafe stops a vehicle still on a reference after 5 s)."""
    positions, velocities, headings, events = [], [], [], []
    for k in range(int(round(seconds / DT))):
        if resend is not None and k > 0 and k % int(round(2.0 / DT)) == 0:
            resend()
        events += sim.step(DT)
        v = sim.vehicles()[0]
        positions.append(v.position)
        velocities.append(v.velocity)
        headings.append(v.heading)
    return np.array(positions), np.array(velocities), np.array(headings), events


def test_reaches_reference_within_limits():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[10.0, 0.0, 5.0]]), np.array([1.0]), **LIMITS)
    p, v, heading, events = fly(sim, 30.0)
    assert np.linalg.norm(p[-1] - [10.0, 0.0, 5.0]) < 0.02
    assert abs(heading[-1] - 1.0) < 1e-6
    assert np.linalg.norm(v[:, :2], axis=1).max() <= LIMITS["max_speed"] + 1e-9
    assert np.abs(v[:, 2]).max() <= LIMITS["max_vertical_speed"] + 1e-9
    # Sampled at 20 Hz the average acceleration over a sample can only be smaller than the peak.
    acceleration = np.linalg.norm(np.diff(np.vstack([np.zeros(3), v]), axis=0), axis=1) / DT
    assert acceleration.max() <= LIMITS["max_acceleration"] + 1e-9
    assert acceleration.max() > 0.9 * LIMITS["max_acceleration"]  # the limit actually bound
    assert np.abs(np.diff(np.unwrap(heading))).max() <= LIMITS["max_heading_rate"] * DT + 1e-9
    assert p[:, 0].max() < 10.5  # braking-aware approach: no big overshoot
    assert events == [("takeoff", "uav1", "")]
    other = sim.vehicles()[1]
    assert np.array_equal(other.position, [0.0, 10.0, 0.0]) and not other.airborne


def test_time_sampled_reference_is_followed():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]]),
                      np.zeros(3), **LIMITS)
    # Before the first step the UAV is on the ground; halfway through second 1 the reference is at 1 m.
    p, *_ = fly(sim, 0.5)
    assert 0.1 < p[-1, 2] < 0.5  # tracking lags a ramp of 2 m/s capped at 1 m/s vertical
    p, *_ = fly(sim, 10.0)
    assert abs(p[-1, 2] - 2.0) < 0.01
    assert sim.time_ns == 10_500_000_000


def test_takeoff_and_landing_events():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 3.0]]), np.zeros(1), **LIMITS)
    _, _, _, events = fly(sim, 10.0)
    assert events == [("takeoff", "uav1", "")] and sim.vehicles()[0].airborne
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[0.0, 0.0, 0.0]]), np.zeros(1), **LIMITS)
    p, _, _, events = fly(sim, 10.0)
    assert events == [("landed", "uav1", "")] and not sim.vehicles()[0].airborne
    assert p[:, 2].min() >= 0.0  # never below ground


def test_resting_uav_does_not_slide():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[10.0, 0.0, 0.0]]), np.zeros(1), **LIMITS)
    p, _, _, events = fly(sim, 3.0)
    assert np.array_equal(p[-1], [0.0, 0.0, 0.0]) and events == []


def test_flying_through_balloon_destroys_it_once():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    path = np.array([[0.0, 0.0, 5.0], [30.0, 0.0, 5.0]])
    sim.set_reference("uav1", 0, 1.0, path[:1], np.zeros(1), **LIMITS)
    fly(sim, 8.0)
    assert not sim.targets()[0].destroyed
    start = sim.time_ns
    sim.set_reference("uav1", start, 10.0, path, np.zeros(2), **LIMITS)  # 3 m/s through the balloon
    _, _, _, events = fly(sim, 15.0, resend=lambda: sim.set_reference("uav1", start, 10.0, path, np.zeros(2),
                                                                       **LIMITS))
    assert events == [("target_destroyed", "red", "uav1")]
    balloon = next(t for t in sim.targets() if t.id == "red")
    assert balloon.destroyed and balloon.kind == "balloon"
    assert np.allclose(balloon.position, [20.0, 0.0, 5.0])


def test_killed_uav_falls_and_ignores_reference():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 5.0]]), np.zeros(1), **LIMITS)
    fly(sim, 10.0)
    sim.kill("uav1")
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[0.0, 0.0, 9.0]]), np.zeros(1), **LIMITS)
    p, v, _, events = fly(sim, 3.0)
    assert events == [("landed", "uav1", "crashed")]
    state = sim.vehicles()[0]
    assert not state.alive and state.position[2] == 0.0 and np.array_equal(state.velocity, np.zeros(3))


def test_drone_circles_deterministically():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.step(math.pi)  # a quarter of the way round: speed / radius = 1/3 rad/s -> angle 0.5 + π/3
    drone = next(t for t in sim.targets() if t.kind == "drone")
    angle = 0.5 + math.pi / 3
    assert np.allclose(drone.position, [6 * math.cos(angle), 6 * math.sin(angle), 8.0], atol=1e-6)
    assert np.allclose(drone.velocity, [-2 * math.sin(angle), 2 * math.cos(angle), 0.0], atol=1e-6)
    assert drone.id == "drone1" and drone.radius == 0.325 and not drone.destroyed


def test_obstacles_include_ground_and_poles():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    kinds = [(o.kind, o.name) for o in sim.obstacles()]
    assert kinds == [("plane", "ground"), ("box", ""), ("cylinder", "red_pole")]
    pole = sim.obstacles()[2]
    assert pole.radius == 0.05 and pole.height == 4.2 and pole.center == (20.0, 0.0, 0.0)


def test_unknown_uav_rejected():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    with pytest.raises(KeyError):
        sim.kill("uav9")


def run_mission(seed: int) -> np.ndarray:
    sim = Simulation(scenario(), ["uav1", "uav2", "uav3"], seed=seed)
    t = np.linspace(0, 1, 40)[:, None]
    sim.set_reference("uav1", 0, 0.5, np.hstack([25 * t, 3 * t, 2 + 3 * t]), 3 * t[:, 0], **LIMITS)
    sim.set_reference("uav2", 1_000_000_000, 0.25, np.hstack([-10 * t, 10 + 5 * t, 4 + 0 * t]), -t[:, 0], **LIMITS)
    rows = []
    for _ in range(400):
        sim.step(DT)
        rows.append(np.concatenate([np.concatenate([v.position, v.velocity, [v.heading]]) for v in sim.vehicles()]))
    return np.array(rows)


def test_determinism():
    assert np.array_equal(run_mission(7), run_mission(7))


# ------------------------------------------------------------------ the IMU of each UAV
NOISE_FREE_IMU = ImuParams(gyroscope_noise_density=0.0, accelerometer_noise_density=0.0, gyroscope_random_walk=0.0,
                           accelerometer_random_walk=0.0, gyroscope_bias_sigma=0.0, accelerometer_bias_sigma=0.0)
UP_G = np.array([0.0, 0.0, GRAVITY])


def published_imu(sim: Simulation, uav: str) -> ImuBatch:
    """The UAV's samples of the last step as the simulator node sends them: through the wire."""
    batch = imu_batch(sim.imu(uav), sim.time_ns, uav, sim.imu_params.rate_hz)
    return msgspec.msgpack.decode(msgspec.msgpack.encode(batch), type=ImuBatch)


def hovering(imu: ImuParams, seed: int = 1) -> Simulation:
    """uav1 climbed to 5 m and settled there; uav2 still on the ground."""
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=seed, imu=imu)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 5.0]]), np.zeros(1), **LIMITS)
    fly(sim, 30.0)
    return sim


def accelerometer_over(sim: Simulation, uav: str, seconds: float) -> np.ndarray:
    """(N, 3): the UAV's published accelerometer samples over the next `seconds`."""
    batches = []
    for _ in range(int(round(seconds / DT))):
        sim.step(DT)
        batches.append(to_numpy(published_imu(sim, uav).accelerometer))
    return np.vstack(batches)


def test_a_hovering_uav_reads_plus_g_up_in_its_body_frame():
    sim = hovering(NOISE_FREE_IMU)
    assert abs(sim.vehicles()[0].position[2] - 5.0) < 0.01
    np.testing.assert_allclose(accelerometer_over(sim, "uav1", 2.0).mean(axis=0), UP_G, atol=1e-6)
    np.testing.assert_allclose(to_numpy(published_imu(sim, "uav1").gyroscope), 0.0, atol=1e-9)
    # With the default (Pixhawk-class) noise the mean is off by the bias only: switch-on σ 0.196 m/s² per axis.
    noisy = hovering(ImuParams())
    mean = accelerometer_over(noisy, "uav1", 2.0).mean(axis=0)
    np.testing.assert_allclose(mean, UP_G, atol=5 * ImuParams().accelerometer_bias_sigma)
    np.testing.assert_allclose(accelerometer_over(noisy, "uav2", 2.0).mean(axis=0), UP_G,  # on the ground
                               atol=5 * ImuParams().accelerometer_bias_sigma)


def test_a_uav_facing_north_accelerating_east_feels_it_on_its_right():
    # Heading 90°: body x (forward) is world +y, body y (left) is world −x, so a push towards world +x
    # reads as −y in the body frame (FLU), and a push towards world +y as +x.
    sim = Simulation(scenario(starts=[[0.0, 0.0, math.pi / 2], [0.0, 10.0, 0.0]]), ["uav1", "uav2"], seed=1,
                     imu=NOISE_FREE_IMU)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 5.0]]), np.array([math.pi / 2]), **LIMITS)
    fly(sim, 20.0)
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[20.0, 0.0, 5.0]]), np.array([math.pi / 2]), **LIMITS)
    pushed = 0
    for _ in range(int(round(4.0 / DT))):
        before = sim.vehicles()[0].velocity
        sim.step(DT)
        after = sim.vehicles()[0]
        assert abs(after.heading - math.pi / 2) < 1e-12
        world = (after.velocity - before) / DT  # the tick's mean acceleration: two samples per 10 ms sub-step
        mean = to_numpy(published_imu(sim, "uav1").accelerometer).mean(axis=0)
        np.testing.assert_allclose(mean, [world[1], -world[0], world[2] + GRAVITY], atol=1e-9)
        pushed += world[0] > 1.0
    assert pushed >= 10  # it did accelerate towards +x, at up to max_acceleration (1.5 m/s²)


def test_a_killed_uav_reads_nothing_falling_and_plus_g_on_the_ground():
    sim = hovering(NOISE_FREE_IMU)
    sim.kill("uav1")
    readings, events = [], []
    for _ in range(int(round(3.0 / DT))):
        events += sim.step(DT)
        readings.append((to_numpy(published_imu(sim, "uav1").accelerometer), sim.vehicles()[0].position[2]))
    assert events == [("landed", "uav1", "crashed")]
    falling = np.vstack([a for a, z in readings[:10]])  # 0.5 s: 1.2 m of a 5 m fall
    np.testing.assert_allclose(falling, 0.0, atol=1e-9)  # free fall: no specific force
    assert max(np.abs(a).max() for a, _ in readings) > 50.0  # the impact: ~10 m/s lost within 10 ms
    np.testing.assert_allclose(np.vstack([a for a, _ in readings[-10:]]), np.tile(UP_G, (100, 1)), atol=1e-9)


def test_consecutive_ticks_tile_the_sample_grid():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[3.0, 0.0, 4.0]]), np.array([2.0]), **LIMITS)
    assert len(sim.imu("uav1")) == 0  # before the first step: no time, no samples
    stamps = []
    for step in range(1, 41):
        start = sim.time_ns
        sim.step(DT)
        batch = published_imu(sim, "uav1")
        ticks = to_numpy(batch.stamps)
        assert batch.header.stamp == sim.time_ns == step * 50_000_000 and batch.header.frame == "uav1"
        assert ticks.dtype == np.int64 and len(ticks) == 10 and start <= ticks[0] and ticks[-1] < sim.time_ns
        assert to_numpy(batch.accelerometer).shape == to_numpy(batch.gyroscope).shape == (10, 3)
        stamps.append(ticks)
    rate = sim.imu_params.rate_hz
    assert rate == 200 and np.array_equal(np.concatenate(stamps), np.arange(40 * 10) * (NS // rate))


def test_imu_samples_are_the_same_for_a_seed_and_differ_between_uavs_and_seeds():
    def samples(seed: int) -> list[np.ndarray]:
        sim = Simulation(scenario(), ["uav1", "uav2"], seed=seed)
        sim.set_reference("uav1", 0, 1.0, np.array([[3.0, 2.0, 4.0]]), np.array([1.0]), **LIMITS)
        out = []
        for _ in range(40):
            sim.step(DT)
            out += [np.hstack([s.accelerometer, s.gyroscope]) for s in (sim.imu("uav1"), sim.imu("uav2"))]
        return out

    first, again, other = samples(7), samples(7), samples(8)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))  # bit for bit, as lockstep needs
    assert not np.array_equal(first[-1], other[-1])
    assert not np.array_equal(first[-1][:, 3:], first[-2][:, 3:])  # each UAV its own noise


def test_a_resumed_simulation_measures_on_from_the_resume_time():
    sim = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    sim.set_reference("uav1", 0, 1.0, np.array([[0.0, 0.0, 4.0]]), np.zeros(1), **LIMITS)
    fly(sim, 2.0)
    restarted = Simulation(scenario(), ["uav1", "uav2"], seed=1)
    restarted.resume(sim.time_ns, [v.truth() for v in sim.vehicles()], [])
    assert len(restarted.imu("uav1")) == 0
    restarted.step(DT)
    assert to_numpy(published_imu(restarted, "uav1").stamps)[0] == 2 * NS  # new stream, same grid
