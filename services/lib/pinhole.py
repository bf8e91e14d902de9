"""A pinhole camera's intrinsics, the one model of how pixels and rays correspond: the simulated
camera renders through it, Object Detect turns a blob back into a ray with it.

Camera frame: x forward along the optical axis, y left, z up (as the body frame, FLU); pixel u to
the right, v down, (cx, cy) the principal point, fx and fy the focal lengths in pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov: float, vertical_fov: float) -> "Intrinsics":
        fx = (width / 2) / math.tan(math.radians(horizontal_fov) / 2)
        fy = (height / 2) / math.tan(math.radians(vertical_fov) / 2)
        return cls(width, height, fx, fy, width / 2, height / 2)

    def rays(self, u, v) -> np.ndarray:
        """(..., 3) rays through pixel coordinates (u, v), camera frame, not unit: 1 along the axis."""
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        return np.stack([np.ones_like(u), (self.cx - u) / self.fx, (self.cy - v) / self.fy], axis=-1)

    def pixel_rays(self) -> np.ndarray:
        """(height · width, 3) unit rays through the pixel centres, camera frame, row-major."""
        uu, vv = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        rays = self.rays(uu, vv)
        return np.ascontiguousarray((rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3))

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates (u, v) of camera-frame points in front of the camera."""
        p = np.asarray(points_camera, dtype=np.float64).reshape(-1, 3)
        return np.stack([self.cx - self.fx * p[:, 1] / p[:, 0], self.cy - self.fy * p[:, 2] / p[:, 0]], axis=1)
