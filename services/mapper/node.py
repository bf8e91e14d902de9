"""mapper node: scans and label sets in, the map out (seed 000 sec. III-A, C, D, E; see core.py).

Subscribes falconry/<uav>/points (PointCloud: the rays, empty ones and the body mask included)
and falconry/<uav>/labels (LabelSet: the classifier's voxel label sets of the same scan), and
falconry/sim/world when the a-priori map is the world model's static obstacles. A scan is
integrated once both halves with its stamp are there (in lockstep, in the same tick). Publishes
falconry/<uav>/map (VoxelMap): after every scan a delta of the voxels whose state changed,
stamped with the scan's stamp, and a snapshot on the first tick and every `snapshot_period`.
"""
from __future__ import annotations

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Header, LabelSet, PointCloud, VoxelMap, WorldModel
from services.lib.lidar.rays import ScanRays, scan_rays
from services.lib.runtime.clock import to_ns
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.errors import UsageError
from services.lib.runtime.node import Node
from services.lib.voxels.apriori import load_map_file, obstacle_voxels
from services.mapper.core import MapDelta, MapperCore, MapperParams, warm_up

PENDING = 8  # scans waiting for their other half; older ones are dropped (counted)


class MapperNode(Node):
    service = "mapper"
    upstream = ("sensor_driver", "classifier", "oracle")  # whichever labels the scans
    params_type = MapperParams

    @classmethod
    def preload(cls) -> None:
        warm_up(MapperParams())

    def setup(self) -> None:
        warm_up(self.params)  # compiled now, before the liveliness token: the first scan must not stall a tick
        self.core = MapperCore(self.params)
        self.map_pub = self.publisher(self.topic("map"), VoxelMap)
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self.subscribe(self.topic("labels"), LabelSet, self.on_labels)
        self._rays: dict[int, ScanRays] = {}  # scan stamp -> its rays
        self._labels: dict[int, LabelSet] = {}
        self._snapshot_period_ns = to_ns(self.params.snapshot_period)
        self._last_snapshot_ns: int | None = None
        self._warned_voxel_size = False
        self._unpaired = 0
        self._bad_input = CountedWarnings(self.log)
        self._warned_model = False
        self._apriori_done = False
        apriori = self.params.apriori
        if apriori == "world":
            self.subscribe(keys.WORLD, WorldModel, self.on_world)
        elif apriori:
            try:
                indices, values = load_map_file(apriori, self.core.geometry)
            except ValueError as exc:
                raise UsageError(str(exc)) from None
            self.core.pin(indices, values)
            self._apriori_done = True
            self.log.info("a-priori map %s: %d voxels", apriori, len(indices))

    def on_world(self, msg: WorldModel, key: str) -> None:
        if self._apriori_done:
            return
        pinned = obstacle_voxels(msg.obstacles, self.core.geometry)
        self.core.pin(pinned)
        self._apriori_done = True
        self._last_snapshot_ns = None  # the next tick publishes the pinned map whole
        self.log.info("a-priori map from the world model: %d voxels of %d static obstacles pinned occupied",
                      len(pinned), len(msg.obstacles))

    def on_points(self, msg: PointCloud, key: str) -> None:
        if msg.sanity:  # a scan the driver found broken carves no free space (the classifier labels none)
            return
        rays = scan_rays(to_numpy(msg.points), msg.width, msg.sensor_model, msg.frame, msg.sensor_pose.position,
                         msg.sensor_pose.orientation, None if msg.mask is None else to_numpy(msg.mask))
        if rays.beams is None and not self._warned_model:
            self._warned_model = True
            self.log.warning("LiDAR model %r unknown or not matching its scans: rays without a return are not "
                             "cast (free space only up to returns)", msg.sensor_model)
        self._rays[msg.header.stamp] = rays
        self._integrate_ready()

    def on_labels(self, msg: LabelSet, key: str) -> None:
        if msg.voxel_size != self.core.voxel_size and not self._warned_voxel_size:
            self._warned_voxel_size = True
            self.log.warning("label sets use %.3f m voxels, the map %.3f m", msg.voxel_size, self.core.voxel_size)
        self._labels[msg.header.stamp] = msg
        self._integrate_ready()

    def _integrate_ready(self) -> None:
        for stamp in sorted(set(self._rays) & set(self._labels)):
            rays = self._rays.pop(stamp)
            labels = self._labels.pop(stamp)
            delta = self.core.integrate(stamp, rays, to_numpy(labels.voxels), to_numpy(labels.voxel_labels),
                                        to_numpy(labels.voxel_weights))
            self._publish(stamp, snapshot=False, delta=delta)
        for waiting in (self._rays, self._labels):
            while len(waiting) > PENDING:
                waiting.pop(min(waiting))
                self._unpaired += 1
        c = self.core.counters
        self._bad_input.update({"label sets refused (impossible contents)": c.rejected_label_sets,
                                "scans whose rays could not be cast (pose or field lengths)": c.rejected_rays,
                                "label voxels outside the map dropped": c.voxels_outside,
                                "scans dropped that never got their other half (points or labels)": self._unpaired})

    def on_tick(self, now_ns: int) -> None:
        if self._last_snapshot_ns is None or now_ns - self._last_snapshot_ns >= self._snapshot_period_ns:
            self._last_snapshot_ns = now_ns
            self._publish(now_ns, snapshot=True, delta=self.core.snapshot())

    def _publish(self, stamp: int, snapshot: bool, delta: MapDelta) -> None:
        core = self.core
        self.map_pub.put(VoxelMap(
            header=Header(stamp=stamp),
            snapshot=snapshot,
            voxel_size=core.voxel_size,
            origin=tuple(float(v) for v in core.origin),
            shape=core.shape,
            indices=from_numpy(delta.indices),
            values=from_numpy(delta.values),
            default_value=self.params.unknown_value,
        ))


NODE = MapperNode
