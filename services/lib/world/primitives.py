"""The simulated world as the sensors see it: primitives (planes, spheres, upright cylinders, boxes,
upright cones) built from the world model's obstacles and targets, the flat table the compiled
caster reads (`pack`, raycast.py), and casting rays into it (`cast`, `cast_with_ids`). Shared by
the simulated LiDAR (services/sensor_driver) and camera (services/camera), so both see one world.

Primitives (`Primitives`, all float64 arrays, one row each):
  planes     (P,)   horizontal planes z = value (the ground)
  spheres    (S, 4) cx, cy, cz, r (balloons)
  cylinders  (C, 5) cx, cy, z_base, r, h (vertical, capped: poles, tree trunks, intruder drones)
  boxes      (B, 6) x_min, y_min, z_min, x_max, y_max, z_max (axis-aligned: buildings)
  cones      (K, 5) cx, cy, z_base, r_base, h (vertical, apex up, base disk closed: trees)
Spheres and cylinders carry a hit id each (0 static world, k >= 1 target k); the other kinds
are always static. Ranges are along unit directions, so a range is also the distance to the hit.
Every primitive also has a colour (sRGB, uint8 (N, 3) per kind; grey unless the world model
says otherwise): the LiDAR ignores it, the simulated camera renders it.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import GroundTruth, Obstacle, TargetTruth, VehicleTruth, WorldModel
from services.lib.world import numpy_caster
from services.lib.world.raycast import BOX, CONE, CYLINDER, PLANE, SPHERE, Packed, cast_kernel

DRONE_BODY_HEIGHT = 0.3  # m: an intruder multirotor is a flat disk of its radius, this thick
REFLECTIVITY = {"ground": 0.2, "static": 0.3, "target": 0.6}
DEFAULT_COLOR = (128, 128, 128)

__all__ = ["DEFAULT_COLOR", "DRONE_BODY_HEIGHT", "REFLECTIVITY", "Packed", "Primitives", "carrier", "cast",
           "cast_with_ids", "finite_pose", "noise_stream_key", "pack", "primitives_from_obstacles", "read_only",
           "target_spheres"]


@dataclass
class Primitives:
    planes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    cones: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    sphere_ids: np.ndarray | None = None  # int32 (S,); None = all static (0)
    cylinder_ids: np.ndarray | None = None
    # sRGB uint8 (N, 3) per kind, in the order of the rows above; None = all DEFAULT_COLOR
    plane_colors: np.ndarray | None = None
    sphere_colors: np.ndarray | None = None
    cylinder_colors: np.ndarray | None = None
    box_colors: np.ndarray | None = None
    cone_colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.planes = np.asarray(self.planes, dtype=float).reshape(-1)
        self.spheres = np.asarray(self.spheres, dtype=float).reshape(-1, 4)
        self.cylinders = np.asarray(self.cylinders, dtype=float).reshape(-1, 5)
        self.boxes = np.asarray(self.boxes, dtype=float).reshape(-1, 6)
        self.cones = np.asarray(self.cones, dtype=float).reshape(-1, 5)
        self.sphere_ids = _ids(self.sphere_ids, len(self.spheres))
        self.cylinder_ids = _ids(self.cylinder_ids, len(self.cylinders))
        self.plane_colors = _colors(self.plane_colors, len(self.planes))
        self.sphere_colors = _colors(self.sphere_colors, len(self.spheres))
        self.cylinder_colors = _colors(self.cylinder_colors, len(self.cylinders))
        self.box_colors = _colors(self.box_colors, len(self.boxes))
        self.cone_colors = _colors(self.cone_colors, len(self.cones))

    def with_spheres(self, spheres: np.ndarray, ids: Sequence[int] | None = None) -> "Primitives":
        """These primitives plus more spheres (moving targets of one scan)."""
        extra = np.asarray(spheres, dtype=float).reshape(-1, 4)
        return Primitives(self.planes, np.vstack([self.spheres, extra]), self.cylinders, self.boxes, self.cones,
                          np.concatenate([self.sphere_ids, _ids(ids, len(extra))]), self.cylinder_ids,
                          self.plane_colors, np.vstack([self.sphere_colors, _colors(None, len(extra))]),
                          self.cylinder_colors, self.box_colors, self.cone_colors)

    def with_targets(self, targets: Sequence[TargetTruth]) -> "Primitives":
        """Plus the standing targets, hit id k for targets[k-1]: balloons are spheres, intruder
        drones flat upright cylinders of their radius, DRONE_BODY_HEIGHT thick, centred on them."""
        spheres, sphere_ids, sphere_colors, cylinders, cylinder_ids, cylinder_colors = [], [], [], [], [], []
        for k, t in enumerate(targets, start=1):
            if t.destroyed:
                continue
            x, y, z = t.position
            if t.kind == "drone":
                cylinders.append((x, y, z - DRONE_BODY_HEIGHT / 2, t.radius, DRONE_BODY_HEIGHT))
                cylinder_ids.append(k)
                cylinder_colors.append(t.color)
            else:
                spheres.append((x, y, z, t.radius))
                sphere_ids.append(k)
                sphere_colors.append(t.color)
        extra_cyl = np.asarray(cylinders, dtype=float).reshape(-1, 5)
        return Primitives(
            self.planes, np.vstack([self.spheres, np.asarray(spheres, dtype=float).reshape(-1, 4)]),
            np.vstack([self.cylinders, extra_cyl]), self.boxes, self.cones,
            np.concatenate([self.sphere_ids, _ids(sphere_ids, len(spheres))]),
            np.concatenate([self.cylinder_ids, _ids(cylinder_ids, len(extra_cyl))]),
            self.plane_colors, np.vstack([self.sphere_colors, _colors(sphere_colors, len(spheres))]),
            np.vstack([self.cylinder_colors, _colors(cylinder_colors, len(extra_cyl))]), self.box_colors,
            self.cone_colors)


def _colors(colors, count: int) -> np.ndarray:
    if colors is None:
        return np.tile(np.asarray(DEFAULT_COLOR, dtype=np.uint8), (count, 1))
    # clipped: a colour outside 0-255 (a bad message) must not stop the LiDAR, which never uses it
    colors = np.clip(np.asarray(colors, dtype=np.float64).reshape(-1, 3), 0, 255).astype(np.uint8)
    if len(colors) != count:
        raise ValueError(f"{len(colors)} colours for {count} primitives")
    return colors


def _ids(ids, count: int) -> np.ndarray:
    if ids is None:
        return np.zeros(count, dtype=np.int32)
    ids = np.asarray(ids, dtype=np.int32).reshape(-1)
    if len(ids) != count:
        raise ValueError(f"{len(ids)} hit ids for {count} primitives")
    return ids


def primitives_from_obstacles(obstacles: Iterable[Obstacle]) -> Primitives:
    """The static world; an obstacle without a colour is DEFAULT_COLOR."""
    rows: dict[str, list] = {kind: [] for kind in ("plane", "sphere", "cylinder", "box", "cone")}
    colors: dict[str, list] = {kind: [] for kind in rows}
    for o in obstacles:
        cx, cy, cz = o.center
        if o.kind == "plane":
            rows["plane"].append(cz)
        elif o.kind == "sphere":
            rows["sphere"].append((cx, cy, cz, o.radius))
        elif o.kind in ("cylinder", "cone"):
            rows[o.kind].append((cx, cy, cz, o.radius, o.height))
        elif o.kind == "box":
            half = np.asarray(o.size, dtype=float) / 2
            rows["box"].append((cx - half[0], cy - half[1], cz - half[2], cx + half[0], cy + half[1], cz + half[2]))
        else:
            continue
        colors[o.kind].append(o.color if o.color is not None else DEFAULT_COLOR)
    return Primitives(rows["plane"], rows["sphere"], rows["cylinder"], rows["box"], rows["cone"],
                      plane_colors=colors["plane"], sphere_colors=colors["sphere"],
                      cylinder_colors=colors["cylinder"], box_colors=colors["box"], cone_colors=colors["cone"])


def target_spheres(targets: Iterable[TargetTruth]) -> np.ndarray:
    """(S, 4) spheres of the targets still standing, every kind as a sphere of its radius."""
    rows = [(*t.position, t.radius) for t in targets if not t.destroyed]
    return np.asarray(rows, dtype=float).reshape(-1, 4)


def pack(p: Primitives) -> Packed:
    """The flat table the compiled caster reads (raycast.py), in the reference's order."""
    rows: list[tuple[int, tuple, tuple, int, float]] = []
    for z in p.planes:
        rows.append((PLANE, (z,), (0.0, 0.0, 0.0, 0.0), 0, REFLECTIVITY["ground"]))
    kinds = ((SPHERE, p.spheres, p.sphere_ids, numpy_caster.sphere_bounds),
             (CYLINDER, p.cylinders, p.cylinder_ids, numpy_caster.upright_bounds),
             (BOX, p.boxes, np.zeros(len(p.boxes), np.int32), numpy_caster.box_bounds),
             (CONE, p.cones, np.zeros(len(p.cones), np.int32), numpy_caster.upright_bounds))
    colors = np.vstack([p.plane_colors, p.sphere_colors, p.cylinder_colors, p.box_colors, p.cone_colors])
    for kind, table, ids, bounds in kinds:
        for row, ident in zip(table, ids):
            centre, radius = bounds(row)
            values = tuple(row) + (((row[3] / row[4]) * (row[3] / row[4]),) if kind == CONE else ())
            rows.append((kind, values, (*centre, radius), int(ident),
                         REFLECTIVITY["target" if ident > 0 else "static"]))
    params = np.zeros((len(rows), 6))
    for i, (_, values, _, _, _) in enumerate(rows):
        params[i, :len(values)] = values
    return Packed(
        kinds=np.array([r[0] for r in rows], dtype=np.int64),
        params=params,
        bounds=np.array([r[2] for r in rows], dtype=float).reshape(-1, 4),
        ids=np.array([r[3] for r in rows], dtype=np.int32),
        reflectivity=np.array([r[4] for r in rows], dtype=float),
        colors=np.ascontiguousarray(colors.reshape(-1, 3), dtype=np.uint8),
    )


def carrier(truth: GroundTruth, uav: str) -> VehicleTruth | None:
    """The vehicle a simulated sensor of `uav` rides on, in this ground truth; None when it is not
    there or no longer alive (a killed UAV's sensors see nothing)."""
    me = next((v for v in truth.uavs if v.name == uav), None)
    return me if me is not None and me.alive else None


def finite_pose(vehicle: VehicleTruth) -> bool:
    """Whether a vehicle's position and heading can place a sensor (a bad message may say NaN)."""
    return all(math.isfinite(v) for v in (*vehicle.position, vehicle.heading))


def noise_stream_key(world: WorldModel, uav: str) -> tuple[int, int]:
    """(run seed, UAV index) of a simulated sensor's noise stream: it starts over only when this
    changes (the world model repeats every second; the stream must go on)."""
    return world.seed, world.uavs.index(uav) if uav in world.uavs else len(world.uavs)


def read_only(array: np.ndarray) -> np.ndarray:
    """A C-contiguous read-only view (a copy only when not contiguous). numba compiles a kernel
    once per argument type and read-only is part of the type: the LiDAR models hand out cached
    read-only beams for a spinning pattern and fresh ones for the Mid-360's, and the first scan of
    the other kind compiled the scan kernel again (3 s on this machine, a stalled lockstep tick)."""
    view = np.ascontiguousarray(array).view()
    view.flags.writeable = False
    return view


def cast_with_ids(origin: np.ndarray, directions: np.ndarray, world: Primitives | Packed
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(range, hit id) along each unit direction (N, 3) from `origin`: inf and -1 if none."""
    packed = world if isinstance(world, Packed) else pack(world)
    d = read_only(np.asarray(directions, dtype=float).reshape(-1, 3))
    ranges = np.empty(len(d))
    index = np.empty(len(d), dtype=np.int64)
    cast_kernel(np.asarray(origin, dtype=float), d, packed.kinds, packed.params, packed.bounds, ranges, index)
    ids = np.where(index >= 0, packed.ids[np.maximum(index, 0)] if len(packed) else -1, -1).astype(np.int32)
    return ranges, ids


def cast(origin: np.ndarray, directions: np.ndarray, world: Primitives | Packed) -> np.ndarray:
    """Distance along each unit direction (N, 3) from `origin` to the nearest surface; inf if none."""
    return cast_with_ids(origin, directions, world)[0]
