"""Scan rays and their uncertainty (seed 000 sec. III-C, IV-A, IV-B): the body mask, the ray ends
of eq. 20, the Jacobian of eq. 42 against numeric differentiation, p_hit of eq. 45–46."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.lib.geometry import rotation_matrix
from services.lib.lidar.models import lidar_model
from services.lib.lidar.rays import body_mask, pack_mask, ray_ends, scan_rays, unpack_mask
from services.lib.lidar.uncertainty import (hit_probability, mean_hit_probability, point_covariance, point_jacobian,
                                        roll_pitch_yaw)
from services.sensor_driver.core import small_rotation
from tests.conftest import REPO, falconry_argv


def test_a_body_in_front_of_the_sensor_masks_the_beams_that_meet_it_a_box_around_it_none():
    beams = lidar_model("os0-32-512").directions(0)
    in_front = body_mask(beams, [-0.3, -0.3, -0.5, 0.3, 0.3, -0.2])  # the frame below the sensor
    assert in_front[-1].all() and not in_front[0].any()  # the lowest beams meet it, the highest look past it
    assert not body_mask(beams, [-0.4, -0.4, -0.4, 0.4, 0.4, 0.4]).any()
    assert not body_mask(beams, []).any()
    assert np.array_equal(unpack_mask(pack_mask(in_front), in_front.shape[1]), in_front)
    assert pack_mask(in_front).shape == (32, 64)


def test_scan_rays_take_beams_from_the_model_and_unpack_the_mask():
    model = lidar_model("os0-32-512")
    points = np.full((32, 512, 3), np.nan, np.float32)
    mask = body_mask(model.directions(0), [-0.3, -0.3, -0.5, 0.3, 0.3, -0.2])
    heading = np.radians(90.0)
    rays = scan_rays(points, 512, "os0-32-512", 0, (1.0, 2.0, 3.0), (np.cos(heading / 2), 0, 0, np.sin(heading / 2)),
                     pack_mask(mask))
    assert np.allclose(rays.beams, model.directions(0).reshape(-1, 3)) and rays.points.shape == (32 * 512, 3)
    assert np.array_equal(rays.masked, mask.reshape(-1))
    assert np.allclose(rays.rotation @ [1.0, 0, 0], [0, 1.0, 0])  # the sensor's x along the world's y
    unknown = scan_rays(points, 512, "os9-1", 0, (0, 0, 0), (1, 0, 0, 0), None)
    assert unknown.beams is None and unknown.masked is None
    assert scan_rays(points, 512, "os0-64-512", 0, (0, 0, 0), (1, 0, 0, 0), None).beams is None  # another layout


def test_ray_ends_follow_eq_20():
    sensor = np.array([1.0, 2.0, 3.0])
    points = np.array([[4.0, 2.0, 3.0], [np.nan] * 3, [1.0, 2.0, 103.0], [1.0, 2.0, 3.5]])
    beams = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, 1.0]])
    ends = ray_ends(sensor, points, beams, np.array([False, False, False, True]), 20.0)
    assert np.allclose(ends, [[4.0, 2.0, 3.0], [1.0, 22.0, 3.0], [1.0, 2.0, 23.0]])


def measured_point(w: np.ndarray, direction: np.ndarray, length: float, angles) -> np.ndarray:
    """Eq. 40 with the noise vector w = (t_n, α_n, β_n, γ_n, l_n)."""
    roll, pitch, yaw = (a + n for a, n in zip(angles, w[3:6]))
    return (length + w[6]) * small_rotation(roll, pitch, yaw) @ direction + w[:3]


@pytest.mark.parametrize("angles", [(0.0, 0.0, 0.0), (0.1, -0.2, 1.3), (-0.4, 0.3, -2.5)])
def test_the_jacobian_of_eq_42_matches_numeric_differentiation(angles):
    direction = np.array([0.6, -0.48, 0.64])
    length = 17.0
    jacobian = point_jacobian(*angles, direction, length)
    step = 1e-6
    numeric = np.column_stack([
        (measured_point(step * e, direction, length, angles) - measured_point(-step * e, direction, length, angles))
        / (2 * step) for e in np.eye(7)])
    assert np.allclose(jacobian, numeric, atol=1e-6)
    assert np.allclose(roll_pitch_yaw(small_rotation(*angles)), angles)


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_roll_pitch_yaw_at_gimbal_lock_still_rebuilds_the_rotation(pitch):
    rotation = small_rotation(0.3, pitch, -1.1)
    assert np.allclose(small_rotation(*roll_pitch_yaw(rotation)), rotation)


def test_rotation_matrix_of_a_wxyz_quaternion_matches_scipy():
    for quaternion_xyzw in Rotation.random(5, random_state=2).as_quat():
        x, y, z, w = quaternion_xyzw
        expected = Rotation.from_quat(quaternion_xyzw).as_matrix()
        assert np.allclose(rotation_matrix([w, x, y, z]), expected)
        assert np.allclose(rotation_matrix([2 * w, 2 * x, 2 * y, 2 * z]), expected)  # not quite unit: normalised


def test_point_covariance_grows_with_range_under_attitude_noise():
    pose = np.diag([0.0] * 3 + [np.radians(1.0) ** 2] * 3)
    near = point_covariance(np.array([5.0, 0, 0]), np.zeros(3), np.eye(3), pose, 0.0)
    far = point_covariance(np.array([50.0, 0, 0]), np.zeros(3), np.eye(3), pose, 0.0)
    assert np.allclose(far, 100 * near)  # lateral errors grow with l: variance with l²
    assert near[0, 0] == pytest.approx(0.0, abs=1e-12)  # an attitude error does not change the range


def test_hit_probability_is_the_gaussian_mass_in_the_measured_voxel():
    rng = np.random.default_rng(5)
    point = np.array([0.3, 0.2, 0.1])
    voxel = np.zeros(3)
    assert hit_probability(point, 1e-8 * np.eye(3), voxel, 0.5) == pytest.approx(1.0, abs=1e-6)
    cov = np.array([[0.02, 0.005, 0.0], [0.005, 0.03, 0.0], [0.0, 0.0, 0.01]])
    samples = rng.multivariate_normal(point, cov, 200_000)
    monte_carlo = np.mean(np.all((samples >= 0) & (samples < 0.5), axis=1))
    assert hit_probability(point, cov, voxel, 0.5) == pytest.approx(monte_carlo, abs=0.01)


def test_hit_probability_is_the_same_every_time_lockstep_runs_depend_on_it():
    point, cov = np.array([10.2, 3.3, 5.1]), np.array([[0.05, 0.01, 0.0], [0.01, 0.03, 0.0], [0.0, 0.0, 0.02]])
    first = hit_probability(point, cov, np.array([10.0, 3.0, 5.0]), 0.5)
    assert all(hit_probability(point, cov, np.array([10.0, 3.0, 5.0]), 0.5) == first for _ in range(5))


def test_mean_hit_probability_falls_with_distance_under_attitude_noise_as_in_fig_5():
    rng = np.random.default_rng(3)
    attitude = np.diag([0.0] * 3 + [np.radians(0.5) ** 2] * 3)
    near, far = (mean_hit_probability(d, attitude, 0.02, 0.5, 60, rng) for d in (2.0, 40.0))
    assert 0.5 < near < 1.0 and far < near - 0.2
    ideal = mean_hit_probability(40.0, np.zeros((6, 6)), 0.0, 0.5, 20, rng)
    assert ideal == pytest.approx(1.0, abs=1e-6)  # no noise: every point is in its own voxel


def test_analyze_hit_probability_prints_a_table_and_draws_the_png(tmp_path):
    plot = tmp_path / "hit.png"
    result = subprocess.run(falconry_argv("analyze", "hit-probability", "--noise", "rtk=0.02,0.1,0.02",
                                          "--noise", "poor=0.3,1,0.05", "--max-distance", "20", "--step", "10",
                                          "--samples", "10", "--plot", str(plot)),
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    rows = [line.split("|") for line in result.stdout.splitlines() if line.strip()[:1].isdigit()]
    assert [float(r[0]) for r in rows] == [10.0, 20.0]
    rtk, poor = zip(*[(float(r[1]), float(r[2])) for r in rows])
    assert all(p < r for p, r in zip(poor, rtk))  # the noisier sensor hits its voxel less often
    assert plot.stat().st_size > 10_000
