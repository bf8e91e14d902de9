"""The rays of an organised scan: which ones the carrier's body blocks, and where each ray that
counts ends for ray casting (seed 000 sec. III-C). Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.lib.geometry import rotation_matrix
from services.lib.lidar.models import lidar_model


def body_mask(directions: np.ndarray, body_box) -> np.ndarray:
    """bool (rows, cols): beams (sensor frame) that meet the carrier's body box in front of the sensor,
    whatever the world holds. A box around the sensor blocks nothing (it only crops returns in it)."""
    d = np.asarray(directions, dtype=np.float64)
    shape = d.shape[:-1]
    box = np.asarray(body_box if body_box is not None else (), dtype=np.float64)
    if len(box) != 6:
        return np.zeros(shape, dtype=bool)
    d = d.reshape(-1, 3)
    near, far = np.full(len(d), -np.inf), np.full(len(d), np.inf)
    inside = np.ones(len(d), dtype=bool)
    for axis in range(3):
        s, lo, hi = d[:, axis], box[axis], box[axis + 3]
        parallel = s == 0.0
        inside &= ~parallel | ((lo <= 0.0) & (hi >= 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = lo / s, hi / s
        near = np.where(parallel, near, np.maximum(near, np.minimum(t1, t2)))
        far = np.where(parallel, far, np.minimum(far, np.maximum(t1, t2)))
    return (inside & (near <= far) & (near > 0.0)).reshape(shape)


def pack_mask(mask: np.ndarray) -> np.ndarray:
    """uint8 (rows, ceil(cols / 8)): each row's bits packed, as PointCloud.mask travels."""
    return np.packbits(np.asarray(mask, dtype=bool), axis=-1)


def unpack_mask(packed: np.ndarray, width: int) -> np.ndarray:
    return np.unpackbits(np.asarray(packed, dtype=np.uint8), axis=-1, count=width).astype(bool)


@dataclass(frozen=True)
class ScanRays:
    """What ray casting needs of one organised scan (seed 000 sec. III-C)."""

    origin: np.ndarray  # (3,) sensor position, world frame
    rotation: np.ndarray  # (3, 3) sensor frame to world
    points: np.ndarray  # (N, 3) float32 returns, world frame, NaN where none
    beams: np.ndarray | None  # (N, 3) unit beams in the sensor frame; None: unknown (returns make rays alone)
    masked: np.ndarray | None  # (N,) bool: rays the carrier's body blocks


def scan_rays(points: np.ndarray, width: int, sensor_model: str, frame: int, position, orientation_wxyz,
              packed_mask: np.ndarray | None) -> ScanRays:
    """The rays of a PointCloud's fields. Beams come from the named LiDAR model (services/lib/lidar/models.py);
    a model we do not know, or a layout that does not fit the scan, leaves them unknown."""
    pts = np.asarray(points, dtype=np.float32)
    beams = None
    try:
        beams = lidar_model(sensor_model).directions(frame) if sensor_model else None
    except ValueError:
        beams = None
    if beams is not None and beams.shape != pts.shape:
        beams = None
    masked = None
    if packed_mask is not None and pts.ndim == 3 and width == pts.shape[1]:  # a lying width would size the unpacking
        masked = unpack_mask(packed_mask, width)
        masked = masked.reshape(-1) if masked.shape == pts.shape[:-1] else None
    if pts.shape[-1:] == (3,):
        pts = pts.reshape(-1, 3)  # anything else is left as it is, for the mapper to refuse and count
    return ScanRays(np.asarray(position, dtype=np.float64), rotation_matrix(orientation_wxyz),
                    pts, None if beams is None else beams.reshape(-1, 3), masked)


def ray_ends(origin, points: np.ndarray, directions: np.ndarray, masked: np.ndarray | None,
             max_distance: float) -> np.ndarray:
    """(M, 3) end of every ray that counts (eq. 20): a return at most `max_distance` away ends the
    ray there, anything farther or no return at all (NaN) ends it at `max_distance` along its beam.
    Rays the body blocks are skipped. `points` and `directions` are (N, 3) or organised (…, 3)."""
    o = np.asarray(origin, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(p), dtype=bool) if masked is None else ~np.asarray(masked, dtype=bool).reshape(-1)
    p, d = p[keep], d[keep]
    offset = p - o
    distance = np.linalg.norm(offset, axis=1)
    returned = np.isfinite(distance) & (distance > 0.0)
    reach = np.where(returned, np.minimum(distance, max_distance), max_distance)
    unit = np.where(returned[:, None], offset / np.where(returned, distance, 1.0)[:, None], d)
    return o + unit * reach[:, None]
