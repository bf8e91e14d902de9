"""One UAV's perception in one process, in the services' order: the benchmarks' harness.

The classifier and mapper services run the same cores in two processes; here one scan goes
through them as a lockstep run hands it on: classify against the map replica, integrate the scan
and its label sets into the map, hand the map delta to the replica (so the next scan is classified
with this one's map: the one-scan lag of docs/architecture.md). Times of each step are returned
so a benchmark can report them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from schemas.messages import Obstacle
from services.classifier.core import ClassifiedScan, ClassifierCore, ClassifierParams, SensorPose
from services.lib.lidar.rays import ScanRays
from services.lib.voxels.apriori import obstacle_voxels
from services.mapper.core import MapDelta, MapperCore, MapperParams


@dataclass(frozen=True)
class StepResult:
    scan: ClassifiedScan
    delta: MapDelta
    classify_s: float  # classification plus applying the map delta to the replica
    map_s: float  # ray casting and the map update


class PerceptionLoop:
    def __init__(self, apriori: list[Obstacle] | None = None, mapper: MapperParams | None = None,
                 classifier: ClassifierParams | None = None) -> None:
        """`apriori`: static obstacles pinned occupied, as the mapper node does with the world model
        (None: learn everything)."""
        self.classifier = ClassifierCore(classifier)
        self.mapper = MapperCore(mapper)
        if apriori:
            self.mapper.pin(obstacle_voxels(apriori, self.mapper.geometry))
            snapshot = self.mapper.snapshot()
            self._replicate(True, snapshot)

    def _replicate(self, snapshot: bool, delta: MapDelta) -> None:
        m = self.mapper
        self.classifier.apply_map(snapshot, m.params.origin, m.shape, m.voxel_size, m.params.unknown_value,
                                  delta.indices, delta.values)

    def step(self, stamp: int, points: np.ndarray, pose: SensorPose, rays: ScanRays) -> StepResult:
        started = time.perf_counter()
        scan = self.classifier.classify(points, pose)
        classified = time.perf_counter()
        delta = self.mapper.integrate(stamp, rays, scan.voxels, scan.voxel_labels, scan.voxel_weights)
        mapped = time.perf_counter()
        self._replicate(False, delta)
        replicated = time.perf_counter()
        return StepResult(scan, delta, classified - started + replicated - mapped, mapped - classified)
