"""localizer node: LiDAR scans and IMU samples in, the UAV's pose out (seed 003's Grape; see core.py).

Subscribes falconry/<uav>/odometry (Odometry: only the first one, the launch pose, known without
GNSS, which starts the map frame; a localizer restarted in flight gets the flight controller's
belief instead, a previous estimate, whose health says so: the map frame starts there with that
estimate's covariance, which every later estimate carries on; a belief without a usable
covariance starts it lost: core.restart_frame_covariance), falconry/<uav>/imu (ImuBatch, every batch) and
falconry/<uav>/points (PointCloud: its world-frame points are taken back to the sensor frame by its
sensor_pose, which is how the driver registered them). Publishes falconry/<uav>/localization
(Odometry with the covariance and the health, stamped with the scan's stamp) for every scan fused.

The first scan at the launch point shows where the sensor driver has the LiDAR in the body frame;
one further than MOUNT_TOLERANCE from lidar_mount (the same mount, stated in two services'
parameters) is warned about once.

Should gtsam give up on the graph (an indeterminate system), every later scan is answered with the
last estimate and health "lost" (the job manager then lands), until the service restarts.

A scan is fused once the IMU samples up to its stamp are in (an ImuBatch stamped at or after it);
lockstep releases a tick's IMU batch first (subscription order), so then at once. A scan that
waits longer than max_imu_wait is dropped and counted. In a GNSS-denied run the flight controller
(the simulator) flies on this estimate and publishes it as the UAV's odometry.
"""
from __future__ import annotations

from collections import deque

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Header, ImuBatch, Odometry, PointCloud, Pose
from services.lib.geometry import quaternion, rotation_matrix
from services.localizer.core import (Localizer, LocalizerParams, ScanResult, restart_frame_covariance,
                                     sensor_frame, warm_up)
from services.localizer.graph import worst_position_sigma
from services.lib.runtime.clock import to_ns
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node


# The estimate is published on fixed grids, far below anything it is good for. iSAM2 is not
# bit-reproducible from run to run: fed the same scans and samples, its estimate differs now and then
# in the last bits (measured: 1.7e-14 m, in one run in three, at a batch of the fixed-lag window
# leaving), and the flight controller flies on it, so one bit would make a lockstep run's every later
# message differ. On the grids the same run publishes the same bytes.
POSITION_STEP = 1e-6  # m (and m/s for the velocity)
ORIENTATION_STEP = 1e-9  # of each quaternion component
COVARIANCE_STEP = 1e-12  # m², rad², m·rad
# m: the first scan at the launch point shows the LiDAR's mount as the sensor driver has it; further
# from lidar_mount than this, the two services' parameters disagree (warned once: every feature
# would sit that far off in the body frame)
MOUNT_TOLERANCE = 0.02


def _on_grid(values, step: float) -> np.ndarray:
    return np.round(np.asarray(values, dtype=np.float64) / step) * step


def _reproducible(values, step: float) -> tuple[float, ...]:
    return tuple(_on_grid(values, step).tolist())


class LocalizerNode(Node):
    service = keys.LOCALIZER
    upstream = ("sensor_driver",)
    params_type = LocalizerParams

    @classmethod
    def preload(cls) -> None:
        warm_up(LocalizerParams())

    def setup(self) -> None:
        warm_up(self.params)  # compiled now, before the liveliness token: the first scan must not stall a tick
        self.core = Localizer(self.params)
        self.pub = self.publisher(self.topic(keys.LOCALIZATION), Odometry)
        # Lockstep releases a tick's inputs in subscription order: the launch pose, then the IMU
        # samples up to the tick, then its scan.
        self.subscribe(self.topic(keys.ODOMETRY), Odometry, self.on_odometry)
        self.subscribe(self.topic(keys.IMU), ImuBatch, self.on_imu, keep=None)  # every sample counts
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self._imu_until: int | None = None  # the IMU's samples are in up to (not including) this stamp
        self._last_sample: int | None = None
        self._waiting: deque[PointCloud] = deque()
        self._health = ""
        self._check_mount = False  # on the first scan after a start at the launch point
        self.mount_seen: np.ndarray | None = None  # (3,) m, the LiDAR's mount that scan showed
        self._last: Odometry | None = None  # the latest estimate published
        self._failed: Odometry | None = None  # once the graph failed: the last estimate, health "lost"
        self._refused: dict[str, int] = {}
        self._bad_input = CountedWarnings(self.log)

    def on_odometry(self, msg: Odometry, key: str) -> None:
        if self.core.started:
            return  # in a GNSS-denied run, our own estimate relayed by the flight controller
        rotation = rotation_matrix(msg.pose.orientation)
        in_flight = bool(msg.health)  # a belief the flight controller carries on from an earlier estimate
        frame = restart_frame_covariance(None if msg.covariance is None else to_numpy(msg.covariance),
                                         self.params.graph.lost_position_sigma) if in_flight else None
        try:
            self.core.start(msg.header.stamp, rotation, np.asarray(msg.pose.position), np.asarray(msg.velocity),
                            frame)
        except ValueError as exc:
            self._refuse("launch poses refused (not finite, or not a rotation)", exc)
            return
        if in_flight:
            self.log.warning("restarted in flight: map frame started at the flight controller's %s belief "
                             "(%.2f, %.2f, %.2f), position sigma %.2f m carried on", msg.health, *msg.pose.position,
                             worst_position_sigma(frame))
        else:
            self.log.info("map frame started at the launch pose (%.2f, %.2f, %.2f)", *msg.pose.position)
            self._check_mount = True

    def on_imu(self, msg: ImuBatch, key: str) -> None:
        if not self.core.started:
            return
        stamps, accelerometer, gyroscope = to_numpy(msg.stamps), to_numpy(msg.accelerometer), to_numpy(msg.gyroscope)
        if stamps.dtype.kind not in "iu" or accelerometer.size != 3 * stamps.size or gyroscope.size != 3 * stamps.size:
            self._refuse("IMU batches refused (stamps not integers, or not one (3,) sample of each per stamp)")
            return
        stamps = stamps.astype(np.int64).reshape(-1)
        after = self.core.start_stamp if self._last_sample is None else self._last_sample + 1
        keep = stamps >= after
        try:
            self.core.add_imu(stamps[keep], accelerometer.reshape(-1, 3)[keep], gyroscope.reshape(-1, 3)[keep])
        except ValueError as exc:
            self._refuse("IMU batches refused (shapes, or samples not finite)", exc)
            return
        if keep.any():
            self._last_sample = int(stamps[keep][-1])
        self._imu_until = max(self._imu_until or 0, msg.header.stamp)
        self._fuse_waiting()

    def on_points(self, msg: PointCloud, key: str) -> None:
        if not self.core.started or msg.header.stamp < self.core.start_stamp:
            return
        if msg.sanity:  # the driver found the scan broken: the IMU carries the estimate past it
            self._refuse("scans skipped: they failed the driver's sanity check")
            return
        self._waiting.append(msg)
        self._fuse_waiting()

    def _fuse_waiting(self) -> None:
        wait = to_ns(self.params.max_imu_wait)
        while self._waiting:
            scan = self._waiting[0]
            ready = self._imu_until is not None and self._imu_until >= scan.header.stamp
            if not ready and self._waiting[-1].header.stamp - scan.header.stamp <= wait:
                return
            self._waiting.popleft()
            if ready:
                self._fuse(scan)
            else:
                self._refuse("scans dropped: no IMU samples up to their stamp within max_imu_wait")

    def _fuse(self, msg: PointCloud) -> None:
        if self._failed is not None:  # the graph cannot go on: say so with every scan
            self.pub.put(msgspec.structs.replace(self._failed, header=Header(stamp=msg.header.stamp)))
            return
        try:
            points = sensor_frame(to_numpy(msg.points).reshape(msg.height, msg.width, 3),
                                  np.asarray(msg.sensor_pose.position), rotation_matrix(msg.sensor_pose.orientation))
            result = self.core.add_scan(msg.header.stamp, points)
            if self._check_mount:
                self._compare_mount(np.asarray(msg.sensor_pose.position))
        except ValueError as exc:
            self._refuse("scans refused (shape, or stamped before the last one)", exc)
            return
        except RuntimeError as exc:  # gtsam gave up on the system (e.g. indeterminate): no estimate from here on
            self.log.error("the factor graph failed, positioning lost until the localizer restarts: %s",
                           str(exc).strip().splitlines()[0])
            last = self._last or Odometry(header=Header(stamp=msg.header.stamp), pose=Pose(
                position=(0.0, 0.0, 0.0), orientation=(1.0, 0.0, 0.0, 0.0)))
            self._failed = msgspec.structs.replace(last, health="lost")
            self.pub.put(msgspec.structs.replace(self._failed, header=Header(stamp=msg.header.stamp)))
            return
        self._publish(result)

    def _compare_mount(self, sensor_position: np.ndarray) -> None:
        self._check_mount = False
        self.mount_seen = seen = self.core.mount_seen(sensor_position)
        if np.linalg.norm(seen - np.asarray(self.params.lidar_mount)) > MOUNT_TOLERANCE:
            self.log.warning("the scans put the LiDAR at (%.3f, %.3f, %.3f) m in the body frame at launch, "
                             "lidar_mount says (%.3f, %.3f, %.3f): set [localizer] lidar_mount to the sensor "
                             "driver's mount", *seen, *self.params.lidar_mount)

    def _publish(self, result: ScanResult) -> None:
        e = result.estimate
        if e.health != self._health:
            say = self.log.info if e.health == "tracking" else self.log.warning
            say("positioning %s (position sigma %.2f m, %d of %d features matched)", e.health, e.position_sigma,
                result.associated, result.planes + result.edges)
            self._health = e.health
        self._last = Odometry(header=Header(stamp=e.stamp_ns), pose=Pose(
            position=_reproducible(e.translation, POSITION_STEP),
            orientation=_reproducible(quaternion(e.rotation), ORIENTATION_STEP)),
            velocity=_reproducible(e.velocity, POSITION_STEP),
            covariance=from_numpy(_on_grid(e.covariance, COVARIANCE_STEP)), health=e.health)
        self.pub.put(self._last)

    def _refuse(self, what: str, why: Exception | None = None) -> None:
        count = self._refused[what] = self._refused.get(what, 0) + 1
        if why is not None and count == 1:
            self.log.warning("the first of the %s: %s", what, why)
        self._bad_input.update(self._refused)


NODE = LocalizerNode
