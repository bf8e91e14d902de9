"""Scenario files: the arena, obstacles, targets and team a simulated mission runs in.

First version (walking skeleton): static obstacles, balloons on poles and intruder drones on
circles. Later issues add scripted drone paths other than circles, a fault schedule and wind.

A scenario is a TOML file; built-in ones live in services/simulator/scenarios/ and are named by
their file stem (`mbzirc`). Unknown fields and wrong types are rejected with a one-line
`ScenarioError` naming the field, e.g. ``mbzirc.toml: balloons[2].height: expected float, got str``.
Lists are indexed from 0 in messages. Units: metres, seconds, radians; x east, y north, z up.

Top-level fields
  name          str, required. Shown in logs and the world model.
  duration      float = 120.0   mission time to simulate, s (> 0).
  seed          int = 1         default random seed of a run (the command line may override it).
  uavs          int = 2         team size, 2 or 3 (the command line may override it).
  arena         [[x, y], ...], required. Flight area polygon, >= 3 points, non-convex allowed,
                must not self-intersect. Either orientation is accepted and stored
                counter-clockwise; a closing point equal to the first is dropped.
  min_height    float = 0.0     lowest flight height above ground, m.
  max_height    float = 20.0    highest flight height above ground, m (> min_height).
  ground_z      float = 0.0     height of the flat ground plane, m.
  needle_reach  float = 0.3     a balloon is destroyed when a UAV's body centre comes within
                                balloon radius + needle_reach of the balloon's centre, m.
  starts        [[x, y, heading], ...] = []   UAV start poses on the ground, inside the arena.
                If fewer than the team size, the rest are placed 5 m apart along x from the
                first (towards +x while inside the arena, then towards -x; spots already taken
                are skipped); with none, the first goes to the arena point furthest from its edges.

[[obstacles]]  static primitives (also seen by the simulated LiDAR)
  kind    "box" | "cylinder" | "cone" | "sphere", required.
  center  [x, y, z] = [0, 0, 0]. Box and sphere: the centre. Cylinder and cone: the centre of
          the base (both stand vertically; a cone's apex is at center + height).
  size    [sx, sy, sz] = [0, 0, 0]   box edge lengths (all > 0 for a box).
  radius  float = 0.0   cylinder, cone (base) and sphere radius (> 0 for those kinds).
  height  float = 0.0   cylinder and cone height (> 0 for those kinds).
  name    str = ""

[[balloons]]  targets: a sphere sitting on top of a thin pole (the pole, radius 0.05 m, is a
              static cylinder obstacle from the ground to the balloon)
  pole    [x, y], required, inside the arena.
  height  float = 3.0   height of the pole's top above the ground, m (> 0).
  radius  float = 0.3   balloon radius (0.6 m diameter), m (> 0).
  name    str = ""      target id; default "balloon<k>" (k from 1).

[[drones]]  intruder drones (targets) flying a scripted path; not destructible in this version
  path         "circle" = "circle"
  center       [x, y, z], required; its (x, y) must be inside the arena. z is the flight height.
  radius       float, required (> 0), m.
  speed        float, required, m/s along the path; negative flies clockwise.
  phase        float = 0.0   angle on the circle at mission time 0, rad (0 = +x of the centre).
  body_radius  float = 0.325 the drone's size as a sphere, m (> 0).
  name         str = ""      target id; default "drone<k>".
"""
from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np

from services.geometry import deepest_point, point_in_polygon, polygon_self_intersection, signed_area

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
POLE_RADIUS = 0.05
START_SPACING = 5.0

Vec3 = tuple[float, float, float]
Point2 = tuple[float, float]


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message is one line naming the file and field."""


class ObstacleSpec(msgspec.Struct, forbid_unknown_fields=True):
    kind: Literal["box", "cylinder", "cone", "sphere"]
    center: Vec3 = (0.0, 0.0, 0.0)
    size: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.0
    height: float = 0.0
    name: str = ""


class BalloonSpec(msgspec.Struct, forbid_unknown_fields=True):
    pole: Point2
    height: float = 3.0
    radius: float = 0.3
    name: str = ""


class DroneSpec(msgspec.Struct, forbid_unknown_fields=True):
    center: Vec3
    radius: float
    speed: float
    path: Literal["circle"] = "circle"
    phase: float = 0.0
    body_radius: float = 0.325
    name: str = ""


class Scenario(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    arena: list[Point2]
    duration: float = 120.0
    seed: int = 1
    uavs: int = 2
    min_height: float = 0.0
    max_height: float = 20.0
    ground_z: float = 0.0
    needle_reach: float = 0.3
    obstacles: list[ObstacleSpec] = []
    balloons: list[BalloonSpec] = []
    drones: list[DroneSpec] = []
    starts: list[Vec3] = []

    def balloon_ids(self) -> list[str]:
        return [b.name or f"balloon{i + 1}" for i, b in enumerate(self.balloons)]

    def drone_ids(self) -> list[str]:
        return [d.name or f"drone{i + 1}" for i, d in enumerate(self.drones)]


def builtin_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def load_scenario(name_or_path: str) -> Scenario:
    """A built-in scenario by name, or a scenario file by path."""
    path = Path(name_or_path)
    looks_like_path = path.suffix == ".toml" or "/" in name_or_path or "\\" in name_or_path
    if not looks_like_path:
        builtin = SCENARIO_DIR / f"{name_or_path}.toml"
        if not builtin.is_file():
            names = ", ".join(builtin_scenarios())
            raise ScenarioError(
                f"unknown scenario {name_or_path!r} (built-in: {names}; or give a path to a .toml)"
            )
        path = builtin
    if not path.is_file():
        raise ScenarioError(f"scenario file not found: {name_or_path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path.name}: invalid TOML: {_one_line(str(exc))}") from None
    return parse_scenario(data, path.name)


def parse_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    """Type-check and validate already-parsed TOML data; `source` prefixes error messages."""
    try:
        scenario = msgspec.convert(data, Scenario)
    except msgspec.ValidationError as exc:
        raise ScenarioError(f"{source}: {_describe_validation_error(str(exc))}") from None
    try:
        return _validated(scenario)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {exc}") from None


def start_poses(scenario: Scenario, count: int) -> list[Vec3]:
    """`count` start poses (x, y, heading): the scenario's, then automatic ones (see module doc)."""
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


# -------------------------------------------------------------- validation
def _validated(s: Scenario) -> Scenario:
    if s.duration <= 0:
        raise ScenarioError(f"duration: must be > 0, got {s.duration}")
    if s.uavs not in (2, 3):
        raise ScenarioError(f"uavs: must be 2 or 3, got {s.uavs}")
    if not s.min_height < s.max_height:
        raise ScenarioError(f"min_height: must be below max_height ({s.min_height} >= {s.max_height})")
    if s.needle_reach < 0:
        raise ScenarioError(f"needle_reach: must be >= 0, got {s.needle_reach}")
    s.arena = _validated_arena(s.arena)
    arena = np.asarray(s.arena)
    for i, o in enumerate(s.obstacles):
        _check_obstacle(o, f"obstacles[{i}]")
    for i, b in enumerate(s.balloons):
        if b.height <= 0 or b.radius <= 0:
            field = "height" if b.height <= 0 else "radius"
            raise ScenarioError(f"balloons[{i}].{field}: must be > 0, got {getattr(b, field)}")
        if not point_in_polygon(np.array([b.pole]), arena)[0]:
            raise ScenarioError(f"balloons[{i}].pole: {tuple(b.pole)} is outside the arena")
    for i, d in enumerate(s.drones):
        if d.radius <= 0 or d.body_radius <= 0:
            field = "radius" if d.radius <= 0 else "body_radius"
            raise ScenarioError(f"drones[{i}].{field}: must be > 0, got {getattr(d, field)}")
        if not point_in_polygon(np.array([d.center[:2]]), arena)[0]:
            raise ScenarioError(f"drones[{i}].center: {tuple(d.center[:2])} is outside the arena")
    for i, start in enumerate(s.starts):
        if not point_in_polygon(np.array([start[:2]]), arena)[0]:
            raise ScenarioError(f"starts[{i}]: {tuple(start[:2])} is outside the arena")
    ids = s.balloon_ids() + s.drone_ids()
    duplicates = sorted({t for t in ids if ids.count(t) > 1})
    if duplicates:
        raise ScenarioError(f"balloons/drones: duplicate target name {duplicates[0]!r}")
    start_poses(s, s.uavs)  # raises when the team cannot be placed
    return s


def _validated_arena(points: list[Point2]) -> list[Point2]:
    pts = [(float(x), float(y)) for x, y in points]
    if len(pts) >= 2 and pts[0] == pts[-1]:
        pts = pts[:-1]
    if len(pts) < 3:
        raise ScenarioError(f"arena: needs at least 3 points, got {len(pts)}")
    polygon = np.asarray(pts)
    for i in range(len(pts)):
        if np.allclose(polygon[i], polygon[(i + 1) % len(pts)]):
            raise ScenarioError(f"arena[{i}]: repeated point {pts[i]}")
    crossing = polygon_self_intersection(polygon)
    if crossing is not None:
        i, j = crossing
        raise ScenarioError(f"arena: edges {i} and {j} cross (the polygon must not self-intersect)")
    area = signed_area(polygon)
    if abs(area) < 1e-9:
        raise ScenarioError("arena: polygon has no area")
    return pts if area > 0 else pts[::-1]


def _check_obstacle(o: ObstacleSpec, where: str) -> None:
    needed: dict[str, tuple[str, ...]] = {
        "box": ("size",), "cylinder": ("radius", "height"), "cone": ("radius", "height"), "sphere": ("radius",),
    }
    for field in needed[o.kind]:
        value = getattr(o, field)
        if (min(value) if isinstance(value, tuple) else value) <= 0:
            raise ScenarioError(f"{where}.{field}: must be > 0 for a {o.kind}, got {value}")


_AT = re.compile(r"^(?P<msg>.*?)(?: - at `\$(?P<path>[^`]*)`)?$")


def _describe_validation_error(text: str) -> str:
    """msgspec's "Expected `float`, got `str` - at `$.a[2].b`" -> "a[2].b: expected float, got str"."""
    match = _AT.match(_one_line(text))
    msg, path = match.group("msg"), (match.group("path") or "").lstrip(".")
    field = re.search(r"(?:unknown|missing required) field `([^`]+)`", msg)
    if field:
        path = f"{path}.{field.group(1)}" if path else field.group(1)
        msg = "unknown field" if "unknown" in msg else "missing required field"
    msg = msg.replace("`", "")
    msg = msg[:1].lower() + msg[1:]
    return f"{path or '(top level)'}: {msg}"


def _one_line(text: str) -> str:
    return " ".join(text.split())
