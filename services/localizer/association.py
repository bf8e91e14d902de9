"""Feature association: seed 003's Grape localizer (sec. 2.1) matching a scan's features to its map.

The scan's features, moved into the map frame by the best-known pose (`transform_features`), are
each compared with the k map features whose centres are nearest (a k-d tree over the centres,
as in the paper). A plane is taken for a map plane when their normals agree within
`max_normal_angle_deg` and its centre lies within `max_plane_distance` of the map plane; an edge
for a map edge when their directions agree within `max_direction_angle_deg` (either sign) and its
centre lies within `max_edge_distance` of the map line. An associated feature carries the map
feature's global id; the others get new ids when added to the map.

What the paper leaves open, and what Falconry chose:
- Normals are compared with their sign. Extraction points every normal toward the sensor
  (services/localizer/features.py), so one surface seen from the same side always has the same
  normal, and the two faces of a thin wall, seen from either side, stay apart.
- Planes and edges are infinite in the factor graph, so a map plane matches by the new centre's
  distance from the plane, not by the distance between centres (the same wall seen from further
  along has its centre metres away). The centres only choose the k candidates.
- Of the candidates that pass, the nearest by centre is taken: the same wall seen in two sectors
  gives two map planes that both pass, and the nearer patch is the better-placed landmark.
- The map only grows here; seed 003 prunes the oldest features from the graph, which is the
  caller's to do: `FeatureMap` never removes a feature.

Pure: numpy and scipy; the k-d trees are rebuilt lazily, on the first query after features were added.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import msgspec
import numpy as np
from scipy.spatial import cKDTree

from services.localizer.features import EdgeFeature, Features, PlaneFeature


class AssociationParams(msgspec.Struct, forbid_unknown_fields=True):
    neighbours: int = 5  # k map features nearest by centre examined per new feature
    # Tolerances for the error of the pose the features were moved by (and the fits' own error)
    max_normal_angle_deg: float = 10.0
    max_plane_distance: float = 0.3  # m, of the new plane's centre from the map plane
    max_direction_angle_deg: float = 10.0
    max_edge_distance: float = 0.3  # m, of the new edge's centre from the map line

    def __post_init__(self) -> None:
        if self.neighbours < 1:
            raise msgspec.ValidationError("neighbours must be at least 1")
        for name in ("max_normal_angle_deg", "max_direction_angle_deg"):
            if not 0.0 < getattr(self, name) <= 90.0:
                raise msgspec.ValidationError(f"{name} must be above 0 and at most 90")
        for name in ("max_plane_distance", "max_edge_distance"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise msgspec.ValidationError(f"{name} must be positive and finite")


@dataclass(frozen=True)
class Association:
    feature: PlaneFeature | EdgeFeature  # the scan's feature, in the map frame
    map_id: int | None  # the map feature it was taken for; None: none matched
    angle: float  # rad between the normals (the directions, either sign); NaN without a match
    distance: float  # m of the feature's centre from the map plane (line); NaN without a match


class _Layer:
    """One kind of map feature: the features, their ids and a k-d tree over their centres."""

    def __init__(self) -> None:
        self.features: list[PlaneFeature | EdgeFeature] = []
        self.ids: list[int] = []
        self._tree: cKDTree | None = None

    def add(self, feature: PlaneFeature | EdgeFeature, feature_id: int) -> None:
        self.features.append(feature)
        self.ids.append(feature_id)
        self._tree = None  # rebuilt on the next query

    def nearest(self, centres: np.ndarray, k: int) -> np.ndarray:
        """(N, min(k, size)) indices of the map features nearest each centre, nearest first."""
        if not self.features:
            return np.zeros((len(centres), 0), dtype=np.int64)
        if self._tree is None:
            self._tree = cKDTree(np.array([f.centre for f in self.features]))
        _, indices = self._tree.query(centres, k=list(range(1, min(k, len(self.features)) + 1)))
        return np.asarray(indices, dtype=np.int64).reshape(len(centres), -1)


class FeatureMap:
    """Map planes and edges under global integer ids (one sequence for both kinds)."""

    def __init__(self) -> None:
        self.planes = _Layer()
        self.edges = _Layer()
        self._by_id: dict[int, PlaneFeature | EdgeFeature] = {}
        self._next_id = 0

    def __len__(self) -> int:
        return len(self._by_id)

    def add(self, feature: PlaneFeature | EdgeFeature) -> int:
        """Adds `feature` (map frame) under a new global id, returned."""
        feature_id = self._next_id
        self._next_id += 1
        (self.planes if isinstance(feature, PlaneFeature) else self.edges).add(feature, feature_id)
        self._by_id[feature_id] = feature
        return feature_id

    def add_unassociated(self, associations: list[Association]) -> list[int]:
        """Adds the features that matched nothing, each under a new id; returns every association's
        global id in order (the map feature's for the others)."""
        return [self.add(a.feature) if a.map_id is None else a.map_id for a in associations]

    def feature(self, feature_id: int) -> PlaneFeature | EdgeFeature:
        return self._by_id[feature_id]


def associate(features: Features, feature_map: FeatureMap,
              params: AssociationParams | None = None) -> list[Association]:
    """One association per feature of `features` (map frame), planes first then edges, in order."""
    params = params or AssociationParams()
    planes = _associate(features.planes, feature_map.planes, params.neighbours, _plane_match,
                        math.cos(math.radians(params.max_normal_angle_deg)), params.max_plane_distance)
    edges = _associate(features.edges, feature_map.edges, params.neighbours, _edge_match,
                       math.cos(math.radians(params.max_direction_angle_deg)), params.max_edge_distance)
    return planes + edges


def _associate(features, layer: _Layer, k: int, match, min_cosine: float, max_distance: float) -> list[Association]:
    if not features:
        return []
    candidates = layer.nearest(np.array([f.centre for f in features]), k)
    associations = []
    for feature, nearest in zip(features, candidates):
        found = Association(feature, None, math.nan, math.nan)
        for index in nearest:  # nearest centre first: the first that passes is taken
            cosine, distance = match(feature, layer.features[index])
            if cosine >= min_cosine and distance <= max_distance:
                found = Association(feature, layer.ids[index], math.acos(min(cosine, 1.0)), distance)
                break
        associations.append(found)
    return associations


def _plane_match(plane: PlaneFeature, mapped: PlaneFeature) -> tuple[float, float]:
    """Cosine between the normals (signed) and distance of the plane's centre from the map plane."""
    return float(plane.normal @ mapped.normal), abs(float(mapped.normal @ plane.centre) + mapped.offset)


def _edge_match(edge: EdgeFeature, mapped: EdgeFeature) -> tuple[float, float]:
    """|Cosine| between the directions and distance of the edge's centre from the map line."""
    offset = edge.centre - mapped.centre
    across = offset - (offset @ mapped.direction) * mapped.direction
    return abs(float(edge.direction @ mapped.direction)), float(np.linalg.norm(across))


def transform_features(features: Features, rotation: np.ndarray, translation: np.ndarray) -> Features:
    """`features` moved by the rigid pose x ↦ R·x + t (e.g. sensor frame to map frame). Sectors stay
    those of the scan."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64).reshape(3)
    if rotation.shape != (3, 3):
        raise ValueError(f"a rotation is a 3 × 3 matrix, got shape {rotation.shape}")
    planes = []
    for plane in features.planes:
        centre, normal = rotation @ plane.centre + translation, rotation @ plane.normal
        planes.append(replace(plane, centre=centre, normal=normal, offset=float(-normal @ centre)))
    edges = [replace(edge, centre=rotation @ edge.centre + translation, direction=rotation @ edge.direction)
             for edge in features.edges]
    return Features(tuple(planes), tuple(edges))
