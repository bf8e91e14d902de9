"""Tracker core (first version): CA Kalman filter per track, gating, confirmation, dropping."""
from __future__ import annotations

import numpy as np

from services.tracker.core import (
    TrackerCore, TrackerParams, measurement_noise, transition, uncertainty_radius,
)

NS = 1_000_000_000
PERIOD = NS // 10  # 10 Hz detections


def stamp(k: int) -> int:
    return k * PERIOD


def test_constant_velocity_target_gives_one_confirmed_track_with_its_velocity():
    rng = np.random.default_rng(7)
    tracker = TrackerCore()
    velocity = np.array([4.0, 0.0, 0.0])
    start = np.array([0.0, 10.0, 6.0])
    for k in range(21):  # 0 .. 2 s
        seen = start + velocity * k / 10 + rng.normal(0.0, 0.1, 3)
        tracker.update(stamp(k), seen[None], np.eye(3)[None] * 0.02)
    [estimate] = tracker.estimates(stamp(20))
    assert estimate.confirmed and estimate.detections == 21 and estimate.id == 1
    assert np.linalg.norm(estimate.state[3:6] - velocity) < 0.5
    assert np.linalg.norm(estimate.state[:3] - (start + velocity * 2.0)) < 0.3
    assert estimate.uncertainty_radius == 2.5
    assert estimate.last_detection == stamp(20)


def test_a_track_is_confirmed_after_two_detections():
    tracker = TrackerCore()
    tracker.update(stamp(0), np.array([[1.0, 2.0, 5.0]]))
    assert not tracker.estimates(stamp(0))[0].confirmed
    tracker.update(stamp(1), np.array([[1.1, 2.0, 5.0]]))
    assert tracker.estimates(stamp(1))[0].confirmed


def test_two_separated_targets_keep_their_ids():
    rng = np.random.default_rng(1)
    tracker = TrackerCore()
    for k in range(30):
        t = k / 10
        a = np.array([2.0 * t, 0.0, 5.0])
        b = np.array([20.0, 10.0 - 3.0 * t, 7.0])
        order = [a, b] if k % 2 == 0 else [b, a]  # detection order must not matter
        ids = tracker.update(stamp(k), np.array(order) + rng.normal(0, 0.05, (2, 3)))
        assert ids == ([1, 2] if k % 2 == 0 else [2, 1])
    estimates = tracker.estimates(stamp(29))
    assert [e.id for e in estimates] == [1, 2] and all(e.confirmed for e in estimates)
    assert np.linalg.norm(estimates[0].state[3:6] - [2.0, 0.0, 0.0]) < 0.5
    assert np.linalg.norm(estimates[1].state[3:6] - [0.0, -3.0, 0.0]) < 0.5


def test_track_without_detections_is_dropped_once_radius_exceeds_5_m():
    params = TrackerParams()
    tracker = TrackerCore(params)
    for k in range(10):
        tracker.update(stamp(k), np.array([[float(k) * 0.3, 0.0, 5.0]]))
    last = stamp(9)
    dropped_at = None
    for k in range(1, 200):  # 20 Hz ticks
        now = last + k * NS // 20
        radius = tracker.estimates(now)[0].uncertainty_radius if len(tracker) else None
        dropped = tracker.prune(now)
        if dropped:
            dropped_at = now
            assert dropped == [1] and radius > 5.0
            break
        assert radius <= 5.0
    assert dropped_at is not None and len(tracker) == 0
    assert 1.0 < (dropped_at - last) / NS < 6.0


def test_far_detection_starts_a_new_tentative_track():
    tracker = TrackerCore()
    for k in range(5):
        tracker.update(stamp(k), np.array([[0.0, 0.0, 5.0]]))
    ids = tracker.update(stamp(5), np.array([[0.1, 0.0, 5.0], [10.0, 0.0, 5.0]]))
    assert ids == [1, 2]
    new = {e.id: e for e in tracker.estimates(stamp(5))}[2]
    assert not new.confirmed and new.detections == 1
    assert np.allclose(new.state[:3], [10.0, 0.0, 5.0]) and np.allclose(new.state[3:], 0.0)
    # Just outside the 2.5 m gate of track 1 is also a new track.
    assert tracker.update(stamp(6), np.array([[0.0, 2.7, 5.0]])) == [3]


def test_estimates_do_not_change_the_filters():
    tracker = TrackerCore()
    tracker.update(stamp(0), np.array([[0.0, 0.0, 5.0]]))
    tracker.update(stamp(1), np.array([[0.4, 0.0, 5.0]]))
    first = tracker.estimates(stamp(30))[0]
    second = tracker.estimates(stamp(30))[0]
    assert np.array_equal(first.state, second.state) and np.array_equal(first.covariance, second.covariance)
    assert tracker.estimates(stamp(1))[0].covariance[0, 0] < first.covariance[0, 0]


def test_model_pieces():
    f = transition(0.5)
    x = np.array([0, 0, 0, 1, 2, 3, 2, 0, 0], dtype=float)
    assert np.allclose((f @ x)[:3], [0.5 + 0.25, 1.0, 1.5])
    params = TrackerParams()
    assert uncertainty_radius(params, np.eye(9) * 0.3) == 2.5
    assert np.isclose(uncertainty_radius(params, np.eye(9) * 8.0), 1.5 * 8.0)
    assert type(uncertainty_radius(params, np.eye(9) * 8.0)) is float  # goes into a Track message
    r = measurement_noise(params, np.diag([0.02, 0.5, 0.05]))
    assert np.allclose(np.diag(r), [0.1, 0.5, 0.1])
    assert np.allclose(measurement_noise(params, None), 0.1 * np.eye(3))


def test_the_number_of_tracks_is_bounded_whatever_the_detections():
    import numpy as np
    from services.tracker.core import TrackerCore, TrackerParams

    core = TrackerCore(TrackerParams(max_tracks=10))
    rng = np.random.default_rng(3)
    for k in range(5):
        ids = core.update(k * 100_000_000, rng.uniform(-50, 50, size=(300, 3)), None)
        assert len(set(i for i in ids if i >= 0)) <= 10
    assert len(core.estimates(500_000_000)) <= 10


def test_detections_that_would_poison_the_filters_are_dropped_and_counted():
    """Found by tests/test_fuzz_messages.py: one NaN detection made a NaN track, after which every
    association raised; an indefinite covariance made the filter's innovation singular."""
    tracker = TrackerCore()
    tracker.update(stamp(0), np.array([[1.0, 2.0, 5.0]]))
    not_a_covariance = np.array([[[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]])
    assert tracker.update(stamp(1), np.array([[np.nan, 2.0, 5.0]])) == [-1]
    assert tracker.update(stamp(2), np.array([[1.0, 2.0, 5.0]]), not_a_covariance) == [-1]
    assert tracker.update(stamp(3), np.array([[1.0, 2.0, 5.0]]), np.eye(3)[None] * 0.02) == [1]
    assert tracker.rejected_detections == 2 and tracker.diverged_tracks == 0
    tracker._tracks[0].kf.x[0] = np.inf  # what extreme (finite) detections can drive a filter to
    assert tracker.prune(stamp(4)) == [] and tracker.ids == [] and tracker.diverged_tracks == 1
