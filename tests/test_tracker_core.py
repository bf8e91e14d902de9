"""Tracker core: seed 000's buffered point-cloud multi-target tracker (Alg. 2)."""
from __future__ import annotations

import msgspec
import numpy as np
import pytest

from schemas.voxels import STATE_OCCUPIED
from services.lib.lidar.surface import half_width_across, surface_offset
from services.lib.runtime.clock import NS
from services.tracker import kernels as tracker_kernels
from services.tracker.core import OccupiedVoxels, TrackEstimate, TrackerCore, TrackerParams, warm_up
from services.tracker.filters.models import manoeuvre_path, manoeuvre_state, turning_path
from services.tracker.kernels import points_near
from services.lib.voxels import kernels as voxel_kernels
from tests.tools.compiled import in_fresh_interpreter, newly_compiled

PERIOD = NS // 10  # 10 Hz scans


def stamp(k: int) -> int:
    return k * PERIOD


def blob(centre, rng: np.random.Generator, count: int = 12, spread: float = 0.15) -> np.ndarray:
    """The returns of a small flying object: a tight cluster around its centre."""
    return np.asarray(centre, dtype=np.float32) + rng.normal(0.0, spread, (count, 3)).astype(np.float32)


def cloud(*parts: np.ndarray) -> np.ndarray:
    """An organised-looking scan: the objects' returns among rows of no return (NaN) and ground."""
    ground = np.stack(np.meshgrid(np.arange(-20, 20, 1.0), np.arange(-20, 20, 1.0), [0.0]), -1).reshape(-1, 3)
    missing = np.full((50, 3), np.nan)
    return np.concatenate([ground, missing, *parts]).astype(np.float32)


def moving(k: int) -> np.ndarray:
    return np.array([2.0 + 3.0 * k / 10, 5.0, 6.0])  # 3 m/s along x


def detections_only(k: int, rng) -> np.ndarray:
    return moving(k)[None] + rng.normal(0.0, 0.1, (1, 3))


def test_points_near_selects_each_balls_points_in_order():
    points = np.array([[0, 0, 0], [1, 0, 0], [5, 0, 0], [np.nan, 0, 0], [0.5, 0, 0]], dtype=np.float32)
    indices, starts = points_near(points, np.array([[0.0, 0, 0], [5.0, 0, 0]]), np.array([1.0, 0.1]))
    assert list(indices[starts[0]:starts[1]]) == [0, 1, 4]
    assert list(indices[starts[1]:starts[2]]) == [2]


def test_a_target_seen_only_by_detections_gives_one_confirmed_track_with_its_velocity():
    rng = np.random.default_rng(7)
    tracker = TrackerCore()
    for k in range(21):
        tracker.new_detections(stamp(k), detections_only(k, rng), np.eye(3)[None] * 0.02)
    [estimate] = tracker.estimates(stamp(20))
    assert estimate.confirmed and estimate.detections == 21 and estimate.id == 1 and estimate.primary
    assert np.linalg.norm(estimate.velocity - [3.0, 0.0, 0.0]) < 0.5
    assert np.linalg.norm(estimate.position - moving(20)) < 0.3
    assert estimate.trajectory.shape == (8, 3)
    assert np.linalg.norm(estimate.trajectory[-1] - moving(40)) < 1.5  # 2 s ahead


def test_clouds_correct_a_track_between_detections():
    """One detection starts the track; the scans alone then carry it along (Alg. 2 line 14)."""
    rng = np.random.default_rng(1)
    tracker = TrackerCore()
    tracker.new_point_cloud(stamp(0), cloud(blob(moving(0), rng)))
    tracker.new_detections(stamp(0), moving(0)[None])
    for k in range(1, 30):
        tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
    [estimate] = tracker.estimates(stamp(29))
    assert estimate.detections == 1 and not estimate.confirmed  # clouds correct, only detections count
    assert estimate.updates == 29
    assert np.linalg.norm(estimate.position - moving(29)) < 0.25
    assert np.linalg.norm(estimate.velocity - [3.0, 0.0, 0.0]) < 0.6
    assert estimate.uncertainty_radius == TrackerParams().radius_min


def test_a_cloud_correction_moves_the_returns_centroid_to_the_targets_centre():
    """A LiDAR sees a drone's near side only: the returns' centroid lies short of its centre along
    the line of sight; with the sensor known the track is corrected to the centre, as detections are."""
    rng = np.random.default_rng(8)
    centre, sensor = np.array([20.0, 0.0, 6.0]), np.array([0.0, 0.0, 6.0])
    normals = rng.normal(0.0, 1.0, (400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    near_side = centre + 0.325 * normals[normals[:, 0] < -0.3]  # the hemisphere facing the sensor
    errors = {}
    for known in (True, False):
        tracker = TrackerCore(TrackerParams(cloud_noise=1e-4))
        tracker.new_detections(stamp(0), centre[None])
        for k in range(1, 10):
            tracker.new_point_cloud(stamp(k), cloud(near_side), sensor if known else None)
        errors[known] = abs(tracker.estimates(stamp(9))[0].position[0] - centre[0])
    assert errors[True] < 0.06 < 0.12 < errors[False]


def front_of_a_sphere(centre: np.ndarray, radius: float, rays: int, rng: np.random.Generator) -> np.ndarray:
    """The returns of `rays` rays spread evenly over a sphere's disc as a sensor far down -x sees
    it: each lands on the near side, sqrt(r² - ρ²) in front of the centre."""
    across = radius * np.sqrt(rng.uniform(0.0, 1.0, rays))
    angle = rng.uniform(0.0, 2 * np.pi, rays)
    depth = np.sqrt(radius ** 2 - across ** 2)
    return (centre + np.stack([-depth, across * np.cos(angle), across * np.sin(angle)], axis=1)).astype(np.float32)


def test_a_track_corrects_sparse_scans_by_the_half_width_it_learnt_from_close_ones():
    """A scan of few returns under-measures the target's width (its rays miss the rim), so the
    classifier's surface offset, from that scan alone, leaves a detection short of the centre; the
    track takes the widest the target's returns ever were and lands on the centre on average."""
    rng = np.random.default_rng(5)
    centre, sensor, radius = np.array([15.0, 0.0, 6.0]), np.array([0.0, 0.0, 6.0]), 0.325
    tracker = TrackerCore(TrackerParams(cloud_noise=1e-3))
    tracker.new_detections(stamp(0), centre[None])
    for k in range(1, 4):  # close: hundreds of returns
        tracker.new_point_cloud(stamp(k), cloud(front_of_a_sphere(centre, radius, 300, rng)), sensor)
    scan_short, track_short = [], []
    for k in range(4, 64):  # far: four returns a scan
        returns = front_of_a_sphere(centre, radius, 4, rng)
        tracker.new_point_cloud(stamp(k), cloud(returns), sensor)
        centroid = returns.mean(axis=0).astype(np.float64)
        one_scan = centroid + surface_offset(centroid, sensor, 0.667, half_width_across(returns, centroid, sensor))
        scan_short.append(centre[0] - one_scan[0])
        track_short.append(centre[0] - tracker.estimates(stamp(k))[0].position[0])
    [estimate] = tracker.estimates(stamp(63))
    assert 0.3 < estimate.half_width <= radius
    assert np.mean(scan_short) > 0.05 and abs(np.mean(track_short)) < 0.02


def test_a_cluster_merged_with_something_wide_makes_the_target_no_wider_than_max_half_width():
    rng = np.random.default_rng(6)
    sensor = np.array([0.0, 0.0, 6.0])
    tracker = TrackerCore(TrackerParams(max_half_width=0.5))
    tracker.new_detections(stamp(0), np.array([[15.0, 0.0, 6.0]]))
    wall = np.stack([np.full(60, 15.0), np.linspace(-3.0, 3.0, 60), np.full(60, 6.0)], axis=1)  # unmapped, 0.1 m apart
    tracker.new_point_cloud(stamp(1), cloud(wall.astype(np.float32)), sensor)
    assert tracker.estimates(stamp(1))[0].half_width == 0.5
    tracker.new_point_cloud(stamp(2), cloud(front_of_a_sphere(np.array([15.0, 0.0, 6.0]), 0.325, 300, rng)), sensor)
    assert tracker.estimates(stamp(2))[0].half_width == 0.5


def test_a_late_detection_replayed_through_the_buffer_equals_in_order_processing():
    """Latency compensation (lines 22-24): detections that arrive scans after their scan give the
    same tracks as detections handed in right after their own scan."""
    rng = np.random.default_rng(3)
    scans = [cloud(blob(moving(k), rng)) for k in range(12)]
    seen = [moving(k)[None] + rng.normal(0, 0.05, (1, 3)) for k in range(12)]
    late, reference = TrackerCore(), TrackerCore()
    for k in range(12):
        late.new_point_cloud(stamp(k), scans[k])
        if k >= 3:
            late.new_detections(stamp(k - 3), seen[k - 3])  # the detector is three scans behind
        reference.new_point_cloud(stamp(k), scans[k])
        if k <= 8:
            reference.new_detections(stamp(k), seen[k])  # the same detections, each right after its scan
    [a], [b] = reference.estimates(stamp(11)), late.estimates(stamp(11))
    assert a.id == b.id and a.detections == b.detections == 9
    np.testing.assert_allclose(a.state, b.state, atol=1e-9)
    np.testing.assert_allclose(a.covariance, b.covariance, atol=1e-9)


def test_a_detection_rewinds_a_track_no_cloud_corrected_and_replays_it():
    """A track whose returns the cloud update cannot use (here: no clouds hold the target) is
    corrected by its detections as if they had come in order."""
    rng = np.random.default_rng(5)
    empty = [cloud() for _ in range(8)]
    seen = [moving(k)[None] + rng.normal(0, 0.05, (1, 3)) for k in range(8)]
    late, direct = TrackerCore(), TrackerCore()
    for k in range(8):
        late.new_point_cloud(stamp(k), empty[k])
        if k >= 2:
            late.new_detections(stamp(k - 2), seen[k - 2])
        direct.new_point_cloud(stamp(k), empty[k])
        if k <= 5:
            direct.new_detections(stamp(k), seen[k])
    [a], [b] = direct.estimates(stamp(7)), late.estimates(stamp(7))
    np.testing.assert_allclose(a.state, b.state, atol=1e-9)
    assert a.detections == b.detections == 6


def test_clusters_next_to_occupied_voxels_do_not_correct_a_track():
    """Line 39: a track passing a wall must not be pulled onto the wall's returns."""
    rng = np.random.default_rng(2)
    size, corner, shape = 0.5, np.zeros(3), np.array([40, 40, 20])
    states = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    wall = np.array([10.0, 5.0, 6.0])
    vx, vy, vz = (wall / size).astype(int)
    states[(vx * shape[1] + vy) * shape[2] + vz] = STATE_OCCUPIED
    tracker = TrackerCore()
    tracker.set_occupied(OccupiedVoxels(states, corner, size, shape))
    tracker.new_detections(stamp(0), np.array([[8.5, 5.0, 6.0]]))
    for k in range(1, 6):  # only the wall's returns within reach, 1.5 m away from the track
        tracker.new_point_cloud(stamp(k), cloud(blob(wall + [0.25, 0.25, 0.25], rng, spread=0.05)))
    [estimate] = tracker.estimates(stamp(5))
    assert estimate.updates == 0 and abs(estimate.position[0] - 8.5) < 1e-9
    tracker.set_occupied(None)  # without the map the same returns do pull it
    tracker.new_point_cloud(stamp(6), cloud(blob(wall + [0.25, 0.25, 0.25], rng, spread=0.05)))
    assert tracker.estimates(stamp(6))[0].updates == 1


def test_a_track_no_scan_or_detection_supports_is_dropped_once_its_radius_exceeds_r_max():
    tracker = TrackerCore()
    rng = np.random.default_rng(0)
    for k in range(10):
        tracker.new_point_cloud(stamp(k), cloud())
        tracker.new_detections(stamp(k), detections_only(k, rng))
    dropped_at = None
    for k in range(10, 200):
        dropped = tracker.new_point_cloud(stamp(k), cloud())
        if dropped:
            dropped_at = k
            assert dropped == [1]
            break
        assert tracker.estimates(stamp(k))[0].uncertainty_radius <= 5.0
    assert dropped_at is not None and len(tracker) == 0
    assert 1.0 < (dropped_at - 9) / 10 < 8.0


def test_sporadic_false_detections_never_become_confirmed_tracks():
    rng = np.random.default_rng(11)
    tracker = TrackerCore()
    confirmed, false_starts = set(), 0
    for k in range(300):
        tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
        seen = [moving(k) + rng.normal(0, 0.05, 3)]
        if rng.random() < 0.2:  # a false detection somewhere in the arena, now and then
            seen.append(rng.uniform([-40, -40, 1], [40, 40, 15]))
            false_starts += 1
        tracker.new_detections(stamp(k), np.array(seen))
        confirmed |= {e.id for e in tracker.estimates(stamp(k), trajectory=False) if e.confirmed}
    [target] = [e for e in tracker.estimates(stamp(299), trajectory=False) if e.confirmed]
    assert np.linalg.norm(target.position - moving(299)) < 0.5
    assert confirmed == {target.id} and false_starts > 40


def test_two_targets_keep_their_identities_and_one_set_of_detections_never_feeds_one_track_twice():
    rng = np.random.default_rng(1)
    tracker = TrackerCore()
    for k in range(30):
        t = k / 10
        a, b = np.array([2.0 * t, 0.0, 5.0]), np.array([1.5 + 2.0 * t, 2.0, 5.0])  # 2.5 m apart
        tracker.new_point_cloud(stamp(k), cloud(blob(a, rng, spread=0.05), blob(b, rng, spread=0.05)))
        order = [a, b] if k % 2 == 0 else [b, a]  # detection order must not matter
        ids = tracker.new_detections(stamp(k), np.array(order) + rng.normal(0, 0.05, (2, 3)))
        assert len(set(ids)) == 2
    estimates = sorted(tracker.estimates(stamp(29)), key=lambda e: e.id)
    assert [e.id for e in estimates] == [1, 2] and all(e.confirmed for e in estimates)
    assert np.linalg.norm(estimates[0].position - [5.8, 0.0, 5.0]) < 0.4
    assert np.linalg.norm(estimates[1].position - [7.3, 2.0, 5.0]) < 0.4


def test_estimates_do_not_change_the_filters():
    tracker = TrackerCore()
    tracker.new_detections(stamp(0), np.array([[0.0, 0.0, 5.0]]))
    tracker.new_detections(stamp(1), np.array([[0.4, 0.0, 5.0]]))
    first = tracker.estimates(stamp(30))[0]
    second = tracker.estimates(stamp(30))[0]
    assert np.array_equal(first.state, second.state) and np.array_equal(first.covariance, second.covariance)
    assert tracker.estimates(stamp(1))[0].covariance[0, 0] < first.covariance[0, 0]


def test_the_number_of_tracks_is_bounded_whatever_the_detections():
    core = TrackerCore(TrackerParams(max_tracks=10))
    rng = np.random.default_rng(3)
    for k in range(5):
        core.new_point_cloud(stamp(k), rng.uniform(-50, 50, size=(20000, 3)))
        ids = core.new_detections(stamp(k), rng.uniform(-50, 50, size=(300, 3)))
        assert len({i for i in ids if i >= 0}) <= 10
    assert len(core.estimates(stamp(5))) <= 10


def test_detections_that_would_poison_the_filters_are_dropped_and_counted():
    """Found by tests/test_fuzz_messages.py: one NaN detection made a NaN track, after which every
    association raised; an indefinite covariance made the filter's innovation singular."""
    tracker = TrackerCore()
    tracker.new_detections(stamp(0), np.array([[1.0, 2.0, 5.0]]))
    not_a_covariance = np.array([[[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]])
    assert tracker.new_detections(stamp(1), np.array([[np.nan, 2.0, 5.0]])) == [-1]
    assert tracker.new_detections(stamp(2), np.array([[1.0, 2.0, 5.0]]), not_a_covariance) == [-1]
    assert tracker.new_detections(stamp(3), np.array([[1.0, 2.0, 5.0]]), np.eye(3)[None] * 0.02) == [1]
    assert tracker.counters.rejected_detections == 2 and tracker.counters.diverged_tracks == 0
    assert tracker.new_point_cloud(stamp(4), np.full((10, 3), np.inf)) == []  # infinite returns select nothing
    assert tracker.ids == [1]


def test_clouds_older_than_the_whole_buffer_are_counted_not_used():
    tracker = TrackerCore(TrackerParams(buffer_size=3))
    for k in range(5, 8):
        tracker.new_point_cloud(stamp(k), cloud())
    tracker.new_point_cloud(stamp(2), cloud())
    assert tracker.counters.late_clouds == 1 and [c.stamp for c in tracker.buffer] == [stamp(5), stamp(6), stamp(7)]
    tracker.new_point_cloud(stamp(6) + 1, cloud())  # out of order but inside: kept in stamp order
    assert [c.stamp for c in tracker.buffer] == [stamp(6), stamp(6) + 1, stamp(7)]


@pytest.mark.parametrize("name", ["kf", "adaptive", "particle"])
def test_every_filter_runs_the_same_tracker(name):
    rng = np.random.default_rng(4)
    tracker = TrackerCore(TrackerParams(filter=name))
    for k in range(20):
        tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
        tracker.new_detections(stamp(k), moving(k)[None] + rng.normal(0, 0.05, (1, 3)))
    [estimate] = tracker.estimates(stamp(19))
    assert estimate.confirmed and np.linalg.norm(estimate.position - moving(19)) < 0.5


def test_params_name_a_known_filter():
    with pytest.raises(msgspec.ValidationError, match="kf, adaptive, particle"):
        msgspec.convert({"filter": "ukf"}, TrackerParams)
    params = msgspec.convert({"filter": "adaptive", "noise": {"q_velocity": 2.0}}, TrackerParams)
    assert params.noise.q_velocity == 2.0


@pytest.mark.parametrize("name", ["kf", "adaptive", "particle"])
def test_a_singular_detection_covariance_is_raised_in_every_direction_not_refused_or_raised_on(name):
    """PSD but singular (a thin cluster's spread): raising only its variances leaves it singular,
    which the particle filter's likelihood cannot factor; the floor raises every direction."""
    tracker = TrackerCore(TrackerParams(filter=name))
    singular = np.array([[[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    for k in range(4):
        assert tracker.new_detections(stamp(k), moving(k)[None], singular) == [1]
    [estimate] = tracker.estimates(stamp(3))
    assert estimate.detections == 4 and np.isfinite(estimate.state).all()


def test_a_target_back_in_sight_soon_near_its_prediction_takes_its_identity_back():
    """Out of sight long enough for its track to be dropped, then seen again where it would be:
    the same identity (and its detections); far from there, or too late, a new one."""
    def run(back_after: float, offset: float) -> list:
        tracker = TrackerCore()
        rng = np.random.default_rng(6)
        for k in range(20):  # 2 s seen, 3 m/s along x
            tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
            tracker.new_detections(stamp(k), moving(k)[None])
        k = 20
        while len(tracker):  # unseen until the track is dropped
            tracker.new_point_cloud(stamp(k), cloud())
            k += 1
        back = k + int(back_after * 10)
        tracker.new_point_cloud(stamp(back), cloud(blob(moving(back) + [0, offset, 0], rng)))
        tracker.new_detections(stamp(back), (moving(back) + [0, offset, 0])[None])
        return tracker.estimates(stamp(back))

    [again] = run(back_after=0.5, offset=0.0)
    assert again.id == 1 and again.detections == 21 and again.confirmed
    assert run(back_after=0.5, offset=8.0)[0].id == 2  # another target's place (until it is confirmed)
    assert run(back_after=4.0, offset=0.0)[0].id == 2  # gone too long for this rule


def seen_then_lost(tracker: TrackerCore, path, rng, scans: int = 20) -> int:
    """`scans` scans of a target on `path(k)` with a detection each, then empty scans until its
    track is dropped; returns the scan index after that."""
    for k in range(scans):
        tracker.new_point_cloud(stamp(k), cloud(blob(path(k), rng)))
        tracker.new_detections(stamp(k), path(k)[None])
    k = scans
    while len(tracker):
        tracker.new_point_cloud(stamp(k), cloud())
        k += 1
    return k


def seen_again(tracker: TrackerCore, path, start: int, rng, scans: int = 3) -> list:
    for k in range(start, start + scans):
        tracker.new_point_cloud(stamp(k), cloud(blob(path(k), rng)))
        tracker.new_detections(stamp(k), path(k)[None])
    return tracker.estimates(stamp(start + scans - 1))


def standing(x: float, y: float = 5.0):
    return lambda k: np.array([x, y, 6.0])


def test_a_newcomer_confirmed_within_a_lost_tracks_reach_and_moving_like_it_takes_its_identity():
    """Track-segment association (stitch_time): the mover lost 10 s ago comes back 20 m on, and
    the balloon out of sight for 10 s is seen where it stood: their identities, with their
    detections, from the moment they are confirmed again."""
    rng = np.random.default_rng(11)
    mover, back = TrackerCore(), None
    back = seen_then_lost(mover, moving, rng) + 100
    elsewhere = lambda k: moving(k) + [-10.0, 6.0, 0.0]  # some 25 m from where it was lost; 3 m/s
    before = seen_again(mover, elsewhere, back, rng, scans=2)
    assert [(e.id, e.confirmed) for e in before] == [(2, False)]  # not yet: a false detection could be this
    [after] = seen_again(mover, elsewhere, back + 2, rng, scans=1)
    assert after.id == 1 and after.confirmed and after.detections == 23 and mover.counters.stitched == 1

    balloon = TrackerCore()
    back = seen_then_lost(balloon, standing(8.0), rng) + 100
    [again] = seen_again(balloon, standing(8.3), back, rng)
    assert again.id == 1 and again.detections == 23


def test_no_identity_is_taken_out_of_reach_across_motions_or_after_stitch_time():
    rng = np.random.default_rng(12)

    def newcomer_id(lost_path, new_path, gap_scans: int, **params) -> int:
        tracker = TrackerCore(TrackerParams(**params))
        back = seen_then_lost(tracker, lost_path, rng) + gap_scans
        return seen_again(tracker, new_path, back, rng)[0].id

    # a balloon never flies off: 8 m from where it stood is another one
    assert newcomer_id(standing(8.0), standing(16.0), 100) == 2
    # a drone passing where a balloon stood does not take its identity, nor a balloon a drone's
    assert newcomer_id(standing(8.0), lambda k: moving(k - 100 - 20) + [6.0, 0.0, 0.0], 100) == 2
    assert newcomer_id(moving, standing(15.0), 100) == 2
    # beyond stitch_speed × the time out of sight (8 m/s × ~1.3 s + r_max), or remembered too long
    assert newcomer_id(moving, lambda k: moving(k) + [0.0, 30.0, 0.0], 4) == 2
    assert newcomer_id(moving, lambda k: moving(k) + [0.0, 6.0, 0.0], 100, stitch_time=5.0) == 2
    assert newcomer_id(moving, lambda k: moving(k) + [0.0, 6.0, 0.0], 100) == 1


def test_a_partner_confirms_a_tentative_track_for_good_under_its_own_identity():
    """Like a count of detections, a partner's confirmation stands: a track that flickered between
    confirmed and not whenever the partner's track left the gate would count fragments."""
    rng = np.random.default_rng(14)
    tracker = TrackerCore()

    def scan(k: int, detected: bool = True) -> TrackEstimate:
        tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
        if detected:
            tracker.new_detections(stamp(k), moving(k)[None])
        [estimate] = tracker.estimates(stamp(k))
        return estimate

    first = scan(0)
    assert not first.confirmed
    assert not tracker.corroborate({first.id + 7: np.zeros(3)})  # no such track: nothing happens
    assert not scan(1, detected=False).confirmed
    assert tracker.corroborate({first.id: np.array([3.0, 0.0, 0.0])})
    corroborated = scan(2, detected=False)
    assert corroborated.id == first.id and corroborated.confirmed and corroborated.detections == 1
    assert corroborated.primary
    assert not tracker.corroborate({first.id: np.array([3.0, 0.0, 0.0])})  # confirmed already: no change
    assert not tracker.corroborate({})  # the partner's track gone
    assert scan(3, detected=False).confirmed and scan(4).detections == 2


def test_a_target_a_partner_confirmed_keeps_its_confirmed_identity_when_it_comes_back_soon():
    """Dropped while only a partner's track confirmed it (1 detection), the target is seen again
    within reidentify_time: it takes its identity back, and a confirmed identity stays confirmed."""
    rng = np.random.default_rng(17)
    tracker = TrackerCore()
    tracker.new_point_cloud(stamp(0), cloud(blob(moving(0), rng)))
    [first] = tracker.new_detections(stamp(0), moving(0)[None])
    tracker.corroborate({first: np.array([3.0, 0.0, 0.0])})
    k = 1
    while len(tracker):
        tracker.new_point_cloud(stamp(k), cloud())
        tracker.prune(stamp(k))
        k += 1
    tracker.corroborate({})  # the partner no longer sees it either
    tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)))
    tracker.new_detections(stamp(k), moving(k)[None])
    [back] = tracker.estimates(stamp(k))
    assert back.id == first and back.detections == 2 and back.confirmed and tracker.counters.reidentified == 1


def test_a_corroborated_newcomer_takes_a_lost_movers_identity_by_the_partners_velocity():
    """One detection leaves a new track's own speed near 0; the partner's track knows it moves."""
    rng = np.random.default_rng(15)

    def newcomer(velocity) -> TrackEstimate:
        tracker = TrackerCore()
        back = seen_then_lost(tracker, moving, rng) + 50
        elsewhere = lambda k: moving(k) + [-6.0, 4.0, 0.0]
        [new] = seen_again(tracker, elsewhere, back, rng, scans=1)
        assert not new.confirmed and tracker.corroborate({new.id: velocity})
        [after] = tracker.estimates(stamp(back))
        assert after.confirmed
        return after

    assert newcomer(np.array([3.0, 0.0, 0.0])).id == 1  # a mover back: its identity and detections
    assert newcomer(np.array([3.0, 0.0, 0.0])).detections == 21
    assert newcomer(np.zeros(3)).id == 2  # standing by the partner's account: not the lost mover


def test_of_two_lost_movers_the_one_nearest_for_its_reach_is_taken():
    rng = np.random.default_rng(13)
    tracker = TrackerCore()
    first = seen_then_lost(tracker, moving, rng)
    other = lambda k: moving(k) + [0.0, 30.0, 0.0]  # a second drone, 30 m to the side, lost later
    k = first + 5
    for j in range(k, k + 20):
        tracker.new_point_cloud(stamp(j), cloud(blob(other(j), rng)))
        tracker.new_detections(stamp(j), other(j)[None])
    k += 20
    while len(tracker):
        tracker.new_point_cloud(stamp(k), cloud())
        k += 1
    [back] = seen_again(tracker, lambda j: other(j) + [2.0, 0.0, 0.0], k + 10, rng)
    assert back.id == 2  # beside where the second was lost, not the first


def test_a_track_coasting_through_missed_scans_is_published_by_the_manoeuvre_model():
    """Eq. 27 holds the last acceleration as long as a track coasts: 2 s of a 4 m/s² brake turn
    into 8 m. The published state carries the last correction on with the acceleration fading
    (manoeuvre_time), the covariance is the filter's prediction (so r_unc and dropping are as before)."""
    rng = np.random.default_rng(3)
    tracker = TrackerCore()
    for k in range(15):
        tracker.new_detections(stamp(k), detections_only(k, rng), np.eye(3)[None] * 0.02)
    corrected = tracker.estimates(stamp(14))[0]
    later = stamp(14) + 2 * NS
    [coasting] = tracker.estimates(later)
    expected = manoeuvre_state(corrected.state, 2.0, tracker.params.manoeuvre_time)
    np.testing.assert_allclose(coasting.state, expected, atol=1e-9)
    np.testing.assert_allclose(coasting.trajectory[0], turning_path(expected, 0.25, 1, tracker.params.manoeuvre_time,
                                                                    coasting.turn)[0])
    assert coasting.uncertainty_radius > corrected.uncertainty_radius


def test_the_manoeuvre_state_is_the_derivative_of_the_manoeuvre_path():
    mean = np.array([1.0, 2.0, 3.0, 4.0, -1.0, 0.5, -4.0, 2.0, 1.0])
    for tau in (0.5, 1.0, np.inf):
        state = manoeuvre_state(mean, 1.3, tau)
        (here,), (ahead,) = manoeuvre_path(mean, 1.3, 1, tau), manoeuvre_path(mean, 1.3 + 1e-6, 1, tau)
        np.testing.assert_allclose(state[:3], here)
        np.testing.assert_allclose(state[3:6], (ahead - here) / 1e-6, atol=1e-4)
        np.testing.assert_allclose(manoeuvre_state(state, 0.7, tau), manoeuvre_state(mean, 2.0, tau), atol=1e-9)


def compiled_by_real_scans_after_warm_up() -> dict:
    """In a fresh interpreter (tests/tools/compiled.py): what warm_up confirmed, then the kernels
    real scans and detections still compile or load after it."""
    modules = (tracker_kernels, voxel_kernels)
    confirmed = []
    warmed = newly_compiled(modules, lambda: confirmed.append(warm_up(TrackerParams())))
    rng = np.random.default_rng(16)
    tracker = TrackerCore()
    states = np.zeros(40 * 40 * 20, dtype=np.uint8)
    states[np.ravel_multi_index((30, 30, 2), (40, 40, 20))] = STATE_OCCUPIED
    tracker.set_occupied(OccupiedVoxels(states, np.array([-10.0, -10.0, -1.0]), 0.5, np.array([40, 40, 20])))

    def scans():
        for k in range(4):
            tracker.new_point_cloud(stamp(k), cloud(blob(moving(k), rng)), np.zeros(3))
            tracker.new_detections(stamp(k), moving(k)[None])
        tracker.prune(stamp(4))
    left = newly_compiled(modules, scans)
    return {"confirmed": confirmed[0], "warmed": warmed, "left": left,
            "tracked": [e.confirmed for e in tracker.estimates(stamp(4))]}


def test_warm_up_confirms_a_track_and_leaves_no_kernel_for_real_scans_to_compile():
    """The node warms up before its liveliness token: real scans must then find every kernel
    compiled for their types (a cold compile takes seconds)."""
    result = in_fresh_interpreter(compiled_by_real_scans_after_warm_up)
    assert result["confirmed"] == 1 and result["warmed"] and result["tracked"] == [True]
    assert result["left"] == []


def test_a_circling_target_is_published_turning_round_its_circle():
    """A drone circling at 3.2 m/s on 4 m (0.8 rad/s), detected every 0.1 s with 0.1 m noise: the
    trajectory published with its track turns with it, where the constant-acceleration filter's
    own acceleration, smoothed by its small jerk noise, would fly it nearly straight on."""
    rng = np.random.default_rng(5)
    radius, speed = 4.0, 3.2
    rate = speed / radius

    def circling(t: float) -> np.ndarray:
        return np.array([20.0 + radius * np.cos(rate * t), 27.0 + radius * np.sin(rate * t), 7.0])

    tracker = TrackerCore()
    for k in range(60):
        tracker.new_detections(stamp(k), circling(k * PERIOD / NS)[None] + rng.normal(0.0, 0.1, (1, 3)),
                               np.eye(3)[None] * 0.01)
    [track] = tracker.estimates(stamp(59))
    now = 59 * PERIOD / NS
    truth = np.array([circling(now + (i + 1) * tracker.params.trajectory_step) for i in range(len(track.trajectory))])
    misses = np.linalg.norm(track.trajectory - truth, axis=1)
    straight = manoeuvre_path(track.state, tracker.params.trajectory_step, len(truth), tracker.params.manoeuvre_time)
    print(f"turn rate {track.turn.rate:.2f} rad/s (true {rate:.2f}); 2 s ahead {misses[-1]:.2f} m off, "
          f"{np.linalg.norm(straight[-1] - truth[-1]):.2f} m without the turn")
    assert abs(track.turn.rate - rate) < 0.15
    assert misses[-1] < 1.0 < np.linalg.norm(straight[-1] - truth[-1])
