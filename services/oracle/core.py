"""Oracle detector core: one detection per target that returned at least `min_points` points, and
the label sets a perfect classifier would hand the mapper. Pure: numpy in, numpy out; the noise
comes from an RNG the caller seeds (`scan_rng`: from the scan stamp and the UAV, so a run is
reproducible and a replayed scan gives the same detections).

A detection is the centroid of the target's returns (float64) plus N(0, sigma²·I) noise, with
covariance sigma²·I plus, given the sensor's beam spacing, where between the beams the target's
centre lies (services/lib/lidar/uncertainty.sampling_covariance: the centroid of a few returns is
not the target's centre, and the classifier says so too), the number of points and the extent
(largest side of their axis-aligned bounding box, as the classifier reports it). Detections come
in ascending target order.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.lib.lidar.models import BeamSpacing
from services.lib.lidar.uncertainty import sampling_covariance
from services.lib.voxels.grid import GridGeometry
from services.lib.voxels.labels import label_sets

RNG_SALT = zlib.crc32(b"oracle")
MAX_PENDING = 8  # scans waiting for their other half; older ones are dropped


class OracleParams(msgspec.Struct, forbid_unknown_fields=True):
    min_points: int = 2  # returns a target needs in one scan to be detected
    sigma: float = 0.1  # m, standard deviation of the position noise per axis


@dataclass
class OracleDetections:
    positions: np.ndarray  # float64 (N, 3)
    covariances: np.ndarray  # float64 (N, 3, 3)
    point_counts: np.ndarray  # int32 (N,)
    extents: np.ndarray  # float32 (N,)
    targets: np.ndarray  # int32 (N,) hit ids k (>= 1) of the detected targets


def scan_rng(stamp: int, uav: str) -> np.random.Generator:
    return np.random.default_rng([int(stamp), zlib.crc32(uav.encode()), RNG_SALT])


def detect(points: np.ndarray, hits: np.ndarray, params: OracleParams, rng: np.random.Generator,
           sensor_position: np.ndarray | None = None, spacing: BeamSpacing | None = None) -> OracleDetections:
    """Detections from one organised scan: `points` (..., 3) and `hits` (...) of the same shape
    (-1 no return, 0 static world, k >= 1 target k), taken from `sensor_position` by beams
    `spacing` apart (either None: the covariance is the added noise's only)."""
    points = np.asarray(points)
    hits = np.asarray(hits)
    if points.shape[:-1] != hits.shape or points.shape[-1:] != (3,):
        raise ValueError(f"points {points.shape} and hit ids {hits.shape} do not describe the same rays")
    flat_hits = hits.reshape(-1)
    flat_points = points.reshape(-1, 3).astype(np.float64)
    on_target = (flat_hits >= 1) & np.isfinite(flat_points).all(axis=1)
    ids, which, counts = np.unique(flat_hits[on_target], return_inverse=True, return_counts=True)
    pts = flat_points[on_target]
    sums = np.stack([np.bincount(which, pts[:, a], len(ids)) for a in range(3)], axis=1)
    lowest = np.full((len(ids), 3), np.inf)
    highest = np.full((len(ids), 3), -np.inf)
    np.minimum.at(lowest, which, pts)
    np.maximum.at(highest, which, pts)
    keep = counts >= max(1, params.min_points)
    n = int(keep.sum())
    centroids = sums[keep] / counts[keep, None]
    noise = rng.normal(0.0, params.sigma, (n, 3)) if params.sigma > 0 else np.zeros((n, 3))
    variance = params.sigma * params.sigma
    covariances = np.tile(variance * np.eye(3), (n, 1, 1))
    if sensor_position is not None and spacing is not None:
        for k, centroid in enumerate(centroids):
            covariances[k] += sampling_covariance(centroid, sensor_position, spacing)
    return OracleDetections(
        positions=centroids + noise,
        covariances=covariances,
        point_counts=counts[keep].astype(np.int32),
        extents=(highest[keep] - lowest[keep]).max(axis=1, initial=0.0).astype(np.float32),
        targets=ids[keep].astype(np.int32),
    )


@dataclass
class OracleLabels:
    """What the classifier's LabelSet carries, from the truth of each ray."""
    points: np.ndarray  # float32 (N, 3) the scan's valid returns
    point_labels: np.ndarray  # uint8 (N,) FLYING on a target, BACKGROUND on the static world
    voxels: np.ndarray  # int32 (M, 3) map voxels holding returns
    voxel_labels: np.ndarray  # uint8 (M,)
    voxel_weights: np.ndarray  # float32 (M,) eq. 16-18: returns per voxel, inf for flying objects


def label(points: np.ndarray, hits: np.ndarray, geometry: GridGeometry, slot: np.ndarray) -> OracleLabels:
    """The label sets of seed 000 eq. 16-18 as a classifier that never errs would make them: a return
    on a target is a flying object's, any other return the background's. With them the mapper learns
    free and occupied space in an oracle run as in a classifier run, so what flies on the map (the
    planner, its guard) flies the same. One difference: a balloon is a target here, so its voxels are
    kept unknown, where the classifier calls a tethered balloon background (rule A, its pole) and the
    planner leaves it out by its mount. `slot`: int32 scratch over the map's voxels, all -1."""
    points = np.asarray(points)
    hits = np.asarray(hits)
    if points.shape[:-1] != hits.shape or points.shape[-1:] != (3,):
        raise ValueError(f"points {points.shape} and hit ids {hits.shape} do not describe the same rays")
    flat = points.reshape(-1, 3).astype(np.float64)
    valid = np.isfinite(flat).all(axis=1)
    xyz = flat[valid]
    point_labels = np.where(hits.reshape(-1)[valid] >= 1, FLYING, BACKGROUND).astype(np.uint8)
    voxels, voxel_labels, voxel_weights, _ = label_sets(
        xyz, point_labels, geometry.corner, geometry.voxel_size, np.asarray(geometry.shape), slot,
        BACKGROUND, FLYING, UNKNOWN)
    return OracleLabels(xyz.astype(np.float32), point_labels, voxels, voxel_labels, voxel_weights)


def warm_up() -> int:
    """Compile the label-set pass now (a fresh numba cache takes seconds), not on the first scan."""
    geometry = GridGeometry((0.0, 0.0, 0.0), (2, 2, 2), 0.5)
    points = np.array([[0.2, 0.2, 0.2], [0.7, 0.2, 0.2], [np.nan, 0.0, 0.0]], dtype=np.float32)
    return len(label(points, np.array([0, 1, -1]), geometry, np.full(geometry.size, -1, np.int32)).voxels)


@dataclass
class ScanPairs:
    """Matches each PointCloud with the PointTruth of the same stamp, whichever comes first.
    `add` returns (cloud, truth) once both halves of a stamp are in; a stamp older than the
    last pair, or beyond MAX_PENDING waiting stamps, is dropped."""
    clouds: dict[int, Any] = field(default_factory=dict)
    truths: dict[int, Any] = field(default_factory=dict)
    last_paired: int = -1
    dropped: int = 0

    def add(self, stamp: int, cloud: Any = None, truth: Any = None) -> tuple[Any, Any] | None:
        if stamp <= self.last_paired:
            self.dropped += 1
            return None
        mine, other = (self.clouds, self.truths) if cloud is not None else (self.truths, self.clouds)
        mine[stamp] = cloud if cloud is not None else truth
        if stamp in other:
            pair = (self.clouds.pop(stamp), self.truths.pop(stamp))
            self.last_paired = stamp
            self._forget(lambda s: s < stamp)
            return pair
        if len(mine) > MAX_PENDING:
            del mine[min(mine)]
            self.dropped += 1
        return None

    def _forget(self, old) -> None:
        for pending in (self.clouds, self.truths):
            for s in [s for s in pending if old(s)]:
                del pending[s]
                self.dropped += 1
