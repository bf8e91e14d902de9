"""The run summary's perception score (services/tools/evaluation/__init__.py): detections and confirmed tracks
against the targets standing at their stamps."""
from __future__ import annotations

import numpy as np

from services.tools.evaluation import PerceptionScore

TARGETS = np.array([[0.0, 0.0, 5.0], [20.0, 0.0, 5.0]])


def test_a_confirmed_track_is_false_only_when_it_never_came_within_a_metre_of_a_target_and_is_listed():
    score = PerceptionScore()
    score.add_tracks(1.0, [1, 2], np.array([[0.5, 0.0, 5.0], [9.0, 0.0, 5.0]]), TARGETS)
    score.add_tracks(1.5, [1, 2, 3], np.array([[3.0, 0.0, 5.0], [12.0, 0.0, 5.0], [20.0, 1.5, 5.0]]), TARGETS)
    score.add_tracks(2.0, [3], np.array([[20.0, 0.9, 5.0]]), TARGETS)  # 3 comes within a metre
    score.add_tracks(2.5, [2], np.array([[5.0, 0.0, 5.0]]), TARGETS[1:])  # the first target went down
    summary = score.summary()
    assert (summary["confirmed_tracks"], summary["false_tracks"]) == (3, 1)
    assert summary["false_track_list"] == [{"id": 2, "t": 1.0, "at": [9.0, 0.0, 5.0], "until": 2.5,
                                            "nearest_m": 8.0}]
    assert score.false_tracks(after=1.2) == 0  # track 2 was confirmed at 1.0 s


def test_a_track_confirmed_when_no_target_stands_is_false_and_has_no_nearest_distance():
    score = PerceptionScore()
    score.add_tracks(3.0, [7], np.array([[1.0, 2.0, 3.0]]), np.zeros((0, 3)))
    assert score.summary()["false_track_list"] == [{"id": 7, "t": 3.0, "at": [1.0, 2.0, 3.0], "until": 3.0,
                                                    "nearest_m": None}]


def test_a_partners_track_shown_after_its_target_went_down_is_the_partners_and_not_false():
    """agile, 2 UAVs, seed 1852: uav1 captured the eight; its own track ended, and uav2's track of the
    eight, coasting on, showed in uav1's fleet picture (fleet id 2000003) 1.8 s later, 29 m from the
    standing drone. It followed a real target in uav2's picture: one track, not a false one."""
    eight, dodger = np.array([30.0, 55.0, 6.0]), np.array([62.0, 44.0, 4.5])
    uav1, uav2 = PerceptionScore(), PerceptionScore()
    uav2.add_tracks(24.0, [3], eight[None], np.array([eight, dodger]), [("uav2", 3)])
    uav2.add_tracks(26.3, [3], (eight + [7.0, 3.0, 0.0])[None], dodger[None], [("uav2", 3)])
    uav1.add_tracks(26.35, [2000003], (eight + [7.0, 3.0, 0.0])[None], dodger[None], [("uav2", 3)])
    uav1.add_tracks(26.35, [2000004], np.array([[10.0, 10.0, 5.0]]), dodger[None], [("uav2", 4)])  # a phantom
    anywhere = uav1.matched_origins() | uav2.matched_origins()
    assert [t["id"] for t in uav1.summary(anywhere)["false_track_list"]] == [2000004]
    assert uav1.summary(anywhere)["false_tracks"] == 1 and uav2.summary(anywhere)["false_tracks"] == 0
    assert uav1.summary()["false_tracks"] == 2  # scored alone, the copy never came near a standing target
