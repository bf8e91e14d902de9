"""object_detect node: balloons by colour in the camera's frames (seed 004 §4.1; see core.py).

Subscribes falconry/<uav>/camera (CameraFrame) and falconry/<uav>/colors (ColorUpdate: a colour
file sent live, e.g. by `falconry colors pick --send`); publishes for every frame, empty ones
included, falconry/<uav>/camera_detections (Detections, detector "camera"), stamped with the
frame's stamp. The colour file at start is the `colors` parameter: a path, or a built-in name
(services/object_detect/colors/<name>.toml); a file that cannot be read stops the service at
start with one line (exit 2), a bad live update is refused with a counted warning and the
current colours stay.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import CameraFrame, ColorUpdate, Detections, Header
from services.lib.pinhole import Intrinsics
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.errors import UsageError
from services.lib.runtime.node import Node
from services.object_detect.colors import ColorFile, ColorFileError, load_color_file, parse_color_file
from services.object_detect.core import CameraView, ObjectDetectParams, detect
from services.object_detect.sanity import FrameSanity

BUILT_IN = Path(__file__).resolve().parent / "colors"


def color_file_path(name_or_path: str) -> Path:
    """A built-in colour file by name, or the given path."""
    path = Path(name_or_path)
    if path.suffix != ".toml" and "/" not in name_or_path:
        return BUILT_IN / f"{name_or_path}.toml"
    return path


class ObjectDetectNode(Node):
    service = "object_detect"
    upstream = ("camera",)
    params_type = ObjectDetectParams

    def setup(self) -> None:
        try:
            self.colors: ColorFile = load_color_file(color_file_path(self.params.colors))
        except ColorFileError as exc:
            raise UsageError(str(exc)) from None
        self.log.info("colours %r (%s, %s, diameter %g m)", self.colors.name, self.colors.method,
                      self.colors.thresholds.space, self.colors.diameter)
        self.detections_pub = self.publisher(self.topic("camera_detections"), Detections)
        self.sanity = FrameSanity()
        self.subscribe(self.topic(keys.COLORS), ColorUpdate, self.on_colors, keep=None)  # first: before a frame
        self.subscribe(self.topic("camera"), CameraFrame, self.on_frame)
        self._refused_colors = 0
        self._bad_frames = 0
        self._bad_input = CountedWarnings(self.log)

    def on_colors(self, msg: ColorUpdate, key: str) -> None:
        import tomllib

        try:
            self.colors = parse_color_file(tomllib.loads(msg.toml), f"live colour update {msg.name!r}")
        except (tomllib.TOMLDecodeError, ColorFileError) as exc:
            self._refused_colors += 1
            self._bad_input.update({"colour updates refused": self._refused_colors})
            self.log.warning("%s", " ".join(str(exc).split()))
            return
        self.log.info("colours now %r (%s, %s, diameter %g m)", self.colors.name, self.colors.method,
                      self.colors.thresholds.space, self.colors.diameter)

    def on_frame(self, msg: CameraFrame, key: str) -> None:
        view = CameraView(Intrinsics(msg.width, msg.height, msg.fx, msg.fy, msg.cx, msg.cy),
                          np.asarray(msg.camera_pose.position, dtype=np.float64), msg.camera_pose.orientation)
        try:
            rgb = to_numpy(msg.color)
            depth = None if msg.depth is None else to_numpy(msg.depth)
            if rgb.shape != (msg.height, msg.width, 3):
                raise ValueError(f"colour image {rgb.shape}, header says {msg.height} × {msg.width}")
            if rgb.dtype != np.uint8:
                raise ValueError(f"colour image of {rgb.dtype}, not uint8")
            if not (np.all(np.isfinite(view.position)) and np.all(np.isfinite(view.orientation))
                    and min(msg.fx, msg.fy) > 0):
                raise ValueError("camera pose or focal length not usable")
            health = self.sanity.check(rgb)
            # a frozen or saturated frame: nothing in it is a detection
            found = detect(rgb if not health else rgb[:0], None if health else depth, view, self.colors, self.params)
        except ValueError as exc:
            self._bad_frames += 1
            self._bad_input.update({"frames refused (image shape or type, camera pose or focal length)": self._bad_frames})
            if self._bad_frames == 1:
                self.log.warning("the first refused frame: %s", " ".join(str(exc).split()))
            return
        self.detections_pub.put(Detections(
            header=Header(stamp=msg.header.stamp, source=msg.header.stamp),
            detector="camera",
            positions=from_numpy(found.positions),
            covariances=from_numpy(found.covariances),
            point_counts=from_numpy(found.pixels),
            extents=from_numpy(found.diameters),
            sensor_position=tuple(float(v) for v in view.position),
            sensor_health=health,
        ))
        if health:
            self._bad_input.update({f"frames failing the sanity check ({check})": count
                                    for check, count in self.sanity.failures.items()})


NODE = ObjectDetectNode
