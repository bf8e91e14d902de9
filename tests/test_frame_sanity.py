"""The camera's frame sanity (services/object_detect/sanity.py) on rendered frames, and the camera
faults that make them fail (services/camera/core.py)."""
from __future__ import annotations

import numpy as np

from services.camera.core import frozen_or_saturated
from services.object_detect.sanity import FrameSanity
from tests.test_object_detect import render_balloon


def frames(count: int):
    """Rendered frames of one balloon with the camera's noise: no two alike."""
    return [render_balloon(8.0 + 0.1 * k, noise=True)[0] for k in range(count)]


def test_real_frames_pass_and_a_frozen_or_saturated_one_fails_until_the_camera_recovers():
    sanity = FrameSanity()
    shots = frames(4)
    assert [sanity.check(f.rgb) for f in shots[:2]] == ["", ""]
    frozen = frozen_or_saturated(shots[2], "camera_frozen", shots[1])
    assert sanity.check(frozen.rgb).startswith("frozen")
    white = frozen_or_saturated(shots[2], "camera_saturated", shots[1])
    assert sanity.check(white.rgb).startswith("saturated: 100 %")
    assert np.array_equal(white.depth_mm, shots[2].depth_mm)  # the depth stream goes on
    assert sanity.check(shots[3].rgb) == ""
    assert sanity.failures == {"frozen": 1, "saturated": 1}


def test_a_black_frame_is_saturated_and_a_dark_scene_is_not():
    sanity = FrameSanity()
    assert sanity.check(np.zeros((36, 64, 3), dtype=np.uint8)).startswith("saturated")
    dusk = np.random.default_rng(0).integers(1, 40, (36, 64, 3)).astype(np.uint8)
    assert sanity.check(dusk) == ""
