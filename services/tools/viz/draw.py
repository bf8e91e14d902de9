"""What the viewer draws, as plain records: one `Log` per entity and moment.

The scene builder (scene.py) decides what to draw from the fleet's messages; the rerun output
(output.py) turns each record into the matching rerun archetype. Keeping the records apart from
rerun makes the builder testable without a viewer and keeps rerun's API churn in one file.
Positions are metres in the world frame (ENU, z up); colours RGBA 0-255; quaternions x-y-z-w.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.tools.viz.geometry import Color


@dataclass(frozen=True)
class Points:
    positions: np.ndarray  # (N, 3)
    colors: np.ndarray | Color  # (N, 4) uint8, or one colour for all
    radius: float
    labels: list[str] | None = None
    show_labels: bool = True  # False: the labels show on hover only


@dataclass(frozen=True)
class Lines:
    strips: list[np.ndarray]  # each (K, 3)
    color: Color
    radius: float
    labels: list[str] | None = None
    show_labels: bool = True  # False: the labels show on hover only


@dataclass(frozen=True)
class Ellipsoids:
    centers: np.ndarray  # (N, 3)
    half_sizes: np.ndarray  # (N, 3)
    quaternions: np.ndarray | None  # (N, 4), None: axis-aligned
    colors: np.ndarray | Color  # (N, 4) or one for all
    labels: list[str] | None = None
    show_labels: bool = True  # False: the labels show on hover only
    solid: bool = False


@dataclass(frozen=True)
class Boxes:
    centers: np.ndarray  # (N, 3)
    half_sizes: np.ndarray  # (N, 3), or (3,): one size for every box
    colors: np.ndarray | Color
    labels: list[str] | None = None
    show_labels: bool = True  # False: the labels show on hover only
    solid: bool = True


@dataclass(frozen=True)
class Cylinders:
    centers: np.ndarray  # (N, 3) middle of each vertical cylinder
    lengths: np.ndarray  # (N,)
    radii: np.ndarray  # (N,)
    color: Color
    labels: list[str] | None = None
    show_labels: bool = True  # False: the labels show on hover only


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3) uint32
    color: Color


@dataclass(frozen=True)
class Pose:
    translation: np.ndarray  # (3,)
    quaternion: np.ndarray  # (4,) x-y-z-w


@dataclass(frozen=True)
class Axes:
    length: float


@dataclass(frozen=True)
class Text:
    text: str
    level: str = "INFO"  # DEBUG, INFO, WARN, ERROR


@dataclass(frozen=True)
class Document:
    markdown: str


@dataclass(frozen=True)
class Image:
    encoded: bytes  # a compressed image as sent (JPEG, PNG)
    media_type: str = "image/jpeg"


@dataclass(frozen=True)
class State:
    value: str


@dataclass(frozen=True)
class StateStyle:
    values: list[str]
    colors: list[Color]


@dataclass(frozen=True)
class Scalar:
    value: float


@dataclass(frozen=True)
class SeriesStyle:
    name: str
    color: Color


@dataclass(frozen=True)
class ZUp:
    """The world frame's axes: right-handed, z up."""


Drawable = (Points | Lines | Ellipsoids | Boxes | Cylinders | Mesh | Pose | Axes | Text | Document | State
            | StateStyle | Scalar | SeriesStyle | ZUp)


def count(item: Drawable) -> int:
    """How many things a record draws (1 for records that are not batches)."""
    match item:
        case Points():
            return len(item.positions)
        case Lines():
            return len(item.strips)
        case Ellipsoids() | Boxes() | Cylinders():
            return len(item.centers)
    return 1


@dataclass(frozen=True)
class Log:
    entity: str  # e.g. "uav1/detections"
    item: Drawable
    stamp: int | None  # mission time, ns; None: static (holds at every time)
    tick: int | None = None  # the mission clock's step at `stamp` (None: no mission clock, e.g. a flight)
    received: int = 0  # wall-clock ns when the message arrived (0: unknown)
