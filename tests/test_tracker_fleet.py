"""The fleet picture: own tracks joined with the partners' by covariance intersection (services/tracker/fleet.py)."""
from __future__ import annotations

import queue
import time

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import Detections, Header, Track, Tracks
from services.lib.runtime.clock import NS
from services.tracker.fleet import (FLEET_ID_BASE, FleetPicture, FleetTrack, FusionParams, PartnerTrack,
                                    covariance_intersection, sound_partner_track)
from tests.tools.health import wait_healthy

PARAMS = FusionParams(radius_min=2.5, radius_confidence=1.5, process_rates=(0.01, 0.8, 0.05), stale_after=1.0)


def random_covariance(rng: np.random.Generator, size: int = 9) -> np.ndarray:
    a = rng.normal(0.0, 1.0, (size, size))
    return a @ a.T + 0.1 * np.eye(size)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.05, 0.95))
def test_covariance_intersection_agrees_with_stone_soup(seed, omega):
    from stonesoup.mixturereducer.gaussianmixture import CovarianceIntersection
    from stonesoup.types.state import GaussianState

    rng = np.random.default_rng(seed)
    mean_a, mean_b = rng.normal(0, 5, 9), rng.normal(0, 5, 9)
    cov_a, cov_b = random_covariance(rng), random_covariance(rng)
    mean, covariance, _ = covariance_intersection(mean_a, cov_a, mean_b, cov_b, omega)
    oracle = CovarianceIntersection.merge_components(GaussianState(mean_a[:, None], cov_a),
                                                     GaussianState(mean_b[:, None], cov_b), weights=[omega, 1 - omega])
    np.testing.assert_allclose(mean, np.asarray(oracle.state_vector, dtype=float).ravel(), rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(covariance, np.asarray(oracle.covar, dtype=float), rtol=1e-7, atol=1e-7)


def test_the_chosen_omega_is_never_worse_than_either_estimate_and_stays_consistent():
    rng = np.random.default_rng(3)
    for _ in range(20):
        cov_a, cov_b = random_covariance(rng), random_covariance(rng)
        _, fused, omega = covariance_intersection(np.zeros(9), cov_a, np.ones(9), cov_b)
        assert 0.0 <= omega <= 1.0
        assert np.trace(fused) <= min(np.trace(cov_a), np.trace(cov_b)) + 1e-6
        # CI's guarantee: the fused covariance bounds the convex combination of the two
        bound = np.linalg.inv(omega * np.linalg.inv(cov_a) + (1 - omega) * np.linalg.inv(cov_b))
        assert np.allclose(fused, bound)
    same = random_covariance(rng)  # identical information fused with itself is not doubled
    _, fused, _ = covariance_intersection(np.zeros(9), same, np.zeros(9), same)
    assert np.allclose(fused, same)


def own(track_id: int, position, variance: float = 0.2, confirmed: bool = True) -> FleetTrack:
    mean = np.concatenate([position, [1.0, 0.0, 0.0], np.zeros(3)])
    return FleetTrack(track_id, mean, np.eye(9) * variance, 5, confirmed, "uav1")


def theirs(track_id: int, position, stamp: int = 0, variance: float = 0.2) -> PartnerTrack:
    mean = np.concatenate([position, [1.0, 0.0, 0.0], np.zeros(3)])
    return PartnerTrack(track_id, stamp, mean, np.eye(9) * variance, 8)


def test_a_target_both_see_is_one_fused_track_and_one_only_a_partner_sees_is_added():
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(4, [10.3, 0.0, 5.0]), theirs(9, [40.0, 20.0, 6.0])])
    out = fleet.fuse([own(1, [10.0, 0.0, 5.0], confirmed=True)], 0)
    fused, added = out
    assert fused.id == 1 and fused.source == "uav1" and fused.fused_with == ("uav2",) and fused.confirmed
    assert 10.0 < fused.mean[0] < 10.3 and fused.detections == 8
    assert added.id == 2 * FLEET_ID_BASE + 9 and added.source == "uav2" and added.confirmed
    assert np.allclose(added.mean[:3], [40.0, 20.0, 6.0])


def test_a_tentative_own_track_is_fused_under_the_partners_identity_until_we_confirm_it():
    """Our tracker has not confirmed the target yet (nor given it its identity, perhaps a lost
    track's; the node confirms it first unless `partner_confirms` is off): the fused track is the
    partner's, not a confirmed own track with a passing number."""
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(4, [10.3, 0.0, 5.0])])
    [fused] = fleet.fuse([own(7, [10.0, 0.0, 5.0], confirmed=False)], 0)
    assert fused.id == 2 * FLEET_ID_BASE + 4 and fused.source == "uav2" and fused.confirmed
    assert fused.fused_with == ("uav2",) and 10.0 < fused.mean[0] < 10.3
    [alone] = fleet.fuse([own(7, [30.0, 0.0, 5.0], confirmed=False)], 0)[:1]
    assert alone.id == 7 and alone.source == "uav1" and not alone.confirmed


def test_own_tentative_tracks_a_partners_confirmed_track_corroborates_are_named_with_its_velocity():
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(4, [10.3, 0.0, 5.0]), theirs(5, [20.2, 0.0, 5.0])])
    mine = [own(7, [10.0, 0.0, 5.0], confirmed=False),  # tentative, where uav2 keeps a target
            own(8, [20.0, 0.0, 5.0], confirmed=True),  # confirmed already
            own(9, [40.0, 0.0, 5.0], confirmed=False)]  # nowhere near a partner's
    corroborated = fleet.corroborating(mine, NS // 2)
    assert list(corroborated) == [7] and np.allclose(corroborated[7], [1.0, 0.0, 0.0])
    assert fleet.corroborating(mine, 2 * NS) == {}  # uav2 silent for over stale_after


def test_a_track_beside_a_partners_target_is_fused_with_it_but_not_corroborated():
    """3 m apart with σ 0.45 m each: within the sum of the uncertainty radii (fusion's rule), far
    outside the χ² gate: a sporadic false detection beside a partner's target stays tentative."""
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(4, [13.0, 0.0, 5.0])])
    beside = [own(7, [10.0, 0.0, 5.0], confirmed=False)]
    assert fleet.corroborating(beside, 0) == {}
    [fused] = fleet.fuse(beside, 0)
    assert fused.fused_with == ("uav2",) and fused.source == "uav2"  # the partner's, until ours is confirmed


def test_partner_tracks_are_carried_to_now_and_dropped_when_the_partner_falls_silent():
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(9, [40.0, 20.0, 6.0])])
    [carried] = fleet.fuse([], NS // 2)
    assert np.allclose(carried.mean[:3], [40.5, 20.0, 6.0]) and carried.covariance[0, 0] > 0.2
    assert fleet.fuse([], NS + NS // 10) == []  # a cut link: its tracks leave the picture, ours stay
    mine = own(1, [0.0, 0.0, 5.0])
    assert fleet.fuse([mine], 2 * NS) == [mine]


def test_two_partners_seeing_a_target_we_do_not_give_one_track():
    fleet = FleetPicture(PARAMS)
    fleet.partner_tracks("uav2", 0, [theirs(3, [20.0, 5.0, 6.0])])
    fleet.partner_tracks("uav3", 0, [theirs(7, [20.4, 5.0, 6.0])])
    [one] = fleet.fuse([], 0)
    assert one.id == 2 * FLEET_ID_BASE + 3 and one.fused_with == ("uav3",)


@pytest.mark.parametrize("mean, covariance, sound", [
    (np.zeros(9), np.eye(9), True),
    (np.zeros(6), np.eye(6), False),  # another filter's layout
    (np.full(9, np.nan), np.eye(9), False),
    (np.zeros(9), -np.eye(9), False),
    (np.zeros(9), np.triu(np.ones((9, 9))), False),
])
def test_only_finite_positive_definite_ca_states_are_fused(mean, covariance, sound):
    assert sound_partner_track(mean, covariance) is sound


def test_a_tracker_node_confirms_its_first_detection_of_a_target_its_partner_keeps(hub, processes):
    """Real processes over Zenoh: uav1's tracker hears uav2 keep a confirmed track, then detects
    the target once; it publishes the target as its own confirmed track (its own identity), fused
    with the partner's (whose detection count it then shows)."""
    session, endpoint = hub
    encoder, decoder = msgspec.msgpack.Encoder(), msgspec.msgpack.Decoder(Tracks)
    heard: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber(keys.uav("uav1", "tracks"), lambda s: heard.put(s.payload.to_bytes()))
    partner, detections = session.declare_publisher(keys.uav("uav2", "tracks")), \
        session.declare_publisher(keys.uav("uav1", "detections"))
    target = np.array([20.0, 5.0, 6.0])
    try:
        processes.start("run", "tracker", "--uav", "uav1", "--clock", "wall", "--connect", endpoint)
        wait_healthy(session, [("uav1", "tracker")])
        deadline, own = time.monotonic() + 10.0, []
        detected = False
        while not own and time.monotonic() < deadline:
            mean = np.concatenate([target, [1.0, 0.0, 0.0], np.zeros(3)])
            partner.put(encoder.encode(Tracks(header=Header(stamp=time.time_ns()), tracks=[Track(
                id=4, state=from_numpy(mean), covariance=from_numpy(np.eye(9) * 0.1), detections=9, confirmed=True,
                uncertainty_radius=2.5, last_detection=0, source="uav2")])))
            if not detected:
                time.sleep(0.3)  # heard first: the detection arrives to a partner's confirmed target
                detections.put(encoder.encode(Detections(
                    header=Header(stamp=time.time_ns()), detector="classifier",
                    positions=from_numpy(target[None] + 0.1), covariances=from_numpy(np.eye(3)[None] * 0.01),
                    point_counts=from_numpy(np.array([12], dtype=np.int32)),
                    extents=from_numpy(np.array([0.6], dtype=np.float32)))))
                detected = True
            time.sleep(0.1)
            while not heard.empty():
                message = decoder.decode(heard.get())
                own += [t for t in message.tracks if t.source == "uav1"]
        assert own, "no own track published within 10 s"
        first = own[0]
        assert first.confirmed and first.detections == 9 and first.id < FLEET_ID_BASE  # fused: the partner's count
        assert first.filter == "kf" and first.uncertainty_radius > 0
    finally:
        sub.undeclare()
        partner.undeclare()
        detections.undeclare()

def test_the_fleet_picture_admits_only_a_healthy_partners_own_sound_confirmed_tracks():
    from services.tracker.fleet import FLEET_ID_BASE, PartnerReport, admitted

    good = np.eye(9)
    reports = [PartnerReport(1, True, "uav2", np.zeros(9), good.reshape(-1), 4, 900),  # kept (covariance flat)
               PartnerReport(2, False, "uav2", np.zeros(9), good, 1, 0),  # tentative: left out
               PartnerReport(3, True, "uav3", np.zeros(9), good, 5, 0),  # uav3's, heard through uav2: left out
               PartnerReport(4, True, "uav2", np.full(9, np.nan), good, 5, 0),  # unsound: refused
               PartnerReport(5, True, "uav2", np.zeros(9), -good, 5, 0),  # not positive definite: refused
               PartnerReport(FLEET_ID_BASE + 1, True, "uav2", np.zeros(9), good, 5, 0),  # a fleet id: refused
               PartnerReport(7, True, "uav2", np.zeros(0), np.zeros(0), 5, 0)]  # no numbers: refused
    tracks, refused = admitted("uav2", 500, True, reports)
    assert [t.id for t in tracks] == [1] and refused == 4
    assert tracks[0].covariance.shape == (9, 9) and tracks[0].stamp == 500 and tracks[0].last_correction == 500
    assert admitted("uav2", 500, False, reports) == ([], 0)  # its LiDAR failing: nothing of it
