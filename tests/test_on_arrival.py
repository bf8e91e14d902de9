"""In real time a sighting's stages act on their input as it arrives: the tracker publishes the
tracks a detection set corrected, the job manager decides on a message holding a sighting, and
the planner plans a new command, without waiting for the next clock tick (issue 39's
scan-to-reference latency). In lockstep they wait for the tick, where the input belongs (the
determinism tests hold that). The nodes run in-process on the fuzz
harness's fake session (tests/tools/fuzz.py): a real-time clock, every other input realistic."""
from __future__ import annotations

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import (Detections, GroundTruth, Header, MissionCommand, Odometry, Tracks, TrajectoryReference,
                              VoxelMap, WorldModel)
from tests.tools.fuzz import UAV, WiredNode, corpus, encode, wire


def test_the_tracker_publishes_the_tracks_a_detection_set_corrected_before_the_next_tick():
    seeds, tracker = corpus(), wire("tracker")
    tracks_key = keys.uav(UAV, "tracks")
    detections = seeds[Detections]
    tracker.tick(100_000_000)
    for seq in (1, 2, 3):  # a track to confirm: a few sets of the same two targets
        stamp = tracker.stamp + 1  # newer than the clock: mission time has reached the scan
        tracker.deliver(tracker.keys_of[Detections], encode(msgspec.structs.replace(
            detections, header=Header(sender=detections.header.sender, seq=seq, stamp=stamp))))
        published = tracker.published(Tracks, tracks_key)
        assert published.header.stamp == stamp, "no tracks until the tick: the detections waited for it"
        assert published.header.source == stamp and len(published.tracks) == 2
        tracker.tick(100_000_000)
    assert any(track.confirmed for track in tracker.published(Tracks, tracks_key).tracks)


def test_the_planner_plans_a_new_command_as_it_arrives():
    seeds, planner = corpus(), wire("planner")
    trajectory_key = keys.uav(UAV, "trajectory")
    for msg_type in (WorldModel, VoxelMap, Odometry):
        planner.deliver(planner.keys_of[msg_type], encode(seeds[msg_type]))
    planner.tick(100_000_000)
    assert trajectory_key not in planner.session.published, "a trajectory without a command"
    command = seeds[MissionCommand]
    for command_id in (1, 2):  # the first command, then a new one while the first is flown
        planner.deliver(planner.keys_of[MissionCommand], encode(msgspec.structs.replace(
            command, header=Header(sender=command.header.sender, seq=command_id, stamp=planner.stamp),
            command_id=command_id)))
        assert trajectory_key in planner.session.published, "the command waited for the next tick"
        reference = planner.published(TrajectoryReference, trajectory_key)
        assert reference.command_id == command_id, "the new command waited for the next tick"
        assert reference.start == planner.stamp
        planner.tick(100_000_000)


def test_a_command_held_before_the_first_tick_is_planned_at_that_tick_s_time():
    """A planner that starts (or restarts) during a real-time run hears the command before the clock:
    planned when the first tick releases it, the reference starts at that tick, not at time 0."""
    seeds, planner = corpus(), wire("planner", first_tick=False)
    for msg_type in (WorldModel, VoxelMap, Odometry, MissionCommand):
        planner.deliver(planner.keys_of[msg_type], encode(seeds[msg_type]))
    assert keys.uav(UAV, "trajectory") not in planner.session.published, "planned before the clock was known"
    planner.tick(5_000_000_000)
    reference = planner.published(TrajectoryReference, keys.uav(UAV, "trajectory"))
    assert reference.command_id == seeds[MissionCommand].command_id and reference.start == 5_000_000_000


def test_the_job_manager_decides_on_a_sighting_as_it_arrives():
    seeds, manager = corpus(), wire("job_manager")
    command_key = keys.uav(UAV, "command")
    for service in ("sensor_driver", "tracker", "planner", "classifier"):  # the pre-flight check
        manager.token(keys.alive(UAV, service), True)
    manager.deliver(manager.keys_of[WorldModel], encode(seeds[WorldModel]))
    ground = seeds[Odometry].pose.position
    for height in (ground[2],) * 3 + (5.0,) * 5:  # take off, then search at 5 m
        fly(manager, (ground[0], ground[1], height))
        sight(manager, "detections", [])  # the LiDAR's scans, empty
        manager.tick(50_000_000)
    searching = manager.published(MissionCommand, command_key)
    assert searching.action == "scan", searching
    balloon = min((t.position for t in seeds[GroundTruth].targets if t.kind == "balloon"),
                  key=lambda position: np.linalg.norm(np.subtract(position, ground)))
    sight(manager, "camera_detections", [balloon])
    stop = manager.published(MissionCommand, command_key)
    assert stop.command_id == searching.command_id + 1, "the sighting waited for the next tick"
    assert stop.action == "stop", stop


def fly(node: WiredNode, position) -> None:
    """Odometry at the node's time: the vehicle at rest at `position`."""
    odometry = corpus()[Odometry]
    node.deliver(keys.uav(UAV, "odometry"), encode(msgspec.structs.replace(
        odometry, header=Header(sender="sim/simulator", seq=node.step + 1, stamp=node.stamp),
        pose=msgspec.structs.replace(odometry.pose, position=tuple(position)))))


def sight(node: WiredNode, topic: str, positions: list) -> None:
    """A detection set at the node's time on `topic` (a detector's: the LiDAR's or the camera's)."""
    n = len(positions)
    node.deliver(keys.uav(UAV, topic), encode(Detections(
        header=Header(sender=f"{UAV}/{topic}", seq=node.step + 1, stamp=node.stamp), detector=topic,
        positions=from_numpy(np.asarray(positions, dtype=np.float64).reshape(-1, 3)),
        covariances=from_numpy(np.tile(0.05 * np.eye(3), (n, 1, 1))),
        point_counts=from_numpy(np.full(n, 40, dtype=np.int32)), extents=from_numpy(np.full(n, 0.6, dtype=np.float32)),
        sensor_position=corpus()[Odometry].pose.position)))
