"""Scenario files: the arena, obstacles, targets, wind, team and fault schedule of a simulated mission.

A scenario is a TOML file; built-in ones live in services/simulator/scenarios/ and are named by
their file stem (`mbzirc`). Unknown fields and wrong types are rejected with a one-line
`ScenarioError` naming the field, e.g. ``mbzirc.toml: balloons[2].height: expected float, got str``.
Lists are indexed from 0 in messages. Units: metres, seconds, radians; x east, y north, z up.
The wind sways the balloons only: UAVs and drones fly as in still air.

Top-level fields
  name            str, required. Shown in logs and the world model.
  duration        float = 120.0   mission time to simulate, s (> 0).
  seed            int = 1         default random seed of a run (the command line may override it).
  uavs            int = 2         team size, 2 or 3 (the command line may override it).
  arena           [[x, y], ...], required. The team's flight area (split into working areas),
                  >= 3 points, non-convex allowed, must not self-intersect. Either orientation is
                  accepted and stored counter-clockwise; a closing point equal to the first is dropped.
  airspace        [[x, y], ...] = []   where targets may be (same rules as arena); empty: the arena.
                  Lets a target fly outside the team's area (e.g. the `sparse` observer setting).
  min_height      float = 0.0     lowest flight height above ground, m.
  max_height      float = 20.0    highest flight height above ground, m (> min_height).
  ground_z        float = 0.0     height of the flat ground plane, m.
  needle_reach    float = 0.3     a balloon is destroyed when a UAV's body centre comes within
                                  balloon radius + needle_reach of the balloon's centre, m.
  capture_radius  float = 1.0     a drone is captured when a UAV's centre comes within this of
                                  the drone's centre, m (> 0) ...
  capture_speed   float = 2.0     ... at a relative speed of at most this, m/s. A captured drone
                                  drops to the ground and counts as destroyed.
  starts          [[x, y, heading], ...] = []   UAV start poses on the ground, inside the arena.
                  If fewer than the team size, the rest are placed 10 m apart along x from the
                  first (towards +x while inside the arena, then towards -x; spots already taken
                  are skipped); with none, the first goes to the arena point furthest from its edges.

[[obstacles]]  static primitives, seen by the simulated LiDAR and camera; a UAV whose body (its [uav]
               radius) touches one crashes (a `collision` event; it falls and is out of the mission)
  kind      "box" | "cylinder" | "cone" | "sphere", required.
  center    [x, y, z] = [0, 0, 0]. Box and sphere: the centre. Cylinder and cone: the centre of
            the base (both stand vertically; a cone's apex is at center + height).
  size      [sx, sy, sz] = [0, 0, 0]   box edge lengths (all > 0 for a box).
  radius    float = 0.0   cylinder, cone (base) and sphere radius (> 0 for those kinds).
  height    float = 0.0   cylinder and cone height (> 0 for those kinds).
  name      str = ""      what events and summaries call it; unnamed: "unnamed <kind> (x, y)".
  color     [r, g, b] = appearance.obstacle   what a camera sees of it, sRGB 0-255.
  surveyed  bool = true   in the mission's a-priori map: the world model carries it to every
            service. false: only the ground truth does, so the simulated sensors see it and the
            run's evaluation measures clearance to it, but no flying service knows it beforehand.

[[balloons]]  targets: a sphere tethered to the top of a thin pole (the pole, radius 0.05 m, is a
              static cylinder obstacle from the ground to its top, surveyed, which a UAV crashes
              into like any other; the balloon itself is a target, never an obstacle)
  pole    [x, y], required, inside the airspace.
  height  float = 3.0   height of the pole's top above the ground, m (> 0).
  radius  float = 0.3   balloon radius (0.6 m diameter), m (> 0).
  tether  float = 0.2   string from the pole top to the balloon, m (>= 0). In still air the centre
                        is tether + radius above the top; wind leans it over like an inverted
                        pendulum, tan(lean) = (wind / 8 m/s)², so it moves at most tether + radius.
  name    str = ""      target id; default "balloon<k>" (k from 1).
  color   [r, g, b] = appearance.balloon   sRGB 0-255 (the pole: appearance.pole).

[wind]  sways the balloons (only them, in this version)
  speed        float = 0.0   steady wind, m/s (>= 0).
  direction    float = 0.0   where the wind blows towards, rad (0 = +x).
  gust         float = 0.0   gust amplitude along the wind, m/s (>= 0); half as much across it at
                             another period. Each balloon has its own gust phase.
  gust_period  float = 8.0   s (> 0).

[[drones]]  intruder drones (targets) on scripted paths that keep their speed and acceleration
            limits exactly (see paths.py); every path must stay inside the airspace and above ground
  path              "circle" | "waypoints" | "figure8" | "random" = "circle"
  speed             float, required, m/s. circle: along the circle, negative flies clockwise;
                    figure8: peak speed (at the crossing), negative reverses; waypoints: cruise
                    speed (> 0); random: top speed (> 0).
  max_acceleration  float = 3.0   m/s² (> 0). A circle or figure8 whose own acceleration is above
                    it is rejected (above 80 % of it with a takeoff_time: the rest speeds it up).
  center            [x, y, z]. circle and figure8: required, the middle (z is the flight height).
                    random: the start point (default: the middle of its region).
  radius            float        circle only, required (> 0).
  size              [length, width]   figure8 only, required: its extent along x and y; the
                    lobes are x = length/2 sin θ, y = width/2 sin 2θ.
  phase             float = 0.0  circle and figure8: θ at the start (circle: 0 = +x of the centre).
  waypoints         [[x, y, z], ...]   waypoints only, >= 2 points: from the first, straight legs
                    that stop at each point (accelerate, cruise, brake).
  loop              bool = false waypoints only: fly back to the first point and start over;
                    otherwise hover at the last point.
  box               [[x0, y0, z0], [x1, y1, z1]]   random only: the region it roams, inside the
                    airspace, >= 1.5 m on every axis; default: the airspace between min_height and
                    max_height. It picks goals, speeds and durations of 0.4-2 s at random (seeded by
                    the run seed and the drone's index) and never comes within 0.5 m of the walls.
  takeoff_time      float        if set, the drone rests on the ground below its start point until
                    this mission time, climbs to it (at climb_speed), then starts its path from rest.
                    Without it, circles and figure8s are already at speed at time 0; waypoints and
                    random paths start from rest at their start point.
  climb_speed       float = 1.0  m/s (> 0), for the take-off climb.
  body_radius       float = 0.325 the drone's size as a sphere, m (> 0).
  name              str = ""     target id; default "drone<k>".
  color             [r, g, b] = appearance.drone   sRGB 0-255.

[appearance]  what a simulated camera sees besides shapes (colours sRGB [r, g, b], 0-255 each)
  sky            = [150, 190, 235]   where a ray meets nothing.
  ground         = [196, 178, 140]   the ground plane (sand).
  obstacle       = [128, 128, 128]   obstacles without a colour of their own.
  pole           = [225, 225, 225]   balloon poles.
  balloon        = [200, 30, 30]     balloons without a colour of their own (the competition's
                                     were announced red and flown green: a scenario can say so).
  drone          = [40, 40, 45]      intruder drones without a colour of their own.
  sun_elevation  float = 50.0        degrees above the horizon (0-90).
  sun_azimuth    float = 135.0       degrees counter-clockwise from +x.
  ambient        float = 0.4         share of the light that does not depend on how a surface
                                     faces the sun (0-1); the rest falls as the cosine of the
                                     sun's angle of incidence.

[uav]  the team's UAVs (all of them; per-UAV changes in [uav.overrides.<uav>])
  sensor                   str = "os0-128"   LiDAR model handed to the sensor driver, one of its
                           models: os0-32, os0-64, os0-128, os1-32, os1-64, os1-128 (optionally
                           with columns: os1-128-2048), mid360.
  sweeping                 {max_speed, max_acceleration, max_heading_rate = 1.0,
                            max_vertical_speed = 2.0} = {5.0, 1.5}   constraint profile for scanning.
  attack                   same fields = {8.3, 3.0}   constraint profile for attacks. The simulated
                           airframe never exceeds the larger of the two profiles, limit by limit.
  odometry_position_sigma  float = 0.0   white noise on the GNSS odometry position, m (>= 0).
  odometry_attitude_sigma  float = 0.0   white noise on the GNSS odometry heading, rad (>= 0).
  positioning              "gnss" | "lidar" = "gnss"   where the flight controller's position comes
                           from: gnss = the odometry above; lidar = flying without GNSS (no such
                           noise), on the onboard localizer's LiDAR-inertial estimate (the run
                           starts a localizer per such UAV; `falconry sim --positioning lidar` sets
                           it for every UAV).
  radius                   float = 0.4   the sphere about its centre the airframe fits in, m (> 0): this
                           body touching an obstacle, a balloon's pole or a flying partner's body
                           is a crash; so is touching the ground outside a landing (an emergency
                           landing, or a reference at most 0.3 m above the ground met at most
                           2.5 m/s down and 1 m/s across).
  overrides.<uav>          a table with any of the fields above, for one UAV (uav1..uav3).

[[faults]]  the fault schedule, injected at mission times (file order kept)
  time      float, required: when, s of mission time (0 <= time <= duration).
  kind      required: "lidar_silent" | "lidar_nan" | "lidar_garbage" | "odometry_jump" | "kill" |
            "link_cut" | "freeze" | "duplicate" | "reorder" | "slow" | "clock_jump" | "router_restart" |
            "camera_frozen" (the camera repeats its last frame) | "camera_saturated" (white frames).
  uav       str: uav1..uav3, required but for router_restart; a run whose team lacks it stops with an error.
  service   str = ""     kill, freeze, slow and clock_jump only: one service (e.g. "planner"); "" = every
            process of the UAV.
  duration  float = 0.0  s (>= 0); 0 = until the end of the run. router_restart: the s of wall time
            the router stays down (> 0; real-time runs only, one restart at a time).
  offset    [x, y, z] = [0, 0, 0]   odometry_jump only, required non-zero: the jump, m.
  failsafe  "land" | "hold" = "land"   whole-UAV kill only: what the flight controller does when the
            onboard computer dies: land where it is, or hold its position in the air until the end.
  topic     str          duplicate and reorder only, required: the UAV's topic whose messages every
            subscriber receives twice, or with neighbours swapped (e.g. "detections").
  delay     float        slow only, required, 0 < delay <= 0.1: s of extra handling time per message
            the slowed service receives (a slow or overloaded computer).
  jump      float        clock_jump only, required non-zero: s the system clock of the UAV's services
            steps (an NTP step); only services on the wall clock that obey simulated faults see it
            (`falconry run --clock wall --simulated-faults on`): `falconry sim` runs none.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import msgspec

from services.simulator.checks import check_team, start_poses, validated
from services.simulator.specs import (
    POLE_RADIUS,
    BalloonSpec,
    DroneSpec,
    FaultSpec,
    ObstacleSpec,
    ProfileSpec,
    Scenario,
    ScenarioError,
    UavOverride,
    AppearanceSpec,
    UavSpec,
    WindSpec,
)

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"

__all__ = [
    "SCENARIO_DIR", "POLE_RADIUS", "AppearanceSpec", "BalloonSpec", "DroneSpec", "FaultSpec", "ObstacleSpec", "ProfileSpec",
    "Scenario", "ScenarioError", "UavSpec", "WindSpec", "builtin_scenarios", "check_team", "load_scenario",
    "parse_scenario", "start_poses",
]


def builtin_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def load_scenario(name_or_path: str) -> Scenario:
    """A built-in scenario by name, or a scenario file by path."""
    path = scenario_path(name_or_path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path.name}: invalid TOML: {_one_line(str(exc))}") from None
    return parse_scenario(data, path.name)


def scenario_path(name_or_path: str) -> Path:
    """The file of a built-in scenario by name, or the given path; ScenarioError when there is none."""
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
    return path


def parse_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    """Type-check and validate already-parsed TOML data; `source` prefixes error messages."""
    try:
        scenario = msgspec.convert(data, Scenario)
    except msgspec.ValidationError as exc:
        raise ScenarioError(f"{source}: {_describe_validation_error(_name_override(str(exc), data))}") from None
    try:
        return validated(scenario)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {exc}") from None


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


def _name_override(text: str, data: dict) -> str:
    """msgspec writes dict keys as `[...]`: name the [uav.overrides.<uav>] table that failed."""
    overrides = (data.get("uav") or {}).get("overrides") if isinstance(data.get("uav"), dict) else None
    if "overrides[...]" not in text or not isinstance(overrides, dict):
        return text
    for name, table in overrides.items():
        try:
            msgspec.convert(table, UavOverride)
        except msgspec.ValidationError:
            return text.replace("overrides[...]", f"overrides.{name}")
    return text


def _one_line(text: str) -> str:
    return " ".join(text.split())
