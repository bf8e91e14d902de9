"""Collisions in the simulator: a UAV's body touching a static obstacle (surveyed or not, a balloon's
pole), a flying partner or the ground outside a landing crashes it (one `collision` event naming
the other party, dead and falling from that sub-step on); the world model's obstacles and the
truth's."""
from __future__ import annotations

import numpy as np
import pytest

from services.simulator import contact
from services.simulator.core import MAX_SUBSTEP_S, Simulation
from services.simulator.node import ground_truth, world_model
from services.simulator.scenario import parse_scenario
from services.simulator.specs import NS

DT = 0.05
LIMITS = dict(max_speed=4.0, max_acceleration=3.0, max_heading_rate=1.0, max_vertical_speed=2.0)
FLIGHT = 3.0  # m: the height every test flies at


def scenario(**extra):
    data = {
        "name": "crashes",
        "arena": [[-50, -50], [50, -50], [50, 50], [-50, 50]],
        "starts": [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]],
        "balloons": [{"pole": [-20.0, -20.0], "height": 4.0, "name": "red"}],
        "obstacles": [
            {"kind": "box", "center": [20.0, 0.0, 3.0], "size": [4.0, 4.0, 6.0], "name": "crate"},
            {"kind": "cylinder", "center": [20.0, -20.0, 0.0], "radius": 0.5, "height": 8.0, "name": "mast",
             "surveyed": False},
            {"kind": "cone", "center": [20.0, 20.0, 0.0], "radius": 2.0, "height": 8.0, "name": "spruce"},
            {"kind": "sphere", "center": [-20.0, 0.0, 3.0], "radius": 1.5, "name": "boulder"},
        ],
    }
    data.update(extra)
    return parse_scenario(data, "crashes.toml")


class Pilot:
    """Flies one Simulation tick by tick with the references a planner would send (re-sent every
    2 s), recording every tick's events and vehicles."""

    def __init__(self, sim: Simulation, tick: float = DT) -> None:
        self.sim, self.tick = sim, tick
        self.events: list[tuple[float, tuple[str, str, str]]] = []  # (mission time after the tick, event)
        self.plans: dict[str, tuple[int, np.ndarray, dict]] = {}

    def go(self, uav: str, *points, dt: float = 1.0, **limits) -> None:
        """A time-sampled reference from now through `points`, dt apart."""
        self.plans[uav] = (self.sim.time_ns, np.array(points, dtype=float), {**LIMITS, **limits})
        self._send(uav)

    def _send(self, uav: str) -> None:
        start, points, limits = self.plans[uav]
        self.sim.set_reference(uav, start, 1.0, points, np.zeros(len(points)), **limits)

    def fly(self, seconds: float) -> list:
        states = []
        for _ in range(int(round(seconds / self.tick))):
            if self.sim.time_ns % (2 * NS) == 0:
                for uav in self.plans:
                    self._send(uav)
            self.events += [(self.sim.time_ns / NS + self.tick, e) for e in self.sim.step(self.tick)]
            states.append(self.sim.vehicles())
        return states

    def kinds(self) -> list[tuple[str, str, str]]:
        return [e for _, e in self.events]


def airborne(pilot: Pilot, uav: str = "uav1") -> None:
    index = pilot.sim.index(uav)
    start = pilot.sim.vehicles()[index].position
    pilot.go(uav, start + (0.0, 0.0, FLIGHT))
    pilot.fly(5.0)
    assert pilot.kinds() == [("takeoff", uav, "")]


def through(pilot: Pilot, target, uav: str = "uav1") -> None:
    """A straight line from where the UAV hovers to `target` at FLIGHT, about 3 m/s."""
    here = pilot.sim.vehicles()[pilot.sim.index(uav)].position
    goal = np.array([target[0], target[1], FLIGHT])
    samples = int(np.ceil(np.linalg.norm(goal - here) / 3.0)) + 1
    pilot.go(uav, *np.linspace(here, goal, samples))


@pytest.mark.parametrize("target, party", [((30.0, 0.0), "crate"), ((30.0, -30.0), "mast"), ((30.0, 30.0), "spruce"),
                                           ((-30.0, 0.0), "boulder"), ((-30.0, -30.0), "red_pole")])
def test_a_uav_that_flies_into_an_obstacle_crashes_once_and_falls(target, party):
    pilot = Pilot(Simulation(scenario(), ["uav1", "uav2"], seed=1))
    airborne(pilot)
    through(pilot, target)
    pilot.fly(20.0)
    events = pilot.kinds()[1:]
    assert [e[:2] for e in events] == [("collision", "uav1"), ("landed", "uav1")], events
    assert events[0][2].startswith(f"{party} at ") and events[1][2] == "crashed"
    state = pilot.sim.vehicles()[0]
    assert not state.alive and not state.airborne and state.position[2] == 0.0
    assert np.array_equal(state.velocity, np.zeros(3))
    pilot.go("uav1", state.position + (0.0, 0.0, 5.0))  # a dead vehicle obeys no reference
    pilot.fly(3.0)
    assert np.array_equal(pilot.sim.vehicles()[0].position, state.position) and len(pilot.events) == 3


def test_the_crash_is_the_first_sub_step_the_body_touches_and_ticks_fly_as_their_sub_steps_do():
    """The step checks its sub-steps together and flies again from the first contact: ticks of
    50 ms give what ticks of one 10 ms sub-step give, before the crash, at it, and falling after."""
    runs = []
    for tick in (DT, MAX_SUBSTEP_S):
        pilot = Pilot(Simulation(scenario(), ["uav1", "uav2"], seed=1), tick)
        airborne(pilot)
        through(pilot, (30.0, 0.0))
        runs.append((pilot, pilot.fly(8.0)))
    (coarse, coarse_states), (fine, fine_states) = runs
    assert coarse.kinds() == fine.kinds()
    every = int(round(DT / MAX_SUBSTEP_S))
    for a, b in zip(coarse_states, fine_states[every - 1::every]):
        assert np.allclose([v.position for v in a], [v.position for v in b], rtol=0, atol=1e-9)
        assert [v.alive for v in a] == [v.alive for v in b]
    crate = contact.shapes(fine.sim.obstacles())
    positions = np.array([states[0].position for states in fine_states])
    gaps = contact.signed_distance(positions, crate)[:, 0] - 0.4  # the body's gap to the crate, each 10 ms
    crash = next(i for i, states in enumerate(fine_states) if not states[0].alive)
    assert gaps[crash] <= 0.0 < gaps[crash - 1]  # dead at the first sub-step it touched, not before
    x, y, z = positions[crash]
    speed = np.linalg.norm(fine_states[crash][0].velocity)
    assert fine.kinds()[1] == ("collision", "uav1", f"crate at {speed:.1f} m/s ({x:.1f}, {y:.1f}, {z:.1f})")
    assert 2.5 < speed < 4.0 and x == pytest.approx(17.6, abs=0.05)  # the crate's face at 18, less the radius


def test_a_gentle_landing_is_no_crash():
    pilot = Pilot(Simulation(scenario(), ["uav1", "uav2"], seed=1))
    airborne(pilot)
    here = pilot.sim.vehicles()[0].position
    pilot.go("uav1", here, here * (1.0, 1.0, 0.0) + (0.5, 0.0, 0.0))  # down to the ground within a second
    pilot.fly(6.0)
    assert pilot.kinds()[1:] == [("landed", "uav1", "")]
    state = pilot.sim.vehicles()[0]
    assert state.alive and not state.airborne
    pilot.go("uav1", state.position + (0.0, 0.0, 3.0))  # and it takes off again
    pilot.fly(4.0)
    assert pilot.kinds()[-1] == ("takeoff", "uav1", "") and pilot.sim.vehicles()[0].airborne


@pytest.mark.parametrize("how, limits", [
    ("across at 4 m/s", dict()),  # the reference dives into the ground 4 m/s across: not gentle
    ("down at 4 m/s", dict(max_vertical_speed=4.0)),  # straight down, faster than a landing touches down
    ("down onto a hover", dict()),  # brought down by an odometry error while holding 3 m: not landing
])
def test_touching_the_ground_outside_a_landing_is_a_crash(how, limits):
    sim = Simulation(scenario(uav={"sweeping": {"max_speed": 5.0, "max_acceleration": 3.0, "max_vertical_speed": 4.0}}),
                     ["uav1", "uav2"], seed=1)
    pilot = Pilot(sim)
    airborne(pilot)
    here = sim.vehicles()[0].position
    if how.startswith("across"):
        pilot.go("uav1", here, here + (4.0, 0.0, -2.0), here + (8.0, 0.0, -4.0), **limits)
    elif how.startswith("down at"):
        pilot.go("uav1", here + (0.0, 0.0, -30.0), **limits)
    else:
        sim.jump_odometry("uav1", (0.0, 0.0, 3.5))  # it believes it is 3.5 m higher than it is
    pilot.fly(6.0)
    events = pilot.kinds()[1:]
    assert [e[:2] for e in events] == [("collision", "uav1"), ("landed", "uav1")], events
    assert events[0][2].startswith("ground at ") and events[1][2] == "crashed"
    state = sim.vehicles()[0]
    assert not state.alive and not state.airborne and state.position[2] == 0.0


def test_two_uavs_whose_references_meet_both_crash_naming_each_other():
    # uav2 with a larger body: they touch when their centres are 0.4 + 1.0 m apart
    pilot = Pilot(Simulation(scenario(uav={"overrides": {"uav2": {"radius": 1.0}}}), ["uav1", "uav2"], seed=1))
    airborne(pilot)
    airborne_too = pilot.sim.vehicles()[1].position + (0.0, 0.0, FLIGHT)
    pilot.go("uav2", airborne_too)
    pilot.fly(5.0)
    pilot.events.clear()
    through(pilot, (0.0, 5.0), "uav1")
    through(pilot, (0.0, 5.0), "uav2")
    states = pilot.fly(6.0)
    collisions = [e for e in pilot.kinds() if e[0] == "collision"]
    assert [(e[1], e[2].split(" ")[0]) for e in collisions] == [("uav1", "uav2"), ("uav2", "uav1")]
    crash = next(i for i, s in enumerate(states) if not s[0].alive)
    assert not states[crash][1].alive and all(s[1].alive for s in states[:crash])  # the same tick
    gap = np.linalg.norm(states[crash - 1][0].position - states[crash - 1][1].position)
    assert gap > 1.4  # apart a tick before
    assert [e[:2] for e in pilot.kinds() if e[0] == "landed"] == [("landed", "uav1"), ("landed", "uav2")]


def test_a_dead_uav_is_no_obstacle_and_a_grounded_one_touches_nothing():
    sim = Simulation(scenario(starts=[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]), ["uav1", "uav2"], seed=1)
    pilot = Pilot(sim)  # uav2 rests on the ground 0.5 m away: not flying, so no contact
    airborne(pilot)
    sim.kill("uav1")
    pilot.fly(2.0)
    assert pilot.kinds()[1:] == [("landed", "uav1", "crashed")]  # no collision: it was killed, not crashed
    pilot.go("uav2", (0.5, 0.0, FLIGHT))  # takes off through where uav1 lies
    pilot.fly(4.0)
    assert pilot.kinds()[2:] == [("takeoff", "uav2", "")] and sim.vehicles()[1].alive


def test_collisions_are_deterministic():
    def run() -> list:
        pilot = Pilot(Simulation(scenario(), ["uav1", "uav2", "uav3"], seed=5))
        for uav in ("uav1", "uav2", "uav3"):
            pilot.go(uav, pilot.sim.vehicles()[pilot.sim.index(uav)].position + (0.0, 0.0, FLIGHT))
        pilot.fly(4.0)
        # uav1 and uav3 (started 10 m east of it) head for each other, uav2 for the spruce
        for uav, target in (("uav1", (30.0, 0.0)), ("uav2", (40.0, 30.0)), ("uav3", (-30.0, 0.0))):
            through(pilot, target, uav)
        return pilot.events, [np.array([v.position for v in s]) for s in pilot.fly(15.0)]

    (events, states), (again, states_again) = run(), run()
    assert events == again and all(np.array_equal(a, b) for a, b in zip(states, states_again))
    collisions = sorted((e[1], e[2].split(" ")[0]) for _, e in events if e[0] == "collision")
    assert collisions == [("uav1", "uav3"), ("uav2", "spruce"), ("uav3", "uav1")]


def test_the_world_model_has_the_surveyed_obstacles_and_the_truth_the_others():
    sim = Simulation(scenario(uav={"overrides": {"uav2": {"radius": 0.7}}}), ["uav1", "uav2"], seed=1)
    world = world_model(sim, 0, 1, 60.0, {"uav1": "gnss", "uav2": "gnss"})
    assert [o.name for o in world.obstacles] == ["ground", "crate", "spruce", "boulder", "red_pole"]
    assert world.uav_radius == {"uav1": 0.4, "uav2": 0.7}
    truth = ground_truth(sim, 0, 0)
    assert [(o.name, o.kind, o.radius, o.height) for o in truth.obstacles] == [("mast", "cylinder", 0.5, 8.0)]
    assert [o.name for o in sim.obstacles()] == [o.name for o in world.obstacles]
    assert sim.unsurveyed_obstacles() == truth.obstacles


def test_a_uav_radius_must_be_positive():
    from services.simulator.scenario import ScenarioError

    with pytest.raises(ScenarioError, match=r"^crashes.toml: uav.overrides.uav2.radius: must be > 0, got 0.0$"):
        scenario(uav={"overrides": {"uav2": {"radius": 0.0}}})
    with pytest.raises(ScenarioError, match=r"^crashes.toml: uav.radius: must be > 0, got -1.0$"):
        scenario(uav={"radius": -1.0})
