"""Scripted intruder-drone paths: position and velocity as pure functions of mission time.

Waypoint, take-off and random paths are chains of constant-acceleration pieces, so their speed
and acceleration limits hold exactly: along a piece |v| is convex in time (never above its ends)
and |a| is the piece's constant. Waypoint legs are trapezoidal (accelerate, cruise, brake to a
stop at each waypoint). Random manoeuvres pick a goal in their region, a speed and a duration,
and accept the piece only if it, and braking to a stop from its end, keep MARGIN of clearance
from the region's walls; otherwise they brake. That invariant keeps them in bounds forever.
Circles and figure-eights are closed curves flown at constant phase rate; after a take-off the
phase rate ramps up with the acceleration left over by the curve's own, so the limit still holds.
Pieces are generated lazily from a seeded generator: a path is the same whatever times are asked.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import numpy as np

from services.lib.geometry import deepest_point, point_in_polygon
from services.simulator.specs import DroneSpec, Scenario

MARGIN = 0.5  # m of clearance random manoeuvres keep from their region's walls
SPACING = 0.8  # m between clearance samples (< 2·MARGIN, so the path between samples stays inside)
CANDIDATES = 16  # random pieces tried before braking
TAKEOFF_HEADROOM = 0.8  # with a take-off, a curve may use this share of max_acceleration
RANDOM_SALT = 0x5EED_D0E

Piece = tuple[float, np.ndarray, np.ndarray, np.ndarray]  # duration, p0, v0, acceleration


class Region:
    """A vertical prism: a simple polygon between two heights."""

    def __init__(self, polygon: np.ndarray, z_low: float, z_high: float) -> None:
        self.polygon = np.asarray(polygon, dtype=float).reshape(-1, 2)
        self.z_low, self.z_high = float(z_low), float(z_high)
        self._edges = np.roll(self.polygon, -1, axis=0) - self.polygon
        self._edge_lengths2 = np.maximum((self._edges**2).sum(-1), 1e-12)

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance to the nearest wall, floor or ceiling; negative outside."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        rel = pts[:, None, :2] - self.polygon
        t = np.clip((rel * self._edges).sum(-1) / self._edge_lengths2, 0.0, 1.0)
        gap = rel - t[..., None] * self._edges
        edge = np.sqrt((gap**2).sum(-1).min(axis=1))
        horizontal = np.where(point_in_polygon(pts[:, :2], self.polygon), edge, -edge)
        return np.minimum(horizontal, np.minimum(pts[:, 2] - self.z_low, self.z_high - pts[:, 2]))

    def sample(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """`count` points with at least MARGIN clearance (rejection sampling in the bounding box)."""
        lo = np.append(self.polygon.min(axis=0), self.z_low)
        hi = np.append(self.polygon.max(axis=0), self.z_high)
        found = np.empty((0, 3))
        for _ in range(64):
            draws = rng.uniform(lo, hi, size=(4 * count, 3))
            found = np.vstack([found, draws[self.clearance(draws) >= MARGIN]])
            if len(found) >= count:
                break
        return found[:count]

    def middle(self) -> np.ndarray:
        x, y = deepest_point(self.polygon, step=0.5)
        return np.array([x, y, 0.5 * (self.z_low + self.z_high)])


class Segments:
    """Piecewise-constant acceleration, generated on demand from an iterator of pieces; the last
    piece lasts forever (finite paths end with a hold)."""

    def __init__(self, pieces: Iterator[Piece]) -> None:
        self._pieces = pieces
        self._starts: list[float] = []
        self._rows: list[np.ndarray] = []  # p0, v0, a as one (9,) row per piece
        self._end = 0.0
        self._arrays: tuple[np.ndarray, np.ndarray] | None = None
        self._exhausted = False

    def _extend_to(self, t: float) -> None:
        while not self._exhausted and (not self._starts or self._end <= t):
            piece = next(self._pieces, None)
            if piece is None:
                self._exhausted = True
                break
            duration, p0, v0, a = piece
            self._starts.append(self._end)
            self._rows.append(np.concatenate([p0, v0, a]).astype(float))
            self._end += duration
            self._arrays = None

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self._extend_to(float(np.max(t)))
        if self._arrays is None:
            self._arrays = (np.asarray(self._starts), np.vstack(self._rows))
        starts, rows = self._arrays
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        tau = np.maximum(t - starts[k], 0.0)[:, None]
        p0, v0, a = rows[k, 0:3], rows[k, 3:6], rows[k, 6:9]
        return p0 + v0 * tau + 0.5 * a * tau**2, v0 + a * tau


class Curve:
    """A closed curve flown at phase rate omega, from mission time `start`, optionally ramping the
    phase rate up from 0 over `ramp` seconds."""

    def __init__(self, spec: DroneSpec, start: float, ramp: float) -> None:
        self.kind, self.phase, self.start, self.ramp = spec.path, spec.phase, start, ramp
        self.center = np.asarray(spec.center, dtype=float)
        if self.kind == "circle":
            self.a = self.b = float(spec.radius)
            self.omega = spec.speed / spec.radius
        else:
            self.a, self.b = spec.size[0] / 2, spec.size[1] / 2
            self.omega = spec.speed / math.hypot(self.a, 2 * self.b)  # |dp/dθ| peaks at θ = 0

    def shape(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """p(θ), dp/dθ, d²p/dθ² for an array of phases."""
        s, c, z = np.sin(theta), np.cos(theta), np.zeros_like(theta)
        if self.kind == "circle":
            r = self.a
            return (np.stack([r * c, r * s, z], -1), np.stack([-r * s, r * c, z], -1),
                    np.stack([-r * c, -r * s, z], -1))
        s2, c2 = np.sin(2 * theta), np.cos(2 * theta)
        a, b = self.a, self.b
        return (np.stack([a * s, b * s2, z], -1), np.stack([a * c, 2 * b * c2, z], -1),
                np.stack([-a * s, -4 * b * s2, z], -1))

    def full_speed_acceleration(self) -> float:
        theta = np.linspace(0.0, 2 * math.pi, 4097)
        return float(np.linalg.norm(self.shape(theta)[2], axis=1).max()) * self.omega**2 * 1.001

    def point(self, theta: float) -> np.ndarray:
        return self.center + self.shape(np.array([theta]))[0][0]

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tau = np.maximum(t - self.start, 0.0)
        if self.ramp > 0:
            progress = np.where(tau < self.ramp, tau**2 / (2 * self.ramp), tau - self.ramp / 2)
            rate = np.minimum(tau / self.ramp, 1.0)
        else:
            progress, rate = tau, np.ones_like(tau)
        p, dp, _ = self.shape(self.phase + self.omega * progress)
        return self.center + p, dp * (self.omega * rate)[:, None]


class DronePath:
    """Position and velocity of one scripted drone at mission times t (s, scalar or array)."""

    def __init__(self, spec: DroneSpec, scenario: Scenario, seed: int, index: int) -> None:
        self.spec = spec
        ground = scenario.ground_z + spec.body_radius
        self.curve: Curve | None = None
        self.switch = math.inf  # from this time on the curve flies
        if spec.path in ("circle", "figure8"):
            curve = Curve(spec, 0.0, 0.0)
            start = curve.point(spec.phase)
            if spec.takeoff_time is None:
                self.curve, self.switch, prefix = curve, -math.inf, []
            else:
                prefix = _takeoff(start, ground, spec)
                self.switch = spec.takeoff_time + sum(p[0] for p in prefix[1:])
                spare = spec.max_acceleration - curve.full_speed_acceleration()
                self.curve = Curve(spec, self.switch, abs(spec.speed) / spare)
            self.segments = Segments(iter(prefix + [_hold(start)])) if prefix else None
            return
        if spec.path == "waypoints":
            points = np.asarray(spec.waypoints, dtype=float)
            start = points[0]
            route = itertools.cycle(range(len(points))) if spec.loop else iter(range(len(points)))
            next(route)
            body: Iterator[Piece] = _route(points, route, spec.speed, spec.max_acceleration)
        else:
            region = random_region(spec, scenario)
            start = np.asarray(spec.center, dtype=float) if spec.center is not None else region.middle()
            rng = np.random.default_rng([seed % (1 << 63), index, RANDOM_SALT])
            body = _random(start, spec.speed, spec.max_acceleration, region, rng)
        prefix = _takeoff(start, ground, spec) if spec.takeoff_time is not None else []
        self.segments = Segments(itertools.chain(prefix, body))

    def state(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(positions (N, 3), velocities (N, 3)) for an array of N times, or (3,) each for a scalar."""
        times = np.atleast_1d(np.asarray(t, dtype=float))
        p, v = np.zeros((len(times), 3)), np.zeros((len(times), 3))
        on_curve = times >= self.switch
        if on_curve.any():
            p[on_curve], v[on_curve] = self.curve.state(times[on_curve])  # type: ignore[union-attr]
        if (~on_curve).any():
            p[~on_curve], v[~on_curve] = self.segments.state(times[~on_curve])  # type: ignore[union-attr]
        return (p[0], v[0]) if np.ndim(t) == 0 else (p, v)


# ------------------------------------------------------------------ pieces
def _hold(point: np.ndarray, duration: float = math.inf) -> Piece:
    return duration, np.asarray(point, float), np.zeros(3), np.zeros(3)


def _leg(start: np.ndarray, end: np.ndarray, speed: float, acceleration: float) -> list[Piece]:
    """Rest to rest along a straight line: accelerate, cruise, brake (or a triangle when short)."""
    offset = end - start
    length = float(np.linalg.norm(offset))
    if length < 1e-9:
        return []
    unit = offset / length
    peak = min(speed, math.sqrt(length * acceleration))
    ramp_time, ramp_length = peak / acceleration, peak**2 / (2 * acceleration)
    pieces: list[Piece] = [(ramp_time, start, np.zeros(3), acceleration * unit)]
    cruise = length - 2 * ramp_length
    if cruise > 1e-9:
        pieces.append((cruise / peak, start + ramp_length * unit, peak * unit, np.zeros(3)))
    pieces.append((ramp_time, end - ramp_length * unit, peak * unit, -acceleration * unit))
    return pieces


def _takeoff(start: np.ndarray, ground_z: float, spec: DroneSpec) -> list[Piece]:
    """Wait on the ground below the path's start until takeoff_time, then climb to it."""
    on_ground = np.array([start[0], start[1], ground_z])
    return [_hold(on_ground, float(spec.takeoff_time))] + _leg(on_ground, start, spec.climb_speed,
                                                              spec.max_acceleration)


def _route(points: np.ndarray, order: Iterator[int], speed: float, acceleration: float) -> Iterator[Piece]:
    here = points[0]
    for k in order:
        yield from _leg(here, points[k], speed, acceleration)
        here = points[k]
    yield _hold(here)


def random_region(spec: DroneSpec, scenario: Scenario) -> Region:
    if spec.box is not None:
        (x0, y0, z0), (x1, y1, z1) = spec.box
        return Region(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), z0, z1)
    return Region(np.asarray(scenario.target_space()), scenario.ground_z + scenario.min_height,
                  scenario.ground_z + scenario.max_height)


def _random(start: np.ndarray, top_speed: float, acceleration: float, region: Region,
            rng: np.random.Generator) -> Iterator[Piece]:
    p, v = np.asarray(start, dtype=float).copy(), np.zeros(3)
    along = np.linspace(0.0, 1.0, math.ceil(2.0 * top_speed / SPACING) + 2)  # pieces last <= 2 s
    braking = np.linspace(0.0, 1.0, math.ceil(top_speed**2 / (2 * acceleration) / SPACING) + 2)
    goal, pieces_left = None, 0
    while True:
        goals = region.sample(rng, CANDIDATES)
        if goal is not None and pieces_left > 0:
            goals[0] = goal  # pursue the current goal first: long runs, not a jitter around the middle
        durations = rng.uniform(0.4, 2.0, size=len(goals))
        speeds = rng.uniform(0.3, 1.0, size=len(goals)) * top_speed
        heading = goals - p
        wanted = heading / np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9) * speeds[:, None]
        acc = (wanted - v) / durations[:, None]
        norm = np.linalg.norm(acc, axis=1, keepdims=True)
        acc *= np.minimum(1.0, acceleration / np.maximum(norm, 1e-12))  # end speed stays a convex mix
        tau = durations[:, None, None] * along[None, :, None]
        samples = p + v * tau + 0.5 * acc[:, None, :] * tau**2
        v_end = v + acc * durations[:, None]
        stop = (v_end * np.linalg.norm(v_end, axis=1, keepdims=True) / (2 * acceleration))
        brake_samples = samples[:, -1:, :] + stop[:, None, :] * braking[None, :, None]
        both = np.concatenate([samples, brake_samples], axis=1)
        ok = (region.clearance(both.reshape(-1, 3)).reshape(len(goals), -1) >= MARGIN).all(axis=1)
        if ok.any():
            k = int(np.argmax(ok))
            if k > 0 or goal is None or pieces_left <= 0:
                goal, pieces_left = goals[k], int(rng.integers(2, 6))
            pieces_left = 0 if np.linalg.norm(goals[k] - samples[k, -1]) < 2.0 else pieces_left - 1
            yield float(durations[k]), p, v, acc[k]
            p, v = samples[k, -1].copy(), v_end[k].copy()
            continue
        goal = None
        speed = float(np.linalg.norm(v))
        if speed < 1e-9:
            yield 0.5, p, v, np.zeros(3)
            continue
        brake = -v / speed * acceleration
        yield speed / acceleration, p, v, brake
        p, v = p + v * speed / acceleration / 2, np.zeros(3)
