"""The one place that builds Falconry key expressions.

Per-UAV data: falconry/<uav>/<topic>; simulator: falconry/sim/<topic>;
liveliness: falconry/<uav>/alive/<service>; health queries: falconry/<uav>/health/<service>;
lockstep acknowledgements: falconry/<uav>/ack/<service>.
"""
from __future__ import annotations

import re

ROOT = "falconry"
SIM = "sim"  # the run-wide segment used in place of a UAV name
UAV_SERVICES = ("sensor_driver", "classifier", "mapper", "tracker", "job_manager", "planner")
# The colour camera and its balloon detector (seed 004 §4.1), beside the LiDAR perception.
CAMERA_SERVICES = ("camera", "object_detect")
# Evaluation-only detector that replaces the classifier: noisy detections made from the LiDAR
# points that really hit a target (simulation only; `falconry sim --detector oracle`).
ORACLE = "oracle"
# The LiDAR-inertial localizer (seed 003's Grape): started for a UAV that flies without GNSS
# (scenario [uav] positioning = "lidar"); its estimate is published on LOCALIZATION.
LOCALIZER = "localizer"
SIM_SERVICES = ("simulator",)
# `falconry sim --detector`: onboard = LiDAR perception for drones and the camera for balloons;
# classifier = the LiDAR perception alone; oracle = the evaluation detector alone.
DETECTORS = ("onboard", "classifier", "oracle")
DEFAULT_DETECTOR = "onboard"


POSITIONING = ("gnss", "lidar")  # where a UAV's position comes from (services/simulator/specs.py)


def uav_services(detector: str = DEFAULT_DETECTOR, positioning: str = "gnss") -> list[str]:
    """The per-UAV services of a run: the oracle, when chosen, replaces the classifier; onboard adds
    the camera and Object Detect; a UAV without GNSS (positioning "lidar") adds the localizer."""
    if detector not in DETECTORS:
        raise ValueError(f"unknown detector {detector!r} (choose from {', '.join(DETECTORS)})")
    if positioning not in POSITIONING:
        raise ValueError(f"unknown positioning {positioning!r} (choose from {', '.join(POSITIONING)})")
    services = [ORACLE if s == "classifier" and detector == ORACLE else s for s in UAV_SERVICES]
    services += list(CAMERA_SERVICES) if detector == "onboard" else []
    return services + ([LOCALIZER] if positioning == "lidar" else [])

SERVICES = SIM_SERVICES + UAV_SERVICES + CAMERA_SERVICES + (ORACLE, LOCALIZER)

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


def check_name(name: str, what: str = "name") -> str:
    """UAV and service names become key segments, so keep them to one plain chunk."""
    if not _NAME.match(name) or name == SIM:
        raise ValueError(f"invalid {what} {name!r}: use lower-case letters, digits and '_'")
    return name


def uav_names(count: int) -> list[str]:
    return [f"uav{i + 1}" for i in range(count)]


def uav(uav_name: str, topic: str) -> str:
    return f"{ROOT}/{uav_name}/{topic}"


def sim(topic: str) -> str:
    return f"{ROOT}/{SIM}/{topic}"


def scope_of(service: str, uav_name: str | None) -> str:
    """The key segment a service lives under: its UAV, or 'sim' for run-wide services."""
    return SIM if service in SIM_SERVICES or uav_name is None else uav_name


def alive(scope: str, service: str) -> str:
    return f"{ROOT}/{scope}/alive/{service}"


def health(scope: str, service: str) -> str:
    return f"{ROOT}/{scope}/health/{service}"


def ack(scope: str, service: str) -> str:
    return f"{ROOT}/{scope}/ack/{service}"


# Per-UAV topics that a party other than the UAV's own services publishes: the access control of
# a team (services/lib/runtime/tls.py) grants exactly these, and their publishers name them from here.
ODOMETRY = "odometry"  # the flight controller's pose; in simulation the simulator stands in for it
IMU = "imu"  # the flight controller's accelerometer and gyroscope samples; in simulation the simulator's
LOCALIZATION = "localization"  # the localizer's estimate (Odometry with its health), which the flight controller flies on
FLIGHT_CONTROLLER_TOPICS = (ODOMETRY, IMU)  # what the flight controller (the simulator) publishes per UAV
COLORS = "colors"  # a colour file sent live from the ground (`falconry colors pick --send`)

ALL_ALIVE = f"{ROOT}/*/alive/*"
ALL_ACKS = f"{ROOT}/*/ack/*"
ALL_STATUS = f"{ROOT}/*/status"
ALL_TRACKS = f"{ROOT}/*/tracks"
CLOCK = sim("clock")
WORLD = sim("world")
TRUTH = sim("truth")
EVENTS = sim("events")
FAULTS = sim("faults")
RESUME = sim("resume")


def ack_owner(key: str) -> str | None:
    """'uav1/classifier' for falconry/uav1/ack/classifier; None for a key that is no acknowledgement."""
    parts = key.split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[2] == "ack":
        return f"{parts[1]}/{parts[3]}"
    return None


def is_ack(key: str) -> bool:
    return ack_owner(key) is not None


def uav_of(key: str) -> str:
    """The UAV segment of a per-UAV key (falconry/uav2/tracks → uav2)."""
    return key.split("/")[1]


def topic_of(key: str) -> str:
    """The topic of a per-UAV key (falconry/uav2/tracks → tracks)."""
    return key.split("/", 2)[2]


def parse_alive(key: str) -> tuple[str, str] | None:
    """(scope, service) of a liveliness key, or None when it is not one."""
    parts = key.split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[2] == "alive":
        return parts[1], parts[3]
    return None
