"""The message catalogue: key expression → type → publisher → subscribers → rate.

README.md carries this table verbatim (`python -m schemas catalogue` prints it; a test
checks the README is in step), so the code is the single source of truth.
"""
from __future__ import annotations

import re
from typing import NamedTuple

import msgspec

from schemas import messages as m


class Entry(NamedTuple):
    key: str
    type: type[msgspec.Struct] | None
    publisher: str
    subscribers: str
    rate: str


CATALOGUE: tuple[Entry, ...] = (
    Entry("falconry/sim/clock", m.SimClock, "simulator", "every service, launcher", "1/tick (20 Hz)"),
    Entry("falconry/sim/world", m.WorldModel, "simulator", "sensor_driver, camera, job_manager, mapper (a-priori map), planner (ground, height limits, body radius), launcher (clearance)", "at start, then 1 Hz"),
    Entry("falconry/sim/truth", m.GroundTruth, "simulator", "sensor_driver and camera (simulated sensors only), launcher (truth log, summary), `falconry evaluate tracking` (from recordings)", "1/tick"),
    Entry("falconry/sim/events", m.SimEvent, "simulator, launcher (restarts)", "launcher", "on event"),
    Entry("falconry/sim/resume", m.GroundTruth, "launcher (queryable: the last ground truth of the run)", "a restarted simulator", "on query"),
    Entry("falconry/sim/faults", m.FaultCommand, "simulator (from the scenario's fault schedule)", "sensor_driver, camera, launcher; every service's runtime in a simulation (never onboard: `--simulated-faults`)", "at each fault's time"),
    Entry("falconry/<uav>/odometry", m.Odometry, "simulator (onboard: flight controller bridge; without GNSS it carries the localizer's estimate and health)", "job_manager, planner; sensor_driver and localizer (without GNSS: scan registration; launch pose, or, restarted in flight, the belief)", "1/tick"),
    Entry("falconry/<uav>/imu", m.ImuBatch, "simulator (onboard: flight controller bridge)", "localizer", "1/tick, 200 samples/s (`[simulator.imu] rate_hz`)"),
    Entry("falconry/<uav>/localization", m.Odometry, "localizer (a UAV flying without GNSS)", "simulator (the flight controller flies on it), `falconry evaluate localization` (from recordings)", "per scan"),
    Entry("falconry/<uav>/points", m.PointCloud, "sensor_driver", "classifier, mapper (ray casting), tracker (track updates)", "10 Hz"),
    Entry("falconry/<uav>/points_truth", m.PointTruth, "sensor_driver (simulated LiDAR only)", "oracle detector, launcher (evaluation: targets in sight)", "with every scan"),
    Entry("falconry/<uav>/camera", m.CameraFrame, "camera (onboard: RealSense driver)", "object_detect, `falconry snapshot` (raw frames stay on their UAV)", "10 Hz, between LiDAR scans"),
    Entry("falconry/<uav>/camera_jpeg", m.CompressedFrame, "camera", "recorder, `falconry colors pick` (from recordings)", "1 Hz"),
    Entry("falconry/<uav>/colors", m.ColorUpdate, "`falconry colors pick --send`", "object_detect (live colour file)", "on demand"),
    Entry("falconry/<uav>/camera_detections", m.Detections, "object_detect (detector \"camera\")", "job_manager (balloons), launcher (summary)", "per frame, also when empty"),
    Entry("falconry/<uav>/labels", m.LabelSet, "classifier (or the oracle detector: from the rays' truth)", "mapper", "per scan"),
    Entry("falconry/<uav>/detections", m.Detections, "classifier (or the oracle detector)", "tracker, job_manager (targets; LiDAR heartbeat of the abort system), launcher (summary), `falconry evaluate tracking` (from recordings: the detection baseline)", "per scan, also when empty"),
    Entry("falconry/<uav>/map", m.VoxelMap, "mapper", "classifier (or the oracle detector: the grid), tracker (occupied voxels), planner (what to keep clear of)", "delta per scan (state changes), snapshot every 5 s"),
    Entry("falconry/<uav>/tracks", m.Tracks, "tracker", "job_manager, partners' trackers (fleet picture), launcher (summary), `falconry evaluate tracking` (from recordings)", "1/tick with tracks, else 1 Hz"),
    Entry("falconry/<uav>/command", m.MissionCommand, "job_manager", "planner", "on change, repeated every 2 s"),
    Entry("falconry/<uav>/trajectory", m.TrajectoryReference, "planner", "simulator (onboard: flight controller), job_manager (its own plan, shared in its status), launcher (data ages)", "on command, re-sent every 2 s"),
    Entry("falconry/<uav>/plan", m.PlanReport, "planner", "job_manager (a balloon every approach to which is blocked becomes a forbidden zone), launcher (summary)", "per plan and per guard action"),
    Entry("falconry/<uav>/status", m.UavStatus, "job_manager", "job_manager (partners: revenge mode, target claims, separation predicted from their planned references), planner (its own: the job manager watchdog), launcher", "5 Hz"),
    Entry("falconry/<scope>/ack/<service>", m.StepAck, "every service (lockstep only)", "simulator, same-UAV downstream services", "1/tick"),
    Entry("falconry/<scope>/health/<service>", m.ServiceHealth, "every service (queryable)", "`falconry health`; recorder and viewer (CPU and memory plots)", "on query; recorder and viewer ask every second"),
    Entry("falconry/<scope>/alive/<service>", None, "every service (liveliness token)", "simulator, job_manager, every service (its UAV's upstream)", "while alive"),
)


def markdown() -> str:
    rows = [
        "| key expression | type | publisher | subscribers | rate |",
        "| --- | --- | --- | --- | --- |",
    ]
    for e in CATALOGUE:
        type_name = f"`{e.type.__name__}`" if e.type else "liveliness token"
        rows.append(f"| `{e.key}` | {type_name} | {e.publisher} | {e.subscribers} | {e.rate} |")
    return "\n".join(rows) + "\n"


def _pattern_regex(pattern: str) -> re.Pattern:
    """falconry/<uav>/points → one key segment in place of each <placeholder>."""
    parts = re.split(r"(<[^>/]+>)", pattern)
    return re.compile("^" + "".join("[^/]+" if p.startswith("<") else re.escape(p) for p in parts) + "$")


_CATALOGUE_REGEXES = [(_pattern_regex(e.key), e) for e in CATALOGUE]


def uav_topics() -> list[str]:
    """The topics of a UAV's own keys (falconry/<uav>/<topic>): "odometry", "points", ..."""
    prefix = "falconry/<uav>/"
    return [e.key.removeprefix(prefix) for e in CATALOGUE if e.key.startswith(prefix) and "<" not in e.key[len(prefix):]]


def catalogue_entry(key: str) -> Entry | None:
    """The catalogue entry a concrete key belongs to (first match; run-wide keys come first)."""
    for regex, entry in _CATALOGUE_REGEXES:
        if regex.match(key):
            return entry
    return None
