"""sensor_driver node: publishes simulated LiDAR scans of its UAV on falconry/<uav>/points.

First version (walking skeleton): ray-casts the simulator's world (static obstacles from
falconry/sim/world, standing targets and the own pose from falconry/sim/truth) at `rate_hz` of
mission time. Only this service and the simulator may read ground truth. Later issues add the
Ouster/Livox models, a recorded-file source and real hardware behind the same output.
"""
from __future__ import annotations

import math
import zlib

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import GroundTruth, Header, PointCloud, Pose, WorldModel
from services.runtime.node import Node
from services.sensor_driver.core import (
    Primitives,
    beam_directions,
    primitives_from_obstacles,
    scan,
    target_spheres,
)

RNG_SALT = zlib.crc32(b"sensor")  # a fixed number, so the stream differs from other services'


class SensorDriverParams(msgspec.Struct, forbid_unknown_fields=True):
    rows: int = 32
    cols: int = 512
    vfov_deg: float = 90.0
    rate_hz: float = 10.0
    min_range: float = 0.3
    max_range: float = 50.0
    range_noise: float = 0.01  # m, standard deviation


class SensorDriverNode(Node):
    service = "sensor_driver"
    upstream = ()
    params_type = SensorDriverParams

    def setup(self) -> None:
        p: SensorDriverParams = self.params
        self.directions = beam_directions(p.rows, p.cols, p.vfov_deg)
        self.period_ns = max(1, int(round(1e9 / p.rate_hz)))
        self.sensor_model = f"rotating-{p.rows}x{p.cols}"
        self.static: Primitives | None = None
        self.obstacles = None
        self.truth: GroundTruth | None = None
        self.rng: np.random.Generator | None = None
        self.rng_key: tuple[int, int] | None = None
        self.last_slot = -1
        self.points_pub = self.publisher(self.topic("points"), PointCloud)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        self.subscribe(keys.TRUTH, GroundTruth, self.on_truth)

    def on_world(self, world: WorldModel, key: str) -> None:
        if world.obstacles != self.obstacles:
            self.obstacles = world.obstacles
            self.static = primitives_from_obstacles(world.obstacles)
        index = world.uavs.index(self.uav) if self.uav in world.uavs else len(world.uavs)
        if (world.seed, index) != self.rng_key:  # the world repeats every second: keep the stream going
            self.rng_key = (world.seed, index)
            self.rng = np.random.default_rng([world.seed, index, RNG_SALT])

    def on_truth(self, truth: GroundTruth, key: str) -> None:
        self.truth = truth

    def on_tick(self, now_ns: int) -> None:
        slot = now_ns // self.period_ns
        if slot <= self.last_slot or self.static is None or self.truth is None or self.rng is None:
            return
        me = next((v for v in self.truth.uavs if v.name == self.uav), None)
        if me is None or not me.alive:
            return
        self.last_slot = slot
        p: SensorDriverParams = self.params
        origin = np.asarray(me.position, dtype=float)
        world = self.static.with_spheres(target_spheres(self.truth.targets))
        points = scan(origin, me.heading, self.directions, world, self.rng,
                      min_range=p.min_range, max_range=p.max_range, range_noise=p.range_noise)
        half = me.heading / 2.0
        self.points_pub.put(PointCloud(
            header=Header(stamp=now_ns),
            width=p.cols,
            height=p.rows,
            sensor_pose=Pose(position=me.position, orientation=(math.cos(half), 0.0, 0.0, math.sin(half))),
            points=from_numpy(points),
            sensor_model=self.sensor_model,
            min_range=p.min_range,
            max_range=p.max_range,
        ))


NODE = SensorDriverNode
