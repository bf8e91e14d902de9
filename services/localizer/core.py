"""Seed 003's Grape localizer as one pipeline (sec. 2.1): an organised LiDAR scan and the IMU's
samples in, the UAV's pose with its covariance and health out.

Per scan: (a) plane and edge features of the organised scan in the sensor frame (features.py),
moved into the body frame by the LiDAR's mount; (b) associated with the feature map by k-d tree on
feature centres plus a normal / direction check (association.py), from the pose the IMU predicts
for the scan's stamp; (c) and (d) the factor graph's fusion and precision steps (graph.py). The map
grows by the features that matched nothing, placed from that predicted pose.

Pure: numpy in, numpy out; no clock (every stamp is the caller's, int ns of mission time).

Where Falconry departs from the paper, and why:
- The map features association compares against stay where they were first placed; the graph
  refines its landmarks, association does not follow. Their drift since first sighting is what the
  association tolerances (AssociationParams, 10° and 0.3 m) absorb; a map re-placed from the graph
  would need the graph's marginalised landmarks back, which it keeps only as priors.
- The scan is taken as instantaneous at its stamp (no motion compensation within the sweep): the
  simulated LiDAR casts every ray from the pose at the stamp.
- The IMU and the LiDAR are taken to share the body's orientation; the LiDAR sits at `lidar_mount`
  in the body frame (the sensor driver's `mount`).
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from services.localizer.association import AssociationParams, FeatureMap, associate, transform_features
from services.localizer.features import FeatureParams, Features, extract_features
from services.localizer.graph import (GraphParams, LocalizerGraph, PoseEstimate, line_residuals, observations,
                                      symmetric_psd, tangent_basis)
from services.lib.lidar.models import DEFAULT_MOUNT


class LocalizerParams(msgspec.Struct, forbid_unknown_fields=True):
    # m, the LiDAR's position in the body frame (x forward, y left, z up): the sensor driver's `mount`
    lidar_mount: list[float] = msgspec.field(default_factory=lambda: list(DEFAULT_MOUNT))
    # s: a scan waits at most this long for the IMU samples up to its stamp, then is dropped (the IMU
    # stream has stalled; a scan cannot be fused without the motion since the last one)
    max_imu_wait: float = 0.5
    features: FeatureParams = msgspec.field(default_factory=FeatureParams)
    association: AssociationParams = msgspec.field(default_factory=AssociationParams)
    graph: GraphParams = msgspec.field(default_factory=GraphParams)

    def __post_init__(self) -> None:
        if len(self.lidar_mount) != 3 or not np.isfinite(self.lidar_mount).all():
            raise msgspec.ValidationError(f"lidar_mount must be [x, y, z] in metres, got {self.lidar_mount}")
        if not 0.0 < self.max_imu_wait < 60.0:
            raise msgspec.ValidationError(f"max_imu_wait must be above 0 and below 60 s, got {self.max_imu_wait}")


@dataclass(frozen=True)
class ScanResult:
    """What one scan gave: the estimate, and how many features it brought and matched."""

    estimate: PoseEstimate
    planes: int
    edges: int
    associated: int  # features taken for map features
    new: int  # features added to the map


def restart_frame_covariance(covariance: np.ndarray | None, lost_position_sigma: float) -> np.ndarray:
    """The (6, 6) uncertainty a localizer restarted in flight starts its map frame with, from the
    covariance of the flight controller's belief it starts at: that covariance, made symmetric. The
    belief's health does not enter: it is "lost" after any restart that outlasts the controller's
    estimate timeout, which says the estimates stopped, not that the pose is poor; the controller
    grows the covariance as its own inertial error grows (docs/deploy.md; the simulated one holds
    the error, which then does not grow). A covariance that is missing or is not one (not 6 × 6, not
    finite, not positive semi-definite) leaves the belief's worth unknown: position σ
    `lost_position_sigma` on each axis, so every later estimate says "lost" (and the job manager
    lands, as for any lost positioning)."""
    usable = covariance is not None and np.size(covariance) == 36 and np.isfinite(covariance).all()
    frame = symmetric_psd(np.asarray(covariance, dtype=np.float64).reshape(6, 6)) if usable else None
    return frame if frame is not None else np.diag([lost_position_sigma ** 2] * 3 + [0.0] * 3)


def sensor_frame(points: np.ndarray, sensor_position: np.ndarray, sensor_rotation: np.ndarray) -> np.ndarray:
    """An organised (H, W, 3) world-frame scan back in the sensor frame it was cast in:
    Rᵀ (p − position), NaN rows kept NaN (a PointCloud's points are registered by its sensor_pose)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"an organised scan is (rows, columns, 3), got shape {points.shape}")
    rotation = np.asarray(sensor_rotation, dtype=np.float64).reshape(3, 3)
    return (points - np.asarray(sensor_position, dtype=np.float64).reshape(3)) @ rotation


class Localizer:
    """start once at the known launch pose, then add_imu as samples come and add_scan per scan."""

    def __init__(self, params: LocalizerParams | None = None) -> None:
        self.params = params or LocalizerParams()
        self.graph = LocalizerGraph(self.params.graph)
        self.map = FeatureMap()
        self._mount = np.asarray(self.params.lidar_mount, dtype=np.float64)
        self.start_stamp = 0  # ns, of the start state (valid once started)
        self._start_pose = (np.eye(3), np.zeros(3))  # rotation body → world and translation (once started)

    @property
    def started(self) -> bool:
        return self.graph.started

    def start(self, stamp_ns: int, rotation: np.ndarray, translation: np.ndarray, velocity: np.ndarray,
              frame_covariance: np.ndarray | None = None) -> None:
        """The body's pose (rotation body → world, translation) and world velocity at `stamp_ns`:
        the map frame's origin (the launch point, known without GNSS; or, restarted in flight, the
        flight controller's belief with its covariance `frame_covariance`: LocalizerGraph.start)."""
        self.graph.start(stamp_ns, rotation, translation, velocity, frame_covariance)
        self.start_stamp = int(stamp_ns)
        self._start_pose = (np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64))

    def mount_seen(self, sensor_position: np.ndarray) -> np.ndarray:
        """(3,) m, where a scan's sensor position sits in the body frame of the start pose:
        R₀ᵀ (p − t₀). For a scan taken at the launch point (on the ground, before take-off) that is
        the LiDAR's mount as whoever registered the scan (the sensor driver) has it; it should be
        `lidar_mount`, which the two services' parameters state separately."""
        rotation, translation = self._start_pose
        return rotation.T @ (np.asarray(sensor_position, dtype=np.float64).reshape(3) - translation)

    def add_imu(self, stamps_ns: np.ndarray, accelerometer: np.ndarray, gyroscope: np.ndarray) -> None:
        self.graph.add_imu(stamps_ns, accelerometer, gyroscope)

    def add_scan(self, stamp_ns: int, sensor_points: np.ndarray) -> ScanResult:
        """One organised scan (H, W, 3) in the sensor frame, NaN where nothing returned."""
        body = transform_features(extract_features(sensor_points, self.params.features), np.eye(3), self._mount)
        return self.add_features(stamp_ns, body)

    def add_features(self, stamp_ns: int, body: Features) -> ScanResult:
        """A scan's features already in the body frame (what add_scan extracts)."""
        rotation, translation = self.graph.predicted_pose(stamp_ns)
        matches = associate(transform_features(body, rotation, translation), self.map, self.params.association)
        associated = sum(m.map_id is not None for m in matches)
        ids = self.map.add_unassociated(matches)
        estimate = self.graph.add_scan(stamp_ns, observations(body, ids))
        return ScanResult(estimate, len(body.planes), len(body.edges), associated, len(matches) - associated)


def warm_up(params: LocalizerParams) -> int:
    """Extract the features of one small synthetic organised scan, so that the extraction's
    compiled kernels (numba, cached on disk after a machine's first run) are ready before the
    first real scan (see classifier/core.py, `warm_up`, for why): 16 rows by 256 columns inside a
    box room with a pole; and linearise one line factor (graph.py), which the first scan's edges
    add. Returns the planes and edges found."""
    elevation = np.radians(np.linspace(-15.0, 15.0, 16))[:, None]
    azimuth = np.linspace(-np.pi, np.pi, 256, endpoint=False)[None, :]
    beams = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                         np.sin(elevation)), axis=-1)
    with np.errstate(divide="ignore"):
        reach = np.abs(np.array([8.0, 6.0, 3.0]) / beams).min(axis=-1)  # the nearest of the room's walls
    grid = beams * reach[..., None]
    pole = np.abs(np.arctan2(grid[..., 1], grid[..., 0]) - np.arctan2(2.0, 4.0)) < 0.02
    grid[pole] = beams[pole] * np.hypot(4.0, 2.0)  # a thin pole at (4, 2) in front of the wall
    features = extract_features(grid, params.features)
    direction = np.array([[0.0, 0.0, 1.0]])  # the pole's line factor, as the smoother linearises it
    line_residuals(np.array([[4.0, 2.0, 0.0]]), direction, np.eye(3)[None], np.zeros((1, 3)), direction,
                   np.array([[4.0, 2.0, 1.0]]), tangent_basis(direction))
    return len(features.planes) + len(features.edges)
