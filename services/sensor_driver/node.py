"""sensor_driver node: simulated LiDAR scans of its UAV on falconry/<uav>/points, and for
evaluation only the id of what every ray hit on falconry/<uav>/points_truth.

Ray-casts the simulator's world (static obstacles from falconry/sim/world and those the mission's
survey lacks from falconry/sim/truth, standing targets and the own pose from the truth too) at
`rate_hz` of mission time with the LiDAR model the
parameters name, or else the one the scenario names for this UAV in the world model
(core.SensorDriverParams, services/lib/lidar/models.py). Both messages of a scan carry the same stamp; the
PointTruth never enters the PointCloud, so perception cannot see it. LiDAR faults scheduled on
falconry/sim/faults for this UAV are acted on here: `lidar_silent` publishes nothing,
`lidar_nan` an all-NaN cloud, `lidar_garbage` random ranges on every beam (truth -1 for both).
Every scan then goes through the sanity checks of services/lib/lidar/sanity.py (`sanity_checks`): one
that fails is still published, for the record, with the reason in `PointCloud.sanity`, which
makes every consumer skip its points; the failures are counted warnings.
Only this service and the simulator may read ground truth. Later issues add a recorded-file
source and real hardware behind the same output.

A UAV that flies without GNSS (the world model's `positioning` says "lidar") registers its scans
by its own odometry (falconry/<uav>/odometry: the localizer's estimate, which its flight
controller flies on) instead of the true pose: the rays are still cast from the true pose, and
every point keeps its place relative to the sensor (core.reregistered). Perception, the tracker
and the job manager then work in the estimate's frame, as they would onboard.
"""
from __future__ import annotations

import zlib

import numpy as np

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import FaultCommand, GroundTruth, Header, Odometry, PointCloud, PointTruth, Pose, WorldModel
from services.lib.geometry import heading_quaternion, yaw_of, yaw_rotation
from services.lib.lidar.models import LidarModel, lidar_model
from services.lib.lidar.rays import body_mask, pack_mask, unpack_mask
from services.lib.lidar.sanity import SanityLimits, ScanSanity, scan_figures
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node
from services.lib.world.primitives import Primitives, carrier, finite_pose, noise_stream_key, primitives_from_obstacles
from services.sensor_driver.core import FALLBACK_MODEL, SensorDriverParams, model_scan, reregistered, scan_ranges
from services.sensor_driver.faults import faulty_scan, lidar_faults

RNG_SALT = zlib.crc32(b"sensor")  # a fixed number, so the stream differs from other services'


def warm_up(params: SensorDriverParams, model: LidarModel) -> None:
    """Run the scan's kernels once on an empty world (compiled, or loaded from numba's cache)."""
    model_scan(params, model, np.zeros(3), 0.0, Primitives(planes=[-1.0]), np.random.default_rng(0))
    scan_figures(np.zeros((1, 3), np.float32), np.zeros(3), *scan_ranges(params, model))  # float32 as scans


class SensorDriverNode(Node):
    service = "sensor_driver"
    upstream = ()
    params_type = SensorDriverParams

    @classmethod
    def preload(cls) -> None:
        params = SensorDriverParams()
        warm_up(params, lidar_model(FALLBACK_MODEL, params.rate_hz))

    def setup(self) -> None:
        p: SensorDriverParams = self.params
        if not p.rate_hz > 0:
            raise ValueError(f"sensor_driver.rate_hz must be > 0, got {p.rate_hz}")
        self._use_model(p.model or FALLBACK_MODEL)
        self.period_ns = max(1, int(round(1e9 / p.rate_hz)))
        self.static: Primitives | None = None  # the world model's obstacles and the truth's, built when either changes
        self.obstacles = None  # the world model's
        self.unsurveyed: list = []  # the truth's
        self.truth: GroundTruth | None = None
        self.rng: np.random.Generator | None = None
        self.rng_key: tuple[int, int] | None = None
        self.last_slot = -1
        self.faults = lidar_faults()
        self.sanity = ScanSanity(SanityLimits(max_return_share=p.max_return_share)) if p.sanity_checks else None
        self._unposed = 0
        self._bad_input = CountedWarnings(self.log)
        warm_up(p, self.model)  # compiled now, before the liveliness token: the first scan must not stall a tick
        self.points_pub = self.publisher(self.topic("points"), PointCloud)
        self.truth_pub = self.publisher(self.topic("points_truth"), PointTruth)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        self.subscribe(keys.TRUTH, GroundTruth, self.on_truth)
        self.subscribe(self.topic(keys.ODOMETRY), Odometry, self.on_odometry)
        self.odometry: Odometry | None = None
        self.registered_by_odometry = False  # the world model says this UAV flies without GNSS
        self.subscribe(keys.FAULTS, FaultCommand, self.on_fault, keep=None)  # events: each one counts

    def _use_model(self, name: str) -> None:
        p: SensorDriverParams = self.params
        self.model = lidar_model(name, p.rate_hz)
        self.min_range, self.max_range = scan_ranges(p, self.model)
        self._masks: dict[int, np.ndarray] = {}
        # What the scan's pose noise is (one draw per scan of position and attitude, core.scan).
        self._pose_covariance = np.diag([p.position_noise ** 2] * 3 + [p.attitude_noise ** 2] * 3)

    def _mask(self, frame: int) -> np.ndarray:
        """The packed body mask of a frame (a repeating pattern's once for all)."""
        key = 0 if self.model.repeats else frame
        mask = self._masks.get(key)
        if mask is None:
            mask = pack_mask(body_mask(self.model.directions(frame), self.params.body_box))
            if self.model.repeats:
                self._masks[key] = mask
        return mask

    def on_world(self, world: WorldModel, key: str) -> None:
        wanted = world.sensors.get(self.uav, "")
        if not self.params.model and wanted and wanted.strip().lower() != self.model.name:
            try:
                self._use_model(wanted)
                self.log.info("LiDAR model %s (the scenario's)", self.model.name)
            except ValueError as err:
                self.log.error("keeping LiDAR model %s: %s", self.model.name, err)
        if world.obstacles != self.obstacles:
            self.obstacles = world.obstacles
            self.static = primitives_from_obstacles([*self.obstacles, *self.unsurveyed])
        lidar = world.positioning.get(self.uav) == "lidar"
        if lidar != self.registered_by_odometry:
            self.registered_by_odometry = lidar
            self.log.info("scans registered by %s", "the odometry (no GNSS)" if lidar else "the true pose")
        if (key := noise_stream_key(world, self.uav)) != self.rng_key:
            self.rng_key = key
            self.rng = np.random.default_rng([*key, RNG_SALT])

    def on_truth(self, truth: GroundTruth, key: str) -> None:
        self.truth = truth
        if truth.obstacles != self.unsurveyed:  # the same every tick of a run: compared, not rebuilt
            self.unsurveyed = truth.obstacles
            if self.obstacles is not None:
                self.static = primitives_from_obstacles([*self.obstacles, *self.unsurveyed])

    def on_odometry(self, odometry: Odometry, key: str) -> None:
        self.odometry = odometry

    def on_fault(self, fault: FaultCommand, key: str) -> None:
        if (said := self.faults.take(self.uav, fault)) is not None:
            self.log.warning("LiDAR fault %s", said)

    def _scan(self, origin: np.ndarray, heading: float, world: Primitives, rng: np.random.Generator,
              frame: int = 0):
        return model_scan(self.params, self.model, origin, heading, world, rng, frame)

    def on_tick(self, now_ns: int) -> None:
        slot = now_ns // self.period_ns
        if slot <= self.last_slot or self.static is None or self.truth is None or self.rng is None:
            return
        me = carrier(self.truth, self.uav)
        if me is None:
            return
        self.last_slot = slot
        if not finite_pose(me):
            self._unposed += 1
            self._bad_input.update({"scans skipped: our pose in the ground truth is not finite": self._unposed})
            return
        fault = self.faults.active(now_ns)
        if fault == "lidar_silent":
            return
        origin = np.asarray(me.position, dtype=float) + yaw_rotation(me.heading) @ np.asarray(self.params.mount)
        world = self.static.with_targets(self.truth.targets)
        result = self._scan(origin, me.heading, world, self.rng, frame=int(slot))
        if fault is not None:
            beams = self.model.directions(int(slot)) @ yaw_rotation(me.heading).T
            result = faulty_scan(result, fault, origin, beams, self.min_range, self.max_range, self.rng)
        points, origin, heading = self._registered(result.points, origin, me.heading)
        rows, cols = result.hits.shape
        mask = self._mask(int(slot))
        sanity = self._sanity(now_ns, points, origin, unpack_mask(mask, cols))
        self.points_pub.put(PointCloud(
            header=Header(stamp=now_ns),
            width=cols,
            height=rows,
            sensor_pose=Pose(position=tuple(origin.tolist()), orientation=heading_quaternion(heading)),
            points=from_numpy(points),
            intensity=None if result.intensity is None else from_numpy(result.intensity),
            sensor_model=self.model.name,
            min_range=self.min_range,
            max_range=self.max_range,
            frame=int(slot),
            mask=from_numpy(mask),
            pose_covariance=from_numpy(self._pose_covariance),
            sanity=sanity,
        ))
        self.truth_pub.put(PointTruth(
            header=Header(stamp=now_ns),
            width=cols,
            height=rows,
            hits=from_numpy(result.hits),
            targets=[t.id for t in self.truth.targets],
        ))

    def _sanity(self, now_ns: int, points: np.ndarray, origin: np.ndarray, blocked: np.ndarray) -> str:
        """Why the scan fails the sanity checks ("" : it passes), the failures counted by kind."""
        if self.sanity is None:
            return ""
        reason = self.sanity.check(now_ns, scan_figures(points, origin, self.min_range, self.max_range, blocked))
        if reason:
            self._bad_input.update({f"scans failing the sanity check ({check})": count
                                    for check, count in self.sanity.failures.items()})
        return reason

    def _registered(self, points: np.ndarray, origin: np.ndarray,
                    heading: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The scan, the sensor's origin and heading as the vehicle registers them: by the true pose,
        or by its odometry when it flies without GNSS (then by the truth until the first odometry)."""
        odometry = self.odometry
        if not self.registered_by_odometry or odometry is None:
            return points, origin, heading
        believed_heading = yaw_of(odometry.pose.orientation)
        believed_origin = np.asarray(odometry.pose.position, dtype=float) + \
            yaw_rotation(believed_heading) @ np.asarray(self.params.mount)
        moved = reregistered(points, origin, heading, believed_origin, believed_heading)
        return moved, believed_origin, believed_heading


NODE = SensorDriverNode
