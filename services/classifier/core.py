"""Classifier core: Euclidean clustering of one LiDAR scan and classification of every
cluster as background / flying object / unknown (seed 000, sec. III-B).

FIRST VERSION (walking skeleton). Simplifications that later issues replace with the
full method of seed 000:
- clustering joins occupied 0.5 m voxels whose centres are within the clustering distance
  (not the exact point-to-point rule of eq. 13-15);
- rule A (closeness to tentative-occupied voxels within d_close) is approximated by "a
  confident-occupied voxel (G >= -0.1) in or next to the cluster's voxels", plus explicit
  ground contact and size limits;
- rule B (BFS flood fill through confident-free voxels, Alg. 1) is replaced by geometric
  tests (at least 1 m above ground, small, within range). The flood fill comes later.

Pure: numpy in, numpy out; the map replica is plain state updated by the node.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from schemas.voxels import BACKGROUND, FLYING, UNKNOWN
from services.voxels.replica import MapReplica


class ClassifierParams(msgspec.Struct, forbid_unknown_fields=True):
    voxel_size: float = 0.5  # m; also the map voxel size until the mapper's map arrives
    cluster_distance: float = 1.5  # m, d_cluster
    cluster_min_points: int = 2
    cluster_max_extent: float = 3.0  # m; larger clusters are background
    max_distance: float = 50.0  # m from the sensor for a flying object
    ground_z: float = 0.0  # m
    ground_contact: float = 0.5  # m; a cluster reaching below ground_z + this is background
    min_height: float = 1.0  # m above ground for every point of a flying object
    confident_occupied: float = -0.1  # G threshold
    touch_voxels: int = 1  # map-occupied voxels this many voxels away still "touch"
    covariance_floor: float = 0.01  # m², added to each detection's sample covariance
    # The map replica's geometry before the first VoxelMap arrives (same as the mapper's defaults).
    map_origin: tuple[float, float, float] = (-10.0, -10.0, -1.0)
    map_shape: tuple[int, int, int] = (240, 200, 52)
    map_default: float = -740.0


@dataclass
class ClassifiedScan:
    points: np.ndarray  # float32 (N, 3) valid returns
    point_labels: np.ndarray  # uint8 (N,)
    voxels: np.ndarray  # int32 (M, 3) relative to the map origin
    voxel_labels: np.ndarray  # uint8 (M,)
    voxel_weights: np.ndarray  # float32 (M,) points per voxel
    positions: np.ndarray  # float64 (D, 3) flying-object centroids
    covariances: np.ndarray  # float64 (D, 3, 3)
    point_counts: np.ndarray  # int32 (D,)
    extents: np.ndarray  # float32 (D,)


def cluster_voxels(voxels: np.ndarray, radius_voxels: float) -> tuple[int, np.ndarray]:
    """Connected components of voxels whose centres are within radius_voxels of each other."""
    count = len(voxels)
    if count == 0:
        return 0, np.zeros(0, dtype=np.int64)
    pairs = cKDTree(voxels.astype(np.float64)).query_pairs(r=radius_voxels + 1e-9, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    n_clusters, labels = connected_components(graph, directed=False)
    return int(n_clusters), labels.astype(np.int64)


class ClassifierCore:
    def __init__(self, params: ClassifierParams | None = None) -> None:
        self.params = params or ClassifierParams()
        p = self.params
        self.map = MapReplica(p.map_origin, p.map_shape, p.voxel_size, p.map_default)

    def apply_map(self, snapshot: bool, origin, shape, voxel_size: float, default_value: float,
                  indices: np.ndarray, values: np.ndarray) -> bool:
        return self.map.apply(snapshot, origin, shape, voxel_size, default_value, indices, values)

    def classify(self, points: np.ndarray, sensor_position) -> ClassifiedScan:
        """Cluster and classify one scan: points (H, W, 3) or (N, 3), world frame, NaN = no return."""
        p = self.params
        flat_points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        valid_points = flat_points[np.isfinite(flat_points).all(axis=1)]
        if len(valid_points) == 0:
            return _empty_scan()
        pts = valid_points.astype(np.float64)
        voxel_size = self.map.voxel_size
        point_voxels = np.floor((pts - self.map.origin) / voxel_size).astype(np.int64)

        # Unique voxels via a key over the scan's own bounding box (no map-size assumption).
        low = point_voxels.min(axis=0)
        span = point_voxels.max(axis=0) - low + 1
        keys = np.ravel_multi_index(tuple((point_voxels - low).T), tuple(span))
        unique_keys, point_voxel, voxel_counts = np.unique(keys, return_inverse=True, return_counts=True)
        voxels = np.stack(np.unravel_index(unique_keys, tuple(span)), axis=1) + low

        n_clusters, voxel_cluster = cluster_voxels(voxels, p.cluster_distance / voxel_size)
        point_cluster = voxel_cluster[point_voxel]

        # Per-cluster statistics over contiguous runs of points sorted by cluster.
        order = np.argsort(point_cluster, kind="stable")
        sorted_pts = pts[order]
        sizes = np.bincount(point_cluster, minlength=n_clusters)
        starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        lowest = np.minimum.reduceat(sorted_pts, starts, axis=0)
        highest = np.maximum.reduceat(sorted_pts, starts, axis=0)
        ranges = np.linalg.norm(sorted_pts - np.asarray(sensor_position, dtype=np.float64), axis=1)
        farthest = np.maximum.reduceat(ranges, starts)
        extent = (highest - lowest).max(axis=1)

        ground = lowest[:, 2] < p.ground_z + p.ground_contact
        too_big = extent > p.cluster_max_extent
        background = ground | too_big
        # Only clusters still in question pay for the map look-up.
        candidate_voxels = ~background[voxel_cluster]
        touching = np.zeros(n_clusters, dtype=bool)
        if candidate_voxels.any():
            near = self.map.occupied_near(voxels[candidate_voxels], p.touch_voxels, p.confident_occupied)
            touching[np.unique(voxel_cluster[candidate_voxels][near])] = True
        background |= touching
        flying = (
            ~background
            & (sizes >= p.cluster_min_points)
            & (lowest[:, 2] >= p.ground_z + p.min_height)
            & (farthest <= p.max_distance)
        )
        cluster_label = np.full(n_clusters, UNKNOWN, dtype=np.uint8)
        cluster_label[background] = BACKGROUND
        cluster_label[flying] = FLYING

        detected = np.flatnonzero(flying)
        positions, covariances = _centroids_and_covariances(pts, point_cluster, sizes, detected, p.covariance_floor)
        return ClassifiedScan(
            points=valid_points,
            point_labels=cluster_label[point_cluster],
            voxels=voxels.astype(np.int32),
            voxel_labels=cluster_label[voxel_cluster],
            voxel_weights=voxel_counts.astype(np.float32),
            positions=positions,
            covariances=covariances,
            point_counts=sizes[detected].astype(np.int32),
            extents=extent[detected].astype(np.float32),
        )


def _centroids_and_covariances(pts, point_cluster, sizes, clusters, floor: float):
    """Centroid (eq. 19) and sample covariance + floor·I of the chosen clusters."""
    if len(clusters) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    slot = np.full(len(sizes), -1)
    slot[clusters] = np.arange(len(clusters))
    mine = slot[point_cluster] >= 0
    which = slot[point_cluster[mine]]
    chosen = pts[mine]
    counts = sizes[clusters].astype(np.float64)
    centroids = np.stack([np.bincount(which, chosen[:, a], len(clusters)) for a in range(3)], axis=1) / counts[:, None]
    centred = chosen - centroids[which]
    products = centred[:, :, None] * centred[:, None, :]  # (n, 3, 3)
    sums = np.stack([np.bincount(which, products[:, i, j], len(clusters)) for i in range(3) for j in range(3)], axis=1)
    covariances = sums.reshape(-1, 3, 3) / np.maximum(counts - 1.0, 1.0)[:, None, None]
    covariances += floor * np.eye(3)
    return centroids, covariances


def _empty_scan() -> ClassifiedScan:
    return ClassifiedScan(
        points=np.zeros((0, 3), np.float32),
        point_labels=np.zeros(0, np.uint8),
        voxels=np.zeros((0, 3), np.int32),
        voxel_labels=np.zeros(0, np.uint8),
        voxel_weights=np.zeros(0, np.float32),
        positions=np.zeros((0, 3)),
        covariances=np.zeros((0, 3, 3)),
        point_counts=np.zeros(0, np.int32),
        extents=np.zeros(0, np.float32),
    )
