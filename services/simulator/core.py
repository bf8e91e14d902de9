"""Simulator physics: the team's UAVs, the targets, their outcomes, all in mission time.

Pure and deterministic: no clocks, no I/O; mission time only moves through `step`, which
integrates the UAVs in sub-steps of at most MAX_SUBSTEP_S and checks collisions, balloon hits and
drone captures at every sub-step. The pieces live in their own modules: `vehicles.py` (UAV point
masses, odometry with noise and jumps, emergency landing, touching the ground), `targets.py`
(balloons swaying in the wind, scripted drones, destruction and capture), `paths.py` (the drones'
scripted paths), services/lib/imu.py (each UAV's accelerometer and gyroscope, the model the localizer fuses), `contact.py` (distances to the
static obstacles).

Collisions: an alive, airborne UAV whose body (a sphere of its [uav] radius about its centre)
touches a static obstacle (every one of the scenario's, surveyed or not, and every balloon's pole),
or another such UAV, crashes: a ("collision", uav, "<the other party> at <speed> m/s (x, y, z)")
event, for both UAVs of a pair, and the vehicle is dead from that sub-step on (it falls as a
killed one does and collides no more); touching the ground outside a landing is a crash too
(vehicles.py). Balloons and drones are targets, never obstacles. The step flies all its sub-steps,
then checks them together; at the first contact it flies again from the step's start with the
crashed UAVs dead from that sub-step on, until no new contact is found.

Obstacles: `obstacles()` are the world model's (the ground, the surveyed obstacles, the balloons'
poles), `unsurveyed_obstacles()` the ones the mission's survey lacks (ground truth only).

IMU: every step hands each UAV's IMU the true motion of the tick at its knots (the start and the
end of every sub-step: velocity and heading), and `imu(uav)` returns the samples stamped in
[the step's start, its end). Each UAV's IMU draws from its own generator, keyed like the odometry
noise by (seed, UAV index, a salt) and by the mission time its stream starts (0 for a new run,
the resume time for a restarted simulator, which gets new biases), so nothing else that draws
moves its samples. The IMU measures whatever the vehicle does, alive or not: resting on the
ground (landed, or dead and fallen) it reads +g along body z, a dead one falling 0, and the
impact a spike of the velocity it lost within one sub-step.

The UAVs feel no wind and have no attitude dynamics (vehicles.py: a point mass tracking its
reference within the profile's limits).
"""
from __future__ import annotations

import math
import zlib
from collections.abc import Mapping

import numpy as np

from schemas.messages import Obstacle
from services.lib.imu import Imu, ImuParams, ImuSamples, TickMotion
from services.simulator import contact
from services.simulator.specs import NS, POLE_RADIUS, Scenario, pole_name
from services.simulator.targets import Balloons, Drones, TargetState
from services.simulator.vehicles import Fleet, OdometryReading, VehicleState, make_reference

MAX_SUBSTEP_S = 0.01
IMU_SALT = zlib.crc32(b"imu")

__all__ = ["Simulation", "VehicleState", "TargetState", "OdometryReading", "ImuSamples", "MAX_SUBSTEP_S"]


class Simulation:
    def __init__(self, scenario: Scenario, uav_names: list[str], seed: int, imu: ImuParams | None = None,
                 positioning: Mapping[str, str] | None = None) -> None:
        """`positioning`: UAV -> "gnss" or "lidar" as the run resolved it (default: the scenario's)."""
        self.scenario = scenario
        self.uav_names = list(uav_names)
        self.seed = seed
        self.time_ns = 0
        self.ground_z = float(scenario.ground_z)
        self.fleet = Fleet(scenario, self.uav_names, seed, positioning)
        self.balloons = Balloons(scenario)
        self.drones = Drones(scenario, seed)
        self._static, self._unsurveyed = self._static_obstacles()
        self._solids = contact.shapes(self._static + self._unsurveyed)  # what a UAV's body may touch
        self._pending: list[tuple[str, str, str]] = []  # events raised between steps
        self.imu_params = imu if imu is not None else ImuParams()
        self._imus = self._switch_on_imus()
        self._imu_samples = [ImuSamples.empty() for _ in self.uav_names]  # of the last step

    # ------------------------------------------------------------ inputs
    def index(self, uav: str) -> int:
        return self.fleet.index(uav)

    def set_reference(self, uav: str, start_ns: int, dt: float, positions: np.ndarray, headings: np.ndarray,
                      max_speed: float, max_acceleration: float, max_heading_rate: float,
                      max_vertical_speed: float) -> None:
        """Follow this time-sampled reference within the profile (capped by the airframe's envelope)."""
        i = self.index(uav)
        reference = make_reference(uav, start_ns, dt, positions, headings)
        limits = np.array([max_speed, max_acceleration, max_heading_rate, max_vertical_speed], dtype=float)
        self.fleet.set_reference(i, reference, limits)

    def kill(self, uav: str) -> None:
        """The vehicle dies: it falls and stays on the ground."""
        self.fleet.crash(self.index(uav))

    def emergency_land(self, uav: str, reason: str = "") -> None:
        """Descend at a safe rate where it is, ignoring every reference from now on. The next step
        reports ("emergency_landing", uav, reason) unless it was already landing that way."""
        if self.fleet.emergency_land(self.index(uav)):
            self._pending.append(("emergency_landing", uav, reason))

    def hold_position(self, uav: str, reason: str = "") -> None:
        """Hover where it is, ignoring every reference from now on (a flight controller's position
        hold). Reports ("position_hold", uav, reason)."""
        if self.fleet.hold_position(self.index(uav)):
            self._pending.append(("position_hold", uav, reason))

    def jump_odometry(self, uav: str, offset) -> None:
        """Add `offset` (x, y, z, m) to the UAV's odometry error from now on (negate to undo)."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        if not np.all(np.isfinite(offset)):
            raise ValueError(f"{uav}: odometry offset must be finite, got {offset}")
        self.fleet.offset[self.index(uav)] += offset
        self.fleet.jumped = True

    def set_odometry_error(self, uav: str, offset) -> None:
        """The UAV's odometry error is `offset` (x, y, z, m) from now on: its flight controller flies on
        truth + offset (a UAV without GNSS, on its localizer's estimate: services/simulator/positioning.py)."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        if not np.all(np.isfinite(offset)):
            raise ValueError(f"{uav}: odometry offset must be finite, got {offset}")
        self.fleet.offset[self.index(uav)] = offset
        self.fleet.jumped = True

    def resume(self, time_ns: int, vehicles: list, targets: list) -> None:
        """Continue a run from its last ground truth (a restarted simulator): mission time, each
        vehicle's position, velocity, heading, airborne and alive flags, and the targets already
        destroyed or captured. References come again from the planners; odometry offsets and
        emergency landings under way are not in the truth and start afresh."""
        self.time_ns = int(time_ns)
        fleet = self.fleet
        for v in vehicles:
            i = self.index(v.name)
            fleet.position[i] = v.position
            fleet.velocity[i] = v.velocity
            fleet.heading[i] = v.heading
            fleet.airborne[i] = v.airborne
            fleet.alive[i] = v.alive
            fleet.hold[i] = v.position
        gone = {t.id: t for t in targets if t.destroyed}
        self.balloons.destroyed[:] = [tid in gone for tid in self.balloons.ids]
        for k, tid in enumerate(self.drones.ids):
            if tid in gone:  # it falls (or rests) from where the truth last saw it
                self.drones.captured_at[k] = self.time_ns / NS
                self.drones.capture_points[k] = gone[tid].position
        self._imus = self._switch_on_imus()
        self._imu_samples = [ImuSamples.empty() for _ in self.uav_names]

    # ------------------------------------------------------------ physics
    def step(self, dt: float) -> list[tuple[str, str, str]]:
        """Advance by dt seconds; returns the events (kind, subject, detail) in the order they happened."""
        events, self._pending = self._pending, []
        total_ns = int(round(dt * NS)) if dt > 0 else 0
        if total_ns <= 0:  # no mission time passes (dt <= 0 or under half a nanosecond): nothing moves
            self._imu_samples = [ImuSamples.empty() for _ in self.uav_names]
            return events
        substeps = max(1, math.ceil(dt / MAX_SUBSTEP_S - 1e-9))
        h = dt / substeps
        fleet = self.fleet
        times_ns = [self.time_ns + total_ns * k // substeps for k in range(1, substeps + 1)]
        start_velocities, start_headings = fleet.velocity.copy(), fleet.heading.copy()
        start = fleet.snapshot()
        crashes: dict[int, list[tuple[int, tuple[str, str, str]]]] = {}  # sub-step -> [(UAV, its event)]
        while True:
            flight = self._fly(times_ns, h, crashes)
            found = self._first_contacts(flight, after=max(crashes, default=-1))
            if found is None:
                break
            crashes[found[0]] = found[1]
            fleet.restore(start)
        tagged, positions, velocities, headings, alive = flight[:5]
        self._measure_imus(np.array([self.time_ns] + times_ns, dtype=np.int64),
                           np.concatenate([start_velocities[None], velocities]),
                           np.concatenate([start_headings[None], headings]))
        # Targets move on closed forms of time, so hits and captures are checked for all sub-steps at once.
        t = np.array(times_ns, dtype=float) / NS
        tagged += [(k, 1, e) for k, e in self.balloons.check_hits(t, positions, alive, self.uav_names)]
        tagged += [(k, 2, e) for k, e in self.drones.check_captures(t, positions, velocities, alive,
                                                                      self.uav_names)]
        tagged.sort(key=lambda item: item[:2])  # stable: same-source events keep their order
        self.time_ns = times_ns[-1]
        return events + [e for _, _, e in tagged]

    def _fly(self, times_ns: list[int], h: float, crashes: Mapping[int, list]) -> tuple:
        """Integrate the sub-steps, killing `crashes[k]`'s UAVs at the end of sub-step k: (tagged events,
        positions (K, U, 3), velocities (K, U, 3), headings (K, U), alive (K, U) and airborne (K, U)
        during each sub-step)."""
        fleet = self.fleet
        shape = (len(times_ns), len(self.uav_names))
        positions, velocities, headings = np.empty(shape + (3,)), np.empty(shape + (3,)), np.empty(shape)
        alive, airborne = np.empty(shape, dtype=bool), np.empty(shape, dtype=bool)
        tagged: list[tuple[int, int, tuple[str, str, str]]] = []  # (sub-step, source, event)
        for k, t_ns in enumerate(times_ns):
            flown: list[tuple[str, str, str]] = []
            fleet.integrate(t_ns, h, flown)
            tagged += [(k, 0, e) for e in flown]
            positions[k], velocities[k], headings[k] = fleet.position, fleet.velocity, fleet.heading
            alive[k], airborne[k] = fleet.alive, fleet.airborne
            for i, event in crashes.get(k, ()):
                fleet.crash(i)
                tagged.append((k, 3, event))
        return tagged, positions, velocities, headings, alive, airborne

    def _first_contacts(self, flight: tuple, after: int) -> tuple[int, list] | None:
        """The first sub-step after `after` in which a flying UAV's body touches an obstacle or another
        flying UAV, and a collision event for each UAV that does, naming what it touches deepest."""
        _, positions, velocities, _, alive, airborne = flight
        flying = alive & airborne  # (K, U)
        if not flying[after + 1:].any():
            return None
        radius = self.fleet.radius
        count = len(self.uav_names)
        # how far each body is from touching each obstacle, then each other UAV (<= 0: touching)
        obstacles = contact.signed_distance(positions, self._solids) - radius[:, None]  # (K, U, N)
        partners = np.linalg.norm(positions[:, :, None] - positions[:, None], axis=-1) - (radius[:, None] + radius)
        partners = np.where(flying[:, None, :] & ~np.eye(count, dtype=bool), partners, np.inf)  # (K, U, U)
        gaps = np.concatenate([obstacles, partners], axis=-1)
        gaps[~flying] = np.inf
        gaps[:after + 1] = np.inf
        touching = gaps.min(axis=-1, initial=np.inf) <= 0.0  # (K, U)
        if not touching.any():
            return None
        k = int(np.argmax(touching.any(axis=1)))
        names = list(self._solids.names) + self.uav_names
        found = []
        for i in np.flatnonzero(touching[k]):
            party = names[int(np.argmin(gaps[k, i]))]
            x, y, z = positions[k, i]
            found.append((int(i), ("collision", self.uav_names[i], f"{party} at {np.linalg.norm(velocities[k, i]):.1f} "
                                                                    f"m/s ({x:.1f}, {y:.1f}, {z:.1f})")))
        return k, found

    # ------------------------------------------------------------ outputs
    def vehicles(self) -> list[VehicleState]:
        return self.fleet.states()

    def odometry(self, uav: str) -> OdometryReading:
        """What the UAV's own state estimate says now: (position, velocity, heading, covariance 6×6)."""
        return self.fleet.odometry(self.index(uav), self.time_ns)

    def imu(self, uav: str) -> ImuSamples:
        """The UAV's IMU samples over the last step, stamped in [its start, its end), body frame (FLU);
        none before the first step."""
        return self._imu_samples[self.index(uav)]

    def targets(self) -> list[TargetState]:
        t = self.time_ns / NS
        return self.balloons.states(t) + self.drones.states(t)

    def obstacles(self) -> list[Obstacle]:
        """The world model's: the ground, the surveyed obstacles and the balloons' poles."""
        return list(self._static)

    def unsurveyed_obstacles(self) -> list[Obstacle]:
        """The obstacles the mission's survey lacks (ObstacleSpec.surveyed false): ground truth only."""
        return list(self._unsurveyed)

    def _switch_on_imus(self) -> list[Imu]:
        """A fresh IMU per UAV (new biases), its stream starting at the current mission time."""
        start_ns = max(self.time_ns, 0)
        return [Imu(self.imu_params, np.random.default_rng([self.fleet.seed, i, IMU_SALT, start_ns]))
                for i in range(len(self.uav_names))]

    def _measure_imus(self, knots_ns: np.ndarray, velocities: np.ndarray, headings: np.ndarray) -> None:
        """Each UAV's samples of the step just flown, from its knots: stamps (K + 1,), velocities
        (K + 1, UAVs, 3) and headings (K + 1, UAVs) at the step's start and each sub-step's end."""
        self._imu_samples = [imu.samples(TickMotion(knots_ns, velocities[:, i], headings[:, i]))
                             for i, imu in enumerate(self._imus)]

    def _static_obstacles(self) -> tuple[list[Obstacle], list[Obstacle]]:
        """(the world model's, the unsurveyed): see obstacles() and unsurveyed_obstacles()."""
        s = self.scenario
        look = s.appearance
        static = [Obstacle(kind="plane", center=(0.0, 0.0, self.ground_z), name="ground", color=tuple(look.ground))]
        unsurveyed = []
        for o in s.obstacles:
            (static if o.surveyed else unsurveyed).append(Obstacle(
                kind=o.kind, center=tuple(map(float, o.center)), size=tuple(map(float, o.size)),
                radius=float(o.radius), height=float(o.height), name=o.name, color=tuple(o.color or look.obstacle)))
        for tid, b in zip(s.balloon_ids(), s.balloons):
            static.append(Obstacle(kind="cylinder", center=(float(b.pole[0]), float(b.pole[1]), self.ground_z),
                                   radius=POLE_RADIUS, height=float(b.height), name=pole_name(tid),
                                   color=tuple(look.pole)))
        return static, unsurveyed
