"""classifier node: scans in, detections and label sets out (first version, see core.py).

Subscribes falconry/<uav>/points (PointCloud) and falconry/<uav>/map (VoxelMap, for its
map replica). Publishes, for every scan and stamped with the scan's stamp,
falconry/<uav>/detections (Detections, detector "classifier") and falconry/<uav>/labels
(LabelSet, for the mapper). The map arrives one tick late (the mapper is downstream of
us), which the seed's method tolerates: the map changes slowly.
"""
from __future__ import annotations

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, LabelSet, PointCloud, VoxelMap
from services.classifier.core import ClassifierCore, ClassifierParams
from services.runtime.node import Node


class ClassifierNode(Node):
    service = "classifier"
    upstream = ("sensor_driver",)
    params_type = ClassifierParams

    def setup(self) -> None:
        self.core = ClassifierCore(self.params)
        self.detections_pub = self.publisher(self.topic("detections"), Detections)
        self.labels_pub = self.publisher(self.topic("labels"), LabelSet)
        # Lockstep releases a tick's inputs in subscription order: map updates first, so each
        # scan is classified against the freshest map.
        self.subscribe(self.topic("map"), VoxelMap, self.on_map)
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self._ignored_deltas = 0

    def on_map(self, msg: VoxelMap, key: str) -> None:
        applied = self.core.apply_map(
            msg.snapshot, msg.origin, msg.shape, msg.voxel_size, msg.default_value,
            to_numpy(msg.indices), to_numpy(msg.values),
        )
        if not applied:
            self._ignored_deltas += 1
            if self._ignored_deltas in (1, 100):
                self.log.info("map delta with another geometry ignored until the next snapshot")

    def on_points(self, msg: PointCloud, key: str) -> None:
        sensor = msg.sensor_pose.position
        scan = self.core.classify(to_numpy(msg.points), sensor)
        stamp = msg.header.stamp
        self.detections_pub.put(Detections(
            header=Header(stamp=stamp),
            detector="classifier",
            positions=from_numpy(scan.positions),
            covariances=from_numpy(scan.covariances),
            point_counts=from_numpy(scan.point_counts),
            extents=from_numpy(scan.extents),
            sensor_position=tuple(sensor),
        ))
        self.labels_pub.put(LabelSet(
            header=Header(stamp=stamp),
            sensor_origin=tuple(sensor),
            points=from_numpy(scan.points),
            point_labels=from_numpy(scan.point_labels),
            voxel_size=self.core.map.voxel_size,
            voxels=from_numpy(scan.voxels),
            voxel_labels=from_numpy(scan.voxel_labels),
            voxel_weights=from_numpy(scan.voxel_weights),
        ))


NODE = ClassifierNode
