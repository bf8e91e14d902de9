"""Simulator physics: UAV point masses tracking their trajectory references, targets, destruction.

First version (walking skeleton). Pure and deterministic: no clocks, no I/O; mission time only
moves through `step`. Later issues deepen it: drone capture, scripted drone paths, collisions
with obstacles, a fault schedule (`kill` is the first hook), wind and attitude dynamics.

Vehicle model: a point mass commanded by a PD law on the time-sampled reference,
a = kp (p_ref - p) + kd (v_ref - v), with the position term's velocity demand capped to what can
still be braked within the acceleration limit (so a far-away step does not overshoot). The
acceleration norm is clipped to max_acceleration, then horizontal speed to max_speed and vertical
speed to max_vertical_speed (together the Euclidean projection onto a convex set, so the clip
never adds acceleration). Heading turns at most max_heading_rate towards the reference heading.
A vehicle resting on the ground does not slide; a killed one falls ballistically and stops.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.messages import Obstacle, TargetTruth, VehicleTruth
from services.simulator.scenario import POLE_RADIUS, Scenario, start_poses

KP = 2.0
KD = 2.5
BRAKING_MARGIN = 0.8  # fraction of max_acceleration the approach speed cap plans to brake with
MAX_SUBSTEP_S = 0.01
TAKEOFF_HEIGHT = 0.2  # above ground: airborne
LANDED_HEIGHT = 0.05  # above ground: landed again (hysteresis against chatter)
GRAVITY = 9.81
NS = 1_000_000_000


@dataclass(frozen=True)
class VehicleState:
    name: str
    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    heading: float
    airborne: bool
    alive: bool

    def truth(self) -> VehicleTruth:
        return VehicleTruth(name=self.name, position=_vec(self.position), velocity=_vec(self.velocity),
                            heading=self.heading, airborne=self.airborne, alive=self.alive)


@dataclass(frozen=True)
class TargetState:
    id: str
    kind: str  # "balloon" | "drone"
    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    radius: float
    destroyed: bool

    def truth(self) -> TargetTruth:
        return TargetTruth(id=self.id, kind=self.kind, position=_vec(self.position),  # type: ignore[arg-type]
                           velocity=_vec(self.velocity), radius=self.radius, destroyed=self.destroyed)


def _vec(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


@dataclass
class _Reference:
    start_ns: int
    dt: float
    positions: np.ndarray  # (N, 3)
    velocities: np.ndarray  # (N, 3): velocity on the interval starting at sample i (0 for the last)
    headings: np.ndarray  # (N,) unwrapped, so interpolation turns the short way

    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, float]:
        u = (t_ns - self.start_ns) / NS / self.dt if self.dt > 0 else 0.0
        last = len(self.positions) - 1
        if u < 0 or last == 0:
            return self.positions[0], np.zeros(3), float(self.headings[0])
        if u >= last:
            return self.positions[last], np.zeros(3), float(self.headings[last])
        i = int(u)
        f = u - i
        position = self.positions[i] + f * (self.positions[i + 1] - self.positions[i])
        heading = self.headings[i] + f * (self.headings[i + 1] - self.headings[i])
        return position, self.velocities[i], float(heading)


class Simulation:
    def __init__(self, scenario: Scenario, uav_names: list[str], seed: int) -> None:
        self.scenario = scenario
        self.uav_names = list(uav_names)
        self.rng = np.random.default_rng(seed)  # for later noisy / random features
        self.time_ns = 0
        self.ground_z = float(scenario.ground_z)
        count = len(self.uav_names)
        starts = np.asarray(start_poses(scenario, count), dtype=float)
        self._position = np.column_stack([starts[:, 0], starts[:, 1], np.full(count, self.ground_z)])
        self._velocity = np.zeros((count, 3))
        self._heading = starts[:, 2].copy()
        self._airborne = np.zeros(count, dtype=bool)
        self._alive = np.ones(count, dtype=bool)
        self._hold = self._position.copy()  # reference until the first trajectory arrives
        self._references: list[_Reference | None] = [None] * count
        # Columns: max_speed, max_acceleration, max_heading_rate, max_vertical_speed.
        self._limits = np.tile([5.0, 1.5, 1.0, 2.0], (count, 1))

        self._balloon_ids = scenario.balloon_ids()
        self._balloon_centres = np.array(
            [[b.pole[0], b.pole[1], self.ground_z + b.height + b.radius] for b in scenario.balloons]
        ).reshape(-1, 3)
        self._balloon_radii = np.array([b.radius for b in scenario.balloons], dtype=float)
        self._balloon_destroyed = np.zeros(len(scenario.balloons), dtype=bool)
        self._drone_ids = scenario.drone_ids()
        self._static = self._static_obstacles()

    # ------------------------------------------------------------ inputs
    def index(self, uav: str) -> int:
        try:
            return self.uav_names.index(uav)
        except ValueError:
            raise KeyError(f"unknown UAV {uav!r} (team: {', '.join(self.uav_names)})") from None

    def set_reference(self, uav: str, start_ns: int, dt: float, positions: np.ndarray, headings: np.ndarray,
                      max_speed: float, max_acceleration: float, max_heading_rate: float,
                      max_vertical_speed: float) -> None:
        i = self.index(uav)
        positions = np.array(positions, dtype=float).reshape(-1, 3)
        headings = np.array(headings, dtype=float).reshape(-1)
        if len(positions) == 0 or len(headings) != len(positions):
            raise ValueError(f"{uav}: reference needs N >= 1 positions and N headings, "
                             f"got {len(positions)} and {len(headings)}")
        if len(positions) > 1 and not dt > 0:
            raise ValueError(f"{uav}: reference dt must be > 0, got {dt}")
        if not np.all(np.isfinite(positions)) or not np.all(np.isfinite(headings)):
            raise ValueError(f"{uav}: reference contains non-finite values")
        velocities = np.zeros_like(positions)
        if len(positions) > 1:
            velocities[:-1] = np.diff(positions, axis=0) / dt
        self._references[i] = _Reference(int(start_ns), float(dt), positions, velocities, np.unwrap(headings))
        self._limits[i] = [max(max_speed, 0.0), max(max_acceleration, 0.0),
                           max(max_heading_rate, 0.0), max(max_vertical_speed, 0.0)]

    def kill(self, uav: str) -> None:
        self._alive[self.index(uav)] = False

    # ------------------------------------------------------------ physics
    def step(self, dt: float) -> list[tuple[str, str, str]]:
        """Advance by dt seconds; returns the events (kind, subject, detail) in the order they happened."""
        if dt <= 0:
            return []
        total_ns = int(round(dt * NS))
        substeps = max(1, math.ceil(dt / MAX_SUBSTEP_S - 1e-9))
        h = dt / substeps
        start_ns = self.time_ns
        events: list[tuple[str, str, str]] = []
        for k in range(1, substeps + 1):
            t_ns = start_ns + total_ns * k // substeps
            self._integrate(t_ns, h, events)
            self.time_ns = t_ns
            self._check_balloons(t_ns, events)
        self.time_ns = start_ns + total_ns
        return events

    def _integrate(self, t_ns: int, h: float, events: list) -> None:
        count = len(self.uav_names)
        p_ref = self._hold.copy()
        v_ref = np.zeros((count, 3))
        heading_ref = self._heading.copy()
        for i, ref in enumerate(self._references):
            if ref is not None:
                p_ref[i], v_ref[i], heading_ref[i] = ref.at(t_ns)
        max_speed, max_acc, max_rate, max_vz = self._limits.T

        error = p_ref - self._position
        distance = np.linalg.norm(error, axis=1)
        # The PD law as a velocity demand: v_ref + (kp/kd)·e, with |(kp/kd)·e| capped by braking distance.
        pull = (KP / KD) * distance
        brake_speed = np.sqrt(2.0 * BRAKING_MARGIN * max_acc * distance)
        scale = np.where(pull > brake_speed, brake_speed / np.maximum(pull, 1e-12), 1.0)
        acc = KP * error * scale[:, None] + KD * (v_ref - self._velocity)
        acc_norm = np.linalg.norm(acc, axis=1)
        acc *= np.where(acc_norm > max_acc, max_acc / np.maximum(acc_norm, 1e-12), 1.0)[:, None]

        dead = ~self._alive
        acc[dead] = (0.0, 0.0, -GRAVITY)
        velocity = self._velocity + acc * h
        alive = self._alive
        horizontal = np.linalg.norm(velocity[:, :2], axis=1)
        shrink = np.where(alive & (horizontal > max_speed), max_speed / np.maximum(horizontal, 1e-12), 1.0)
        velocity[:, :2] *= shrink[:, None]
        velocity[alive, 2] = np.clip(velocity[alive, 2], -max_vz[alive], max_vz[alive])
        position = self._position + velocity * h

        on_ground = position[:, 2] <= self.ground_z
        position[on_ground, 2] = self.ground_z
        velocity[on_ground, 2] = np.maximum(velocity[on_ground, 2], 0.0)
        velocity[on_ground & ~self._airborne, :2] = 0.0  # resting on the ground: no sliding
        position[on_ground & ~self._airborne, :2] = self._position[on_ground & ~self._airborne, :2]
        velocity[on_ground & dead] = 0.0

        turn = (heading_ref - self._heading + np.pi) % (2 * np.pi) - np.pi
        step = np.clip(turn, -max_rate * h, max_rate * h)
        self._heading = np.where(alive, (self._heading + step + np.pi) % (2 * np.pi) - np.pi, self._heading)
        self._position, self._velocity = position, velocity

        height = position[:, 2] - self.ground_z
        for i, name in enumerate(self.uav_names):
            if not self._airborne[i] and height[i] > TAKEOFF_HEIGHT:
                self._airborne[i] = True
                events.append(("takeoff", name, ""))
            elif self._airborne[i] and height[i] <= LANDED_HEIGHT:
                self._airborne[i] = False
                self._hold[i] = position[i]
                events.append(("landed", name, "" if self._alive[i] else "crashed"))

    def _check_balloons(self, t_ns: int, events: list) -> None:
        if not len(self._balloon_radii):
            return
        reach = self._balloon_radii + self.scenario.needle_reach
        gap = np.linalg.norm(self._position[:, None, :] - self._balloon_centres[None, :, :], axis=2)
        hit = (gap <= reach[None, :]) & self._alive[:, None] & ~self._balloon_destroyed[None, :]
        for j in np.flatnonzero(hit.any(axis=0)):
            self._balloon_destroyed[j] = True
            uav = self.uav_names[int(np.argmax(hit[:, j]))]  # the first UAV in team order on a tie
            events.append(("target_destroyed", self._balloon_ids[j], uav))

    # ------------------------------------------------------------ outputs
    def vehicles(self) -> list[VehicleState]:
        return [
            VehicleState(name, self._position[i].copy(), self._velocity[i].copy(), float(self._heading[i]),
                         bool(self._airborne[i]), bool(self._alive[i]))
            for i, name in enumerate(self.uav_names)
        ]

    def targets(self) -> list[TargetState]:
        states = [
            TargetState(tid, "balloon", self._balloon_centres[j].copy(), np.zeros(3),
                        float(self._balloon_radii[j]), bool(self._balloon_destroyed[j]))
            for j, tid in enumerate(self._balloon_ids)
        ]
        t = self.time_ns / NS
        for tid, drone in zip(self._drone_ids, self.scenario.drones):
            angle = drone.phase + drone.speed / drone.radius * t
            cx, cy, cz = drone.center
            position = np.array([cx + drone.radius * math.cos(angle), cy + drone.radius * math.sin(angle), cz])
            velocity = np.array([-drone.speed * math.sin(angle), drone.speed * math.cos(angle), 0.0])
            states.append(TargetState(tid, "drone", position, velocity, float(drone.body_radius), False))
        return states

    def obstacles(self) -> list[Obstacle]:
        return list(self._static)

    def _static_obstacles(self) -> list[Obstacle]:
        s = self.scenario
        static = [Obstacle(kind="plane", center=(0.0, 0.0, self.ground_z), name="ground")]
        for o in s.obstacles:
            static.append(Obstacle(kind=o.kind, center=tuple(map(float, o.center)), size=tuple(map(float, o.size)),
                                   radius=float(o.radius), height=float(o.height), name=o.name))
        for tid, b in zip(self._balloon_ids, s.balloons):
            static.append(Obstacle(kind="cylinder", center=(float(b.pole[0]), float(b.pole[1]), self.ground_z),
                                   radius=POLE_RADIUS, height=float(b.height), name=f"{tid}_pole"))
        return static
