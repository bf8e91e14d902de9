"""Is this frame what a working camera gives? (numpy and OpenCV; Object Detect asks it of every frame)

A frame fails when it is **frozen** — the same pixels as the frame before, to the bit: a camera's
own noise makes two real frames differ somewhere, so an identical one is a driver or link
repeating its last image — or **saturated**: more than `max_clipped` of its pixels at full scale in
every channel, or black in every channel (a blinding glare, a lens cap, an exposure control gone
wrong); a balloon's colour cannot be told in either. Like a failing LiDAR scan, a failing frame's
detections are none, and those of the next `SETTLE_TIME` s are not acted on
(services/lib/lidar/sanity.py, `SensorTrust`).
"""
from __future__ import annotations

import zlib

import cv2
import numpy as np

MAX_CLIPPED = 0.5  # share of pixels at full scale or black in every channel


class FrameSanity:
    def __init__(self, max_clipped: float = MAX_CLIPPED) -> None:
        self.max_clipped = max_clipped
        self._last: tuple[int, tuple[int, ...]] | None = None  # the previous frame's checksum and shape
        self.failures: dict[str, int] = {}  # frames failed, by check

    def check(self, rgb: np.ndarray) -> str:
        """"" when the (H, W, 3) uint8 frame passes, else why it fails."""
        rgb = np.ascontiguousarray(rgb)
        signature = (zlib.crc32(rgb.data), rgb.shape)
        frozen = self._last is not None and signature == self._last and rgb.size > 0
        self._last = signature
        if frozen:
            return self._failed("frozen", "frozen: the same image as the frame before")
        clipped = clipped_share(rgb)
        if clipped > self.max_clipped:
            return self._failed("saturated", f"saturated: {100 * clipped:.0f} % of pixels at full scale or black")
        return ""

    def _failed(self, check: str, reason: str) -> str:
        self.failures[check] = self.failures.get(check, 0) + 1
        return reason


def clipped_share(rgb: np.ndarray) -> float:
    """Share of the (H, W, 3) uint8 frame's pixels at full scale, or black, in every channel. By
    OpenCV's range test: numpy's reductions over each pixel's three channels take some 15 times
    longer, as long as rendering and detecting the frame."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"a colour image is (height, width, 3) uint8, got {rgb.shape} {rgb.dtype}")
    pixels = rgb.shape[0] * rgb.shape[1]
    if pixels == 0:
        return 0.0
    full = cv2.countNonZero(cv2.inRange(rgb, (255, 255, 255), (255, 255, 255)))
    black = cv2.countNonZero(cv2.inRange(rgb, (0, 0, 0), (0, 0, 0)))
    return (full + black) / pixels
