"""How uncertain a LiDAR point is, given the sensor's pose and range noise (seed 000 sec. IV).

A point p = l·R·d + t (eq. 34) with R = Rz(γ)·Ry(β)·Rx(α); the noise w = (t_n, α_n, β_n, γ_n, l_n)
(eq. 35) maps through the Jacobian J of eq. 42 to the point's covariance Σ = J·Σ_w·Jᵀ (eq. 41).
The probability that the measured voxel is the true one, p_hit (eq. 45–46), is the integral of
that Gaussian over the measured voxel's cube: scipy's multivariate normal CDF over the box.
Pure numpy and scipy (scipy.stats imported where p_hit needs it: see services/lib/runtime/warmup.py).
"""
from __future__ import annotations

import math

import numpy as np

from services.lib.geometry import yaw_rotation
from services.lib.lidar.models import BeamSpacing


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(b: float) -> np.ndarray:
    c, s = math.cos(b), math.sin(b)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


_rz = yaw_rotation  # the rotation about z


def _drx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[0.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]])


def _dry(b: float) -> np.ndarray:
    c, s = math.cos(b), math.sin(b)
    return np.array([[-s, 0.0, c], [0.0, 0.0, 0.0], [-c, 0.0, -s]])


def _drz(g: float) -> np.ndarray:
    c, s = math.cos(g), math.sin(g)
    return np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])


def roll_pitch_yaw(rotation: np.ndarray) -> tuple[float, float, float]:
    """(α, β, γ) of R = Rz(γ)·Ry(β)·Rx(α) (intrinsic z-y-x, as ROS and MAVLink report attitude)."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = math.asin(float(np.clip(-r[2, 0], -1.0, 1.0)))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])
    return 0.0, pitch, math.atan2(-r[0, 1], r[1, 1])  # gimbal lock: only roll ∓ yaw is known; put it in yaw


def point_jacobian(roll: float, pitch: float, yaw: float, direction: np.ndarray, length: float) -> np.ndarray:
    """J (3, 7) of eq. 42: ∂p/∂(t_n, α_n, β_n, γ_n, l_n) for a ray of sensor-frame unit `direction`
    and range `length`."""
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    rx, ry, rz = _rx(roll), _ry(pitch), _rz(yaw)
    return np.column_stack([
        np.eye(3),
        length * rz @ ry @ _drx(roll) @ d,
        length * rz @ _dry(pitch) @ rx @ d,
        length * _drz(yaw) @ ry @ rx @ d,
        rz @ ry @ rx @ d,
    ])


def point_covariance(point: np.ndarray, sensor_position: np.ndarray, rotation: np.ndarray,
                     pose_covariance: np.ndarray | None, range_sigma: float) -> np.ndarray:
    """Σ (3, 3) of eq. 41 for a measured point: pose covariance 6×6 over (x, y, z, roll, pitch, yaw)
    (None: a perfectly known pose) and range standard deviation."""
    offset = np.asarray(point, dtype=np.float64) - np.asarray(sensor_position, dtype=np.float64)
    length = float(np.linalg.norm(offset))
    if length == 0.0:
        return np.zeros((3, 3))
    rotation = np.asarray(rotation, dtype=np.float64)
    direction = rotation.T @ (offset / length)
    noise = np.zeros((7, 7))
    if pose_covariance is not None:
        noise[:6, :6] = np.asarray(pose_covariance, dtype=np.float64).reshape(6, 6)
    noise[6, 6] = range_sigma ** 2
    jacobian = point_jacobian(*roll_pitch_yaw(rotation), direction, length)
    return jacobian @ noise @ jacobian.T


def sampling_covariance(centroid: np.ndarray, sensor_position: np.ndarray, spacing: BeamSpacing) -> np.ndarray:
    """Σ (3, 3) of where a target's centre lies about the centroid of its returns, given how far
    apart the beams lie (services/lib/lidar/models.beam_spacing).

    Seed 000 gives a detection the uncertainty of its points only (sec. IV-A). A target a few
    beams wide is sampled only where the beams cross it, and where they cross it shifts with every
    move of the sensor: a 0.6 m balloon 27 m from an OS0-32 (rows 1.4 m apart there) shows one row
    of returns at any height across it, so its centroid wanders by decimetres while it stands
    still, and a velocity fit over a second of approach reads that as motion. Across the line of
    sight, the sampled slice lies anywhere over one beam gap s = range × spacing: a uniform error
    of variance s²/12 each way. That bounds a target narrower than the gap (whose size the
    detector does not know) and holds for a wider one too (its outermost returns lie within a
    gap of its edges). Along the line of sight the range measures the surface; that is
    point_covariance's and the classifier's surface offset's business. Across = horizontal and vertical of a level sensor: a UAV's tilt
    of a few degrees turns the ellipse by as much, which is far below what it describes."""
    offset = np.asarray(centroid, dtype=np.float64) - np.asarray(sensor_position, dtype=np.float64)
    distance = float(np.linalg.norm(offset))
    if distance == 0.0:
        return np.zeros((3, 3))
    sight = offset / distance
    across = np.cross((0.0, 0.0, 1.0), sight)
    if np.linalg.norm(across) < 1e-9:  # straight up or down: any horizontal pair will do
        across = np.array([1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    up = np.cross(sight, across)
    return ((distance * spacing.vertical) ** 2 / 12.0 * np.outer(up, up)
            + (distance * spacing.horizontal) ** 2 / 12.0 * np.outer(across, across))


def hit_probability(point: np.ndarray, covariance: np.ndarray, voxel_low: np.ndarray, voxel_size: float) -> float:
    """p_hit of eq. 45–46: the probability that the true point lies in the measured voxel, the cube
    [voxel_low, voxel_low + voxel_size) holding the measured `point`, Σ the point's covariance."""
    from scipy.stats import multivariate_normal  # imported here: see services/lib/runtime/warmup.py

    cov = np.asarray(covariance, dtype=np.float64) + 1e-12 * np.eye(3)  # a perfect pose is a degenerate Gaussian
    low = np.asarray(voxel_low, dtype=np.float64)
    # scipy integrates with randomised quasi-Monte Carlo: a fixed seed keeps lockstep runs identical
    dist = multivariate_normal(mean=np.asarray(point, dtype=np.float64), cov=cov, allow_singular=True, seed=0)
    return float(np.clip(dist.cdf(low + voxel_size, lower_limit=low), 0.0, 1.0))


def mean_hit_probability(distance: float, pose_covariance: np.ndarray, range_sigma: float, voxel_size: float,
                         samples: int, rng: np.random.Generator) -> float:
    """p_hit of eq. 46 averaged over where a point at `distance` falls inside its voxel and over the
    ray's direction (uniform on the sphere; the sensor level): the curves of seed 000's Fig. 5."""
    total = 0.0
    for _ in range(samples):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        voxel_low = np.floor(distance * direction / voxel_size) * voxel_size
        point = voxel_low + rng.uniform(0.0, voxel_size, 3)  # the measured point, somewhere in its voxel
        covariance = point_covariance(point, np.zeros(3), np.eye(3), pose_covariance, range_sigma)
        total += hit_probability(point, covariance, voxel_low, voxel_size)
    return total / samples
