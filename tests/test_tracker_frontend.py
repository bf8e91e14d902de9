"""Seed 002's single-target pipeline: the LiDAR front end (services/tracker/frontend.py) and the
tracking loop (services/tracker/single.py)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import msgspec
import numpy as np
import pytest

from services.lib.runtime.clock import NS
from services.tracker.filters import FilterParams, make_filter
from services.tracker.filters.base import Estimate, Filter, Innovation, Update
from services.tracker.filters.deleting import MissedStepsDeleter
from services.tracker.filters.gating import MahalanobisGater
from services.tracker.frontend import (Candidates, FrontEndParams, cluster_labels, front_end, in_cylinder,
                                       voxel_downsample)
from services.tracker.single import Outcome, SingleTargetParams, SingleTargetTracker, single_target_tracker, track

PERIOD = NS // 10  # 10 Hz scans
OBSERVER = np.array([0.0, 0.0, 5.0])


def drone_returns(centre) -> np.ndarray:
    """Three returns on a 0.65 m drone, as a Mid-360 gives at 20 m."""
    return np.asarray(centre, dtype=float) + [[-0.25, 0.0, 0.05], [0.1, 0.1, -0.05], [0.25, -0.05, 0.0]]


def wall(x: float) -> np.ndarray:
    """A building's face at x, 6 m wide and 4 m high, returns every 0.5 m (chained by DBSCAN)."""
    y, z = np.meshgrid(np.arange(-3.0, 3.01, 0.5), np.arange(2.0, 6.01, 0.5))
    return np.stack([np.full(y.size, x), y.ravel(), z.ravel()], axis=1)


def ground() -> np.ndarray:
    xy = np.stack(np.meshgrid(np.arange(-30, 30, 0.7), np.arange(-30, 30, 0.7)), -1).reshape(-1, 2)
    return np.hstack([xy, np.random.default_rng(1).normal(0.0, 0.02, (len(xy), 1))])


def candidates_at(*positions) -> Candidates:
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    return Candidates(positions, np.zeros((len(positions), 3, 3)), np.full(len(positions), 2))


# -- front end -----------------------------------------------------------------------------------

def test_voxel_downsampling_replaces_each_voxel_by_its_points_centroid():
    points = np.array([[0.01, 0.02, 0.03], [0.05, 0.06, 0.07],  # one voxel of 0.1 m
                       [0.31, 0.0, 0.0],  # alone in another
                       [0.02, 0.04, 0.08]])  # the first voxel again, not next to its fellows
    out = voxel_downsample(points, 0.1)
    assert len(out) == 2
    rows = {tuple(np.round(p, 6)) for p in out}
    assert tuple(np.round(points[[0, 1, 3]].mean(axis=0), 6)) in rows
    assert (0.31, 0.0, 0.0) in rows
    assert len(voxel_downsample(np.zeros((0, 3)), 0.1)) == 0


def test_voxel_downsampling_of_a_dense_surface_keeps_one_point_per_voxel():
    rng = np.random.default_rng(2)
    points = rng.uniform(0.0, 1.0, (20_000, 3))
    out = voxel_downsample(points, 0.25)
    assert len(out) == 64  # 4 × 4 × 4 voxels, all occupied
    cells = np.floor(out / 0.25)
    assert len(np.unique(cells, axis=0)) == 64  # every centroid lies inside its own voxel


def test_the_cylindrical_roi_keeps_the_flight_envelope_around_the_observer():
    params = FrontEndParams(roi_radius=40.0, roi_min_altitude=1.0, roi_max_altitude=15.0)
    points = np.array([
        [20.0, 10.0, 8.0],  # inside
        [39.0, 0.0, 14.9],  # near the wall and the ceiling, inside
        [30.0, 30.0, 8.0],  # 42 m away horizontally
        [10.0, 0.0, 0.1],  # ground
        [10.0, 0.0, 16.0],  # above the airspace
    ])
    assert in_cylinder(points, OBSERVER, params).tolist() == [True, True, False, False, False]


def test_no_return_rows_are_dropped():
    cloud = np.full((4, 50, 3), np.nan, dtype=np.float32)  # an organised scan of no returns...
    cloud[2, 7:10] = drone_returns([20.0, 0.0, 8.0])  # ...but the drone
    found = front_end(cloud, OBSERVER, FrontEndParams())
    assert found.points == 3 and len(found) == 1


def test_dbscan_finds_a_compact_three_point_cluster_and_leaves_a_lone_return_as_noise():
    params = FrontEndParams()
    points = np.vstack([drone_returns([20.0, 5.0, 8.0]), [[10.0, -10.0, 6.0]]])
    labels = cluster_labels(points, params)
    assert labels[0] == labels[1] == labels[2] >= 0 and labels[3] == -1
    found = front_end(points, OBSERVER, params)
    assert len(found) == 1 and found.sizes.tolist() == [3]
    assert np.allclose(found.positions[0], drone_returns([20.0, 5.0, 8.0]).mean(axis=0))
    assert np.allclose(found.covariances[0], np.cov(drone_returns([20.0, 5.0, 8.0]).T))  # eq. 5, n - 1


def test_the_eigenvalue_rule_rejects_an_extended_wall_and_single_points():
    params = FrontEndParams()
    points = np.vstack([wall(25.0), drone_returns([15.0, 5.0, 8.0]), [[10.0, -10.0, 6.0]]])
    found = front_end(points, OBSERVER, params)
    assert found.clusters == 2  # DBSCAN: the wall and the drone; the lone return is noise
    assert len(found) == 1 and np.linalg.norm(found.positions[0] - [15.0, 5.0, 8.0]) < 0.2

    singles = msgspec.structs.replace(params, cluster_min_points=1)  # every return its own cluster...
    found = front_end(np.array([[10.0, -10.0, 6.0], [12.0, 10.0, 6.0]]), OBSERVER, singles)
    assert found.clusters == 2 and len(found) == 0  # ...whose zero covariance eq. 6 rejects


def test_the_size_bound_tightens_with_the_number_of_returns():
    params = FrontEndParams()  # a drone's returns span at most 0.8 m
    pair = np.array([[20.0, 0.0, 8.0], [20.0, 0.75, 8.0]])  # two returns on either rotor
    pole = np.stack([np.full(8, 12.0), np.full(8, 12.0), np.linspace(6.0, 7.5, 8)], axis=1)  # 1.5 m
    found = front_end(np.vstack([pair, pole]), OBSERVER, params)
    assert np.linalg.eigvalsh(np.cov(pole.T))[-1] < np.linalg.eigvalsh(np.cov(pair.T))[-1]  # the pole is less spread...
    assert found.clusters == 2 and len(found) == 1  # ...but too long for eight returns on a drone
    assert np.allclose(found.positions[0], pair.mean(axis=0))


def test_two_returns_on_one_spot_are_not_a_drone():
    spot = np.array([[20.0, 0.0, 8.0], [20.01, 0.0, 8.005]])  # range noise apart, in two voxels
    found = front_end(spot, OBSERVER, FrontEndParams(voxel_size=0.005))
    assert found.clusters == 1 and len(found) == 0


def test_the_ground_and_a_wall_yield_no_candidate_beside_the_drone():
    cloud = np.vstack([ground(), wall(30.0), drone_returns([18.0, -6.0, 7.0]), np.full((100, 3), np.nan)])
    found = front_end(cloud, OBSERVER, FrontEndParams())
    assert len(found) == 1 and np.linalg.norm(found.positions[0] - [18.0, -6.0, 7.0]) < 0.2


def test_parameters_are_checked():
    with pytest.raises(ValueError):
        FrontEndParams(roi_min_altitude=5.0, roi_max_altitude=2.0)
    with pytest.raises(ValueError):
        FrontEndParams(min_spread=0.5, max_extent=0.8)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"eps": 0.5}, FrontEndParams)


# -- the single-target loop ----------------------------------------------------------------------

def path(k: int) -> np.ndarray:
    return np.array([15.0 + 0.3 * k, 4.0, 8.0])  # 3 m/s along x


def tracker_for(name: str, recovery: bool, max_missed: int = 5) -> SingleTargetTracker:
    return single_target_tracker(make_filter(name, FilterParams()),
                                 SingleTargetParams(recovery=recovery, max_missed=max_missed))


def test_the_first_candidate_starts_the_track_and_later_ones_update_it():
    tracker = tracker_for("kf", recovery=True)
    assert tracker.step(0, Candidates.none()).outcome is Outcome.WAITING
    records = track(tracker, [(k * PERIOD, candidates_at(path(k))) for k in range(1, 30)])
    assert records[0].outcome is Outcome.INITIATED
    assert all(r.outcome is Outcome.UPDATED and r.updated for r in records[1:])
    assert np.linalg.norm(records[-1].estimate.position - path(29)) < 0.2
    assert np.linalg.norm(records[-1].estimate.velocity - [3.0, 0.0, 0.0]) < 0.5


def test_a_seed_position_restricts_where_the_track_may_start():
    tracker = single_target_tracker(make_filter("kf", FilterParams()), SingleTargetParams(seed_radius=3.0),
                                    seed=np.array([15.0, 4.0, 8.0]))
    assert tracker.step(0, candidates_at([30.0, 0.0, 8.0])).outcome is Outcome.WAITING
    record = tracker.step(PERIOD, candidates_at([30.0, 0.0, 8.0], [16.0, 4.0, 8.0]))
    assert record.outcome is Outcome.INITIATED and np.allclose(record.estimate.position, [16.0, 4.0, 8.0])


@pytest.mark.parametrize("name", ["kf", "adaptive", "particle"])
def test_missed_scans_coast_on_the_prediction(name):
    tracker = tracker_for(name, recovery=True, max_missed=5)
    track(tracker, [(k * PERIOD, candidates_at(path(k))) for k in range(20)])
    before = tracker.estimate
    records = track(tracker, [(k * PERIOD, Candidates.none()) for k in range(20, 24)])
    assert [r.outcome for r in records] == [Outcome.COASTED] * 4
    assert [r.missed for r in records] == [1, 2, 3, 4]
    assert records[-1].estimate.stamp == 23 * PERIOD
    assert np.linalg.norm(records[-1].estimate.position - path(23)) < 0.5  # carried on at 3 m/s
    assert np.trace(records[-1].estimate.position_covariance) > np.trace(before.position_covariance)


def test_after_n_missed_scans_recovery_reinitialises_from_the_next_candidate():
    tracker = tracker_for("kf", recovery=True, max_missed=5)
    track(tracker, [(k * PERIOD, candidates_at(path(k))) for k in range(20)])
    gap = track(tracker, [(k * PERIOD, Candidates.none()) for k in range(20, 30)])
    assert [r.outcome for r in gap] == [Outcome.COASTED] * 5 + [Outcome.LOST] * 5
    held = gap[4].estimate
    assert all(r.estimate is held for r in gap[5:])  # no extrapolation beyond N steps

    # The target turned round during the gap: it reappears far outside the gate, with a clutter
    # return farther still from where it was last seen.
    back = np.array([19.0, 8.0, 8.0])
    record = tracker.step(30 * PERIOD, candidates_at([5.0, -12.0, 8.0], back))
    assert record.outcome is Outcome.REINITIATED and record.updated
    assert np.allclose(record.estimate.position, back) and np.allclose(record.estimate.velocity, 0.0)
    assert tracker.step(31 * PERIOD, candidates_at(back + [0.1, 0, 0])).outcome is Outcome.UPDATED


def test_without_recovery_the_track_keeps_coasting_past_n_missed_scans():
    tracker = tracker_for("kf", recovery=False, max_missed=5)
    track(tracker, [(k * PERIOD, candidates_at(path(k))) for k in range(20)])
    gap = track(tracker, [(k * PERIOD, Candidates.none()) for k in range(20, 30)])
    assert [r.outcome for r in gap] == [Outcome.COASTED] * 10 and gap[-1].missed == 10
    assert gap[-1].estimate.stamp == 29 * PERIOD
    record = tracker.step(30 * PERIOD, candidates_at([19.0, 8.0, 8.0]))
    assert record.outcome is Outcome.COASTED  # outside the gate: no re-initialisation either


# A stand-in filter with a fixed, elongated uncertainty: long along x (σ 2 m), short across (0.2 m).
@dataclass(frozen=True)
class StillFilter:
    covariance: np.ndarray

    def initiate(self, position, noise, stamp) -> Estimate:
        return Estimate(np.concatenate([position, np.zeros(6)]), self.covariance, stamp)

    def predict(self, estimate: Estimate, stamp: int) -> Estimate:
        return replace(estimate, stamp=max(stamp, estimate.stamp))

    def innovation(self, predicted: Estimate, position, noise) -> Innovation:
        return Innovation(np.asarray(position) - predicted.position, predicted.position_covariance + noise)

    def update(self, predicted: Estimate, position, noise) -> Update:
        return Update(replace(predicted, mean=np.concatenate([position, np.zeros(6)])),
                      self.innovation(predicted, position, noise))


def test_gating_takes_the_candidate_nearest_in_mahalanobis_distance_and_ignores_far_clutter():
    still = StillFilter(np.diag([4.0, 0.04, 0.04, 1, 1, 1, 1, 1, 1]))
    parts = Filter("still", still, still, still)
    tracker = SingleTargetTracker(parts, MahalanobisGater(0.99), MissedStepsDeleter(5), 0.01 * np.eye(3))
    tracker.step(0, candidates_at([20.0, 0.0, 8.0]))
    along = [21.5, 0.0, 8.0]  # 1.5 m away along the long axis: d² ≈ 0.56
    across = [20.0, 0.5, 8.0]  # 0.5 m away across it: d² = 5, nearer in metres
    clutter = [20.0, 6.0, 8.0]  # a cluster 6 m off: d² = 720
    record = tracker.step(PERIOD, candidates_at(clutter, across, along))
    assert record.outcome is Outcome.UPDATED and np.allclose(record.estimate.position, along)
    assert record.innovation.squared_mahalanobis == pytest.approx(1.5**2 / 4.01)

    record = tracker.step(2 * PERIOD, candidates_at([21.5, 6.0, 8.0]))  # the clutter alone
    assert record.outcome is Outcome.COASTED and np.allclose(record.estimate.position, along)
