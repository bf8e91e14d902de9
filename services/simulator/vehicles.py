"""The team's UAVs: point masses tracking their trajectory references, and their odometry.

Control: a PD law on the time-sampled reference with the reference's acceleration fed forward, a =
a_ref + kp (p_ref - p̂) + kd (v_ref - v), as a flight controller's trajectory setpoint carries it
(PX4's offboard trajectory setpoint, MRS's MPC tracker), with the position term's velocity demand
capped to what can still be braked within the acceleration limit (so a far-away step does not
overshoot). v_ref and a_ref are the samples' central differences, interpolated between samples.
Without the feed-forward the vehicle lagged every acceleration of its reference and overshot every
stop: 2.4 m past the end of a 20 m goto at 5 m/s and 1.5 m/s², 3.1 m at 8.3 m/s and 3 m/s², into
whatever a plan had stopped short of (with it: 0.01 m and none). The acceleration norm is clipped to
max_acceleration, then horizontal speed to max_speed and vertical speed to max_vertical_speed
(together the Euclidean projection onto a convex set, so the clip never adds acceleration). Heading
turns at most max_heading_rate towards the reference heading. The limits are the reference's
profile, capped by the airframe's envelope (the larger of the scenario's sweeping and attack
profiles). A vehicle resting on the ground does not slide; a killed one falls ballistically and
stops.

Odometry: p̂ = p + offset + noise. `jump_odometry` adds to the offset (a relocalisation error);
an airborne UAV's controller closes its loop on p + offset, so after a jump the vehicle really
moves by -offset while its odometry keeps matching the reference, as a real one would. The
white noise (position and heading, σ from the scenario) is drawn from a generator keyed by
(seed, UAV, mission time): the same for a run whoever asks and how often.

Emergency landing ignores the reference for good: brake horizontally and descend at
EMERGENCY_DESCENT (capped by the vertical limit) until on the ground.

Touching the ground: an airborne UAV that comes down to LANDED_HEIGHT has landed when it was
landing, and crashed otherwise. Landing is an emergency landing, or a reference at the ground
(at most LANDING_REFERENCE_HEIGHT above it) met gently (at most LANDING_VERTICAL_SPEED down and
LANDING_HORIZONTAL_SPEED across); anything else is a ("collision", uav, "ground at ...") event, and
the vehicle is dead from then on, as one killed. Obstacles and partners are the simulation's to
check (core.py), since they need the whole team's sub-steps at once.

Offboard loss: an airborne UAV that has received no trajectory reference for OFFBOARD_TIMEOUT_S
(its planner re-sends the current one every 2 s) while that reference still moves it brakes and
holds its position until the next one arrives, as a flight controller's offboard failsafe does
(PX4's COM_OF_LOSS_T), instead of flying a dead planner's last reference to its end. (A reference
flown to its end holds its last point anyway.)
"""
from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from schemas.messages import VehicleTruth
from services.lib.geometry import GRAVITY
from services.simulator.checks import start_poses
from services.simulator.specs import NS, Scenario

KP = 2.0
KD = 2.5
BRAKING_MARGIN = 0.8  # fraction of max_acceleration the approach speed cap plans to brake with
TAKEOFF_HEIGHT = 0.2  # above ground: airborne
LANDED_HEIGHT = 0.05  # above ground: landed again (hysteresis against chatter)
EMERGENCY_DESCENT = 1.0  # m/s
OFFBOARD_TIMEOUT_S = 5.0  # s without a trajectory reference before an airborne UAV holds its position
LANDING_REFERENCE_HEIGHT = 0.3  # m above ground: a reference this low is a landing
LANDING_VERTICAL_SPEED = 2.5  # m/s: a landing touches down no faster than this, ...
LANDING_HORIZONTAL_SPEED = 1.0  # ... and drifts no faster than this; else it is a crash
MIN_VARIANCE = 1e-6  # reported for a noiseless estimate, so the covariance stays invertible
ODOMETRY_SALT = zlib.crc32(b"odometry")


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


class OdometryReading(NamedTuple):
    position: np.ndarray  # (3,) estimate, m
    velocity: np.ndarray  # (3,) m/s
    heading: float  # rad, in [-π, π)
    covariance: np.ndarray  # (6, 6) over x, y, z, roll, pitch, yaw


def _vec(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


@dataclass
class _Reference:
    start_ns: int
    dt: float
    positions: np.ndarray  # (N, 3)
    velocities: np.ndarray  # (N, 3) at each sample: central differences (one-sided at the ends)
    accelerations: np.ndarray  # (N, 3) at each sample: second differences (the neighbour's at the ends)
    headings: np.ndarray  # (N,) unwrapped, so interpolation turns the short way

    def end_ns(self) -> int:
        return self.start_ns + int(round((len(self.positions) - 1) * self.dt * NS))

    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(position, velocity, acceleration, heading) at t, held still before and after the samples."""
        u = (t_ns - self.start_ns) / NS / self.dt if self.dt > 0 else 0.0
        last = len(self.positions) - 1
        if u < 0 or last == 0:
            return self.positions[0], np.zeros(3), np.zeros(3), float(self.headings[0])
        if u >= last:
            return self.positions[last], np.zeros(3), np.zeros(3), float(self.headings[last])
        i = int(u)
        f = u - i

        def between(values: np.ndarray):
            return values[i] + f * (values[i + 1] - values[i])

        return between(self.positions), between(self.velocities), between(self.accelerations), \
            float(between(self.headings))


class Fleet:
    def __init__(self, scenario: Scenario, names: list[str], seed: int,
                 positioning: Mapping[str, str] | None = None) -> None:
        """`positioning`: UAV -> "gnss" or "lidar" as the run resolved it (default: the scenario's)."""
        self.names = list(names)
        self.seed = seed % (1 << 63)
        self.ground_z = float(scenario.ground_z)
        count = len(self.names)
        starts = np.asarray(start_poses(scenario, count), dtype=float)
        self.position = np.column_stack([starts[:, 0], starts[:, 1], np.full(count, self.ground_z)])
        self.velocity = np.zeros((count, 3))
        self.heading = starts[:, 2].copy()
        self.airborne = np.zeros(count, dtype=bool)
        self.alive = np.ones(count, dtype=bool)
        self.emergency = np.zeros(count, dtype=bool)
        self.holding = np.zeros(count, dtype=bool)  # position hold by the flight controller
        self.hold = self.position.copy()  # reference until the first trajectory arrives
        self.references: list[_Reference | None] = [None] * count
        self.now_ns = 0  # mission time of the last integration step
        self.reference_at = np.zeros(count, dtype=np.int64)  # when each UAV's last reference arrived
        specs = [scenario.uav_spec(n) for n in self.names]
        # Columns: max_speed, max_acceleration, max_heading_rate, max_vertical_speed.
        self.envelope = np.array([_limits(s.envelope()) for s in specs]).reshape(count, 4)
        self.limits = np.array([_limits(s.sweeping) for s in specs]).reshape(count, 4)
        # the GNSS odometry's white noise; a UAV without GNSS publishes its localizer's belief instead
        # (services/simulator/positioning.py), which carries its own error: no noise about the truth
        gnss = [((positioning or {}).get(n) or scenario.positioning(n)) == "gnss" for n in self.names]
        self.sigmas = np.array([[s.odometry_position_sigma, s.odometry_attitude_sigma] if with_gnss else [0.0, 0.0]
                                for s, with_gnss in zip(specs, gnss)]).reshape(-1, 2)
        self.offset = np.zeros((count, 3))
        self.jumped = False  # any odometry offset yet (skips work in the common case)
        self.radius = np.array([s.radius for s in specs], dtype=float)  # the body's sphere, m

    def index(self, uav: str) -> int:
        try:
            return self.names.index(uav)
        except ValueError:
            raise KeyError(f"unknown UAV {uav!r} (team: {', '.join(self.names)})") from None

    # ------------------------------------------------------------ inputs
    def set_reference(self, i: int, reference: _Reference, limits: np.ndarray) -> None:
        if self.holding[i]:
            return
        self.references[i] = reference
        self.reference_at[i] = self.now_ns
        self.limits[i] = np.minimum(np.maximum(limits, 0.0), self.envelope[i])

    def hold_position(self, i: int) -> bool:
        """Hover where it is from now on; False when already holding, landing or dead."""
        if self.holding[i] or self.emergency[i] or not self.alive[i]:
            return False
        self.holding[i] = True
        self.hold[i] = self.position[i]
        self.references[i] = None
        return True

    def crash(self, i: int) -> None:
        """The vehicle is dead from now on: it falls and stays on the ground."""
        self.alive[i] = False

    def emergency_land(self, i: int) -> bool:
        """Start an emergency landing; False when already landing that way or dead."""
        if self.emergency[i] or not self.alive[i]:
            return False
        self.emergency[i] = True
        return True

    # ------------------------------------------------------------ physics
    def integrate(self, t_ns: int, h: float, events: list) -> None:
        count = len(self.names)
        self.now_ns = t_ns
        self._offboard_failsafe(t_ns, events)
        p_ref = self.hold.copy()
        v_ref, a_ref = np.zeros((count, 3)), np.zeros((count, 3))
        heading_ref = self.heading.copy()
        for i, ref in enumerate(self.references):
            if ref is not None:
                p_ref[i], v_ref[i], a_ref[i], heading_ref[i] = ref.at(t_ns)
        max_speed, max_acc, max_rate, max_vz = self.limits.T

        error = p_ref - self.position
        if self.jumped:
            error -= self.offset * self.airborne[:, None]  # the controller flies on its estimate
        distance = np.linalg.norm(error, axis=1)
        # The PD law as a velocity demand: v_ref + (kp/kd)·e, with |(kp/kd)·e| capped by braking distance.
        pull = (KP / KD) * distance
        brake_speed = np.sqrt(2.0 * BRAKING_MARGIN * max_acc * distance)
        scale = np.where(pull > brake_speed, brake_speed / np.maximum(pull, 1e-12), 1.0)
        acc = a_ref + KP * error * scale[:, None] + KD * (v_ref - self.velocity)
        if self.emergency.any():
            landing = self.emergency
            descent = np.zeros((count, 3))
            descent[:, 2] = -np.minimum(EMERGENCY_DESCENT, max_vz)
            acc[landing] = KD * (descent - self.velocity)[landing]
            heading_ref[landing] = self.heading[landing]
        acc_norm = np.linalg.norm(acc, axis=1)
        acc *= np.where(acc_norm > max_acc, max_acc / np.maximum(acc_norm, 1e-12), 1.0)[:, None]

        dead = ~self.alive
        acc[dead] = (0.0, 0.0, -GRAVITY)
        velocity = self.velocity + acc * h
        alive = self.alive
        horizontal = np.linalg.norm(velocity[:, :2], axis=1)
        shrink = np.where(alive & (horizontal > max_speed), max_speed / np.maximum(horizontal, 1e-12), 1.0)
        velocity[:, :2] *= shrink[:, None]
        velocity[alive, 2] = np.clip(velocity[alive, 2], -max_vz[alive], max_vz[alive])
        position = self.position + velocity * h
        touching = velocity.copy()  # what a vehicle meets the ground with, before the ground stops it

        on_ground = position[:, 2] <= self.ground_z
        resting = on_ground & ~self.airborne
        position[on_ground, 2] = self.ground_z
        velocity[on_ground, 2] = np.maximum(velocity[on_ground, 2], 0.0)
        velocity[resting, :2] = 0.0  # resting on the ground: no sliding
        position[resting, :2] = self.position[resting, :2]
        velocity[on_ground & dead] = 0.0

        turn = (heading_ref - self.heading + np.pi) % (2 * np.pi) - np.pi
        step = np.clip(turn, -max_rate * h, max_rate * h)
        self.heading = np.where(alive, (self.heading + step + np.pi) % (2 * np.pi) - np.pi, self.heading)
        self.position, self.velocity = position, velocity

        height = position[:, 2] - self.ground_z
        for i, name in enumerate(self.names):
            if not self.airborne[i] and height[i] > TAKEOFF_HEIGHT:
                self.airborne[i] = True
                events.append(("takeoff", name, ""))
            elif self.airborne[i] and height[i] <= LANDED_HEIGHT:
                self.airborne[i] = False
                self.hold[i] = position[i]
                if self.alive[i] and not self._landing(i, p_ref[i], touching[i]):
                    self.crash(i)
                    events.append(("collision", name, f"ground at {np.linalg.norm(touching[i]):.1f} m/s "
                                                      f"({position[i, 0]:.1f}, {position[i, 1]:.1f}, "
                                                      f"{position[i, 2]:.1f})"))
                detail = "crashed" if not self.alive[i] else "emergency" if self.emergency[i] else ""
                events.append(("landed", name, detail))

    def _landing(self, i: int, reference: np.ndarray, velocity: np.ndarray) -> bool:
        """Whether touching the ground with this velocity, on this reference, is a landing."""
        if self.emergency[i]:
            return True
        return bool(reference[2] <= self.ground_z + LANDING_REFERENCE_HEIGHT
                    and abs(velocity[2]) <= LANDING_VERTICAL_SPEED
                    and math.hypot(velocity[0], velocity[1]) <= LANDING_HORIZONTAL_SPEED)

    def snapshot(self) -> tuple:
        """What integrating changes, to fly the same sub-steps again from here (`restore`)."""
        return (self.position.copy(), self.velocity.copy(), self.heading.copy(), self.airborne.copy(),
                self.alive.copy(), self.hold.copy(), list(self.references), self.now_ns)

    def restore(self, state: tuple) -> None:
        position, velocity, heading, airborne, alive, hold, references, now_ns = state
        self.position, self.velocity, self.heading = position.copy(), velocity.copy(), heading.copy()
        self.airborne, self.alive, self.hold = airborne.copy(), alive.copy(), hold.copy()
        self.references, self.now_ns = list(references), now_ns

    def _offboard_failsafe(self, t_ns: int, events: list) -> None:
        for i, name in enumerate(self.names):
            reference = self.references[i]
            if reference is not None and self.airborne[i] and t_ns < reference.end_ns() and \
                    t_ns - self.reference_at[i] > OFFBOARD_TIMEOUT_S * NS:
                # brake to a stop and hold there (where its own estimate says), not back to where it was
                speed = float(np.linalg.norm(self.velocity[i]))
                stopping = self.velocity[i] * speed / (2.0 * BRAKING_MARGIN * max(self.limits[i][1], 1e-9))
                self.references[i] = None
                self.hold[i] = self.position[i] + self.offset[i] + stopping
                events.append(("offboard_lost", name, f"no trajectory reference for {OFFBOARD_TIMEOUT_S:g} s: "
                                                      f"position hold until the next"))

    # ------------------------------------------------------------ outputs
    def odometry(self, i: int, t_ns: int) -> OdometryReading:
        position_sigma, attitude_sigma = self.sigmas[i]
        rng = np.random.default_rng([self.seed, i, ODOMETRY_SALT, max(int(t_ns), 0)])
        noise = rng.standard_normal(4)
        position = self.position[i] + self.offset[i] + position_sigma * noise[:3]
        heading = (self.heading[i] + attitude_sigma * noise[3] + math.pi) % (2 * math.pi) - math.pi
        variances = np.repeat(np.maximum([position_sigma**2, attitude_sigma**2], MIN_VARIANCE), 3)
        return OdometryReading(position, self.velocity[i].copy(), float(heading), np.diag(variances))

    def states(self) -> list[VehicleState]:
        return [VehicleState(name, self.position[i].copy(), self.velocity[i].copy(), float(self.heading[i]),
                             bool(self.airborne[i]), bool(self.alive[i])) for i, name in enumerate(self.names)]


def _limits(profile) -> list[float]:
    return [profile.max_speed, profile.max_acceleration, profile.max_heading_rate, profile.max_vertical_speed]


MIN_REFERENCE_DT, MAX_REFERENCE_DT = 1e-6, 1e6  # s between a reference's samples: far beyond any planner's


def make_reference(uav: str, start_ns: int, dt: float, positions: np.ndarray, headings: np.ndarray) -> _Reference:
    positions = np.array(positions, dtype=float).reshape(-1, 3)
    headings = np.array(headings, dtype=float).reshape(-1)
    if len(positions) == 0 or len(headings) != len(positions):
        raise ValueError(f"{uav}: reference needs N >= 1 positions and N headings, "
                         f"got {len(positions)} and {len(headings)}")
    if len(positions) > 1 and not MIN_REFERENCE_DT <= dt <= MAX_REFERENCE_DT:  # NaN too
        # beyond these dt² overflows (an exception) or underflows to 0 (infinite accelerations)
        raise ValueError(f"{uav}: reference dt must lie in [{MIN_REFERENCE_DT:g}, {MAX_REFERENCE_DT:g}] s, got {dt}")
    if len(positions) == 1:
        dt = 0.0  # one sample has no period: whatever came (NaN, inf) must not reach end_ns
    if not np.all(np.isfinite(positions)) or not np.all(np.isfinite(headings)):
        raise ValueError(f"{uav}: reference contains non-finite values")
    velocities, accelerations = np.zeros_like(positions), np.zeros_like(positions)
    if len(positions) > 1:
        velocities = np.gradient(positions, dt, axis=0, edge_order=1)
    if len(positions) > 2:
        accelerations[1:-1] = (positions[2:] - 2.0 * positions[1:-1] + positions[:-2]) / dt**2
        accelerations[0], accelerations[-1] = accelerations[1], accelerations[-2]
    return _Reference(int(start_ns), float(dt), positions, velocities, accelerations, np.unwrap(headings))
