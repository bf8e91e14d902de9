"""UAVs: odometry noise and jumps, emergency landing, the airframe's envelope, per-UAV settings."""
from __future__ import annotations

import numpy as np

from services.simulator.core import Simulation
from services.simulator.scenario import parse_scenario

DT = 0.05
LIMITS = dict(max_speed=5.0, max_acceleration=1.5, max_heading_rate=1.0, max_vertical_speed=2.0)


def world(**extra):
    data = {"name": "vehicles", "arena": [[-50, -50], [50, -50], [50, 50], [-50, 50]],
            "starts": [[0.0, 0.0, 0.5], [0.0, 10.0, 0.0]]}
    data.update(extra)
    return parse_scenario(data, "vehicles.toml")


def hovering(sim: Simulation, uav: str = "uav1", at=(0.0, 0.0, 5.0), seconds: float = 7.0) -> list:
    """Hover at `at`, the reference re-sent every 2 s as the planner does."""
    events = []
    for k in range(int(seconds / DT)):
        if k % int(2.0 / DT) == 0:
            sim.set_reference(uav, sim.time_ns, 1.0, np.array([at]), np.array([0.5]), **LIMITS)
        events += sim.step(DT)
    return events


def test_odometry_noise_matches_its_sigmas_and_is_deterministic():
    noisy = {"odometry_position_sigma": 0.2, "odometry_attitude_sigma": 0.05}
    sim = Simulation(world(uav=noisy), ["uav1", "uav2"], seed=3)
    true = sim.vehicles()[0]
    readings = [sim.fleet.odometry(0, t_ns) for t_ns in range(0, 4000 * 50_000_000, 50_000_000)]
    errors = np.array([r.position - true.position for r in readings])
    headings = np.array([(r.heading - true.heading + np.pi) % (2 * np.pi) - np.pi for r in readings])
    assert np.allclose(errors.std(axis=0), 0.2, rtol=0.05) and np.abs(errors.mean(axis=0)).max() < 0.015
    assert abs(headings.std() - 0.05) < 0.0025 and abs(headings.mean()) < 0.004
    assert abs(np.corrcoef(errors[:, 0], errors[:, 1])[0, 1]) < 0.06  # independent axes
    assert np.allclose(np.diag(readings[0].covariance), [0.04] * 3 + [0.0025] * 3)
    assert readings[0].covariance.shape == (6, 6)
    # The same for a run whoever asks and how often; different for another seed or UAV.
    again = Simulation(world(uav=noisy), ["uav1", "uav2"], seed=3)
    assert np.array_equal(sim.odometry("uav1").position, again.odometry("uav1").position)
    assert np.array_equal(sim.odometry("uav1").position, sim.odometry("uav1").position)
    other = Simulation(world(uav=noisy), ["uav1", "uav2"], seed=4)
    assert not np.array_equal(sim.odometry("uav1").position, other.odometry("uav1").position)
    sim.step(DT)
    assert not np.array_equal(sim.odometry("uav1").position, again.odometry("uav1").position)


def test_noiseless_odometry_is_the_truth_with_a_tiny_covariance():
    sim = Simulation(world(), ["uav1", "uav2"], seed=3)
    hovering(sim, seconds=2.0)
    position, velocity, heading, covariance = sim.odometry("uav1")
    state = sim.vehicles()[0]
    assert np.array_equal(position, state.position) and np.array_equal(velocity, state.velocity)
    assert heading == state.heading and np.all(np.linalg.eigvalsh(covariance) > 0)


def test_odometry_jump_moves_the_estimate_and_the_vehicle_follows_it():
    sim = Simulation(world(), ["uav1", "uav2"], seed=3)
    hovering(sim)
    before = sim.vehicles()[0].position
    sim.jump_odometry("uav1", (2.0, -1.0, 0.5))
    assert np.allclose(sim.odometry("uav1").position, before + [2.0, -1.0, 0.5])  # at once
    hovering(sim, seconds=8.0)
    # The controller flies on its estimate: the estimate settles on the reference, the vehicle off it.
    assert np.allclose(sim.odometry("uav1").position, [0, 0, 5], atol=0.02)
    assert np.allclose(sim.vehicles()[0].position, [-2.0, 1.0, 4.5], atol=0.02)
    sim.jump_odometry("uav1", (-2.0, 1.0, -0.5))  # undone
    hovering(sim, seconds=8.0)
    assert np.allclose(sim.vehicles()[0].position, [0, 0, 5], atol=0.02)


def test_a_uav_without_gnss_has_no_gnss_noise_and_flies_on_its_localizers_error():
    """The odometry noise models GNSS: a UAV flying without it (the scenario's positioning, or the
    run's --positioning) gets none, its published position is truth + the estimate's error, and the
    vehicle flies by that belief (services/simulator/positioning.py sets the error per estimate)."""
    noisy = {"odometry_position_sigma": 0.2, "odometry_attitude_sigma": 0.05,
             "overrides": {"uav2": {"positioning": "lidar"}}}
    for positioning in (None, {"uav1": "lidar", "uav2": "lidar"}):
        sim = Simulation(world(uav=noisy), ["uav1", "uav2"], seed=3, positioning=positioning)
        odometry, truth = sim.odometry("uav2"), sim.vehicles()[1]
        assert np.array_equal(odometry.position, truth.position) and odometry.heading == truth.heading
        assert (positioning is None) != np.array_equal(sim.odometry("uav1").position, sim.vehicles()[0].position)
    hovering(sim, "uav2", at=(0.0, 10.0, 5.0))
    sim.set_odometry_error("uav2", (0.4, -0.2, 0.1))  # an estimate 0.4 m east of the truth, ...
    sim.set_odometry_error("uav2", (0.3, -0.2, 0.1))  # ... then a newer one: replaced, not added
    hovering(sim, "uav2", at=(0.0, 10.0, 5.0), seconds=8.0)
    assert np.allclose(sim.odometry("uav2").position, [0.0, 10.0, 5.0], atol=0.02)
    assert np.allclose(sim.vehicles()[1].position, [-0.3, 10.2, 4.9], atol=0.02)


def test_emergency_landing_descends_gently_and_ignores_the_reference():
    sim = Simulation(world(), ["uav1", "uav2"], seed=3)
    assert hovering(sim) == [("takeoff", "uav1", "")]
    sim.emergency_land("uav1", "lidar silent")
    sim.emergency_land("uav1")  # a second call changes nothing
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[10.0, 0.0, 8.0]]), np.zeros(1), **LIMITS)
    heights, events = [], []
    for _ in range(int(6.0 / DT)):
        events += sim.step(DT)
        heights.append(sim.vehicles()[0].position[2])
    assert events == [("emergency_landing", "uav1", "lidar silent"), ("landed", "uav1", "emergency")]
    assert np.diff(heights).min() >= -1.0 * DT - 1e-9 and np.diff(heights).max() <= 1e-9
    state = sim.vehicles()[0]
    assert not state.airborne and state.position[2] == 0.0 and np.linalg.norm(state.position[:2]) < 0.01
    assert hovering(sim, seconds=2.0) == [] and not sim.vehicles()[0].airborne  # stays down for good


def test_airframe_envelope_caps_the_reference_profile():
    slow = {"sweeping": {"max_speed": 2.0, "max_acceleration": 1.0},
            "attack": {"max_speed": 3.0, "max_acceleration": 1.2, "max_vertical_speed": 1.0},
            "overrides": {"uav2": {"attack": {"max_speed": 9.0, "max_acceleration": 4.0}}}}
    sim = Simulation(world(uav=slow), ["uav1", "uav2"], seed=3)
    attack = dict(max_speed=8.3, max_acceleration=3.0, max_heading_rate=1.0, max_vertical_speed=2.0)
    for uav in ("uav1", "uav2"):
        sim.set_reference(uav, 0, 1.0, np.array([[30.0, 0.0, 5.0]]), np.zeros(1), **attack)
    speeds, climbs = [], []
    for _ in range(int(8.0 / DT)):
        sim.step(DT)
        speeds.append([np.linalg.norm(v.velocity[:2]) for v in sim.vehicles()])
        climbs.append(sim.vehicles()[0].velocity[2])
    speeds = np.array(speeds)
    assert 2.99 < speeds[:, 0].max() <= 3.0 + 1e-9 and max(climbs) <= 1.0 + 1e-9
    assert speeds[:, 1].max() > 6.0  # uav2's own, faster airframe


def test_position_hold_hovers_where_it_is_and_ignores_every_reference():
    """A whole-UAV kill with failsafe = "hold": the flight controller keeps the vehicle in the air."""
    sim = Simulation(world(), ["uav1", "uav2"], seed=3)
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[0.0, 0.0, 5.0], [20.0, 0.0, 5.0]]), np.zeros(2), **LIMITS)
    for _ in range(int(8.0 / DT)):
        sim.step(DT)
    sim.hold_position("uav1", "onboard computer lost")
    sim.hold_position("uav1")  # a second call changes nothing
    held = sim.vehicles()[0].position.copy()
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([[-10.0, 0.0, 1.0]]), np.zeros(1), **LIMITS)
    events = [e for _ in range(int(10.0 / DT)) for e in sim.step(DT)]
    assert events == [("position_hold", "uav1", "onboard computer lost")]
    state = sim.vehicles()[0]
    assert state.airborne and np.linalg.norm(state.position - held) < 2.0  # braked from its speed, then still
    assert np.linalg.norm(state.velocity) < 0.05


def test_a_uav_whose_planner_falls_silent_holds_its_position_until_the_next_reference():
    """The offboard failsafe: a reference flown on with nobody re-sending it for 5 s is dropped."""
    sim = Simulation(world(), ["uav1", "uav2"], seed=3)
    line = np.array([[0.0, 0.0, 5.0], [400.0, 0.0, 5.0]])  # 400 s of flight at 1 m/s samples
    sim.set_reference("uav1", sim.time_ns, 100.0, line, np.zeros(2), **LIMITS)
    events = [e for _ in range(int(14.0 / DT)) for e in sim.step(DT)]
    assert ("offboard_lost", "uav1", "no trajectory reference for 5 s: position hold until the next") in events
    state = sim.vehicles()[0]
    assert state.airborne and np.linalg.norm(state.velocity) < 0.05, state.velocity
    held = state.position.copy()
    sim.set_reference("uav1", sim.time_ns, 1.0, np.array([held, held + (0.0, 5.0, 0.0)]), np.zeros(2), **LIMITS)
    for _ in range(int(4.0 / DT)):
        sim.step(DT)
    assert np.linalg.norm(sim.vehicles()[0].position - (held + (0.0, 5.0, 0.0))) < 0.5  # obeys the next one


def test_a_reference_whose_sample_period_would_overflow_the_differences_is_refused():
    """Found by the message fuzzer: dt = 1.6e277 s is a finite float whose square overflows (an
    OverflowError in the simulator's handler, not a refusal); one whose square underflows to 0
    would give infinite accelerations."""
    import math

    import pytest

    from services.simulator.vehicles import make_reference

    line = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [2.0, 0.0, 5.0]])
    assert make_reference("uav1", 0, 0.1, line, np.zeros(3)).dt == 0.1
    for dt in (1.6e277, 1e-200, 0.0, -0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="dt must lie in"):
            make_reference("uav1", 0, dt, line, np.zeros(3))
    for dt in (math.nan, math.inf):  # one sample has no period: taken, and its end is its start
        one = make_reference("uav1", 7, dt, line[:1], np.zeros(1))
        assert one.dt == 0.0 and one.end_ns() == 7 and np.array_equal(one.at(10)[0], line[0])
