"""The viewer's pure parts: geometry, the map tiles and the scene builder on hand-made messages."""
from __future__ import annotations

import msgspec
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from schemas import voxels
from schemas.arrays import from_numpy
from schemas.messages import (
    Detections,
    ForbiddenZoneStatus,
    GroundTruth,
    Header,
    LabelSet,
    Obstacle,
    Odometry,
    Pose,
    ServiceHealth,
    SimEvent,
    TargetTruth,
    Track,
    Tracks,
    UavStatus,
    VehicleTruth,
    VoxelMap,
    WorldModel,
)
from services.lib.tracks import predicted_path
from services.tools.viz import draw
from services.tools.viz.geometry import cone_mesh, covariance_ellipsoids, thin_out
from services.tools.viz.mapview import MapView
from services.tools.viz.scene import SceneBuilder
from services.tools.viz.settings import ViewParams
from services.tools.viz.style import DETECTION_COLOR, FALSE_COLOR, MATCHED_COLOR

S = 1_000_000_000
encode = msgspec.msgpack.encode


def entities(logs) -> dict[str, list[draw.Log]]:
    out: dict[str, list[draw.Log]] = {}
    for log in logs:
        out.setdefault(log.entity, []).append(log)
    return out


# ------------------------------------------------------------------ geometry
def test_covariance_ellipsoid_axes_and_rotation_rebuild_the_covariance():
    rng = np.random.default_rng(3)
    rotation = Rotation.random(random_state=5).as_matrix()
    cov = rotation @ np.diag([4.0, 1.0, 0.25]) @ rotation.T
    half, quats = covariance_ellipsoids(np.stack([cov, np.diag([0.09, 0.04, 0.01])]), sigma=2.0)
    assert np.allclose(sorted(half[0]), [1.0, 2.0, 4.0])  # 2 sigma of 0.5, 1, 2
    assert np.allclose(half[1], [0.2, 0.4, 0.6])
    axes = Rotation.from_quat(quats[0]).as_matrix()
    assert np.allclose(axes @ np.diag((half[0] / 2) ** 2) @ axes.T, cov)
    assert covariance_ellipsoids(np.zeros((0, 3, 3)), 2.0)[0].shape == (0, 3)
    # round-off below zero is a flat axis, not a NaN
    half, _ = covariance_ellipsoids(np.diag([1.0, 1.0, -1e-12])[None] + rng.normal(0, 0, (1, 3, 3)), 1.0)
    assert np.isfinite(half).all() and half[0].min() == 0.0


def test_a_tracks_predicted_path_is_its_filters_trajectory_or_the_tracker_model():
    state = np.array([1.0, 2.0, 3.0, 1.0, 0.0, -1.0, 0.0, 2.0, 0.0])
    old = Track(id=1, state=from_numpy(state), covariance=from_numpy(np.eye(9)), detections=3, confirmed=True,
                uncertainty_radius=2.5, last_detection=0)  # a recording made before trajectories
    path = predicted_path(old, horizon=2.0, step=0.5)
    assert path.shape == (5, 3)
    assert np.allclose(path[0], [1, 2, 3])
    assert np.allclose(path[-1], [3.0, 2.0 + 0.5 * 2.0 * 4.0, 1.0])
    ahead = np.array([[1.5, 2.0, 3.0], [2.0, 2.1, 3.0], [2.5, 2.3, 3.0]])
    new = msgspec.structs.replace(old, position=(1.0, 2.0, 3.0), trajectory=from_numpy(ahead), trajectory_dt=0.5)
    assert np.allclose(predicted_path(new, horizon=1.0), [[1, 2, 3], ahead[0], ahead[1]])


def test_thin_out_and_cone_mesh():
    assert list(thin_out(3, 10)) == [0, 1, 2]
    picked = thin_out(1000, 10)
    assert len(picked) == 10 and picked[0] == 0 and picked[-1] == 999
    vertices, triangles = cone_mesh(np.array([1.0, 2.0, 0.0]), radius=1.0, height=3.0, sides=8)
    assert vertices.shape == (10, 3) and triangles.shape == (16, 3) and triangles.max() == 9
    assert np.isclose(vertices[:, 2].max(), 3.0)


# ------------------------------------------------------------------ map layers
GEOMETRY = dict(origin=(0.0, 0.0, 0.0), shape=(40, 40, 10), voxel_size=0.5, default_value=-740.0)


def flat(*voxel):
    return np.ravel_multi_index(tuple(np.array(v) for v in zip(*voxel)), (40, 40, 10))


def test_map_view_draws_named_voxels_by_state_in_layers_of_what_changed():
    view = MapView(cell=2, max_layers=64)
    occupied, tentative = flat((1, 1, 0), (2, 1, 0)), flat((20, 30, 3))
    view.apply(False, **GEOMETRY, indices=np.r_[occupied, tentative],
               values=np.array([0.0, 0.0, -200.0], dtype=np.float32))
    (first,) = view.drain()
    # (1,1,0) is in cell (0,0,0) and (2,1,0) in cell (1,0,0): 1 m cubes centred on their cells
    assert np.allclose(sorted(first.occupied.tolist()), [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [10.5, 15.5, 1.5]])
    assert len(first.unknown) == 0  # never-named voxels say nothing

    view.apply(False, **GEOMETRY, indices=occupied, values=np.array([-0.05, -0.01], dtype=np.float32))
    assert view.drain() == []  # still confidently occupied: nothing to draw
    view.apply(False, **GEOMETRY, indices=occupied, values=np.array([-200.0, 0.0], dtype=np.float32))
    assert view.drain() == []  # confident to tentative is still occupied: no layer is drawn again
    view.apply(False, **GEOMETRY, indices=tentative, values=np.array([-900.0], dtype=np.float32))
    (redrawn,) = view.drain()  # a voxel that went free leaves its layer: that layer is drawn again
    assert redrawn.layer == first.layer and len(redrawn.occupied) == 2

    grown = flat((30, 5, 1))
    view.apply(False, **GEOMETRY, indices=grown, values=np.array([0.0], dtype=np.float32))
    (second,) = view.drain()  # only the new cell, in a layer of its own; the first layer is untouched
    assert second.layer != first.layer and np.allclose(second.occupied, [[15.5, 2.5, 0.5]])

    # a snapshot that no longer lists a voxel returns it to the initial value: named, now unknown
    view.apply(True, **GEOMETRY, indices=np.r_[occupied[:1], grown], values=np.zeros(2, dtype=np.float32))
    layers = {layer.layer: layer for layer in view.drain()}
    assert first.layer in layers  # redrawn without what left it
    assert np.allclose(sorted(layers[first.layer].occupied.tolist()), [[0.5, 0.5, 0.5]])
    newest = layers[max(layers)]
    assert np.allclose(sorted(newest.unknown.tolist()), [[1.5, 0.5, 0.5], [10.5, 15.5, 1.5]])


def test_map_view_folds_its_layers_to_bound_the_entity_count():
    view = MapView(cell=1, max_layers=3)
    drawn = []
    for i in range(4):
        view.apply(False, **GEOMETRY, indices=flat((i, 0, 0)), values=np.array([0.0], dtype=np.float32))
        drawn.append(view.drain())
    folded = drawn[-1]
    assert [len(d) for d in drawn[:3]] == [1, 1, 1]
    assert len(folded) == 4  # the three old layers cleared, one new layer with everything
    assert all(len(layer.occupied) == 0 for layer in folded[:-1]) and len(folded[-1].occupied) == 4
    assert view.layers == 1


def test_map_view_waits_for_a_snapshot_after_a_delta_of_another_geometry():
    view = MapView(cell=1, max_layers=64)
    view.apply(False, **GEOMETRY, indices=np.array([5]), values=np.array([0.0], dtype=np.float32))
    (old,) = view.drain()
    other = dict(GEOMETRY, origin=(1.0, 0.0, 0.0))
    update = view.apply(False, **other, indices=np.array([6]), values=np.array([0.0], dtype=np.float32))
    assert not update.accepted and update.void == []
    assert view.drain() == []
    update = view.apply(True, **other, indices=np.array([6]), values=np.array([0.0], dtype=np.float32))
    assert update.accepted and update.void == [old.layer]
    (layer,) = view.drain()
    assert np.allclose(layer.occupied[:, 0], 1.25)


def test_map_view_reuses_layer_numbers_so_a_long_mission_draws_into_few_entities():
    view = MapView(cell=1, max_layers=4)
    used = set()
    for i in range(200):
        view.apply(False, **GEOMETRY, indices=flat((i % 40, i // 40, 0)), values=np.array([0.0], dtype=np.float32))
        used |= {layer.layer for layer in view.drain()}
    assert used <= set(range(5)), used
    assert view.layers <= 4


def test_a_snapshot_with_another_initial_value_is_read_from_the_new_grid():
    view = MapView(cell=1, max_layers=64)
    view.apply(False, **GEOMETRY, indices=flat((1, 1, 1)), values=np.array([-200.0], dtype=np.float32))
    view.drain()
    other = dict(GEOMETRY, default_value=-100.0)  # same geometry, a tentative-occupied initial value
    view.apply(True, **other, indices=flat((2, 2, 2)), values=np.array([0.0], dtype=np.float32))
    (layer,) = view.drain()
    # voxel (1,1,1) went back to the new initial value -100: still tentatively occupied, so unchanged;
    # (2,2,2) is new and occupied
    assert np.allclose(layer.occupied, [[1.25, 1.25, 1.25]])


def test_map_states_follow_eq_7_thresholds():
    g = np.array([0.0, -0.1, -0.2, -300.0, -301.0, -750.0, -751.0, -1000.0])
    assert voxels.map_states(g).tolist() == [3, 3, 2, 2, 1, 1, 0, 0]


# ------------------------------------------------------------------ scene
def world() -> bytes:
    return encode(WorldModel(
        header=Header(stamp=0), scenario="test", arena=[(0, 0), (50, 0), (50, 40), (0, 40)], min_height=1,
        max_height=20, uavs=["uav1", "uav2"],
        obstacles=[Obstacle(kind="plane", center=(0, 0, 0), name="ground"),
                   Obstacle(kind="box", center=(10, 10, 2), size=(4, 4, 4), name="house"),
                   Obstacle(kind="cylinder", center=(20, 5, 0), radius=1, height=6, name="tree"),
                   Obstacle(kind="cone", center=(30, 5, 0), radius=1, height=4, name="pine"),
                   Obstacle(kind="sphere", center=(40, 5, 2), radius=1, name="rock")]))


def test_world_is_drawn_once_as_static_entities_and_registers_the_team():
    scene = SceneBuilder()
    logs = entities(scene.feed("falconry/sim/world", world()))
    for name in ("world/arena", "world/ground", "world/obstacles/boxes", "world/obstacles/cylinders",
                 "world/obstacles/cones", "world/obstacles/spheres", "uav1/state", "uav2/state"):
        assert name in logs and all(log.stamp is None for log in logs[name]), name
    assert logs["world/obstacles/boxes"][0].item.labels == ["house"]
    assert sorted(scene.uavs) == ["uav1", "uav2"] and scene.layout_changed
    assert not [log for log in scene.feed("falconry/sim/world", world()) if log.entity.startswith("world")]


def test_obstacles_the_survey_lacks_are_drawn_once_as_truth():
    scene = SceneBuilder()
    scene.feed("falconry/sim/world", world())
    wall = Obstacle(kind="box", center=(25, 20, 4), size=(20, 1, 8), name="wall")
    truth = GroundTruth(header=Header(stamp=S), step=20, obstacles=[wall])
    logs = entities(scene.feed("falconry/sim/truth", encode(truth)))
    assert logs["truth/obstacles/boxes"][0].item.labels == ["wall"] and logs["truth/obstacles/boxes"][0].stamp is None
    truth.header.stamp = 2 * S
    assert not [log for log in scene.feed("falconry/sim/truth", encode(truth)) if log.entity.startswith("truth/obst")]


def test_scan_keeps_every_flying_and_unknown_point_when_thinning():
    scene = SceneBuilder(ViewParams(scan_points=50, scan_period=0.5))
    points = np.random.default_rng(1).uniform(0, 30, (1000, 3)).astype(np.float32)
    labels = np.zeros(1000, dtype=np.uint8)
    labels[[3, 500, 999]] = voxels.FLYING
    labels[7] = voxels.UNKNOWN
    msg = LabelSet(header=Header(stamp=S), sensor_origin=(0, 0, 5), points=from_numpy(points),
                   point_labels=from_numpy(labels), voxel_size=0.5, voxels=from_numpy(np.zeros((0, 3), np.int32)),
                   voxel_labels=from_numpy(np.zeros(0, np.uint8)), voxel_weights=from_numpy(np.zeros(0, np.float32)))
    (scan,) = entities(scene.feed("falconry/uav1/labels", encode(msg)))["uav1/scan"]
    assert len(scan.item.positions) == 50 and scan.stamp == S
    red = (scan.item.colors == [230, 25, 25, 255]).all(axis=1)
    assert red.sum() == 3
    msg.header.stamp = S + S // 10  # 0.1 s later: not yet due
    assert "uav1/scan" not in entities(scene.feed("falconry/uav1/labels", encode(msg)))


def test_detections_tracks_and_lag_from_one_scan():
    scene = SceneBuilder()
    cloud_stamp = 2 * S
    labels = LabelSet(header=Header(stamp=cloud_stamp), sensor_origin=(0, 0, 5),
                      points=from_numpy(np.zeros((1, 3), np.float32)), point_labels=from_numpy(np.zeros(1, np.uint8)),
                      voxel_size=0.5, voxels=from_numpy(np.zeros((0, 3), np.int32)),
                      voxel_labels=from_numpy(np.zeros(0, np.uint8)), voxel_weights=from_numpy(np.zeros(0, np.float32)))
    scene.feed("falconry/uav1/labels", encode(labels), received=1_000_000_000)
    scene._uav("uav1").scans_received[cloud_stamp] = 1_000_000_000  # the scan arrived then
    detections = Detections(header=Header(stamp=cloud_stamp), detector="classifier",
                            positions=from_numpy(np.array([[5.0, 5.0, 5.0]])),
                            covariances=from_numpy(np.diag([0.04, 0.04, 0.01])[None]),
                            point_counts=from_numpy(np.array([12], np.int32)), extents=from_numpy(np.ones(1, np.float32)))
    logs = entities(scene.feed("falconry/uav1/detections", encode(detections), received=1_004_000_000))
    (det,) = logs["uav1/detections"]
    assert np.allclose(sorted(det.item.half_sizes[0]), [0.2, 0.4, 0.4]) and det.item.labels == ["12 pts"]
    detections.header.stamp = cloud_stamp + S // 10  # the same second: folded into one plot point
    scene.feed("falconry/uav1/detections", encode(detections))
    scene._uav("uav1").scans_received[3 * S] = 1_100_000_000
    detections.header.stamp = 3 * S  # the next second: the last one's figures are plotted
    logs = entities(scene.feed("falconry/uav1/detections", encode(detections), received=1_101_000_000))
    (count,) = logs["plots/detections/uav1"]
    assert count.item.value == 2.0 and count.stamp == 2 * S
    assert logs["plots/lag_ms/uav1/detections"][0].item.value == pytest.approx(4.0)  # the worst of t=2 s

    state = np.array([5.0, 5, 5, 1, 0, 0, 0, 0, 0])
    cov = np.eye(9) * 0.25
    tracks = Tracks(header=Header(stamp=cloud_stamp), tracks=[
        Track(id=7, state=from_numpy(state), covariance=from_numpy(cov), detections=4, confirmed=True,
              uncertainty_radius=2.5, last_detection=cloud_stamp, half_width=0.325),
        Track(id=8, state=from_numpy(state + 3), covariance=from_numpy(cov), detections=1, confirmed=False,
              uncertainty_radius=2.5, last_detection=cloud_stamp)])
    logs = entities(scene.feed("falconry/uav1/tracks", encode(tracks)))
    assert logs["uav1/tracks/confirmed"][0].item.labels == ["#7 r=2.5 m, 4 det, 0.65 m wide"]
    assert logs["uav1/tracks/tentative"][0].item.labels == ["#8 r=2.5 m, 1 det"]  # no width learnt yet
    (path,) = logs["uav1/tracks/predicted"][0].item.strips
    assert np.allclose(path[-1], [8.0, 5.0, 5.0])  # 3 s at 1 m/s
    assert logs["plots/track_uncertainty/uav1/7"][0].item.value == 2.5


def test_with_truth_detections_are_coloured_matched_or_false_and_false_ones_plotted():
    scene = SceneBuilder()
    truth = GroundTruth(header=Header(stamp=2 * S), step=40, uavs=[], targets=[
        TargetTruth(id="drone1", kind="drone", position=(10, 0, 5), velocity=(0, 0, 0), radius=0.3),
        TargetTruth(id="gone", kind="drone", position=(0, 10, 5), velocity=(0, 0, 0), radius=0.3, destroyed=True)])
    scene.feed("falconry/sim/truth", encode(truth))

    def detections(stamp):
        return encode(Detections(header=Header(stamp=stamp), detector="classifier",
                                 positions=from_numpy(np.array([[10.4, 0.3, 5.2], [0.0, 10.0, 5.0]])),
                                 covariances=from_numpy(np.tile(np.eye(3) * 0.01, (2, 1, 1))),
                                 point_counts=from_numpy(np.array([9, 4], np.int32)),
                                 extents=from_numpy(np.ones(2, np.float32))))
    (det,) = entities(scene.feed("falconry/uav1/detections", detections(2 * S)))["uav1/detections"]
    assert det.item.colors.tolist() == [list(MATCHED_COLOR), list(FALSE_COLOR)]  # a destroyed target matches nothing
    assert det.item.labels == ["9 pts, matched", "4 pts, false"]
    logs = entities(scene.feed("falconry/uav1/detections", detections(3 * S)))
    assert logs["plots/false_detections/uav1"][0].item.value == 1.0


def test_the_camera_frame_and_its_balloon_detections_are_drawn_and_judged_by_truth():
    from schemas.messages import CompressedFrame
    scene = SceneBuilder()
    scene.feed("falconry/sim/truth", encode(GroundTruth(header=Header(stamp=S), step=20, uavs=[], targets=[
        TargetTruth(id="balloon1", kind="balloon", position=(10, 0, 4), velocity=(0, 0, 0), radius=0.3)])))
    jpeg = b"\xff\xd8 a jpeg \xff\xd9"
    frame = CompressedFrame(header=Header(stamp=S), width=640, height=360, camera_pose=Pose(), fx=460.0, fy=460.0,
                            cx=320.0, cy=180.0, jpeg=jpeg)
    (image,) = entities(scene.feed("falconry/uav1/camera_jpeg", encode(frame)))["uav1/camera/image"]
    assert image.item == draw.Image(jpeg)
    seen = Detections(header=Header(stamp=S), detector="camera",
                      positions=from_numpy(np.array([[10.2, 0.1, 4.0], [20.0, 5.0, 3.0]])),
                      covariances=from_numpy(np.tile(np.eye(3) * 0.04, (2, 1, 1))),
                      point_counts=from_numpy(np.array([300, 40], np.int32)), extents=from_numpy(np.ones(2, np.float32)))
    logs = entities(scene.feed("falconry/uav1/camera_detections", encode(seen)))
    (det,) = logs["uav1/camera_detections"]
    assert det.item.colors.tolist() == [list(MATCHED_COLOR), list(FALSE_COLOR)]
    assert "uav1/detections" not in logs  # the LiDAR's detections are another entity


def test_without_truth_detections_keep_the_flying_object_colour():
    scene = SceneBuilder()
    msg = Detections(header=Header(stamp=S), detector="classifier", positions=from_numpy(np.ones((1, 3))),
                     covariances=from_numpy(np.eye(3)[None] * 0.01), point_counts=from_numpy(np.array([5], np.int32)),
                     extents=from_numpy(np.ones(1, np.float32)))
    (det,) = entities(scene.feed("falconry/uav1/detections", encode(msg)))["uav1/detections"]
    assert det.item.colors == DETECTION_COLOR and det.item.labels == ["5 pts"]


def test_map_age_is_the_scan_stamp_minus_the_map_stamp_it_was_classified_with():
    scene = SceneBuilder()

    def labels(stamp, map_stamp):
        return encode(LabelSet(header=Header(stamp=stamp), sensor_origin=(0, 0, 5), map_stamp=map_stamp,
                               points=from_numpy(np.zeros((1, 3), np.float32)),
                               point_labels=from_numpy(np.zeros(1, np.uint8)), voxel_size=0.5,
                               voxels=from_numpy(np.zeros((0, 3), np.int32)), voxel_labels=from_numpy(np.zeros(0, np.uint8)),
                               voxel_weights=from_numpy(np.zeros(0, np.float32))))
    scene.feed("falconry/uav1/labels", labels(S, 0))  # no map yet: no age
    scene.feed("falconry/uav1/labels", labels(S + S // 10, S))
    scene.feed("falconry/uav1/labels", labels(S + S // 5, S + S // 20))
    logs = entities(scene.feed("falconry/uav1/labels", labels(2 * S, 2 * S - S // 10)))
    assert logs["plots/map_age_ms/uav1"][0].item.value == pytest.approx(150.0)  # the worst of second 1


def test_status_draws_state_changes_working_area_and_forbidden_zones_with_remaining_life():
    scene = SceneBuilder()
    status = UavStatus(header=Header(stamp=10 * S), uav="uav1", state="GOING_AROUND", flying_normally=True,
                       airborne=True, position=(1, 2, 5), working_area=[(0, 0), (25, 0), (25, 40), (0, 40)],
                       forbidden_zones=[ForbiddenZoneStatus(center=(5, 5, 3), radius=4.5, expires=22 * S,
                                                            reason="CHECKING_TARGET took over 30 s")])
    logs = entities(scene.feed("falconry/uav1/status", encode(status)))
    assert logs["uav1/state"][-1].item.value == "GOING_AROUND"
    assert logs["uav1/working_area"][0].item.strips[0].shape == (5, 3)
    (zones,) = logs["uav1/forbidden_zones"]
    assert np.allclose(zones.item.half_sizes, [[4.5, 4.5, 4.5]])
    assert "12 s left" in zones.item.labels[0]
    assert "GOING_AROUND" in logs["uav1/status"][0].item.markdown
    status.header.stamp = 10 * S + S // 5  # same view, 0.2 s later: nothing new to draw
    assert scene.feed("falconry/uav1/status", encode(status)) == []
    status.header.stamp = 11 * S  # a second later the zone's remaining life is drawn again
    logs = entities(scene.feed("falconry/uav1/status", encode(status)))
    assert "11 s left" in logs["uav1/forbidden_zones"][0].item.labels[0]
    assert "uav1/state" not in logs


def test_truth_events_and_health():
    scene = SceneBuilder()
    scene.feed("falconry/sim/world", world())
    truth = GroundTruth(header=Header(stamp=5 * S), step=100,
                        uavs=[VehicleTruth(name="uav1", position=(0, 0, 5), velocity=(0, 0, 0), heading=0, airborne=True),
                              VehicleTruth(name="uav2", position=(3, 4, 5), velocity=(0, 0, 0), heading=0, airborne=True)],
                        targets=[TargetTruth(id="balloon1", kind="balloon", position=(9, 9, 3), velocity=(0, 0, 0),
                                             radius=0.3)])
    logs = entities(scene.feed("falconry/sim/truth", encode(truth)))
    assert logs["truth/targets"][0].item.labels == ["truth: balloon1"]
    assert logs["plots/nearest_partner/uav1"][0].item.value == pytest.approx(5.0)
    event = SimEvent(header=Header(stamp=6 * S), kind="target_destroyed", subject="balloon1", detail="uav2")
    logs = entities(scene.feed("falconry/sim/events", encode(event)))
    assert "balloon1 destroyed by uav2" in logs["truth/destroyed"][0].item.labels[0]
    fault = SimEvent(header=Header(stamp=7 * S), kind="fault_injected", subject="uav2/tracker", detail="kill")
    logs = entities(scene.feed("falconry/sim/events", encode(fault)))
    assert logs["uav2/events"][0].item.level == "WARN" and logs["events"][0].item.text.startswith("fault_injected")

    def health(uptime, cpu):
        return encode(ServiceHealth(header=Header(stamp=int(uptime * S)), uav="uav1", service="mapper", pid=42,
                                    uptime=uptime, state="running", cpu_time=cpu, memory=80_000_000))
    scene.feed("falconry/uav1/health/mapper", health(10.0, 2.0))
    logs = entities(scene.feed("falconry/uav1/health/mapper", health(12.0, 3.0)))
    assert logs["plots/cpu/uav1/mapper"][0].item.value == pytest.approx(50.0)


def test_bad_payloads_are_counted_and_never_raise():
    scene = SceneBuilder()
    assert scene.feed("falconry/uav1/detections", b"\x93garbage") == []
    wrong_shape = Detections(header=Header(stamp=S), detector="classifier", positions=from_numpy(np.zeros((2, 3))),
                             covariances=from_numpy(np.zeros((1, 3, 3))), point_counts=from_numpy(np.zeros(2, np.int32)),
                             extents=from_numpy(np.zeros(2, np.float32)))
    scene.feed("falconry/uav1/detections", encode(wrong_shape))
    assert scene.decode_errors == 2
    assert scene.feed("falconry/uav1/no_such_topic", b"") == []


def test_wall_clock_stamps_count_from_the_first_one_and_zones_expire_on_their_own_clock():
    scene = SceneBuilder()
    epoch = 1_790_000_000 * S
    for offset in (0, 2 * S):
        odometry = Odometry(header=Header(stamp=epoch + offset), pose=Pose(position=(1, 2, 3)))
        (pose, *_) = scene.feed("falconry/uav1/odometry", encode(odometry))
    assert pose.entity == "uav1/pose" and pose.stamp == 2 * S
    assert pose.tick is None  # no mission clock in a flight: no tick timeline
    status = UavStatus(header=Header(stamp=epoch + 3 * S), uav="uav1", state="IDLE", flying_normally=True,
                       airborne=True, position=(0, 0, 5),
                       forbidden_zones=[ForbiddenZoneStatus(center=(1, 1, 1), radius=4.5, expires=epoch + 10 * S)])
    logs = entities(scene.feed("falconry/uav1/status", encode(status)))
    assert "7 s left" in logs["uav1/forbidden_zones"][0].item.labels[0]
    assert logs["uav1/forbidden_zones"][0].stamp == 3 * S


def test_a_track_that_appears_between_draws_is_drawn_at_once():
    scene = SceneBuilder(ViewParams(track_period=1.0))

    def tracks(stamp, *ids):
        return encode(Tracks(header=Header(stamp=stamp), tracks=[
            Track(id=i, state=from_numpy(np.zeros(9)), covariance=from_numpy(np.eye(9)), detections=1,
                  confirmed=i < 10, uncertainty_radius=2.5, last_detection=stamp) for i in ids]))
    assert "uav1/tracks/confirmed" in entities(scene.feed("falconry/uav1/tracks", tracks(S, 1)))
    assert scene.feed("falconry/uav1/tracks", tracks(S + S // 5, 1)) == []  # the same set, not yet due
    logs = entities(scene.feed("falconry/uav1/tracks", tracks(S + S // 4, 1, 11)))  # a tentative one appears
    assert [len(log.item.centers) for log in logs["uav1/tracks/tentative"]] == [1]


def test_finish_draws_the_last_second_of_each_plot():
    scene = SceneBuilder()
    det = Detections(header=Header(stamp=S + 1), detector="classifier", positions=from_numpy(np.zeros((2, 3))),
                     covariances=from_numpy(np.tile(np.eye(3), (2, 1, 1))),
                     point_counts=from_numpy(np.ones(2, np.int32)), extents=from_numpy(np.ones(2, np.float32)))
    held = entities(scene.feed("falconry/uav1/detections", encode(det))).get("plots/detections/uav1", [])
    assert [log for log in held if log.stamp is not None] == []  # only the series' static style so far
    (last,) = entities(scene.finish())["plots/detections/uav1"]
    assert last.item.value == 2.0 and last.stamp == S


def test_every_map_message_updates_the_view_but_layers_are_drawn_at_the_map_rate():
    scene = SceneBuilder(ViewParams(map_period=1.0))

    def delta(stamp, index):
        return encode(VoxelMap(header=Header(stamp=stamp), snapshot=False, voxel_size=0.5, origin=(0, 0, 0),
                               shape=(40, 40, 10), indices=from_numpy(np.array([index], np.int64)),
                               values=from_numpy(np.array([0.0], np.float32))))
    first = entities(scene.feed("falconry/uav1/map", delta(S, 0)))
    assert len(first["uav1/map/occupied/0000"][0].item.centers) == 1
    assert not [e for e in entities(scene.feed("falconry/uav1/map", delta(S + S // 2, 800))) if "/map/" in e]
    later = entities(scene.feed("falconry/uav1/map", delta(2 * S, 1600)))
    assert len(later["uav1/map/occupied/0001"][0].item.centers) == 2  # the voxel of the skipped draw too


def test_a_map_snapshot_is_applied_only_when_messages_went_missing():
    scene = SceneBuilder(ViewParams(map_period=0.0))

    def voxel_map(seq, snapshot, indices):
        return encode(VoxelMap(header=Header(stamp=seq * S, seq=seq), snapshot=snapshot, voxel_size=0.5,
                               origin=(0, 0, 0), shape=(40, 40, 10), indices=from_numpy(np.array(indices, np.int64)),
                               values=from_numpy(np.zeros(len(indices), np.float32))))

    def drawn(logs):
        return sum(len(log.item.centers) for log in logs if "/map/occupied/" in log.entity)
    assert drawn(scene.feed("falconry/uav1/map", voxel_map(1, True, [0]))) == 1
    assert drawn(scene.feed("falconry/uav1/map", voxel_map(2, False, [800]))) == 1
    # in sequence: the snapshot says what the deltas said (and here would wrongly drop voxel 800)
    assert drawn(scene.feed("falconry/uav1/map", voxel_map(3, True, [0]))) == 0
    # a delta of another geometry is refused: the map is no longer exact, the next snapshot counts
    refused = encode(VoxelMap(header=Header(stamp=4 * S, seq=4), snapshot=False, voxel_size=0.5, origin=(1, 0, 0),
                              shape=(40, 40, 10), indices=from_numpy(np.array([5], np.int64)),
                              values=from_numpy(np.zeros(1, np.float32))))
    scene.feed("falconry/uav1/map", refused)
    assert not scene.uavs["uav1"].map_exact
    # and message 5 went missing: the next snapshot is the truth again
    assert drawn(scene.feed("falconry/uav1/map", voxel_map(6, False, [1600]))) == 1
    scene.feed("falconry/uav1/map", voxel_map(7, True, [0, 1600, 2400]))
    final = scene.uavs["uav1"].map
    assert final.replica.grid.reshape(-1)[[0, 800, 1600, 2400]].tolist() == [0.0, -740.0, 0.0, 0.0]
