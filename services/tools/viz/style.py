"""Colours shared by the viewer and the run timeline plot, so a UAV or a state looks the same in both."""
from __future__ import annotations

import numpy as np

from services.tools.viz.geometry import Color

UAV_COLORS: tuple[Color, ...] = ((31, 119, 180, 255), (255, 127, 14, 255), (44, 160, 44, 255),
                                 (148, 103, 189, 255), (140, 86, 75, 255))
TRUTH_COLOR: Color = (255, 0, 255, 110)  # the evaluation layer: never what a UAV believes
DETECTION_COLOR: Color = (230, 25, 25, 255)  # the flying-object label's red
MATCHED_COLOR: Color = (40, 200, 60, 255)  # with truth: a detection within 1 m of a target
FALSE_COLOR: Color = (255, 255, 255, 255)  # ... and one that is not
LABEL_COLORS = np.array([[150, 150, 150, 255], [230, 25, 25, 255], [245, 200, 0, 255]], dtype=np.uint8)  # by code
STATE_COLORS: dict[str, Color] = {
    "PREFLIGHT": (190, 190, 190, 255), "TAKING_OFF": (160, 200, 255, 255), "IDLE": (200, 200, 120, 255),
    "GOING_AROUND": (31, 119, 180, 255), "CHECKING_TARGET": (245, 200, 0, 255),
    "GOING_TO_TARGET": (255, 127, 14, 255), "DESTROYING": (214, 39, 40, 255), "LANDING": (120, 120, 120, 255),
    "LANDED": (70, 70, 70, 255), "EMERGENCY_LANDING": (148, 0, 211, 255),
}
OTHER_STATE: Color = (230, 230, 230, 255)


def uav_color(index: int) -> Color:
    return UAV_COLORS[index % len(UAV_COLORS)]
