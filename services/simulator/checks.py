"""Value checks of a type-checked scenario, each failing with a one-line ScenarioError naming the field.

The rules are documented in `services/simulator/scenario.py`; the path-shape checks reuse the
path code itself (`paths.py`), so what is checked is exactly what will fly.
"""
from __future__ import annotations

import math
import re

import numpy as np

from schemas import keys
from schemas.catalogue import uav_topics
from services.lib.runtime.delivery import MAX_DELAY_S
from services.lib.geometry import deepest_point, point_in_polygon, polygon_self_intersection, signed_area
from services.lib.lidar.models import lidar_model
from services.simulator import paths
from services.simulator.specs import (
    MAX_UAVS,
    PATH_FIELDS,
    PATH_REQUIRED,
    DroneSpec,
    ObstacleSpec,
    Point2,
    ProfileSpec,
    Scenario,
    ScenarioError,
    Vec3,
)

START_SPACING = 10.0  # m: twice the job manager's safety distance, so a take-off is no separation violation
FAULT_SERVICES = keys.UAV_SERVICES + (keys.ORACLE,)
SERVICE_FAULTS = ("kill", "freeze", "slow", "clock_jump")  # the kinds that may target one service
_UAV_NAME = re.compile(r"^uav([1-9][0-9]*)$")


def validated(s: Scenario) -> Scenario:
    _positive(s.duration, "duration")
    if s.uavs not in (2, 3):
        raise ScenarioError(f"uavs: must be 2 or 3, got {s.uavs}")
    if not s.min_height < s.max_height:
        raise ScenarioError(f"min_height: must be below max_height ({s.min_height} >= {s.max_height})")
    _not_negative(s.needle_reach, "needle_reach")
    _positive(s.capture_radius, "capture_radius")
    _not_negative(s.capture_speed, "capture_speed")
    s.arena = validated_polygon(s.arena, "arena")
    if s.airspace:
        s.airspace = validated_polygon(s.airspace, "airspace")
    arena = np.asarray(s.arena)
    space, space_name = np.asarray(s.target_space()), "airspace" if s.airspace else "arena"
    for i, o in enumerate(s.obstacles):
        _check_obstacle(o, f"obstacles[{i}]")
    for i, b in enumerate(s.balloons):
        for field in ("height", "radius"):
            _positive(getattr(b, field), f"balloons[{i}].{field}")
        _not_negative(b.tether, f"balloons[{i}].tether")
        if not point_in_polygon(np.array([b.pole]), space)[0]:
            raise ScenarioError(f"balloons[{i}].pole: {tuple(b.pole)} is outside the {space_name}")
    _not_negative(s.wind.speed, "wind.speed")
    _not_negative(s.wind.gust, "wind.gust")
    _positive(s.wind.gust_period, "wind.gust_period")
    if not 0.0 <= s.appearance.sun_elevation <= 90.0:
        raise ScenarioError(f"appearance.sun_elevation: must lie in [0, 90] degrees, got {s.appearance.sun_elevation}")
    if not 0.0 <= s.appearance.ambient <= 1.0:
        raise ScenarioError(f"appearance.ambient: must lie in [0, 1], got {s.appearance.ambient}")
    for i, d in enumerate(s.drones):
        _check_drone(s, d, f"drones[{i}]", space, space_name)
    for i, start in enumerate(s.starts):
        if not point_in_polygon(np.array([start[:2]]), arena)[0]:
            raise ScenarioError(f"starts[{i}]: {tuple(start[:2])} is outside the arena")
    ids = s.balloon_ids() + s.drone_ids()
    duplicates = sorted({t for t in ids if ids.count(t) > 1})
    if duplicates:
        raise ScenarioError(f"balloons/drones: duplicate target name {duplicates[0]!r}")
    _check_uav_table(s)
    for i, fault in enumerate(s.faults):
        _check_fault(s, fault, f"faults[{i}]")
    _check_router_restarts(s)
    start_poses(s, s.uavs)  # raises when the team cannot be placed
    return s


def check_team(s: Scenario, uav_names: list[str]) -> None:
    """The run's team (the command line may change its size) holds every UAV the scenario names."""
    named = [(f"faults[{i}].uav", f.uav) for i, f in enumerate(s.faults) if f.uav]
    named += [(f"uav.overrides.{name}", name) for name in s.uav.overrides]
    for field, name in named:
        if name not in uav_names:
            raise ScenarioError(f"{field}: {name} is not in the team ({', '.join(uav_names)})")


def start_poses(scenario: Scenario, count: int) -> list[Vec3]:
    """`count` start poses (x, y, heading): the scenario's, then automatic ones (see scenario.py)."""
    poses = [tuple(float(v) for v in s) for s in scenario.starts[:count]]
    arena = np.asarray(scenario.arena, dtype=float)
    if not poses:
        x, y = deepest_point(arena)
        poses.append((x, y, 0.0))
    x0, y0, heading0 = poses[0]
    lo, hi = arena[:, 0].min(), arena[:, 0].max()
    ahead = np.arange(1, int((hi - x0) // START_SPACING) + 1)
    behind = np.arange(1, int((x0 - lo) // START_SPACING) + 1)
    offsets = np.concatenate([ahead, -behind]) * START_SPACING
    spots = np.column_stack([x0 + offsets, np.full(len(offsets), y0)])
    for x, y in spots[point_in_polygon(spots, arena)]:
        if len(poses) >= count:
            break
        if all(math.hypot(p[0] - x, p[1] - y) >= 1.0 for p in poses):
            poses.append((float(x), float(y), heading0))
    if len(poses) < count:
        raise ScenarioError(f"starts: no room in the arena to place {count} UAVs automatically")
    return poses


def validated_polygon(points: list[Point2], field: str) -> list[Point2]:
    pts = [(float(x), float(y)) for x, y in points]
    if len(pts) >= 2 and pts[0] == pts[-1]:
        pts = pts[:-1]
    if len(pts) < 3:
        raise ScenarioError(f"{field}: needs at least 3 points, got {len(pts)}")
    polygon = np.asarray(pts)
    for i in range(len(pts)):
        if np.allclose(polygon[i], polygon[(i + 1) % len(pts)]):
            raise ScenarioError(f"{field}[{i}]: repeated point {pts[i]}")
    crossing = polygon_self_intersection(polygon)
    if crossing is not None:
        i, j = crossing
        raise ScenarioError(f"{field}: edges {i} and {j} cross (the polygon must not self-intersect)")
    area = signed_area(polygon)
    if abs(area) < 1e-9:
        raise ScenarioError(f"{field}: polygon has no area")
    return pts if area > 0 else pts[::-1]


# -------------------------------------------------------------- parts
def _positive(value: float, field: str) -> None:
    if not value > 0:
        raise ScenarioError(f"{field}: must be > 0, got {value}")


def _not_negative(value: float, field: str) -> None:
    if not value >= 0:
        raise ScenarioError(f"{field}: must be >= 0, got {value}")


def _check_obstacle(o: ObstacleSpec, where: str) -> None:
    needed: dict[str, tuple[str, ...]] = {
        "box": ("size",), "cylinder": ("radius", "height"), "cone": ("radius", "height"), "sphere": ("radius",),
    }
    for field in needed[o.kind]:
        value = getattr(o, field)
        if (min(value) if isinstance(value, tuple) else value) <= 0:
            raise ScenarioError(f"{where}.{field}: must be > 0 for a {o.kind}, got {value}")


def _check_drone(s: Scenario, d: DroneSpec, where: str, space: np.ndarray, space_name: str) -> None:
    defaults = DroneSpec(speed=0.0)
    for field in ("center", "radius", "size", "phase", "waypoints", "loop", "box"):
        if field not in PATH_FIELDS[d.path] and getattr(d, field) != getattr(defaults, field):
            raise ScenarioError(f"{where}.{field}: not used by a {d.path} path")
    for field in PATH_REQUIRED[d.path]:
        if getattr(d, field) == getattr(defaults, field):
            raise ScenarioError(f"{where}.{field}: required for a {d.path} path")
    if d.path in ("circle", "figure8"):
        if d.speed == 0:
            raise ScenarioError(f"{where}.speed: must not be 0")
    else:
        _positive(d.speed, f"{where}.speed")
    if d.path == "circle":
        _positive(d.radius, f"{where}.radius")
    if d.path == "figure8" and min(d.size) <= 0:
        raise ScenarioError(f"{where}.size: both extents must be > 0, got {tuple(d.size)}")
    if d.path == "waypoints" and len(d.waypoints) < 2:
        raise ScenarioError(f"{where}.waypoints: needs at least 2 points, got {len(d.waypoints)}")
    for field in ("max_acceleration", "climb_speed", "body_radius"):
        _positive(getattr(d, field), f"{where}.{field}")
    if d.takeoff_time is not None:
        _not_negative(d.takeoff_time, f"{where}.takeoff_time")
    if d.center is not None and not point_in_polygon(np.array([d.center[:2]]), space)[0]:
        raise ScenarioError(f"{where}.center: {tuple(d.center[:2])} is outside the {space_name}")
    try:
        _check_path(d, s, space)
    except _PathError as exc:
        raise ScenarioError(f"{where}.{exc.field}: {exc}") from None


class _PathError(ValueError):
    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def _check_path(spec: DroneSpec, scenario: Scenario, space: np.ndarray) -> None:
    """Raise _PathError (field, message) when the path leaves the target space, goes underground
    or needs more acceleration than max_acceleration. Uses the path code itself."""
    lowest = scenario.ground_z + spec.body_radius
    where = "airspace" if scenario.airspace else "arena"
    if spec.path in ("circle", "figure8"):
        curve = paths.Curve(spec, 0.0, 0.0)
        if curve.center[2] < lowest:
            raise _PathError("center", f"height {curve.center[2]} puts the drone below the ground")
        ring = curve.center[:2] + curve.shape(np.linspace(0, 2 * math.pi, 256))[0][:, :2]
        outside = ~point_in_polygon(ring, space)
        if outside.any():
            x, y = ring[int(np.argmax(outside))]
            raise _PathError("radius" if spec.path == "circle" else "size",
                            f"the {spec.path} leaves the {where} at ({x:.1f}, {y:.1f})")
        needed = curve.full_speed_acceleration()
        share = paths.TAKEOFF_HEADROOM if spec.takeoff_time is not None else 1.0
        if needed > share * spec.max_acceleration:
            raise _PathError("speed", f"{abs(spec.speed)} m/s on this {spec.path} needs {needed:.2f} m/s², more "
                            f"than {share:.0%} of max_acceleration {spec.max_acceleration}")
    elif spec.path == "waypoints":
        points = np.asarray(spec.waypoints, dtype=float)
        route = np.vstack([points, points[:1]]) if spec.loop else points
        for k in range(len(route) - 1):
            steps = np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(route[k + 1] - route[k]) / 0.25) + 1))
            line = route[k] + steps[:, None] * (route[k + 1] - route[k])
            if not point_in_polygon(line[:, :2], space).all():
                index = k + 1 if k + 1 < len(points) else 0
                raise _PathError(f"waypoints[{index}]", f"the leg to it leaves the {where}")
        low = int(np.argmin(points[:, 2]))
        if points[low, 2] < lowest:
            raise _PathError(f"waypoints[{low}]", f"height {points[low, 2]} puts the drone below the ground")
    else:
        _check_random(spec, scenario, space, lowest, where)


def _check_random(spec: DroneSpec, scenario: Scenario, space: np.ndarray, lowest: float, where: str) -> None:
    region = paths.random_region(spec, scenario)
    if spec.box is not None:
        low, high = np.asarray(spec.box[0], float), np.asarray(spec.box[1], float)
        if not (high - low >= 2 * paths.MARGIN + 0.5).all():
            raise _PathError("box", f"needs [low corner, high corner] at least {2 * paths.MARGIN + 0.5} m apart "
                            f"on every axis, got {tuple(spec.box[0])} to {tuple(spec.box[1])}")
        gx, gy = np.meshgrid(np.linspace(low[0], high[0], 41), np.linspace(low[1], high[1], 41))
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        outside = ~point_in_polygon(grid, space)
        if outside.any():
            x, y = grid[int(np.argmax(outside))]
            raise _PathError("box", f"reaches outside the {where} at ({x:.1f}, {y:.1f})")
    if region.z_low - paths.MARGIN < lowest:
        raise _PathError("box" if spec.box is not None else "path",
                        f"the random region starts at height {region.z_low}, too close to the ground")
    if spec.center is not None and region.clearance(np.asarray(spec.center))[0] < paths.MARGIN:
        raise _PathError("center", f"the start must be at least {paths.MARGIN} m inside the random region")


def _check_profile(p: ProfileSpec, where: str) -> None:
    for field in ProfileSpec.__struct_fields__:
        _positive(getattr(p, field), f"{where}.{field}")


def _check_uav_settings(u, where: str) -> None:
    if u.sensor is not None:
        try:
            lidar_model(u.sensor)
        except ValueError as exc:
            raise ScenarioError(f"{where}.sensor: {exc}") from None
    for profile in ("sweeping", "attack"):
        if getattr(u, profile) is not None:
            _check_profile(getattr(u, profile), f"{where}.{profile}")
    for field in ("odometry_position_sigma", "odometry_attitude_sigma"):
        if getattr(u, field) is not None:
            _not_negative(getattr(u, field), f"{where}.{field}")
    if u.radius is not None:
        _positive(u.radius, f"{where}.radius")


def _check_uav_table(s: Scenario) -> None:
    _check_uav_settings(s.uav, "uav")
    for name, override in s.uav.overrides.items():
        _check_uav_name(name, f"uav.overrides.{name}")
        _check_uav_settings(override, f"uav.overrides.{name}")


def _check_router_restarts(s: Scenario) -> None:
    """One router: a restart must be over before the next begins."""
    restarts = sorted((f.time, i) for i, f in enumerate(s.faults) if f.kind == "router_restart")
    for (start, i), (later, j) in zip(restarts, restarts[1:]):
        if later < start + s.faults[i].duration:
            raise ScenarioError(f"faults[{j}].time: the router is still down from faults[{i}] until "
                                f"{start + s.faults[i].duration:g} s")


def _check_fault_fields(f, where: str) -> None:
    """topic, delay and jump: required by their kind, refused on any other."""
    if f.kind in ("duplicate", "reorder"):
        if f.topic not in uav_topics():
            raise ScenarioError(f"{where}.topic: a {f.kind} fault needs one of the UAV's topics "
                                f"({', '.join(uav_topics())}), not {f.topic!r}")
    elif f.topic:
        raise ScenarioError(f"{where}.topic: only duplicate and reorder faults take a topic")
    if f.kind == "slow":
        if not 0 < f.delay <= MAX_DELAY_S:
            raise ScenarioError(f"{where}.delay: a slow fault needs 0 < delay <= {MAX_DELAY_S:g} s per message "
                                f"(a longer one is a freeze)")
    elif f.delay:
        raise ScenarioError(f"{where}.delay: only slow faults take a delay")
    if f.kind == "clock_jump":
        if not (math.isfinite(f.jump) and f.jump != 0):
            raise ScenarioError(f"{where}.jump: a clock_jump needs a non-zero finite jump, s")
    elif f.jump:
        raise ScenarioError(f"{where}.jump: only clock_jump faults take a jump")


def _check_uav_name(name: str, field: str) -> None:
    match = _UAV_NAME.match(name)
    if not match or int(match.group(1)) > MAX_UAVS:
        raise ScenarioError(f"{field}: {name!r} is not a UAV of a team of at most {MAX_UAVS} (uav1..uav{MAX_UAVS})")


def _check_fault(s: Scenario, f, where: str) -> None:
    if f.kind == "router_restart":
        if f.uav:
            raise ScenarioError(f"{where}.uav: a router_restart concerns the run's router, not one UAV")
        if f.duration <= 0:
            raise ScenarioError(f"{where}.duration: a router_restart needs the time the router stays down (> 0 s)")
    else:
        _check_uav_name(f.uav, f"{where}.uav")
    if not 0 <= f.time <= s.duration:
        raise ScenarioError(f"{where}.time: {f.time} s is outside the mission (0 to duration {s.duration} s)")
    _not_negative(f.duration, f"{where}.duration")
    _check_fault_fields(f, where)
    if f.service:
        if f.kind not in SERVICE_FAULTS:
            raise ScenarioError(f"{where}.service: only {', '.join(SERVICE_FAULTS)} faults target one service")
        if f.service not in FAULT_SERVICES:
            raise ScenarioError(f"{where}.service: unknown service {f.service!r} "
                                f"(one of {', '.join(FAULT_SERVICES)})")
    if f.failsafe != "land" and (f.kind != "kill" or f.service):
        raise ScenarioError(f"{where}.failsafe: only a whole-UAV kill (no service) takes a failsafe")
    moved = any(v != 0 for v in f.offset)
    if f.kind == "odometry_jump" and not moved:
        raise ScenarioError(f"{where}.offset: an odometry_jump needs a non-zero offset")
    if f.kind != "odometry_jump" and moved:
        raise ScenarioError(f"{where}.offset: only odometry_jump faults take an offset")
