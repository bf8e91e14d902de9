"""Targets and their outcomes: balloons swaying on their tethers, scripted intruder drones.

Balloon sway: each balloon's centre sits `tether + radius` (its arm) above the pole top and leans
with the wind like an inverted pendulum held up by its stiffness: tan(lean) = (|w| / LEAN_45_WIND)²
(drag grows with the square of the wind speed). The wind a balloon feels is the scenario's steady
wind plus a gust along it (period gust_period) and a weaker one across it at an incommensurate
period, each balloon with its own phase, so balloons do not sway in unison. Everything is a
closed form of mission time: the horizontal offset never exceeds the arm, whatever the wind.

Outcomes: a balloon is destroyed when a live UAV's centre comes within radius + needle_reach of
the balloon's centre; a drone is captured when a live UAV comes within capture_radius of it at a
relative speed of at most capture_speed. A captured drone drops straight down (the net stops it
horizontally) and rests on the ground; both report destroyed=True in the ground truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.messages import TargetTruth
from services.lib.geometry import GRAVITY
from services.simulator.paths import DronePath
from services.simulator.specs import Scenario

LEAN_45_WIND = 8.0  # m/s of wind at which a balloon leans 45°
CROSS_GUST_SHARE = 0.5  # the cross-wind gust's amplitude relative to the along-wind gust
CROSS_GUST_FREQUENCY = 1.618  # relative to the along-wind gust's; irrational, so the sway never repeats exactly
VELOCITY_STEP_S = 1e-3  # central differences for the balloons' (smooth, closed-form) velocity


@dataclass(frozen=True)
class TargetState:
    id: str
    kind: str  # "balloon" | "drone"
    position: np.ndarray  # (3,)
    velocity: np.ndarray  # (3,)
    radius: float
    destroyed: bool
    color: tuple[int, int, int] = (200, 30, 30)  # sRGB, what a camera sees

    def truth(self) -> TargetTruth:
        return TargetTruth(id=self.id, kind=self.kind, position=_vec(self.position),  # type: ignore[arg-type]
                           velocity=_vec(self.velocity), radius=self.radius, destroyed=self.destroyed,
                           color=self.color)


def _vec(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


class Balloons:
    def __init__(self, scenario: Scenario) -> None:
        s = scenario
        self.ids = s.balloon_ids()
        self.anchors = np.array([[b.pole[0], b.pole[1], s.ground_z + b.height] for b in s.balloons]).reshape(-1, 3)
        self.radii = np.array([b.radius for b in s.balloons], dtype=float)
        self.arms = np.array([b.tether + b.radius for b in s.balloons], dtype=float)
        self.reach = self.radii + s.needle_reach
        self.destroyed = np.zeros(len(self.ids), dtype=bool)
        self.colors = [tuple(b.color or s.appearance.balloon) for b in s.balloons]
        self.phases = 2 * math.pi * ((np.arange(len(self.ids)) * 0.6180339887498949) % 1.0)
        w = s.wind
        self.along = np.array([math.cos(w.direction), math.sin(w.direction)])
        self.across = np.array([-self.along[1], self.along[0]])
        self.wind = w

    def wind_at(self, t: np.ndarray) -> np.ndarray:
        """(S, N, 2) wind each balloon feels at the S mission times t, m/s."""
        w = self.wind
        phase = (2 * math.pi / w.gust_period) * np.asarray(t, dtype=float).reshape(-1, 1)
        along = w.speed + w.gust * np.sin(phase + self.phases)
        across = CROSS_GUST_SHARE * w.gust * np.sin(CROSS_GUST_FREQUENCY * phase + 2 * self.phases)
        return along[..., None] * self.along + across[..., None] * self.across

    def positions(self, t: np.ndarray) -> np.ndarray:
        """(S, N, 3) balloon centres at the S mission times t."""
        wind = self.wind_at(t)
        speed = np.linalg.norm(wind, axis=-1)
        lean = np.arctan((speed / LEAN_45_WIND) ** 2)
        direction = wind / np.maximum(speed, 1e-12)[..., None]
        sideways = (self.arms * np.sin(lean))[..., None] * direction
        return self.anchors + np.concatenate([sideways, (self.arms * np.cos(lean))[..., None]], axis=-1)

    def velocities(self, t: np.ndarray) -> np.ndarray:
        h = VELOCITY_STEP_S
        t = np.asarray(t, dtype=float)
        return (self.positions(t + h) - self.positions(t - h)) / (2 * h)

    def check_hits(self, t: np.ndarray, uav_positions: np.ndarray, alive: np.ndarray, names: list[str]) -> list:
        """Balloons hit during S sub-steps (UAV positions (S, U, 3); alive (U,), or (S, U) when a UAV
        died within the step): [(sub-step, event), ...]."""
        if not len(self.ids):
            return []
        gap = np.linalg.norm(uav_positions[:, :, None, :] - self.positions(t)[:, None, :, :], axis=-1)
        hit = (gap <= self.reach) & np.broadcast_to(alive, gap.shape[:2])[:, :, None]
        hit &= ~self.destroyed  # (S, U, N)
        found = []
        for j in np.flatnonzero(hit.any(axis=(0, 1))):
            k = int(np.argmax(hit[:, :, j].any(axis=1)))
            self.destroyed[j] = True
            found.append((k, ("target_destroyed", self.ids[j], names[int(np.argmax(hit[k, :, j]))])))
        return found

    def states(self, t: float) -> list[TargetState]:
        positions, velocities = self.positions(t)[0], self.velocities(t)[0]
        return [TargetState(tid, "balloon", positions[j], velocities[j], float(self.radii[j]), bool(self.destroyed[j]),
                            self.colors[j]) for j, tid in enumerate(self.ids)]


class Drones:
    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.ids = scenario.drone_ids()
        self.paths = [DronePath(d, scenario, seed, k) for k, d in enumerate(scenario.drones)]
        self.radii = np.array([d.body_radius for d in scenario.drones], dtype=float)
        self.colors = [tuple(d.color or scenario.appearance.drone) for d in scenario.drones]
        self.rest_z = scenario.ground_z + self.radii
        self.capture_radius = scenario.capture_radius
        self.capture_speed = scenario.capture_speed
        self.captured_at = np.full(len(self.ids), math.nan)  # mission time, s
        self.capture_points = np.zeros((len(self.ids), 3))

    @property
    def captured(self) -> np.ndarray:
        return ~np.isnan(self.captured_at)

    def kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S, M, 3) positions and velocities at the S mission times t."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        positions, velocities = np.zeros((len(t), len(self.ids), 3)), np.zeros((len(t), len(self.ids), 3))
        for k, path in enumerate(self.paths):
            if self.captured[k]:
                positions[:, k], velocities[:, k] = self._falling(k, t)
            else:
                positions[:, k], velocities[:, k] = path.state(t)
        return positions, velocities

    def _falling(self, k: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fall = np.maximum(t - self.captured_at[k], 0.0)
        start = self.capture_points[k]
        rest = min(self.rest_z[k], start[2])
        z = start[2] - 0.5 * GRAVITY * fall**2
        landed = z <= rest
        positions = np.tile(start, (len(t), 1))
        positions[:, 2] = np.where(landed, rest, z)
        velocities = np.zeros((len(t), 3))
        velocities[:, 2] = np.where(landed, 0.0, -GRAVITY * fall)
        return positions, velocities

    def check_captures(self, t: np.ndarray, uav_positions: np.ndarray, uav_velocities: np.ndarray,
                       alive: np.ndarray, names: list[str]) -> list:
        """Drones captured during S sub-steps (UAV states (S, U, 3); alive (U,) or (S, U)):
        [(sub-step, event), ...]."""
        if not len(self.ids) or self.captured.all():
            return []
        positions, velocities = self.kinematics(t)
        gap = np.linalg.norm(uav_positions[:, :, None, :] - positions[:, None, :, :], axis=-1)
        relative = np.linalg.norm(uav_velocities[:, :, None, :] - velocities[:, None, :, :], axis=-1)
        caught = (gap <= self.capture_radius) & (relative <= self.capture_speed)
        caught &= np.broadcast_to(alive, gap.shape[:2])[:, :, None]
        caught &= ~self.captured  # (S, U, M)
        found = []
        for j in np.flatnonzero(caught.any(axis=(0, 1))):
            k = int(np.argmax(caught[:, :, j].any(axis=1)))
            self.captured_at[j] = t[k]
            self.capture_points[j] = positions[k, j]
            found.append((k, ("target_captured", self.ids[j], names[int(np.argmax(caught[k, :, j]))])))
        return found

    def states(self, t: float) -> list[TargetState]:
        positions, velocities = self.kinematics(t)
        return [TargetState(tid, "drone", positions[0, k], velocities[0, k], float(self.radii[k]),
                            bool(self.captured[k]), self.colors[k]) for k, tid in enumerate(self.ids)]
