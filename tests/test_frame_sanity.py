"""The camera's frame sanity (services/object_detect/sanity.py) on rendered frames, and the camera
faults that make them fail (services/camera/core.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.camera.core import frozen_or_saturated
from services.object_detect.sanity import FrameSanity, clipped_share
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


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(seed=st.integers(0, 2**32 - 1), height=st.integers(0, 40), width=st.integers(0, 40))
def test_the_clipped_share_is_the_plain_numpy_share(seed, height, width):
    rng = np.random.default_rng(seed)
    rgb = rng.choice(np.array([0, 1, 128, 254, 255], dtype=np.uint8), (height, width, 3))
    plain = float(np.mean(np.all(rgb == 255, axis=-1) | np.all(rgb == 0, axis=-1))) if rgb.size else 0.0
    assert clipped_share(rgb) == pytest.approx(plain, abs=1e-12)


def test_a_frame_that_is_not_8_bit_colour_is_refused():
    with pytest.raises(ValueError, match="uint8"):
        clipped_share(np.zeros((4, 4, 3), dtype=np.uint16))
