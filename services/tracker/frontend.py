"""Seed 002's Stage I (sec. 4.1, Algorithm 1): from one raw LiDAR scan to the few point clusters
that may be the tracked drone.

1. Voxel downsampling (eq. 1): the cloud's finite points are binned in cubic voxels; each
   non-empty voxel becomes its points' centroid.
2. Cylindrical region of interest around the observer (eq. 2): horizontal distance at most a
   radius, altitude between two limits (the flight envelope; the ground and anything above the
   airspace go).
3. DBSCAN (eq. 3, scikit-learn's).
4. Characterisation (eq. 4-5: centroid and sample covariance of every cluster) and validation by
   the covariance's eigenvalues (eq. 6): a candidate's largest eigenvalue, the variance of its
   returns along their main axis, must lie between a floor and what returns on an object of a
   drone's size can reach (see FrontEndParams).

Pure: numpy in, numpy out. The seed's numeric values were lost in extraction; the defaults below
are chosen for its setting (a Livox Mid-360, a 0.65 m drone 10-35 m away returning 1-4 points
per 0.1 s scan) and each says why.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

class FrontEndParams(msgspec.Struct, forbid_unknown_fields=True):
    # Eq. 1. Below the gaps between the Mid-360's returns on a drone 10-35 m away (in the sparse
    # scenario: median 0.37 m, 5 % under 0.11 m), so the target's 1-4 returns pass through (about
    # 1 % merge), while dense surfaces near the sensor (ground, walls) shrink before DBSCAN.
    voxel_size: float = 0.1  # m
    # Eq. 2. The Mid-360's datasheet range (40 m at 10 % reflectivity): nothing useful lies farther.
    roi_radius: float = 40.0  # m, horizontal distance from the observer
    # Eq. 2, the flight envelope in world altitude: the scenarios' min_height / max_height
    # (sparse.toml: 1-15 m). 1 m above the ground drops the ground's returns and anything standing
    # low, however rough the terrain's returns are (range noise 2 cm).
    roi_min_altitude: float = 1.0  # m
    roi_max_altitude: float = 15.0  # m
    # Eq. 3, DBSCAN's eps: two returns on the seed's drone, 0.65 m wide and 0.3 m thick, are at
    # most its side view's diagonal apart, 0.72 m; 0.8 m adds room for range noise and voxel centroids, so all of one scan's returns on
    # the target form one cluster. Larger merges the drone with clutter near it.
    cluster_distance: float = 0.8  # m
    # Eq. 3, DBSCAN's min_samples; scikit-learn counts the point itself, so 2 = a point and one
    # neighbour. The target returns 1-4 points, so anything above 2 loses most scans; 2 makes a
    # lone return noise (seed: "rejects single-point spurious returns"). 1 would make every lone
    # return a cluster of its own, whose covariance is zero: min_spread rejects those anyway.
    cluster_min_points: int = 2
    # Eq. 6, lower bound on the largest eigenvalue (m²): a standard deviation of at least 3 cm
    # along the returns' main axis (two returns at least 4.5 cm apart), more than the range noise
    # (2 cm): an object with extent, not one spot returned twice. Also what rejects single
    # points when cluster_min_points is 1.
    min_spread: float = 1e-3  # m²
    # Eq. 6, upper bound, as the largest extent of a drone's returns (m): n returns spread over a
    # length L have a largest covariance eigenvalue (their sample variance along the main axis) of
    # at most (L/2)² · n/(n-1) (Popoviciu's inequality, with eq. 5's n-1), reached with the returns
    # split between both ends. With L this extent the bound is 0.32 m² for two returns, 0.21 m² for
    # four, 0.16 m² for many: a fixed bound would have to be the two-return one and would pass a
    # string of eight returns 1.5 m long (a pole). 0.8 m: the drone's 0.72 m plus range noise
    # and voxel centroids. A wall, tree or roof chained by DBSCAN is far beyond.
    max_extent: float = 0.8  # m

    def __post_init__(self) -> None:
        for name in ("voxel_size", "roi_radius", "cluster_distance", "max_extent"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.roi_min_altitude < self.roi_max_altitude:
            raise ValueError(f"roi_min_altitude ({self.roi_min_altitude}) must be below "
                             f"roi_max_altitude ({self.roi_max_altitude})")
        if self.cluster_min_points < 1:
            raise ValueError(f"cluster_min_points must be >= 1, got {self.cluster_min_points}")
        if not 0 <= self.min_spread < (self.max_extent / 2) ** 2:
            raise ValueError(f"need 0 <= min_spread < (max_extent / 2)², got {self.min_spread}, {self.max_extent}")


@dataclass(frozen=True)
class Candidates:
    """One scan's target candidates (eq. 4-6) and what the stages kept, for diagnosis."""

    positions: np.ndarray  # (N, 3) cluster centroids, eq. 4
    covariances: np.ndarray  # (N, 3, 3) sample covariances, eq. 5
    sizes: np.ndarray  # (N,) points (voxel centroids) per cluster
    points: int = 0  # finite returns in the scan
    in_roi: int = 0  # voxel centroids inside the region of interest
    clusters: int = 0  # DBSCAN clusters before validation

    def __len__(self) -> int:
        return len(self.positions)

    @staticmethod
    def none() -> "Candidates":
        return Candidates(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64))


def finite_points(cloud: np.ndarray) -> np.ndarray:
    """(N, 3) float64 of an organised or flat cloud's returns: rows with a NaN (no return) dropped."""
    points = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
    return points[np.isfinite(points).all(axis=1)]


def voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    """One int64 per point naming its voxel (equal keys: same voxel)."""
    cells = np.floor(points / size).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        return np.ravel_multi_index(cells.T, dims)
    # a cloud spread too wide for one int64 (a broken return far away): rank the rows instead
    return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)


def group_means(values: np.ndarray, groups: np.ndarray, count: int) -> np.ndarray:
    """(count, D) mean of the rows of `values` (M, D) in each group 0..count-1 (none empty)."""
    sizes = np.bincount(groups, minlength=count).astype(np.float64)
    sums = np.stack([np.bincount(groups, weights=values[:, d], minlength=count) for d in range(values.shape[1])],
                    axis=1)
    return sums / sizes[:, None]


def voxel_downsample(points: np.ndarray, size: float) -> np.ndarray:
    """Eq. 1: the centroid of the points in every non-empty voxel of side `size`."""
    if len(points) == 0:
        return np.zeros((0, 3))
    _, voxel = np.unique(voxel_keys(points, size), return_inverse=True)
    voxel = voxel.reshape(-1)
    return group_means(points, voxel, int(voxel.max()) + 1)


def in_cylinder(points: np.ndarray, observer: np.ndarray, params: FrontEndParams) -> np.ndarray:
    """Eq. 2: (N,) mask of the points within roi_radius horizontally of the observer and between
    the altitude limits."""
    offset = points[:, :2] - np.asarray(observer, dtype=np.float64)[:2]
    near = np.einsum("ij,ij->i", offset, offset) <= params.roi_radius**2
    return near & (points[:, 2] >= params.roi_min_altitude) & (points[:, 2] <= params.roi_max_altitude)


def cluster_labels(points: np.ndarray, params: FrontEndParams) -> np.ndarray:
    """Eq. 3: DBSCAN's label per point, -1 for noise."""
    if len(points) < params.cluster_min_points:
        return np.full(len(points), -1, dtype=np.int64)
    from sklearn.cluster import DBSCAN  # imported here: scikit-learn takes ~1 s to import

    return DBSCAN(eps=params.cluster_distance, min_samples=params.cluster_min_points).fit_predict(points)


def characterise(points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 4-5 for every cluster (labels >= 0): centroids (K, 3), sample covariances (K, 3, 3)
    (divided by n - 1; zero for a one-point cluster) and sizes (K,)."""
    member = labels >= 0
    if not member.any():
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    _, group = np.unique(labels[member], return_inverse=True)
    group = group.reshape(-1)
    chosen = points[member]
    count = int(group.max()) + 1
    sizes = np.bincount(group, minlength=count)
    centroids = group_means(chosen, group, count)
    deviation = chosen - centroids[group]
    outer = (deviation[:, :, None] * deviation[:, None, :]).reshape(-1, 9)
    scatter = group_means(outer, group, count) * sizes[:, None]
    covariances = (scatter / np.maximum(sizes - 1, 1)[:, None]).reshape(-1, 3, 3)
    return centroids, covariances, sizes


def largest_spread(params: FrontEndParams, sizes: np.ndarray) -> np.ndarray:
    """(K,) the largest covariance eigenvalue n returns on an object of max_extent can have."""
    n = np.asarray(sizes, dtype=np.float64)
    return (params.max_extent / 2) ** 2 * n / np.maximum(n - 1, 1)


def drone_like(covariances: np.ndarray, sizes: np.ndarray, params: FrontEndParams) -> np.ndarray:
    """Eq. 6: (K,) mask of the clusters whose largest covariance eigenvalue lies between
    min_spread and largest_spread. Only the largest is tested: two returns, the usual case, have a
    rank-1 covariance and three are coplanar, so the smaller eigenvalues are zero on a drone too."""
    if len(covariances) == 0:
        return np.zeros(0, dtype=bool)
    largest = np.linalg.eigvalsh(covariances)[:, -1]
    return (largest >= params.min_spread) & (largest <= largest_spread(params, sizes))


def front_end(cloud: np.ndarray, observer: np.ndarray, params: FrontEndParams) -> Candidates:
    """Stage I on one scan (world frame, NaN rows for no return) seen from `observer` (3,)."""
    points = finite_points(cloud)
    downsampled = voxel_downsample(points, params.voxel_size)
    kept = downsampled[in_cylinder(downsampled, observer, params)]
    centroids, covariances, sizes = characterise(kept, cluster_labels(kept, params))
    valid = drone_like(covariances, sizes, params)
    return Candidates(centroids[valid], covariances[valid], sizes[valid],
                      points=len(points), in_roi=len(kept), clusters=len(centroids))
