"""Object Detect (seed 004 §4.1): round objects of a known colour and size in a colour image,
placed in 3D with the aligned depth image where it has depth.

1. Colour segmentation by the colour file (colors.py: thresholds per channel, eq. 4.9-4.10, or a
   2D histogram LUT, in HSV or L*a*b*), then a morphological opening that drops lone pixels.
2. Blobs: connected components (OpenCV) that are round enough: the component fills at least
   `min_fill` of the disc of its equivalent diameter's bounding box and is at most `max_aspect`
   elongated, at least `min_pixels` large.
3. Distance from the known diameter (the seed cites "methods from [21]" without giving them):
   a sphere of radius R seen under the half-angle α is R / sin α away. Its outline, θ off the
   optical axis, is an ellipse stretched by 1/cos θ across and 1/cos² θ along the radial
   direction, so its area is π (f tan α)² / cos³ θ: α = atan(r cos^1.5 θ / f) with r the blob's
   equivalent radius sqrt(area / π). (Half the larger side of the blob's box, tried first, read
   ranges 18 % short on mbzirc: at the D435's 35° half-width the outline is 22 % longer radially.)
   Pixels the segmentation misses on the shaded side make the range a little long instead.
4. Distance from depth where the blob has valid depth pixels: the median range of those pixels
   plus 0.707 R (the median depth of a sphere's visible half lies R/√2 in front of its centre,
   for points spread evenly over its image disc).
5. The two are combined by their variances: from the diameter σ = d² σ_px / (f R) (σ_px the
   outline's pixel error), from depth the camera's σ = k z² over the square root of the pixels
   used, plus a floor for the median's own bias. The 3D point is the combined range along the
   ray through the blob's centre, in the world by the frame's camera pose; its covariance has the
   range's variance along the ray and (range · σ_px / f)² across it.

Pure: numpy and OpenCV in, numpy out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import msgspec
import numpy as np

from services.lib.geometry import rotation_matrix
from services.lib.pinhole import Intrinsics
from services.object_detect.colors import ColorFile

MEDIAN_DEPTH_OFFSET = 1 / math.sqrt(2)  # × R: the median depth of a sphere's visible half in front of its centre


class ObjectDetectParams(msgspec.Struct, forbid_unknown_fields=True):
    # The colour file (falconry colors pick): a path, or the name of a built-in one in
    # services/object_detect/colors/ ("red", "green").
    colors: str = "red"
    min_pixels: int = 12  # a blob smaller than this is noise
    min_fill: float = 0.55  # share of its box's inscribed ellipse a round blob fills at least
    max_aspect: float = 1.8  # longer side over shorter side of a round blob's box at most
    max_distance: float = 40.0  # m; farther blobs are dropped (a few pixels: no size to trust)
    outline_sigma: float = 0.7  # px, error of a blob's outline (its radius in the image)
    depth_floor: float = 0.05  # m, added in quadrature to the depth estimate's σ
    depth_noise: float = 0.004  # σ = depth_noise · z² of one depth pixel, m (the camera's)

    def __post_init__(self) -> None:
        if self.min_pixels < 1:
            raise ValueError("min_pixels must be at least 1")
        if not 0.0 <= self.min_fill <= 1.0:
            raise ValueError("min_fill must lie in [0, 1]")
        for name in ("max_aspect", "max_distance", "outline_sigma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")


@dataclass(frozen=True)
class CameraView:
    """What Object Detect needs of a frame besides its pixels."""

    intrinsics: Intrinsics
    position: np.ndarray  # camera centre, world
    orientation: tuple[float, float, float, float]  # camera frame → world (w, x, y, z)


@dataclass(frozen=True)
class Blob:
    u: float  # centre, pixels
    v: float
    radius: float  # pixels
    pixels: int
    fill: float
    clipped: bool = False  # it touches the image's edge: part of the object may lie beyond it
    half_extent: float = 0.0  # pixels: half the larger side of its box


@dataclass(frozen=True)
class ObjectDetections:
    positions: np.ndarray  # (N, 3) world
    covariances: np.ndarray  # (N, 3, 3)
    pixels: np.ndarray  # int32 (N,) blob sizes
    diameters: np.ndarray  # float32 (N,) the object's diameter, m (from the colour file)
    ranges_from_size: np.ndarray  # (N,) m, along the ray (step 3)
    ranges_from_depth: np.ndarray  # (N,) m, NaN where no depth (step 4)
    blobs: list[Blob]


def find_blobs(mask: np.ndarray, params: ObjectDetectParams) -> list[Blob]:
    """Round blobs of a binary image (steps 1-2 after segmentation)."""
    binary = np.ascontiguousarray(mask.view(np.uint8) if mask.dtype == bool else (mask != 0).view(np.uint8))
    opened = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    # Components only within the box of what is left: most frames hold no pixel of the colour at all,
    # and labelling the whole image was most of Object Detect's time. The box starts on even rows and
    # columns: OpenCV labels 2 × 2 blocks, so the components come in the whole image's order.
    x0, y0, w, h = cv2.boundingRect(opened)
    if w == 0 or h == 0:
        return []
    w, h, x0, y0 = w + x0 % 2, h + y0 % 2, x0 - x0 % 2, y0 - y0 % 2
    count, _, stats, centroids = cv2.connectedComponentsWithStats(opened[y0:y0 + h, x0:x0 + w], connectivity=8)
    blobs = []
    for k in range(1, count):
        width, height, area = stats[k, cv2.CC_STAT_WIDTH], stats[k, cv2.CC_STAT_HEIGHT], stats[k, cv2.CC_STAT_AREA]
        if area < params.min_pixels:
            continue
        long, short = max(width, height), max(min(width, height), 1)
        fill = area / (math.pi * width * height / 4)
        if long / short > params.max_aspect or fill < params.min_fill:
            continue
        left, top = x0 + stats[k, cv2.CC_STAT_LEFT], y0 + stats[k, cv2.CC_STAT_TOP]
        clipped = left == 0 or top == 0 or left + width == mask.shape[1] or top + height == mask.shape[0]
        blobs.append(Blob(x0 + float(centroids[k, 0]), y0 + float(centroids[k, 1]), math.sqrt(area / math.pi),
                          int(area), float(fill), bool(clipped), 0.5 * float(long)))
    return blobs


def detect(rgb: np.ndarray, depth_mm: np.ndarray | None, view: CameraView, colors: ColorFile,
           params: ObjectDetectParams) -> ObjectDetections:
    """The objects of `colors` in one frame (module docstring)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"a colour image is (height, width, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth_mm is not None and np.shape(depth_mm) != rgb.shape[:2]:
        raise ValueError(f"the depth image {np.shape(depth_mm)} does not match the colour image {rgb.shape[:2]}")
    mask = colors.segment(rgb)
    blobs = find_blobs(mask, params) if mask.size else []
    radius_m = colors.diameter / 2
    rotation = rotation_matrix(view.orientation)
    focal = 0.5 * (view.intrinsics.fx + view.intrinsics.fy)
    rows = []
    for blob in blobs:
        ray = view.intrinsics.rays(blob.u, blob.v)
        ray /= np.linalg.norm(ray)
        # the outline of a sphere seen θ off the optical axis is an ellipse stretched by 1/cos θ across
        # and 1/cos² θ along the radial direction: its area is π (f tan α)² / cos³ θ
        radius_px = max(blob.radius, blob.half_extent)  # the segmentation only ever loses a balloon's pixels
        size_range = radius_m / math.sin(math.atan(radius_px * ray[0] ** 1.5 / focal))
        if size_range > params.max_distance:
            continue
        size_var = (size_range ** 2 * params.outline_sigma / (focal * radius_m)) ** 2
        depth_range, depth_var = _depth_range(depth_mm, blob, view, radius_m, params)
        if math.isnan(depth_range) and blob.clipped:
            continue  # cut by the image's edge, its size says only that it is nearer: no range to trust
        if math.isnan(depth_range):
            rng, var = size_range, size_var
        else:
            weight = depth_var / (depth_var + size_var)  # the share of the size estimate
            rng = weight * size_range + (1 - weight) * depth_range
            var = size_var * depth_var / (size_var + depth_var)
        across = (rng * params.outline_sigma / focal) ** 2
        local = across * np.eye(3) + (var - across) * np.outer(ray, ray)
        rows.append((view.position + rotation @ (rng * ray), rotation @ local @ rotation.T, blob, size_range,
                     depth_range))
    return ObjectDetections(
        positions=np.array([r[0] for r in rows]).reshape(-1, 3),
        covariances=np.array([r[1] for r in rows]).reshape(-1, 3, 3),
        pixels=np.array([r[2].pixels for r in rows], dtype=np.int32),
        diameters=np.full(len(rows), colors.diameter, dtype=np.float32),
        ranges_from_size=np.array([r[3] for r in rows], dtype=np.float64),
        ranges_from_depth=np.array([r[4] for r in rows], dtype=np.float64),
        blobs=[r[2] for r in rows])


def _depth_range(depth_mm, blob: Blob, view: CameraView, radius_m: float,
                 params: ObjectDetectParams) -> tuple[float, float]:
    """(range of the sphere's centre from the depth pixels of the blob, its variance), NaN if none."""
    if depth_mm is None:
        return math.nan, math.inf
    h, w = np.shape(depth_mm)
    r = max(blob.radius * 0.8, 1.0)  # inside the outline: an edge pixel may see the background
    u0, u1 = max(int(blob.u - r), 0), min(int(blob.u + r) + 1, w)
    v0, v1 = max(int(blob.v - r), 0), min(int(blob.v + r) + 1, h)
    patch = np.asarray(depth_mm[v0:v1, u0:u1], dtype=np.float64) / 1000.0
    uu, vv = np.meshgrid(np.arange(u0, u1) + 0.5, np.arange(v0, v1) + 0.5)
    inside = ((uu - blob.u) ** 2 + (vv - blob.v) ** 2 <= r * r) & (patch > 0)
    if inside.sum() < 3:
        return math.nan, math.inf
    # depth is along the optical axis: the range of each pixel's point is z · |ray| / ray_x
    rays = view.intrinsics.rays(uu, vv)
    stretch = np.sqrt(1.0 + rays[..., 1] ** 2 + rays[..., 2] ** 2)
    ranges = patch[inside] * stretch[inside]
    median = float(np.median(ranges))
    sigma = params.depth_noise * median ** 2 / math.sqrt(inside.sum())
    return median + MEDIAN_DEPTH_OFFSET * radius_m, sigma ** 2 + params.depth_floor ** 2
