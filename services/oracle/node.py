"""oracle node (evaluation only): noisy detections from the points that really hit a target.

Subscribes falconry/<uav>/points (PointCloud) and falconry/<uav>/points_truth (PointTruth) of
its UAV, pairs them by stamp and publishes, for every scan and with its stamp,
falconry/<uav>/detections (Detections, detector "oracle"). It replaces the classifier in a run
(`falconry sim --detector oracle`); it never reads GroundTruth. See core.py for the model.
"""
from __future__ import annotations

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, PointCloud, PointTruth
from services.oracle.core import OracleParams, ScanPairs, detect, scan_rng
from services.runtime.node import Node


class OracleNode(Node):
    service = "oracle"
    upstream = ("sensor_driver",)
    params_type = OracleParams

    def setup(self) -> None:
        self.pairs = ScanPairs()
        self.detections_pub = self.publisher(self.topic("detections"), Detections)
        self.subscribe(self.topic("points"), PointCloud, self.on_points)
        self.subscribe(self.topic("points_truth"), PointTruth, self.on_truth)

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
            found = detect(to_numpy(cloud.points), to_numpy(truth.hits), self.params, scan_rng(stamp, self.uav))
        except ValueError as err:
            self.log.warning("scan at %d ns skipped: %s", stamp, err)
            return
        self.detections_pub.put(Detections(
            header=Header(stamp=stamp),
            detector="oracle",
            positions=from_numpy(found.positions),
            covariances=from_numpy(found.covariances),
            point_counts=from_numpy(found.point_counts),
            extents=from_numpy(found.extents),
            sensor_position=tuple(cloud.sensor_pose.position),
        ))


NODE = OracleNode
