"""camera node: the simulated RGB-D camera of its UAV (core.py) on falconry/<uav>/camera, and a
compressed frame for the ground (recordings, `falconry snapshot`) on falconry/<uav>/camera_jpeg.

Renders the simulator's world (static obstacles and appearance from falconry/sim/world, the
obstacles the mission's survey lacks, standing targets and the own pose from falconry/sim/truth,
as the simulated LiDAR does) at `rate_hz` of
mission time, `phase` of a period after the LiDAR's scans. Only this service, the sensor driver
and the simulator may read ground truth; the frames carry none of it. Onboard, a RealSense
driver publishes the same messages. Camera faults scheduled on falconry/sim/faults for this UAV
are acted on here: `camera_frozen` repeats the last frame, `camera_saturated` sends white ones.
"""
from __future__ import annotations

import zlib

import cv2
import numpy as np

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import (
    Appearance,
    CameraFrame,
    CompressedFrame,
    FaultCommand,
    GroundTruth,
    Header,
    Pose,
    WorldModel,
)
from services.camera.core import CAMERA_FAULTS, Camera, CameraParams, Gains, frozen_or_saturated
from services.lib.geometry import quaternion
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.node import Node
from services.lib.runtime.sensor_faults import SensorFaults
from services.lib.world.primitives import (
    Primitives,
    carrier,
    finite_pose,
    noise_stream_key,
    pack,
    primitives_from_obstacles,
)

RNG_SALT = zlib.crc32(b"camera")  # a fixed number, so the stream differs from other services'


class CameraNode(Node):
    service = "camera"
    upstream = ()
    params_type = CameraParams

    @classmethod
    def preload(cls) -> None:
        warm = Camera(CameraParams(width=16, height=16), np.random.default_rng(0))  # the kernels' types are any size's
        warm.render(pack(Primitives(planes=[-1.0])), Appearance(), np.zeros(3), np.eye(3), np.ones(3),
                    np.random.default_rng(0))

    def setup(self) -> None:
        p: CameraParams = self.params
        self.period_ns = max(1, int(round(1e9 / p.rate_hz)))
        self.phase_ns = int(p.phase * self.period_ns)
        self.preview_ns = int(round(1e9 / p.preview_hz)) if p.preview_hz > 0 else 0
        self.camera: Camera | None = None
        self.rng: np.random.Generator | None = None
        self.rng_key: tuple[int, int] | None = None
        self.gains = Gains()
        self.static: Primitives | None = None  # the world model's obstacles and the truth's, built when either changes
        self.obstacles = None  # the world model's
        self.unsurveyed: list = []  # the truth's
        self.appearance = Appearance()
        self.truth: GroundTruth | None = None
        self.last_slot = -1
        self.last_preview_ns: int | None = None
        self._unposed = 0
        self._bad_input = CountedWarnings(self.log)
        self.preload()  # compiled now, before the token: the first frame must not stall a lockstep tick
        self.frame_pub = self.publisher(self.topic("camera"), CameraFrame)
        self.preview_pub = self.publisher(self.topic("camera_jpeg"), CompressedFrame)
        self.subscribe(keys.WORLD, WorldModel, self.on_world)
        self.subscribe(keys.TRUTH, GroundTruth, self.on_truth)
        self.faults = SensorFaults(CAMERA_FAULTS)
        self.last_frame = None
        self.subscribe(keys.FAULTS, FaultCommand, self.on_fault, keep=None)  # events: each one counts

    def on_fault(self, fault: FaultCommand, key: str) -> None:
        if (said := self.faults.take(self.uav, fault)) is not None:
            self.log.warning("camera fault %s", said)

    def on_world(self, world: WorldModel, key: str) -> None:
        if world.obstacles != self.obstacles:
            self.obstacles = world.obstacles
            self.static = primitives_from_obstacles([*self.obstacles, *self.unsurveyed])
        self.appearance = world.appearance
        if (key := noise_stream_key(world, self.uav)) != self.rng_key:
            self.rng_key = key
            self.rng = np.random.default_rng([*key, RNG_SALT])
            self.camera = Camera(self.params, self.rng)
            self.gains = Gains()

    def on_truth(self, truth: GroundTruth, key: str) -> None:
        self.truth = truth
        if truth.obstacles != self.unsurveyed:  # the same every tick of a run: compared, not rebuilt
            self.unsurveyed = truth.obstacles
            if self.obstacles is not None:
                self.static = primitives_from_obstacles([*self.obstacles, *self.unsurveyed])

    def on_tick(self, now_ns: int) -> None:
        if now_ns < self.phase_ns:
            return
        slot = (now_ns - self.phase_ns) // self.period_ns
        if slot <= self.last_slot or self.static is None or self.truth is None or self.camera is None:
            return
        me = carrier(self.truth, self.uav)
        if me is None:
            return
        self.last_slot = slot
        if not finite_pose(me):
            self._unposed += 1
            self._bad_input.update({"frames skipped: our pose in the ground truth is not finite": self._unposed})
            return
        position, rotation = self.camera.pose(me.position, me.heading)
        self.gains.step(self.rng, self.params)
        world = pack(self.static.with_targets(self.truth.targets))
        frame = self.camera.render(world, self.appearance, position, rotation, self.gains.factors(), self.rng)
        fault = self.faults.active(now_ns)
        if fault is not None:
            frame = frozen_or_saturated(frame, fault, self.last_frame)
        self.last_frame = frame
        k = self.camera.intrinsics
        pose = Pose(position=tuple(float(v) for v in position), orientation=quaternion(rotation))
        self.frame_pub.put(CameraFrame(
            header=Header(stamp=now_ns), width=k.width, height=k.height, camera_pose=pose,
            fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, color=from_numpy(frame.rgb),
            depth=from_numpy(frame.depth_mm) if self.params.depth else None, camera_model="d435"))
        if self.preview_ns and (self.last_preview_ns is None or now_ns - self.last_preview_ns >= self.preview_ns):
            self.last_preview_ns = now_ns
            self.preview_pub.put(compress(now_ns, frame.rgb, frame.depth_mm if self.params.depth else None, pose, k,
                                          self.params.jpeg_quality))


def compress(stamp: int, rgb: np.ndarray, depth_mm: np.ndarray | None, pose: Pose, k, quality: int) -> CompressedFrame:
    """JPEG colour and PNG depth of one frame (OpenCV)."""
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    png = b""
    if depth_mm is not None:
        ok_depth, encoded = cv2.imencode(".png", depth_mm)
        png = encoded.tobytes() if ok_depth else b""
    return CompressedFrame(header=Header(stamp=stamp), width=rgb.shape[1], height=rgb.shape[0], camera_pose=pose,
                           fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, jpeg=jpeg.tobytes() if ok else b"", depth_png=png,
                           camera_model="d435")


NODE = CameraNode
