"""Plane and edge features of one organised LiDAR scan: the feature extraction of seed 003's Grape
localizer (sec. 2.1), with LOAM's smoothness (seed 003 ref. 14, Zhang & Singh 2014) as the filter.

The scan is an organised (H, W, 3) cloud in the sensor frame: row = beam (elevation), column =
azimuth order, NaN where a ray returned nothing. Three steps, none needing a neighbour search:

1. Candidates. Along every row and every column, LOAM's smoothness of each point,
   c_i = ||Σ_j (p_j − p_i)|| / (n·||p_i||) over the `window` neighbours on each side (n = 2·window).
   The grid is cut into tiles; in each, the point smooth along both rows and columns with the lowest
   c is a plane candidate and the point with the highest c is an edge candidate.
2. Fit. A plane candidate's region of interest (ROI) is the block of rows × columns around it; a
   plane is fitted by principal axes (the eigenvectors of the ROI's scatter matrix, i.e. the SVD of
   its centred points: normal = least axis) and scored by its point-to-plane RMSE.
   An edge candidate's ROI is the edge itself, traced through the grid (below); a 3-D line is
   fitted (direction = principal axis through the centroid), scored by its point-to-line RMSE.
3. Selection. The scan is divided into `sectors` azimuth sectors (4: forward, left, back, right);
   in each the `per_sector` planes and edges of lowest RMSE are kept, among those with enough ROI
   points and an RMSE below the maximum.

Departures by default (FeatureParams; the seed's selection is per_sector = 1,
min_angle_between_deg = 0, poles_per_sector = 0): two planes and two edges per sector, the second
at least `min_angle_between_deg` (45°) from the first, since by RMSE alone every plane of an open
field is the floor; and up to `poles_per_sector` pole axes per sector (poles.py), returned among the
edges (`EdgeFeature.pole`).

What the paper leaves open, and where Falconry departs from it, and why:
- c leaves out the component of Σ_j (p_j − p_i) along the chord p_{i+w} − p_{i−w}. The beams of
  a column fan out, so a plane is sampled along a column at uneven spacing: its points are
  collinear but LOAM's sum then measures the unevenness, and floor 20° below the horizon reads as
  sharp as a 90° corner. Across the chord only a fold of the surface counts. (At a corner the sum
  points across the chord, and c is LOAM's.)
- LOAM's rejected points are not candidates: points on surfaces nearly parallel to the beam and
  points beside an occlusion. Both show as a step between successive returns longer than the
  angle between their beams explains at `max_incidence_deg`; a point with such a step within its
  window has no c. The silhouette of an object against the background is thus not an edge (LOAM
  keeps its near side): a silhouette moves with the viewpoint on anything round (poles, trunks),
  so it would not associate from scan to scan.
- Gaps: a window holding more than `max_dropouts` NaN (the sky, a window pane) gives no c, as in
  LOAM; an isolated dropout is left out together with its mirror neighbour, so the sum stays
  balanced. Otherwise 2 % dropouts would leave a fifth of the points without c.
- Candidates are picked per tile (`tile_rows` × `tile_columns`) rather than per scan-line
  sub-region as in LOAM: it spreads them over the scan and bounds the fits (256 tiles per kind on
  a 128 × 1024 scan). A plane candidate must be smooth along both rows and columns.
- An edge point must also stand off its neighbours by `edge_min_deviation` metres: c is relative
  to range, so range noise looks sharp on a close wall (A-LOAM's threshold on the unnormalised
  sum is likewise absolute, about 3 cm of mean deviation).
- The edge ROI. A line fitted to the block around an edge would fit the two surfaces meeting
  there, and its RMSE would say nothing about the edge; a line through one column would be any
  line on a wall. So the edge is followed through the grid: an edge sharp along the rows (a
  vertical corner) crosses the rows, and from the candidate the trace steps row by row, in each
  taking the sharpest point within `edge_search` columns of the previous pick, for up to
  `edge_roi_half_length` rows each way, bridging up to `edge_max_gap` rows with nothing sharp (a
  dropout at the corner). A vertical edge seen by a level sensor stays in one column; a tilted one
  drifts a column every few rows, which the search follows. An edge sharp along the columns (a
  wall's foot) is traced column by column the same way. The line through these samples is what
  selection ranks by (the RMSE of the paper).
- A selected edge's line is then refined. The samples are the returns nearest the edge, up to
  half a sample spacing beside it (r·π/W across a vertical edge: 1.5 cm at 5 m on 1024 columns,
  more along a wall seen at an angle). In each line of the trace, lines fitted to the returns on
  either side meet at the corner to well under a spacing; the edge is the line through these.
- Normals point toward the sensor (the offset d of n·x + d = 0 is then the plane's distance from
  the sensor, ≥ 0), so association may compare normals with their sign. Edge directions are
  signless; they are reported with their largest component positive.
- Sectors go by the azimuth of a feature's centre (sector 0 centred on +x, then counter-clockwise),
  not by column, so they do not depend on where the column count starts.
- `per_sector` > 1 skips a candidate whose centre is within `min_separation` of one already kept
  in the sector: the next-best fits are otherwise neighbouring patches of the same surface.

Pure: numpy in, numpy out; the passes over every point or ROI point are compiled (numba,
`cache=True`): about 8 ms for a 128 × 1024 scan, half of it the two smoothness passes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np
from numba import njit

from services.localizer.poles import group_poles, pole_slices


class FeatureParams(msgspec.Struct, forbid_unknown_fields=True):
    # The thresholds below are reasoned for 1 cm of range noise (σ); the sensor driver's scans carry
    # 2 cm (its range_noise), at which they were flown and measured (benchmarks/localization.py,
    # tests/test_localizer_core.py's flights).
    sectors: int = 4  # azimuth sectors, each giving its own features (seed 003: forward, left, back, right)
    # planes and edges kept per sector (seed 003: one of each). Two, with min_angle_between_deg, give
    # a wall beside the floor: the floor alone leaves x, y and yaw to the IMU (an open field's scans)
    per_sector: int = 2
    window: int = 5  # neighbours on each side in the smoothness (LOAM: 5)
    # Steps between successive returns longer than a surface at this incidence would give mark
    # occlusions and grazing surfaces, whose points get no c (LOAM rejects both)
    max_incidence_deg: float = 75.0
    # NaN tolerated within a window, each with its mirror left out so the sum stays balanced: an
    # isolated dropout. More is a gap (the sky, a window) and the point is skipped, as in LOAM
    max_dropouts: int = 2
    wrap_columns: bool = True  # the columns close a full turn (a spinning sensor): the last neighbours the first
    tile_rows: int = 16  # candidates: one plane and one edge per tile of the grid
    tile_columns: int = 32
    # c along rows and columns of a plane candidate: at most this. Range noise σ gives c ≈ σ/r,
    # 0.005 for 1 cm at 2 m; a 90° corner seen square on is about 0.015 on 1024 columns
    plane_max_smoothness: float = 0.005
    edge_min_smoothness: float = 0.008  # c of an edge point: at least this, about half a 90° corner's
    edge_min_deviation: float = 0.03  # m an edge point stands off its neighbours' centroid: 3σ of 1 cm range noise
    # Plane ROI: (2·6 + 1) rows × (2·12 + 1) columns, about 9° square on an OS0-128: fewer points
    # than these 325 leave the normal of a 1 m patch a degree off with 1 cm range noise
    plane_roi_half_rows: int = 6
    plane_roi_half_columns: int = 12
    edge_roi_half_length: int = 16  # edge ROI: up to this many grid lines each way along the edge
    edge_search: int = 1  # columns (rows) an edge may drift per row (column) it is followed across
    edge_max_gap: int = 2  # lines in a row without a sharp point (dropouts) the trace bridges
    plane_min_points: int = 150  # of the 325 in the default plane ROI
    edge_min_points: int = 20  # of the 33 in the default edge ROI
    # m, RMSE of selected fits: a few times the range noise. A larger plane RMSE is a bent or
    # cluttered ROI; a larger edge RMSE a rounded or ragged edge
    plane_max_rmse: float = 0.03
    # the traced samples sit up to half a sample spacing off the edge, alternating along an edge
    # that runs obliquely through the grid (a wall meeting the floor): 2–3 cm RMSE at 5 m
    edge_max_rmse: float = 0.05
    min_separation: float = 1.0  # m between the centres of features kept in one sector (per_sector > 1)
    # A further plane (edge) in a sector is kept only when its normal (direction) lies at least this
    # far from every one kept there, either sign; 0: by RMSE alone (the seed). The floor is the smoothest
    # surface in every sector of an open field: by RMSE alone every plane is floor, which observes
    # height, roll and pitch and nothing else, while a wall 30 m off goes unused
    min_angle_between_deg: float = 45.0
    # Poles (poles.py: the axes of trunks and poles as lines, beyond the seed): kept per sector; 0: none
    poles_per_sector: int = 2
    pole_min_step: float = 0.5  # m: a free-standing run's ends step back at least this far
    pole_thin_width: float = 0.3  # m: a run this narrow is a thin pole, its returns' mean the axis
    pole_max_radius: float = 3.0  # m, of a fitted trunk
    pole_max_fit_rmse: float = 0.03  # m, radial RMSE of a trunk's circle fit: a few times the range noise
    pole_match: float = 0.3  # m between a row's axis point and its pole's
    pole_min_rows: int = 6  # rows with an axis point on the pole
    pole_min_height: float = 1.0  # m the axis points span: a drone or a balloon spans less
    pole_max_rmse: float = 0.1  # m, of the axis points from the pole's line

    def __post_init__(self) -> None:
        if self.poles_per_sector < 0 or self.pole_min_rows < 2:
            raise msgspec.ValidationError("poles_per_sector must not be negative, pole_min_rows at least 2")
        for name in ("pole_min_step", "pole_thin_width", "pole_max_radius", "pole_max_fit_rmse", "pole_match",
                     "pole_min_height", "pole_max_rmse"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise msgspec.ValidationError(f"{name} must be positive and finite")
        for name in ("sectors", "per_sector", "window", "tile_rows", "tile_columns", "edge_roi_half_length"):
            if getattr(self, name) < 1:
                raise msgspec.ValidationError(f"{name} must be at least 1")
        for name in ("plane_roi_half_rows", "plane_roi_half_columns", "edge_search", "edge_max_gap",
                     "max_dropouts"):
            if getattr(self, name) < 0:
                raise msgspec.ValidationError(f"{name} must not be negative")
        if not 0.0 < self.max_incidence_deg < 90.0:
            raise msgspec.ValidationError("max_incidence_deg must be between 0 and 90")
        for name in ("plane_max_smoothness", "plane_max_rmse", "edge_max_rmse"):
            if not getattr(self, name) > 0:
                raise msgspec.ValidationError(f"{name} must be positive")
        if not 0.0 <= self.min_angle_between_deg <= 90.0:
            raise msgspec.ValidationError("min_angle_between_deg must be from 0 to 90")
        for name in ("edge_min_smoothness", "edge_min_deviation", "min_separation"):
            if not 0.0 <= getattr(self, name) < math.inf:
                raise msgspec.ValidationError(f"{name} must be finite and not negative")
        if not 3 <= self.plane_min_points <= (2 * self.plane_roi_half_rows + 1) * (2 * self.plane_roi_half_columns + 1):
            raise msgspec.ValidationError("plane_min_points must be from 3 to the points of the plane ROI")
        if not 4 <= self.edge_min_points <= 2 * self.edge_roi_half_length + 1:
            raise msgspec.ValidationError("edge_min_points must be from 4 to the points of the edge ROI")


@dataclass(frozen=True)
class PlaneFeature:
    centre: np.ndarray  # (3,) centroid of the ROI points, on the plane
    normal: np.ndarray  # (3,) unit, pointing toward the sensor
    offset: float  # d in n·x + d = 0: the plane's distance from the sensor (m)
    rmse: float  # m, point-to-plane
    point_count: int  # ROI points in the fit
    sector: int


@dataclass(frozen=True)
class EdgeFeature:
    centre: np.ndarray  # (3,) on the line, abreast of the traced samples' centroid
    direction: np.ndarray  # (3,) unit, signless (largest component positive)
    rmse: float  # m, of the traced samples from their own line (what selection ranks by)
    point_count: int  # traced samples (a pole's: rows)
    sector: int
    pole: bool = False  # the axis of a trunk or pole (poles.py), not a corner


@dataclass(frozen=True)
class Features:
    planes: tuple[PlaneFeature, ...]
    edges: tuple[EdgeFeature, ...]


def extract_features(points: np.ndarray, params: FeatureParams | None = None) -> Features:
    """Seed 003's planes and edges of one organised (H, W, 3) sensor-frame scan (NaN: no return)."""
    params = params or FeatureParams()
    grid = np.asarray(points, dtype=np.float64)
    if grid.ndim != 3 or grid.shape[2] != 3:
        raise ValueError(f"an organised scan is (rows, columns, 3), got shape {grid.shape}")
    grid = np.ascontiguousarray(grid)
    step_factor = 1.0 / math.cos(math.radians(params.max_incidence_deg))
    along_rows = line_smoothness(grid, params.window, step_factor, params.max_dropouts, True, params.wrap_columns)
    along_columns = line_smoothness(grid, params.window, step_factor, params.max_dropouts, False, False)
    return Features(_plane_features(grid, along_rows[0], along_columns[0], params),
                    _edge_features(grid, along_rows, along_columns, params) + _pole_features(grid, params))


def _pole_features(grid, params: FeatureParams) -> tuple[EdgeFeature, ...]:
    """Per sector the `poles_per_sector` poles of lowest RMSE (poles.py), as lines."""
    if params.poles_per_sector == 0:
        return ()
    slices = pole_slices(grid, params.pole_min_step, params.pole_thin_width, params.pole_max_radius,
                         params.pole_max_fit_rmse)
    poles = [p for p in group_poles(slices, params.pole_match, params.pole_min_rows, params.pole_min_height)
             if p[2] <= params.pole_max_rmse]
    if not poles:
        return ()
    centres = np.array([p[0] for p in poles])
    sectors = sector_of(centres, params.sectors)
    kept = []
    for sector in range(params.sectors):
        members = [k for k in np.flatnonzero(sectors == sector)]
        members.sort(key=lambda k: poles[k][2])
        kept += [(k, sector) for k in members[:params.poles_per_sector]]
    return tuple(EdgeFeature(poles[k][0].copy(), poles[k][1].copy(), float(poles[k][2]), int(poles[k][3]), sector,
                             pole=True) for k, sector in kept)


# ---------------------------------------------------------------------------------------------
# Candidates


@njit(cache=True)
def line_smoothness(points, window, step_factor, max_dropouts, along_rows, wrap):
    """Smoothness c and deviation (m) of every point of the (H, W, 3) grid along its row
    (`along_rows`) or column, over `window` neighbours each side: v = Σ_j (p_j − p_i) without its
    component along the chord p_{i+w} − p_{i−w}; deviation = ||v|| / n, c = deviation / ||p_i||
    (n = 2·window). A NaN neighbour is left out with its mirror, so the sum stays balanced. Both NaN
    where the window holds more than `max_dropouts` NaN or runs off the grid (unless `wrap`), or
    where a step between successive returns in it is longer than `step_factor` × (range · angle
    between their beams). Sums and step counts are prefix differences: O(1) per point whatever
    the window, but for windows with dropouts."""
    rows, cols = points.shape[0], points.shape[1]
    lines, length = (rows, cols) if along_rows else (cols, rows)
    smoothness = np.full((rows, cols), np.nan)
    deviation = np.full((rows, cols), np.nan)
    if wrap and length < 2 * window + 1:
        return smoothness, deviation  # the window would hold a point twice
    extended = length + 2 * window
    p = np.zeros((extended, 3))
    unit = np.zeros((extended, 3))  # p / |p|: the chord between two beams is their angle
    ranges = np.zeros(extended)
    valid = np.zeros(extended, dtype=np.bool_)
    sums = np.zeros((extended + 1, 3))  # prefix sums over the extended line
    missing = np.zeros(extended + 1, dtype=np.int64)
    last_valid = np.zeros(extended, dtype=np.int64)  # the last return at or before each position
    long_steps = np.zeros(extended + 1, dtype=np.int64)  # prefix counts, by start, of steps too long
    limit = step_factor * step_factor
    n = 2 * window
    for line in range(lines):
        previous = -1
        for e in range(extended):
            pos = e - window
            if wrap:
                pos %= length
            valid[e] = False
            if 0 <= pos < length:
                r, c = (line, pos) if along_rows else (pos, line)
                x, y, z = points[r, c, 0], points[r, c, 1], points[r, c, 2]
                rng = math.sqrt(x * x + y * y + z * z)
                if math.isfinite(rng) and rng > 0.0:
                    valid[e] = True
                    p[e, 0], p[e, 1], p[e, 2] = x, y, z
                    unit[e, 0], unit[e, 1], unit[e, 2] = x / rng, y / rng, z / rng
                    ranges[e] = rng
            for a in range(3):
                sums[e + 1, a] = sums[e, a] + (p[e, a] if valid[e] else 0.0)
            missing[e + 1] = missing[e] + (0 if valid[e] else 1)
            if valid[e]:  # the step from the previous return to this one, counted at the previous one
                if previous >= 0 and _too_long(p, unit, ranges, previous, e, limit):
                    for k in range(previous + 1, e + 1):
                        long_steps[k] += 1
                previous = e
            long_steps[e + 1] = long_steps[e]
            last_valid[e] = previous
        for i in range(length):
            e = i + window
            dropouts = missing[e + window + 1] - missing[e - window]
            if dropouts > max_dropouts or not valid[e]:
                continue
            if long_steps[last_valid[e + window]] - long_steps[e - window] > 0:  # steps within the window
                continue
            if dropouts == 0:
                top, bottom = e + window + 1, e - window
                bend = _bend(sums[top, 0] - sums[bottom, 0], sums[top, 1] - sums[bottom, 1],
                             sums[top, 2] - sums[bottom, 2], p, e, e - window, e + window, n)
            else:
                bend = _bend_around_dropouts(p, valid, e, window)
            if not bend >= 0.0:
                continue  # NaN: too few pairs
            r, c = (line, i) if along_rows else (i, line)
            deviation[r, c] = bend
            smoothness[r, c] = bend / ranges[e]
    return smoothness, deviation


@njit(cache=True)
def _bend(sum_x, sum_y, sum_z, p, e, first, last, n):
    """||v|| / n for v = Σ_j (p_j − p_e) over n neighbours whose sum with p_e is `sum`, without
    its component along the chord p_last − p_first."""
    vx, vy, vz = sum_x - (n + 1) * p[e, 0], sum_y - (n + 1) * p[e, 1], sum_z - (n + 1) * p[e, 2]
    cx, cy, cz = p[last, 0] - p[first, 0], p[last, 1] - p[first, 1], p[last, 2] - p[first, 2]
    chord_squared = cx * cx + cy * cy + cz * cz
    along = (vx * cx + vy * cy + vz * cz) / chord_squared if chord_squared > 0.0 else 0.0
    vx, vy, vz = vx - along * cx, vy - along * cy, vz - along * cz
    return math.sqrt(vx * vx + vy * vy + vz * vz) / n


@njit(cache=True)
def _bend_around_dropouts(p, valid, e, window):
    """`_bend` of extended point e over the pairs of neighbours at equal offsets that both returned;
    NaN with fewer than half the pairs."""
    sum_x, sum_y, sum_z = p[e, 0], p[e, 1], p[e, 2]
    pairs = 0
    first = last = e
    for offset in range(1, window + 1):
        if valid[e - offset] and valid[e + offset]:
            sum_x += p[e - offset, 0] + p[e + offset, 0]
            sum_y += p[e - offset, 1] + p[e + offset, 1]
            sum_z += p[e - offset, 2] + p[e + offset, 2]
            pairs += 1
            first, last = e - offset, e + offset
    if 2 * pairs < window:
        return np.nan
    return _bend(sum_x, sum_y, sum_z, p, e, first, last, 2 * pairs)


@njit(cache=True)
def _too_long(p, unit, ranges, a, b, limit):
    """Whether the step between returns a and b is longer than a surface at the maximum incidence
    gives: squared, step² > limit · (nearer range)² · (chord between their unit beams)²."""
    step = chord = 0.0
    for axis in range(3):
        step += (p[b, axis] - p[a, axis]) ** 2
        chord += (unit[b, axis] - unit[a, axis]) ** 2
    near = min(ranges[a], ranges[b])
    return step > limit * near * near * chord


def _tile_best(score: np.ndarray, tile_rows: int, tile_columns: int, highest: bool) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of each tile's lowest (or highest) finite score; tiles with none give nothing."""
    rows, cols = score.shape
    tiles_down, tiles_across = -(-rows // tile_rows), -(-cols // tile_columns)
    padded = np.full((tiles_down * tile_rows, tiles_across * tile_columns), np.nan)
    padded[:rows, :cols] = -score if highest else score
    padded[np.isnan(padded)] = np.inf
    tiles = padded.reshape(tiles_down, tile_rows, tiles_across, tile_columns).transpose(0, 2, 1, 3)
    tiles = tiles.reshape(tiles_down, tiles_across, tile_rows * tile_columns)
    best = np.argmin(tiles, axis=-1)
    found = np.isfinite(np.take_along_axis(tiles, best[..., None], axis=-1)[..., 0])
    tile_down, tile_across = np.nonzero(found)
    inside = best[found]
    return tile_down * tile_rows + inside // tile_columns, tile_across * tile_columns + inside % tile_columns


# ---------------------------------------------------------------------------------------------
# Planes


def _plane_features(grid, smooth_rows, smooth_columns, params: FeatureParams) -> tuple[PlaneFeature, ...]:
    score = np.maximum(smooth_rows, smooth_columns)  # NaN unless smooth both ways
    score[score > params.plane_max_smoothness] = np.nan
    rows, cols = _tile_best(score, params.tile_rows, params.tile_columns, highest=False)
    moments = block_moments(grid, rows, cols, params.plane_roi_half_rows, params.plane_roi_half_columns,
                            params.wrap_columns)
    centres, axes, eigenvalues, counts = _axes_from_moments(*moments, params.plane_min_points)
    normals = axes[:, :, 0]
    normals *= np.where(np.einsum("ki,ki->k", normals, centres) > 0, -1.0, 1.0)[:, None]  # toward the sensor
    rmse = np.sqrt(np.maximum(eigenvalues[:, 0], 0.0) / np.maximum(counts, 1))
    chosen = _select(centres, normals, rmse, counts >= params.plane_min_points, params.plane_max_rmse, params)
    return tuple(PlaneFeature(centres[k].copy(), normals[k].copy(), float(-normals[k] @ centres[k]), float(rmse[k]),
                              int(counts[k]), sector) for k, sector in chosen)


@njit(cache=True)
def block_moments(points, rows, cols, half_rows, half_columns, wrap):
    """Point counts (K,), sums (K, 3) and sums of outer products (K, 3, 3) of the returns in the
    (2·half_rows + 1) × (2·half_columns + 1) block of the (H, W, 3) grid around each (row, column);
    columns wrap if `wrap`. Accumulated in place: no gathered copy of the blocks."""
    height, width = points.shape[0], points.shape[1]
    counts = np.zeros(rows.shape[0], dtype=np.int64)
    sums = np.zeros((rows.shape[0], 3))
    products = np.zeros((rows.shape[0], 3, 3))
    for k in range(rows.shape[0]):
        for r in range(max(rows[k] - half_rows, 0), min(rows[k] + half_rows + 1, height)):
            for shift in range(-half_columns, half_columns + 1):
                c = cols[k] + shift
                if wrap:
                    c %= width
                elif c < 0 or c >= width:
                    continue
                x, y, z = points[r, c, 0], points[r, c, 1], points[r, c, 2]
                if not math.isfinite(x + y + z):
                    continue
                counts[k] += 1
                sums[k, 0] += x
                sums[k, 1] += y
                sums[k, 2] += z
                products[k, 0, 0] += x * x
                products[k, 0, 1] += x * y
                products[k, 0, 2] += x * z
                products[k, 1, 1] += y * y
                products[k, 1, 2] += y * z
                products[k, 2, 2] += z * z
        for i, j in ((1, 0), (2, 0), (2, 1)):  # symmetric
            products[k, i, j] = products[k, j, i]
    return counts, sums, products


def _gather(grid, rows, cols, wrap) -> np.ndarray:
    """grid[rows, cols] with NaN where the index is off the grid (columns wrap if `wrap`)."""
    height, width = grid.shape[:2]
    if wrap:
        cols = cols % width
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    points = grid[np.clip(rows, 0, height - 1), np.clip(cols, 0, width - 1)]
    points[~inside] = np.nan
    return points


def _principal_axes(roi: np.ndarray, min_points: int):
    """`_axes_from_moments` of the finite points of each (K, M, 3) ROI (NaN: no point)."""
    finite = np.isfinite(roi[..., 0] + roi[..., 1] + roi[..., 2])  # faster than .all(axis=-1) on 3 values
    filled = np.where(finite[..., None], roi, 0.0)
    # Batched products (matmul) rather than reductions over the middle axis: several times faster.
    sums = (finite[:, None, :].astype(np.float64) @ filled)[:, 0]
    return _axes_from_moments(finite.sum(axis=1), sums, filled.transpose(0, 2, 1) @ filled, min_points)


def _axes_from_moments(counts, sums, products, min_points: int):
    """Centroids (K, 3), principal axes (K, 3, 3: columns by ascending eigenvalue), eigenvalues (K, 3)
    of the scatter Σ(p − m)(p − m)ᵀ, and the counts, of K point sets given by their counts, sums
    and sums of outer products. Sets of fewer than `min_points` get NaN axes: never selected."""
    centres = sums / np.maximum(counts, 1)[:, None]
    # Σppᵀ − N·mmᵀ: the cancellation costs ~1e-16 × N·r², far below any RMSE of interest.
    scatter = products - counts[:, None, None] * centres[:, :, None] * centres[:, None, :]
    eigenvalues = np.full((len(counts), 3), np.nan)
    axes = np.full((len(counts), 3, 3), np.nan)
    enough = counts >= min_points
    if enough.any():
        eigenvalues[enough], axes[enough] = np.linalg.eigh(scatter[enough])
    return centres, axes, eigenvalues, counts


# ---------------------------------------------------------------------------------------------
# Edges


def _edge_features(grid, along_rows, along_columns, params: FeatureParams) -> tuple[EdgeFeature, ...]:
    sharp_rows = _edge_strength(*along_rows, params)
    sharp_columns = _edge_strength(*along_columns, params)
    rows, cols = _tile_best(np.fmax(sharp_rows, sharp_columns), params.tile_rows, params.tile_columns, highest=True)
    crosses_rows = ~(sharp_columns[rows, cols] > sharp_rows[rows, cols])  # sharp along its row: runs across rows
    path_rows, path_cols = trace_edges(sharp_rows, sharp_columns, rows, cols, crosses_rows,
                                       params.edge_roi_half_length, params.edge_search, params.edge_max_gap,
                                       params.wrap_columns)
    roi = grid[path_rows, path_cols]  # -1 marks an unused slot: read, then blanked
    roi[path_rows < 0] = np.nan
    centres, axes, eigenvalues, counts = _principal_axes(roi, params.edge_min_points)
    directions = axes[:, :, 2]
    largest = np.take_along_axis(directions, np.abs(np.nan_to_num(directions)).argmax(axis=1)[:, None], axis=1)
    directions *= np.where(largest < 0, -1.0, 1.0)
    rmse = np.sqrt(np.maximum(eigenvalues[:, 0] + eigenvalues[:, 1], 0.0) / np.maximum(counts, 1))
    chosen = _select(centres, directions, rmse, counts >= params.edge_min_points, params.edge_max_rmse, params)
    edges = []
    for k, sector in chosen:
        centre, direction = _corner_line(grid, path_rows[k], path_cols[k], crosses_rows[k], params)
        if centre is None:  # too few lines give a corner: keep the samples' line
            centre, direction = centres[k], directions[k]
        else:  # abreast of the samples, where the ROI is (and in their sector)
            centre = centre + ((centres[k] - centre) @ direction) * direction
        edges.append(EdgeFeature(centre.copy(), direction.copy(), float(rmse[k]), int(counts[k]), sector))
    return tuple(edges)


def _edge_strength(smoothness, deviation, params: FeatureParams) -> np.ndarray:
    """c where a point is an edge point (sharp and standing off its neighbours beyond noise), else NaN."""
    sharp = (smoothness >= params.edge_min_smoothness) & (deviation >= params.edge_min_deviation)
    return np.where(sharp, smoothness, np.nan)


@njit(cache=True)
def trace_edges(sharp_rows, sharp_columns, rows, cols, crosses_rows, half_length, search, max_gap, wrap_columns):
    """(path_rows, path_cols), each (K, 2·half_length + 1), of the points of each edge followed from
    its candidate (rows[k], cols[k]); -1 in the slots the trace did not reach.

    An edge sharp along its row (`crosses_rows`) is followed row by row, in each taking the
    sharpest point (`sharp_rows`: c where a point is an edge point, else NaN) within `search`
    columns of the previous pick; otherwise column by column through `sharp_columns`, searching
    rows. A dropout within the smoothness window leaves a line without c: up to `max_gap` such
    lines in a row are bridged, more and the edge has ended."""
    height, width = sharp_rows.shape
    slots = 2 * half_length + 1
    path_rows = np.full((rows.shape[0], slots), -1, dtype=np.int64)
    path_cols = np.full((rows.shape[0], slots), -1, dtype=np.int64)
    for k in range(rows.shape[0]):
        path_rows[k, half_length], path_cols[k, half_length] = rows[k], cols[k]
        across = crosses_rows[k]
        step_count, offset_count = (height, width) if across else (width, height)
        wrap_steps, wrap_offsets = (False, wrap_columns) if across else (wrap_columns, False)
        start_step, start_offset = (rows[k], cols[k]) if across else (cols[k], rows[k])
        for direction in (-1, 1):
            current, misses = start_offset, 0
            for n in range(1, half_length + 1):
                step = start_step + direction * n
                if wrap_steps:
                    step %= step_count
                elif step < 0 or step >= step_count:
                    break
                best, best_offset = -1.0, -1
                for shift in range(-search, search + 1):
                    offset = current + shift
                    if wrap_offsets:
                        offset %= offset_count
                    elif offset < 0 or offset >= offset_count:
                        continue
                    value = sharp_rows[step, offset] if across else sharp_columns[offset, step]
                    if value > best:  # NaN (not sharp) never is
                        best, best_offset = value, offset
                if best_offset < 0:
                    misses += 1
                    if misses > max_gap:
                        break
                    continue
                misses, current = 0, best_offset
                slot = half_length + direction * n
                path_rows[k, slot], path_cols[k, slot] = (step, current) if across else (current, step)
    return path_rows, path_cols


def _without_outliers(points, centre, direction, factor: float = 3.0) -> np.ndarray:
    """The (M, 3) points (NaN: none) with those farther from the line than `factor` × the median
    distance blanked: a line of the trace whose two sides were not clean surfaces (a dropout, a
    third surface near the end of the edge) gives a stray corner, and a few tilt the line."""
    offsets = points - centre
    along = offsets @ direction
    distances = np.sqrt(np.maximum(np.einsum("mi,mi->m", offsets, offsets) - along * along, 0.0))
    finite = np.isfinite(distances)
    trimmed = points.copy()
    if finite.any():
        trimmed[finite & (distances > factor * np.median(distances[finite]))] = np.nan
    return trimmed


def _corner_line(grid, path_rows, path_cols, crosses_rows: bool, params: FeatureParams):
    """(centre, direction) of a selected edge through sub-sample corner points, or (None, None).

    The traced samples are the returns nearest the edge, up to half a sample spacing off it (r·π/W
    across a vertical edge, 1.5 cm at 5 m on 1024 columns, and more along a wall at an angle). In
    each line of the trace, a line is fitted to 2·window returns on each side of the traced one
    (beyond its neighbours, in case the trace runs a sample beside the edge), and the point where
    the two lines pass closest is the corner in that line. Lines whose sides do not meet at a
    clear angle, or meet farther from the traced sample than their centroids, give none; at least
    half of edge_min_points lines must give one."""
    used = path_rows >= 0
    rows, cols = path_rows[used], path_cols[used]
    if len(rows) < params.edge_min_points:
        return None, None
    side = np.arange(2, 2 * params.window + 2)[None, :]
    if crosses_rows:  # sides along the row
        before = _gather(grid, rows[:, None] + 0 * side, cols[:, None] - side, params.wrap_columns)
        after = _gather(grid, rows[:, None] + 0 * side, cols[:, None] + side, params.wrap_columns)
    else:
        before = _gather(grid, rows[:, None] - side, cols[:, None] + 0 * side, params.wrap_columns)
        after = _gather(grid, rows[:, None] + side, cols[:, None] + 0 * side, params.wrap_columns)
    start_before, axes_before, _, _ = _principal_axes(before, 3)
    start_after, axes_after, _, _ = _principal_axes(after, 3)
    corners = _closest_approach(start_before, axes_before[:, :, 2], start_after, axes_after[:, :, 2])
    sample = grid[rows, cols]
    reach = np.minimum(np.linalg.norm(start_before - sample, axis=1), np.linalg.norm(start_after - sample, axis=1))
    corners[~(np.linalg.norm(corners - sample, axis=1) < reach)] = np.nan  # NaN compares False: dropped too
    centres, axes, _, _ = _principal_axes(corners[None], params.edge_min_points // 2)
    corners = _without_outliers(corners, centres[0], axes[0, :, 2])
    centres, axes, _, counts = _principal_axes(corners[None], params.edge_min_points // 2)
    if counts[0] < params.edge_min_points // 2:
        return None, None
    direction = axes[0, :, 2]
    return centres[0], direction * (-1.0 if direction[np.abs(direction).argmax()] < 0 else 1.0)


def _closest_approach(a, u, b, v, min_angle_deg: float = 20.0) -> np.ndarray:
    """(N, 3) midpoints of the closest approach of lines a + s·u and b + t·v (unit u, v); NaN where
    they are within `min_angle_deg` of parallel (a flat surface, no corner) or undefined."""
    cosine = np.einsum("ni,ni->n", u, v)
    between = a - b
    along_u, along_v = np.einsum("ni,ni->n", u, between), np.einsum("ni,ni->n", v, between)
    denominator = 1.0 - cosine * cosine
    with np.errstate(all="ignore"):
        s = (cosine * along_v - along_u) / denominator
        t = (along_v - cosine * along_u) / denominator
    midpoints = (a + s[:, None] * u + b + t[:, None] * v) / 2.0
    midpoints[~(denominator > math.sin(math.radians(min_angle_deg)) ** 2)] = np.nan
    return midpoints


# ---------------------------------------------------------------------------------------------
# Selection


def sector_of(centres: np.ndarray, sectors: int) -> np.ndarray:
    """Azimuth sector of each (N, 3) sensor-frame point: 0 centred on +x (forward), counting
    counter-clockwise (with 4: forward, left, back, right)."""
    width = 2.0 * np.pi / sectors
    azimuth = np.arctan2(centres[:, 1], centres[:, 0])
    return (np.floor((azimuth + width / 2) / width).astype(np.int64)) % sectors


def _select(centres, vectors, rmse, enough_points, max_rmse, params: FeatureParams) -> list[tuple[int, int]]:
    """(index, sector) of the fits kept: per sector the `per_sector` lowest RMSE among those with
    enough points and an RMSE within `max_rmse`, at least `min_separation` apart and with normals
    (directions, `vectors`) at least `min_angle_between_deg` apart."""
    max_cosine = math.cos(math.radians(params.min_angle_between_deg))
    eligible = np.flatnonzero(enough_points & (rmse <= max_rmse))
    if len(eligible) == 0:
        return []
    sectors = sector_of(centres[eligible], params.sectors)
    chosen: list[tuple[int, int]] = []
    for sector in range(params.sectors):
        members = eligible[sectors == sector]
        kept: list[int] = []
        for k in members[np.argsort(rmse[members], kind="stable")]:
            if len(kept) == params.per_sector:
                break
            if all(np.linalg.norm(centres[k] - centres[j]) >= params.min_separation
                   and (max_cosine >= 1.0 or abs(float(vectors[k] @ vectors[j])) <= max_cosine) for j in kept):
                kept.append(int(k))
        chosen.extend((k, sector) for k in kept)
    return chosen
