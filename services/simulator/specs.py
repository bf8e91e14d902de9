"""The shape of a scenario file: msgspec Structs the TOML converts into.

Field meanings, units and defaults are documented once, in the docstring of
`services/simulator/scenario.py` (copied into docs/scenarios.md). Value checks that need more
than a type live in `checks.py`.
"""
from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.messages import DEFAULT_UAV_RADIUS, ConstraintProfile, FaultCommand, FaultKind, Header
from services.lib.runtime.clock import NS

MAX_UAVS = 3  # the largest team the command line accepts (--uavs 2|3)
POLE_RADIUS = 0.05


def pole_name(balloon: str) -> str:
    """The name of a balloon's pole among the world's static obstacles (its balloon's target id + '_pole')."""
    return f"{balloon}_pole"


Vec3 = tuple[float, float, float]
Point2 = tuple[float, float]
Channel = Annotated[int, msgspec.Meta(ge=0, le=255)]
Color = tuple[Channel, Channel, Channel]  # sRGB


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message is one line naming the file and field."""


class ObstacleSpec(msgspec.Struct, forbid_unknown_fields=True):
    kind: Literal["box", "cylinder", "cone", "sphere"]
    center: Vec3 = (0.0, 0.0, 0.0)
    size: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.0
    height: float = 0.0
    name: str = ""
    color: Color | None = None
    surveyed: bool = True  # in the mission's a-priori map (the world model); False: only sensors find it


class BalloonSpec(msgspec.Struct, forbid_unknown_fields=True):
    pole: Point2
    height: float = 3.0
    radius: float = 0.3
    tether: float = 0.2
    name: str = ""
    color: Color | None = None


class AppearanceSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    sky: Color = (150, 190, 235)
    ground: Color = (196, 178, 140)
    obstacle: Color = (128, 128, 128)
    pole: Color = (225, 225, 225)
    balloon: Color = (200, 30, 30)
    drone: Color = (40, 40, 45)
    sun_elevation: float = 50.0
    sun_azimuth: float = 135.0
    ambient: float = 0.4


class WindSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    speed: float = 0.0
    direction: float = 0.0
    gust: float = 0.0
    gust_period: float = 8.0


DronePath = Literal["circle", "waypoints", "figure8", "random"]


class DroneSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    speed: float
    path: DronePath = "circle"
    center: Vec3 | None = None
    radius: float = 0.0
    size: Point2 = (0.0, 0.0)
    phase: float = 0.0
    waypoints: list[Vec3] = []
    loop: bool = False
    box: tuple[Vec3, Vec3] | None = None
    max_acceleration: float = 3.0
    climb_speed: float = 1.0
    takeoff_time: float | None = None
    body_radius: float = 0.325
    name: str = ""
    color: Color | None = None


# Fields each path reads besides the common ones (speed, max_acceleration, climb_speed,
# takeoff_time, body_radius, name); any other field set on a drone is a mistake worth reporting.
PATH_FIELDS: dict[str, tuple[str, ...]] = {
    "circle": ("center", "radius", "phase"),
    "figure8": ("center", "size", "phase"),
    "waypoints": ("waypoints", "loop"),
    "random": ("center", "box"),
}
PATH_REQUIRED: dict[str, tuple[str, ...]] = {
    "circle": ("center", "radius"), "figure8": ("center", "size"), "waypoints": ("waypoints",), "random": (),
}


class ProfileSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    max_speed: float
    max_acceleration: float
    max_heading_rate: float = 1.0
    max_vertical_speed: float = 2.0

    def message(self, name: str) -> ConstraintProfile:
        return ConstraintProfile(name=name, max_speed=self.max_speed, max_acceleration=self.max_acceleration,
                                 max_heading_rate=self.max_heading_rate,
                                 max_vertical_speed=self.max_vertical_speed)


def _sweeping() -> ProfileSpec:
    return ProfileSpec(max_speed=5.0, max_acceleration=1.5)


def _attack() -> ProfileSpec:
    return ProfileSpec(max_speed=8.3, max_acceleration=3.0)


# Where a UAV's flight controller takes its position from: "gnss", the simulator's odometry (truth plus
# odometry_*_sigma noise); "lidar", GNSS-denied: the onboard localizer's LiDAR-inertial estimate, which
# the vehicle then flies on (services/localizer).
Positioning = Literal["gnss", "lidar"]


class UavSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """One UAV's configuration (the [uav] table merged with its override)."""

    sensor: str = "os0-128"
    sweeping: ProfileSpec = msgspec.field(default_factory=_sweeping)
    attack: ProfileSpec = msgspec.field(default_factory=_attack)
    odometry_position_sigma: float = 0.0
    odometry_attitude_sigma: float = 0.0
    positioning: Positioning = "gnss"
    radius: float = DEFAULT_UAV_RADIUS  # m: the sphere the airframe fits in (touching anything with it is a crash)

    def envelope(self) -> ProfileSpec:
        """What the airframe can do at most: the larger of its profiles, limit by limit."""
        a, b = self.sweeping, self.attack
        return ProfileSpec(max_speed=max(a.max_speed, b.max_speed),
                           max_acceleration=max(a.max_acceleration, b.max_acceleration),
                           max_heading_rate=max(a.max_heading_rate, b.max_heading_rate),
                           max_vertical_speed=max(a.max_vertical_speed, b.max_vertical_speed))


class UavOverride(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    sensor: str | None = None
    sweeping: ProfileSpec | None = None
    attack: ProfileSpec | None = None
    odometry_position_sigma: float | None = None
    odometry_attitude_sigma: float | None = None
    positioning: Positioning | None = None
    radius: float | None = None


class UavTable(UavSpec, kw_only=True):
    overrides: dict[str, UavOverride] = {}


class FaultSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    time: float
    kind: FaultKind
    uav: str = ""  # every kind but router_restart (the run's router) names one
    service: str = ""
    duration: float = 0.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    failsafe: Literal["land", "hold"] = "land"  # a whole-UAV kill: what the flight controller does then
    topic: str = ""  # duplicate / reorder: the UAV's topic whose deliveries are disturbed
    delay: float = 0.0  # slow: s of extra handling time per message
    jump: float = 0.0  # clock_jump: s the system clock steps

    def command(self) -> FaultCommand:
        """The FaultCommand announcing this fault, stamped with its mission time."""
        return FaultCommand(header=Header(stamp=int(round(self.time * NS))), kind=self.kind, uav=self.uav,
                            service=self.service, duration=self.duration, offset=self.offset, topic=self.topic,
                            delay=self.delay, jump=self.jump)


class Scenario(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    name: str
    arena: list[Point2]
    duration: float = 120.0
    seed: int = 1
    uavs: int = 2
    min_height: float = 0.0
    max_height: float = 20.0
    ground_z: float = 0.0
    needle_reach: float = 0.3
    capture_radius: float = 1.0
    capture_speed: float = 2.0
    airspace: list[Point2] = []
    obstacles: list[ObstacleSpec] = []
    balloons: list[BalloonSpec] = []
    drones: list[DroneSpec] = []
    starts: list[Vec3] = []
    wind: WindSpec = msgspec.field(default_factory=WindSpec)
    appearance: AppearanceSpec = msgspec.field(default_factory=AppearanceSpec)
    uav: UavTable = msgspec.field(default_factory=UavTable)
    faults: list[FaultSpec] = []

    def balloon_ids(self) -> list[str]:
        return [b.name or f"balloon{i + 1}" for i, b in enumerate(self.balloons)]

    def drone_ids(self) -> list[str]:
        return [d.name or f"drone{i + 1}" for i, d in enumerate(self.drones)]

    def target_space(self) -> list[Point2]:
        """Where targets may be: the airspace polygon, or the arena when none is given."""
        return self.airspace or self.arena

    def positioning(self, uav: str, override: str | None = None) -> str:
        """Where the UAV's position comes from: `override` (a run's --positioning, for every UAV) or
        its [uav] table's positioning."""
        return override or self.uav_spec(uav).positioning

    def uav_spec(self, uav: str) -> UavSpec:
        """The [uav] table with this UAV's override applied."""
        base = {f: getattr(self.uav, f) for f in UavSpec.__struct_fields__}
        override = self.uav.overrides.get(uav)
        if override is not None:
            base.update({f: v for f in UavOverride.__struct_fields__ if (v := getattr(override, f)) is not None})
        return UavSpec(**base)
