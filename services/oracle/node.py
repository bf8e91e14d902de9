"""oracle node (evaluation only): noisy detections from the points that really hit a target, and
the label sets of a classifier that never errs.

Subscribes falconry/<uav>/points (PointCloud) and falconry/<uav>/points_truth (PointTruth) of
its UAV, pairs them by stamp and publishes, for every scan and with its stamp,
falconry/<uav>/detections (Detections, detector "oracle") and, once the map's geometry is known
(falconry/<uav>/map, VoxelMap), falconry/<uav>/labels (LabelSet, for the mapper). It replaces the
classifier in a run (`falconry sim --detector oracle`); it never reads GroundTruth. See core.py.
"""
from __future__ import annotations

import numpy as np

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, LabelSet, PointCloud, PointTruth, VoxelMap
from services.lib.lidar.models import beam_spacing
from services.lib.runtime.node import Node
from services.lib.voxels.grid import GridGeometry
from services.lib.voxels.replica import MapReplica, geometry_of
from services.oracle.core import OracleParams, ScanPairs, detect, label, scan_rng, warm_up


class OracleNode(Node):
    service = "oracle"
    upstream = ("sensor_driver",)
    params_type = OracleParams

    @classmethod
    def preload(cls) -> None:
        warm_up()

    def setup(self) -> None:
        warm_up()  # compiled before the liveliness token: the first scan must not stall a tick
        self.pairs = ScanPairs()
        self.detections_pub = self.publisher(self.topic("detections"), Detections)
        self.labels_pub = self.publisher(self.topic("labels"), LabelSet)
        self.geometry: GridGeometry | None = None
        self._slot = np.zeros(0, dtype=np.int32)
        self.subscribe(self.topic("map"), VoxelMap, self.on_map)  # its geometry only
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self.subscribe(self.topic("points_truth"), PointTruth, self.on_truth)

    def on_map(self, msg: VoxelMap, key: str) -> None:
        try:
            geometry = geometry_of(msg.origin, msg.shape, msg.voxel_size)
        except ValueError:
            return
        if geometry != self.geometry and geometry.size <= MapReplica.MAX_VOXELS:
            self.geometry = geometry
            self._slot = np.full(geometry.size, -1, dtype=np.int32)

    def on_points(self, msg: PointCloud, key: str) -> None:
        self._publish(self.pairs.add(msg.header.stamp, cloud=msg))

    def on_truth(self, msg: PointTruth, key: str) -> None:
        self._publish(self.pairs.add(msg.header.stamp, truth=msg))

    def _publish(self, pair: tuple[PointCloud, PointTruth] | None) -> None:
        if pair is None:
            return
        cloud, truth = pair
        stamp = cloud.header.stamp
        try:
            sensor = np.asarray(cloud.sensor_pose.position, dtype=np.float64)
            found = detect(to_numpy(cloud.points), to_numpy(truth.hits), self.params, scan_rng(stamp, self.uav),
                           sensor if np.isfinite(sensor).all() else None,
                           beam_spacing(cloud.sensor_model, cloud.height, cloud.width))
        except ValueError as err:
            self.log.warning("scan at %d ns skipped: %s", stamp, err)
            return
        self.detections_pub.put(Detections(
            header=Header(stamp=stamp, source=stamp),
            detector="oracle",
            positions=from_numpy(found.positions),
            covariances=from_numpy(found.covariances),
            point_counts=from_numpy(found.point_counts),
            extents=from_numpy(found.extents),
            sensor_position=tuple(cloud.sensor_pose.position),
        ))
        if self.geometry is not None:
            self._publish_labels(stamp, cloud, truth)

    def _publish_labels(self, stamp: int, cloud: PointCloud, truth: PointTruth) -> None:
        labels = label(to_numpy(cloud.points), to_numpy(truth.hits), self.geometry, self._slot)
        self.labels_pub.put(LabelSet(
            header=Header(stamp=stamp),
            sensor_origin=tuple(cloud.sensor_pose.position),
            points=from_numpy(labels.points),
            point_labels=from_numpy(labels.point_labels),
            voxel_size=self.geometry.voxel_size,
            voxels=from_numpy(labels.voxels),
            voxel_labels=from_numpy(labels.voxel_labels),
            voxel_weights=from_numpy(labels.voxel_weights),
        ))


NODE = OracleNode
