"""The simulated camera's compiled renderer: one ray per pixel through the sensor driver's caster
(services/sensor_driver/raycast.py, the same world the LiDAR sees), then shading, the camera's
gains, sRGB encoding and sensor noise; and the aligned depth image. numba, `cache=True`,
deterministic (the noise comes from tables and offsets the caller draws).

Light: each primitive's colour (sRGB, decoded to linear light) lit by an ambient share and a sun
whose light falls as the cosine of its angle of incidence; the sky is its colour. No cast
shadows, no reflections: enough for colour segmentation to face shading across a sphere and
surfaces of similar hue, not a photograph.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from services.sensor_driver.raycast import cull_setup, nearest_hit, outward_normal

ENCODE_LEVELS = 4096  # linear light is quantised to this many levels before the sRGB table


def srgb_to_linear(colors: np.ndarray) -> np.ndarray:
    """sRGB 0-255 → linear light 0-1 (IEC 61966-2-1)."""
    c = np.asarray(colors, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def encode_table() -> np.ndarray:
    """uint8 sRGB value of each of ENCODE_LEVELS linear levels in [0, 1]."""
    x = np.linspace(0.0, 1.0, ENCODE_LEVELS)
    c = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)


@njit(cache=True, error_model="numpy")
def render_kernel(origin, rotation, pixel_rays, kinds, params, bounds, linear_colors, sky, sun, ambient, gains,
                  encode, color_noise, color_offset, depth_noise, depth_offset, depth_sigma, depth_min, depth_max,
                  dropout, rgb, depth_mm, hit_index):
    """For every pixel ray (camera frame, unit, (N, 3); x the optical axis): the RGB value (uint8
    (N, 3)), the depth along the optical axis in mm with noise σ = depth_sigma · z² (uint16 (N,),
    0: none: nothing hit, outside [depth_min, depth_max] m, or a dropout, which a pixel is when
    its depth noise draw is beyond `dropout` standard deviations) and the packed index of the
    primitive it sees (-1: sky). Noise tables are read from the offsets on, wrapping around."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    r = rotation
    cull = cull_setup(ox, oy, oz, kinds, bounds)
    color_mask = len(color_noise) - 1  # table lengths are powers of two
    depth_mask = len(depth_noise) - 1
    top = ENCODE_LEVELS - 1
    for i in range(pixel_rays.shape[0]):
        cx, cy, cz = pixel_rays[i, 0], pixel_rays[i, 1], pixel_rays[i, 2]
        dx = r[0, 0] * cx + r[0, 1] * cy + r[0, 2] * cz
        dy = r[1, 0] * cx + r[1, 1] * cy + r[1, 2] * cz
        dz = r[2, 0] * cx + r[2, 1] * cy + r[2, 2] * cz
        t, q = nearest_hit(ox, oy, oz, dx, dy, dz, kinds, params, cull)
        hit_index[i] = q
        if q >= 0:
            nx, ny, nz = outward_normal(kinds[q], params[q], ox + t * dx, oy + t * dy, oz + t * dz)
            if nx * dx + ny * dy + nz * dz > 0.0:  # the inside of a surface (a camera within a primitive)
                nx, ny, nz = -nx, -ny, -nz
            light = ambient + (1.0 - ambient) * max(0.0, nx * sun[0] + ny * sun[1] + nz * sun[2])
            lr, lg, lb = linear_colors[q, 0] * light, linear_colors[q, 1] * light, linear_colors[q, 2] * light
        else:
            lr, lg, lb = sky[0], sky[1], sky[2]
        base = color_offset + 3 * i
        rgb[i, 0] = _channel(lr * gains[0], encode, top, color_noise[base & color_mask])
        rgb[i, 1] = _channel(lg * gains[1], encode, top, color_noise[(base + 1) & color_mask])
        rgb[i, 2] = _channel(lb * gains[2], encode, top, color_noise[(base + 2) & color_mask])
        z = t * cx if q >= 0 else 0.0
        draw = depth_noise[(depth_offset + i) & depth_mask]
        if q >= 0 and depth_min <= z <= depth_max and abs(draw) <= dropout:
            depth_mm[i] = np.uint16(min(max((z + depth_sigma * z * z * draw) * 1000.0 + 0.5, 1.0), 65535.0))
        else:
            depth_mm[i] = 0


@njit(cache=True, error_model="numpy", inline="always")
def _channel(linear, encode, top, noise):
    if not linear > 0.0:  # NaN too (a world with a NaN in it): an index from NaN would read anywhere
        linear = 0.0
    level = int(min(linear, 1.0) * top + 0.5)
    return np.uint8(min(max(np.int64(encode[level]) + np.int64(noise), 0), 255))


def noise_table(rng: np.random.Generator, size: int, sigma: float, dtype) -> np.ndarray:
    """Gaussian noise drawn once; frames read it from random offsets (a fresh draw per pixel per
    frame would cost more than the rendering). `size` is rounded up to a power of two."""
    size = 1 << max(1, math.ceil(math.log2(size)))
    values = rng.normal(0.0, sigma, size)
    if np.issubdtype(np.dtype(dtype), np.integer):
        values = np.round(values)
    return values.astype(dtype)
