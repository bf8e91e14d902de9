"""mapper node: label sets in, the map out (first version, see core.py).

Subscribes falconry/<uav>/labels (LabelSet). Publishes falconry/<uav>/map (VoxelMap): a delta
(snapshot=False, the voxels this label set changed, stamped with the label set's stamp)
after every label set, and a snapshot (snapshot=True, every voxel != default) on the first
tick and then once per second of mission time.
"""
from __future__ import annotations

from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Header, LabelSet, VoxelMap
from services.mapper.core import MapperCore, MapperParams
from services.runtime.clock import to_ns
from services.runtime.node import Node


class MapperNode(Node):
    service = "mapper"
    upstream = ("classifier",)
    params_type = MapperParams

    def setup(self) -> None:
        self.core = MapperCore(self.params)
        self.map_pub = self.publisher(self.topic("map"), VoxelMap)
        self.subscribe(self.topic("labels"), LabelSet, self.on_labels)
        self._snapshot_period_ns = to_ns(self.params.snapshot_period)
        self._last_snapshot_ns: int | None = None
        self._warned_voxel_size = False

    def on_labels(self, msg: LabelSet, key: str) -> None:
        if msg.voxel_size != self.core.voxel_size and not self._warned_voxel_size:
            self._warned_voxel_size = True
            self.log.warning("label sets use %.3f m voxels, the map %.3f m", msg.voxel_size, self.core.voxel_size)
        indices, values = self.core.apply_labels(
            msg.sensor_origin, to_numpy(msg.points), to_numpy(msg.voxels), to_numpy(msg.voxel_labels)
        )
        self._publish(msg.header.stamp, snapshot=False, indices=indices, values=values)

    def on_tick(self, now_ns: int) -> None:
        if self._last_snapshot_ns is None or now_ns - self._last_snapshot_ns >= self._snapshot_period_ns:
            self._last_snapshot_ns = now_ns
            indices, values = self.core.snapshot()
            self._publish(now_ns, snapshot=True, indices=indices, values=values)

    def _publish(self, stamp: int, snapshot: bool, indices, values) -> None:
        core = self.core
        self.map_pub.put(VoxelMap(
            header=Header(stamp=stamp),
            snapshot=snapshot,
            voxel_size=core.voxel_size,
            origin=tuple(float(v) for v in core.origin),
            shape=core.shape,
            indices=from_numpy(indices),
            values=from_numpy(values),
            default_value=self.params.unknown_value,
        ))


NODE = MapperNode
