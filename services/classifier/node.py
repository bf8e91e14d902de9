"""classifier node: scans in, detections and label sets out (seed 000 sec. III-B; see core.py).

Subscribes falconry/<uav>/points (PointCloud) and falconry/<uav>/map (VoxelMap, for its map
replica). Publishes, for every scan and stamped with the scan's stamp,
falconry/<uav>/detections (Detections, detector "classifier") and falconry/<uav>/labels
(LabelSet, for the mapper, with the stamp of the map the classification used). In lockstep the
map update made from scan k arrives one tick later, before scan k+1 (scans come every other
tick): every scan is classified against the map that integrated the scan before it, as in VoFOD.
"""
from __future__ import annotations

import numpy as np

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, LabelSet, PointCloud, VoxelMap
from services.classifier.core import ClassifierCore, ClassifierParams, SensorPose, warm_up
from services.lib.geometry import rotation_matrix
from services.lib.lidar.models import beam_spacing
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node


class ClassifierNode(Node):
    service = "classifier"
    upstream = ("sensor_driver",)
    params_type = ClassifierParams

    @classmethod
    def preload(cls) -> None:
        warm_up(ClassifierParams())

    def setup(self) -> None:
        self.import_when_up("scipy.stats")  # p_hit's Gaussian CDF, after the token
        warm_up(self.params)  # compiled now, before the liveliness token: the first scan must not stall a tick
        self.core = ClassifierCore(self.params)
        self.detections_pub = self.publisher(self.topic("detections"), Detections)
        self.labels_pub = self.publisher(self.topic("labels"), LabelSet)
        # Lockstep releases a tick's inputs in subscription order: map updates first, so each
        # scan is classified against the freshest map.
        self.subscribe(self.topic("map"), VoxelMap, self.on_map, keep=None)  # deltas: each one counts
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self._ignored_deltas = 0
        self._refused_maps = 0
        self._map_stamp = 0
        self._bad_input = CountedWarnings(self.log)
        self._said_outside = False

    def on_map(self, msg: VoxelMap, key: str) -> None:
        try:
            applied = self.core.apply_map(
                msg.snapshot, msg.origin, msg.shape, msg.voxel_size, msg.default_value,
                to_numpy(msg.indices), to_numpy(msg.values),
            )
        except (ValueError, MemoryError):  # an impossible geometry or contents, or a grid too large to hold
            self._refused_maps += 1
            self._bad_input.update({"map messages refused (impossible geometry or contents)": self._refused_maps})
            return
        if applied:
            self._map_stamp = msg.header.stamp
        else:
            self._ignored_deltas += 1
            self._bad_input.update({"map deltas of another geometry ignored (until the next snapshot)":
                                    self._ignored_deltas})

    def on_points(self, msg: PointCloud, key: str) -> None:
        if msg.sanity:  # the driver found the scan broken: nothing in it is a detection, nor a map update
            self.detections_pub.put(Detections(
                header=Header(stamp=msg.header.stamp, source=msg.header.stamp), detector="classifier",
                positions=from_numpy(np.zeros((0, 3))), covariances=from_numpy(np.zeros((0, 3, 3))),
                point_counts=from_numpy(np.zeros(0, dtype=np.int32)), extents=from_numpy(np.zeros(0, dtype=np.float32)),
                sensor_position=tuple(msg.sensor_pose.position), sensor_health=msg.sanity))
            return
        covariance = None if msg.pose_covariance is None else to_numpy(msg.pose_covariance).reshape(6, 6)
        pose = SensorPose(np.asarray(msg.sensor_pose.position, dtype=np.float64),
                          rotation_matrix(msg.sensor_pose.orientation), covariance,
                          beam_spacing(msg.sensor_model, msg.height, msg.width))
        scan = self.core.classify(to_numpy(msg.points), pose)
        self._report_bad_input()
        stamp = msg.header.stamp
        sensor = tuple(msg.sensor_pose.position)
        self.detections_pub.put(Detections(
            header=Header(stamp=stamp, source=stamp),
            detector="classifier",
            positions=from_numpy(scan.positions),
            covariances=from_numpy(scan.covariances),
            point_counts=from_numpy(scan.point_counts),
            extents=from_numpy(scan.extents),
            sensor_position=sensor,
            confidences=from_numpy(scan.confidences),
        ))
        self.labels_pub.put(LabelSet(
            header=Header(stamp=stamp),
            sensor_origin=sensor,
            points=from_numpy(scan.points),
            point_labels=from_numpy(scan.point_labels),
            voxel_size=self.core.map.voxel_size,
            voxels=from_numpy(scan.voxels),
            voxel_labels=from_numpy(scan.voxel_labels),
            voxel_weights=from_numpy(scan.voxel_weights),
            map_stamp=self._map_stamp,
        ))

    def _report_bad_input(self) -> None:
        """Refused input, counted (services/lib/runtime/counted.py); returns outside the map are normal at
        the arena's edge: said once."""
        c = self.core.counters
        self._bad_input.update({"points with infinite coordinates dropped": c.invalid_points,
                                "scans refused (shape or sensor pose)": c.rejected_scans})
        if c.points_outside_map and not self._said_outside:
            self._said_outside = True
            self.log.info("returns outside the map are clustered but never update it")

NODE = ClassifierNode
