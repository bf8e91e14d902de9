"""The simulated camera's compiled renderer: one ray per pixel through the shared caster
(services/lib/world/raycast.py, the same world the LiDAR sees), then shading, the camera's
gains, sRGB encoding and sensor noise; and the aligned depth image. numba, `cache=True`,
deterministic (the noise comes from tables and offsets the caller draws).

Light: each primitive's colour (sRGB, decoded to linear light) lit by an ambient share and a sun
whose light falls as the cosine of its angle of incidence; the sky is its colour. No cast
shadows, no reflections: enough for colour segmentation to face shading across a sphere and
surfaces of similar hue, not a photograph.

Tiles: a primitive can only be seen in the tiles of the image its bounding sphere reaches, so the
image is cut into tiles (TILE × TILE pixels) and each frame first lists, per tile, the primitives
whose bounding sphere meets the tile's cone of rays (`tile_candidates`); each pixel then tests only
its tile's list, in the packed order, so a frame is the same bits as testing every primitive. On
mbzirc (16 primitives) most tiles see the ground and one or two others. A tile whose only
candidate is the ground plane (or another plane) takes a short path: its pixels see that plane or
the sky, each with one shade for the whole tile, so only their ranges and noise are per pixel.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from services.lib.world.raycast import INF, PLANE, ahead, cull_setup, hit_range, outward_normal

ENCODE_LEVELS = 4096  # linear light is quantised to this many levels before the sRGB table
TILE = 16  # pixels on a side of a culling tile
CONE_SLACK = 1e-9  # cosine margin of the tile test: a grazing ray is kept, never lost


def srgb_to_linear(colors: np.ndarray) -> np.ndarray:
    """sRGB 0-255 → linear light 0-1 (IEC 61966-2-1)."""
    c = np.asarray(colors, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def encode_table() -> np.ndarray:
    """uint8 sRGB value of each of ENCODE_LEVELS linear levels in [0, 1]."""
    x = np.linspace(0.0, 1.0, ENCODE_LEVELS)
    c = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Tiles:
    """The image cut into tiles for culling: the pixels of tile k are order[start[k]:start[k + 1]]
    (row-major indices); each tile's cone of rays in the camera frame has the unit `axes[k]` and
    the half-angle whose cosine and sine are cos_half[k], sin_half[k] (the widest of its rays)."""

    order: np.ndarray  # int64 (N,)
    start: np.ndarray  # int64 (T + 1,)
    axes: np.ndarray  # (T, 3)
    cos_half: np.ndarray  # (T,)
    sin_half: np.ndarray  # (T,)

    @classmethod
    def of(cls, pixel_rays: np.ndarray, width: int, height: int, size: int = TILE) -> "Tiles":
        rows, cols = np.divmod(np.arange(width * height), width)
        tile = (rows // size) * (-(-width // size)) + cols // size
        order = np.argsort(tile, kind="stable")
        count = np.bincount(tile)
        start = np.concatenate([[0], np.cumsum(count)])
        sums = np.zeros((len(count), 3))
        np.add.at(sums, tile, pixel_rays)
        axes = sums / np.linalg.norm(sums, axis=1, keepdims=True)
        cosines = np.einsum("ij,ij->i", pixel_rays, axes[tile])
        cos_half = np.full(len(count), 1.0)
        np.minimum.at(cos_half, tile, cosines)
        cos_half = np.clip(cos_half, -1.0, 1.0)
        return cls(order.astype(np.int64), start.astype(np.int64), np.ascontiguousarray(axes), cos_half,
                   np.sqrt(1.0 - cos_half ** 2))


@njit(cache=True, error_model="numpy")
def tile_candidates(origin, rotation, axes, cos_half, sin_half, kinds, bounds, candidates, counts):
    """counts[k] primitives in candidates[k, :counts[k]] (ascending) whose bounding sphere meets
    tile k's cone of rays: a ray θ or less off the axis reaches a sphere seen ρ wide around the
    direction ĉ only if the axis is at most θ + ρ off ĉ (planes, and spheres around the camera,
    are in every tile)."""
    counts[:] = 0
    world_axes = np.empty_like(axes)
    for k in range(len(axes)):
        for row in range(3):
            world_axes[k, row] = rotation[row, 0] * axes[k, 0] + rotation[row, 1] * axes[k, 1] + rotation[row, 2] * axes[k, 2]
    for q in range(len(kinds)):
        cx, cy, cz = bounds[q, 0] - origin[0], bounds[q, 1] - origin[1], bounds[q, 2] - origin[2]
        dist = math.sqrt(cx * cx + cy * cy + cz * cz)
        radius = abs(bounds[q, 3])  # the caster squares it: a negative radius is a sphere of |r|
        everywhere = kinds[q] == PLANE or dist <= radius
        if not everywhere:
            sin_rho = radius / dist
            cos_rho = math.sqrt(1.0 - sin_rho * sin_rho)
            cx, cy, cz = cx / dist, cy / dist, cz / dist
        for k in range(len(counts)):
            if not everywhere:  # cos(angle to ĉ) < cos(θ + ρ), both angles below π: no ray of the tile reaches it
                cos_angle = world_axes[k, 0] * cx + world_axes[k, 1] * cy + world_axes[k, 2] * cz
                if cos_angle < cos_half[k] * cos_rho - sin_half[k] * sin_rho - CONE_SLACK:
                    continue
            candidates[k, counts[k]] = q
            counts[k] += 1


@njit(cache=True, error_model="numpy")
def render_kernel(origin, rotation, tile_rays, order, start, candidates, counts, kinds, params, bounds,
                  linear_colors, sky, sun, ambient, gains, encode, color_noise, color_offset, depth_noise,
                  depth_offset, depth_sigma, depth_min, depth_max, dropout, rgb, depth_mm, hit_index):
    """For every pixel, tile by tile (`Tiles`, `tile_candidates`; tile_rays[j] is the unit ray of
    pixel order[j], camera frame, x the optical axis): the RGB value (uint8 (N, 3), row-major),
    the depth along the optical axis in mm with noise σ = depth_sigma · z² (uint16 (N,), 0: none:
    nothing hit, outside [depth_min, depth_max] m, or a dropout, which a pixel is when its depth
    noise draw is beyond `dropout` standard deviations) and the packed index of the primitive it
    sees (-1: sky). Noise tables are read in tile order from the offsets on, wrapping around, as
    the rays are: reading both in the image's order cost a fifth of a frame."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    r = rotation
    cull = cull_setup(ox, oy, oz, kinds, bounds)
    top = ENCODE_LEVELS - 1
    sky_r, sky_g, sky_b = (_encoded(sky[0] * gains[0], encode, top), _encoded(sky[1] * gains[1], encode, top),
                           _encoded(sky[2] * gains[2], encode, top))
    for k in range(len(counts)):
        listed = counts[k]
        if listed == 1 and kinds[candidates[k, 0]] == PLANE:
            _plane_tile(oz, r, tile_rays, order, start[k], start[k + 1], candidates[k, 0], params, linear_colors,
                        sun, ambient, gains, encode, sky_r, sky_g, sky_b, color_noise, color_offset, depth_noise,
                        depth_offset, depth_sigma, depth_min, depth_max, dropout, rgb, depth_mm, hit_index)
            continue
        for j in range(start[k], start[k + 1]):
            i = order[j]
            cx, cy, cz = tile_rays[j, 0], tile_rays[j, 1], tile_rays[j, 2]
            dx = r[0, 0] * cx + r[0, 1] * cy + r[0, 2] * cz
            dy = r[1, 0] * cx + r[1, 1] * cy + r[1, 2] * cz
            dz = r[2, 0] * cx + r[2, 1] * cy + r[2, 2] * cz
            t, q = INF, -1  # the nearest hit over the tile's list: written out (services/lib/world/raycast.py's note)
            for m in range(listed):
                p = candidates[k, m]
                if kinds[p] == PLANE:
                    t_p = ahead((params[p, 0] - oz) / dz)
                elif dx * cull[p, 0] + dy * cull[p, 1] + dz * cull[p, 2] < cull[p, 3]:
                    continue
                else:
                    t_p = hit_range(kinds[p], params, p, ox, oy, oz, dx, dy, dz)
                if t_p < t:
                    t, q = t_p, p
            hit_index[i] = q
            if q >= 0:
                nx, ny, nz = outward_normal(kinds[q], params, q, ox + t * dx, oy + t * dy, oz + t * dz)
                if nx * dx + ny * dy + nz * dz > 0.0:  # the inside of a surface (a camera within a primitive)
                    nx, ny, nz = -nx, -ny, -nz
                light = ambient + (1.0 - ambient) * max(0.0, nx * sun[0] + ny * sun[1] + nz * sun[2])
                lr, lg, lb = linear_colors[q, 0] * light, linear_colors[q, 1] * light, linear_colors[q, 2] * light
            else:
                lr, lg, lb = sky[0], sky[1], sky[2]
            _write_pixel(i, j, _encoded(lr * gains[0], encode, top), _encoded(lg * gains[1], encode, top),
                         _encoded(lb * gains[2], encode, top), q >= 0, t * cx if q >= 0 else 0.0, color_noise,
                         color_offset, depth_noise, depth_offset, depth_sigma, depth_min, depth_max, dropout,
                         rgb, depth_mm)


@njit(cache=True, error_model="numpy")
def _plane_tile(oz, r, tile_rays, order, first, end, p, params, linear_colors, sun, ambient, gains, encode,
                sky_r, sky_g, sky_b, color_noise, color_offset, depth_noise, depth_offset, depth_sigma, depth_min,
                depth_max, dropout, rgb, depth_mm, hit_index):
    """`render_kernel` over the pixels first … end-1 of a tile whose only candidate is plane p:
    the same bits. Every ray that meets the plane meets it from the camera's side, so its shade
    (and each channel's encoded value) is one for the tile, and only the range varies."""
    top = ENCODE_LEVELS - 1
    height = params[p, 0]
    below = height - oz > 0.0  # rays hitting from below point up: the normal turns to face them
    light = ambient + (1.0 - ambient) * max(0.0, -sun[2] if below else sun[2])
    plane_r = _encoded(linear_colors[p, 0] * light * gains[0], encode, top)
    plane_g = _encoded(linear_colors[p, 1] * light * gains[1], encode, top)
    plane_b = _encoded(linear_colors[p, 2] * light * gains[2], encode, top)
    for j in range(first, end):
        i = order[j]
        cx, cy, cz = tile_rays[j, 0], tile_rays[j, 1], tile_rays[j, 2]
        dz = r[2, 0] * cx + r[2, 1] * cy + r[2, 2] * cz
        t = ahead((height - oz) / dz)
        hit = t < INF
        hit_index[i] = p if hit else -1
        _write_pixel(i, j, plane_r if hit else sky_r, plane_g if hit else sky_g, plane_b if hit else sky_b, hit,
                     t * cx if hit else 0.0, color_noise, color_offset, depth_noise, depth_offset, depth_sigma,
                     depth_min, depth_max, dropout, rgb, depth_mm)


@njit(cache=True, error_model="numpy", inline="always")
def _write_pixel(i, j, red, green, blue, hit, z, color_noise, color_offset, depth_noise, depth_offset, depth_sigma,
                 depth_min, depth_max, dropout, rgb, depth_mm):
    """Pixel i (the j-th in tile order, which the noise tables are read in) from its encoded
    colour and, when its ray hit, the depth z (m) along the optical axis: both with their noise."""
    base = color_offset + 3 * j
    color_mask = len(color_noise) - 1  # table lengths are powers of two
    rgb[i, 0] = _noisy(red, color_noise[base & color_mask])
    rgb[i, 1] = _noisy(green, color_noise[(base + 1) & color_mask])
    rgb[i, 2] = _noisy(blue, color_noise[(base + 2) & color_mask])
    draw = depth_noise[(depth_offset + j) & (len(depth_noise) - 1)]
    if hit and depth_min <= z <= depth_max and abs(draw) <= dropout:
        depth_mm[i] = np.uint16(min(max((z + depth_sigma * z * z * draw) * 1000.0 + 0.5, 1.0), 65535.0))
    else:
        depth_mm[i] = 0


@njit(cache=True, error_model="numpy", inline="always")
def _encoded(linear, encode, top):
    """The sRGB value of linear light (clipped to [0, 1]) from the table."""
    if not linear > 0.0:  # NaN too (a world with a NaN in it): an index from NaN would read anywhere
        linear = 0.0
    return np.int64(encode[int(min(linear, 1.0) * top + 0.5)])


@njit(cache=True, error_model="numpy", inline="always")
def _noisy(encoded, noise):
    return np.uint8(min(max(encoded + np.int64(noise), 0), 255))


def noise_table(rng: np.random.Generator, size: int, sigma: float, dtype) -> np.ndarray:
    """Gaussian noise drawn once; frames read it from random offsets (a fresh draw per pixel per
    frame would cost more than the rendering). `size` is rounded up to a power of two."""
    size = 1 << max(1, math.ceil(math.log2(size)))
    values = rng.normal(0.0, sigma, size)
    if np.issubdtype(np.dtype(dtype), np.integer):
        values = np.round(values)
    return values.astype(dtype)
