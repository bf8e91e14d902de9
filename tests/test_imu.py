"""The simulated IMU (services/lib/imu.py): noise statistics at rest, the bias random walk, the
frame conventions, reproducibility across tick splits, and preintegration with GTSAM against the
closed-form motion, noise-free (exact to rounding) and noisy (within the σ the densities give).

Every random check runs on fixed seeds with a tolerance of about 5 standard errors of the statistic
checked, so it fails only when the model is wrong, never by chance."""
from __future__ import annotations

import math

import gtsam
import msgspec
import numpy as np
import pytest

from services.lib.imu import Imu, ImuParams, ImuSamples, TickMotion, grid_stamps
from services.simulator.specs import NS

TICK_NS = NS // 20  # the simulator's 50 ms tick
SUBSTEP_NS = NS // 100  # its 10 ms physics sub-step
NOISE_FREE = ImuParams(gyroscope_noise_density=0.0, accelerometer_noise_density=0.0, gyroscope_random_walk=0.0,
                       accelerometer_random_walk=0.0, gyroscope_bias_sigma=0.0, accelerometer_bias_sigma=0.0)
WHITE_ONLY = ImuParams(gyroscope_random_walk=0.0, accelerometer_random_walk=0.0, gyroscope_bias_sigma=0.0,
                       accelerometer_bias_sigma=0.0)


class Trajectory(msgspec.Struct, frozen=True):
    """Closed-form motion: constant world acceleration, constant yaw rate."""

    position: tuple[float, float, float] = (3.0, -4.0, 5.0)  # m at t = 0
    velocity: tuple[float, float, float] = (2.0, -1.0, 0.3)  # m/s at t = 0
    acceleration: tuple[float, float, float] = (0.8, 0.5, -0.2)  # m/s², world frame
    heading: float = 2.8  # rad at t = 0 (crosses ±π within a few seconds)
    yaw_rate: float = 0.6  # rad/s

    def position_at(self, t: float) -> np.ndarray:
        return np.add(self.position, np.multiply(self.velocity, t)) + 0.5 * np.multiply(self.acceleration, t * t)

    def velocity_at(self, t) -> np.ndarray:
        return np.add(self.velocity, np.multiply.outer(t, self.acceleration))

    def heading_at(self, t):
        return wrapped(self.heading + self.yaw_rate * np.asarray(t))

    def motion(self, start_ns: int, end_ns: int) -> TickMotion:
        """As the simulator would report it: knots at every sub-step end, headings wrapped."""
        stamps = np.arange(start_ns, end_ns + 1, SUBSTEP_NS)
        t = stamps / NS
        return TickMotion(stamps, self.velocity_at(t), self.heading_at(t))


def wrapped(angle):
    return (np.asarray(angle) + math.pi) % (2 * math.pi) - math.pi


def fly(imu: Imu, trajectory: Trajectory, duration_s: float) -> ImuSamples:
    """The IMU's samples over [0, duration) from the trajectory, tick by tick as the simulator steps."""
    ticks = [imu.samples(trajectory.motion(k * TICK_NS, (k + 1) * TICK_NS))
             for k in range(int(round(duration_s * NS)) // TICK_NS)]
    return ImuSamples(np.concatenate([s.stamps_ns for s in ticks]), np.vstack([s.accelerometer for s in ticks]),
                      np.vstack([s.gyroscope for s in ticks]))


def preintegrated(samples: ImuSamples, end_ns: int, measurements):
    """Feed the samples to GTSAM, each held until the next one's stamp (the last until end_ns)."""
    ends = np.append(samples.stamps_ns[1:], end_ns)
    for start, end, force, rate in zip(samples.stamps_ns, ends, samples.accelerometer, samples.gyroscope):
        measurements.integrateMeasurement(force, rate, (end - start) / NS)
    return measurements


def noise_params(params: ImuParams, params_type=gtsam.PreintegrationParams):
    """GTSAM's parameters for this IMU: its covariances are continuous-time densities squared."""
    gtsam_params = params_type.MakeSharedU(params.gravity)
    gtsam_params.setAccelerometerCovariance(params.accelerometer_noise_density ** 2 * np.eye(3))
    gtsam_params.setGyroscopeCovariance(params.gyroscope_noise_density ** 2 * np.eye(3))
    gtsam_params.setIntegrationCovariance(1e-12 * np.eye(3))  # no integration error: the samples are exact
    return gtsam_params


def start_state(trajectory: Trajectory) -> gtsam.NavState:
    return gtsam.NavState(gtsam.Rot3.Yaw(trajectory.heading), np.array(trajectory.position),
                          np.array(trajectory.velocity))


# ------------------------------------------------------------------ parameters
@pytest.mark.parametrize("fields, named", [
    ({"rate_hz": 50}, "rate_hz"),
    ({"rate_hz": 200.0}, "rate_hz"),
    ({"rate_hz": True}, "rate_hz"),
    ({"rate_hz": 20_000}, "rate_hz"),
    ({"gravity": 0.0}, "gravity"),
    ({"gravity": math.nan}, "gravity"),
    ({"accelerometer_noise_density": -1e-3}, "accelerometer_noise_density"),
    ({"gyroscope_noise_density": math.inf}, "gyroscope_noise_density"),
    ({"accelerometer_random_walk": math.nan}, "accelerometer_random_walk"),
    ({"gyroscope_random_walk": -1.0}, "gyroscope_random_walk"),
    ({"accelerometer_bias_sigma": -0.1}, "accelerometer_bias_sigma"),
    ({"gyroscope_bias_sigma": math.inf}, "gyroscope_bias_sigma"),
])
def test_bad_parameters_are_refused_with_a_one_line_error(fields, named):
    with pytest.raises(msgspec.ValidationError) as built:
        ImuParams(**fields)
    with pytest.raises(msgspec.ValidationError) as decoded:  # as a parameter file would give them
        msgspec.convert(fields, ImuParams)
    for error in (built.value, decoded.value):
        assert named in str(error) and "\n" not in str(error)


def test_unknown_parameters_are_refused():
    with pytest.raises(msgspec.ValidationError, match="sample_rate"):
        msgspec.convert({"sample_rate": 200}, ImuParams)


def test_defaults_are_the_documented_pixhawk_class_numbers():
    params = ImuParams()
    assert params.rate_hz == 200 and params.gravity == 9.80665
    assert params.gyroscope_noise_density == pytest.approx(1.7453e-4, rel=1e-4)  # MPU-9250: 0.01 °/s/√Hz
    assert params.accelerometer_noise_density == pytest.approx(2.942e-3, rel=1e-3)  # 300 µg/√Hz
    accelerometer, gyroscope = params.white_noise_sigmas
    assert accelerometer == pytest.approx(2.942e-3 * math.sqrt(200), rel=1e-3)
    assert gyroscope == pytest.approx(1.7453e-4 * math.sqrt(200), rel=1e-4)


@pytest.mark.parametrize("stamps, velocities, headings", [
    ([0], [[0, 0, 0]], [0]),  # a single knot spans no time
    ([0, 10, 10], np.zeros((3, 3)), [0, 0, 0]),  # not increasing
    ([0, 10], np.zeros((3, 3)), [0, 0]),  # lengths differ
    ([0, 10], [[0, 0, 0], [0, math.nan, 0]], [0, 0]),
])
def test_a_malformed_motion_is_refused(stamps, velocities, headings):
    with pytest.raises(ValueError) as error:
        TickMotion(np.array(stamps), np.array(velocities, dtype=float), np.array(headings, dtype=float))
    assert "\n" not in str(error.value)


# ------------------------------------------------------------------ the sample grid and conventions
def test_ticks_tile_the_sample_grid_without_gap_or_overlap():
    assert grid_stamps(0, TICK_NS, 200).tolist() == [k * 5_000_000 for k in range(10)]
    for rate in (100, 200, 300, 1000):
        whole = grid_stamps(0, NS, rate)
        pieces = np.concatenate([grid_stamps(k * TICK_NS, (k + 1) * TICK_NS, rate) for k in range(20)])
        assert len(whole) == rate and np.array_equal(pieces, whole)
    # Wall-clock stamps (~1.7e18 ns) stay exact: no int64 overflow on the way.
    late = grid_stamps(1_700_000_000 * NS, 1_700_000_000 * NS + TICK_NS, 300)
    assert len(late) == 15 and np.all(np.diff(late) >= 3_333_333)


def test_body_frame_is_forward_left_up_with_heading_as_yaw():
    # Facing world +y (heading π/2) and accelerating towards world +x, i.e. to its right, while turning left.
    stamps = np.array([0, SUBSTEP_NS])
    motion = TickMotion(stamps, [[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]], [math.pi / 2, math.pi / 2 + 0.001])
    samples = Imu(NOISE_FREE, np.random.default_rng(0)).samples(motion)
    np.testing.assert_allclose(samples.accelerometer[0], [0.0, -2.0, 9.80665], atol=1e-12)
    np.testing.assert_allclose(samples.gyroscope, [[0.0, 0.0, 0.1]] * 2, atol=1e-12)


def test_a_falling_vehicle_feels_no_specific_force():
    fall = Trajectory(velocity=(0.0, 0.0, 0.0), acceleration=(0.0, 0.0, -9.80665), yaw_rate=0.0)
    samples = fly(Imu(NOISE_FREE, np.random.default_rng(0)), fall, 0.1)
    np.testing.assert_allclose(samples.accelerometer, 0.0, atol=1e-12)


# ------------------------------------------------------------------ noise statistics
def test_at_rest_level_it_reads_plus_g_up_and_no_rotation_with_the_configured_noise():
    count = 20_000  # 100 s at 200 Hz
    rest = TickMotion(np.array([0, count * NS // WHITE_ONLY.rate_hz]), np.zeros((2, 3)), np.array([1.2, 1.2]))
    samples = Imu(WHITE_ONLY, np.random.default_rng(3)).samples(rest)
    assert len(samples) == count
    accelerometer_sigma, gyroscope_sigma = WHITE_ONLY.white_noise_sigmas
    for readings, truth, sigma in ((samples.accelerometer, [0.0, 0.0, 9.80665], accelerometer_sigma),
                                   (samples.gyroscope, [0.0, 0.0, 0.0], gyroscope_sigma)):
        # Mean within 5 standard errors; the sample σ within 5 of its standard errors, σ / √(2 N).
        np.testing.assert_allclose(readings.mean(axis=0), truth, rtol=0, atol=5 * sigma / math.sqrt(count))
        np.testing.assert_allclose(readings.std(axis=0) / sigma, 1.0, rtol=0, atol=5 / math.sqrt(2 * count))


def test_bias_spread_over_seeds_grows_as_density_times_root_time():
    params = ImuParams()
    seeds = range(400)
    rest = Trajectory(velocity=(0.0, 0.0, 0.0), acceleration=(0.0, 0.0, 0.0), yaw_rate=0.0)
    split_ns = NS // 4
    drifts = {0.25: [], 1.0: []}  # T (s) -> (seeds, 6) accelerometer and gyroscope bias moved since t = 0
    for seed in seeds:
        imu = Imu(params, np.random.default_rng(seed))
        switch_on = np.concatenate([imu.accelerometer_bias, imu.gyroscope_bias])
        imu.samples(rest.motion(0, split_ns))
        drifts[0.25].append(np.concatenate([imu.accelerometer_bias, imu.gyroscope_bias]) - switch_on)
        imu.samples(rest.motion(split_ns, NS))
        drifts[1.0].append(np.concatenate([imu.accelerometer_bias, imu.gyroscope_bias]) - switch_on)
    values = 3 * len(seeds)  # three axes per seed
    tolerance = 5 / math.sqrt(2 * values)  # 5 standard errors of a sample σ
    for duration, drift in drifts.items():
        drift = np.array(drift)
        for columns, density in ((slice(0, 3), params.accelerometer_random_walk),
                                 (slice(3, 6), params.gyroscope_random_walk)):
            spread = drift[:, columns].std()
            assert spread / (density * math.sqrt(duration)) == pytest.approx(1.0, abs=tolerance)


def test_switch_on_biases_have_the_configured_spread():
    params = ImuParams()
    biases = np.array([np.concatenate([imu.accelerometer_bias, imu.gyroscope_bias])
                       for imu in (Imu(params, np.random.default_rng(seed)) for seed in range(2000))])
    tolerance = 5 / math.sqrt(2 * 3 * 2000)
    assert biases[:, :3].std() / params.accelerometer_bias_sigma == pytest.approx(1.0, abs=tolerance)
    assert biases[:, 3:].std() / params.gyroscope_bias_sigma == pytest.approx(1.0, abs=tolerance)


# ------------------------------------------------------------------ reproducibility
def test_samples_do_not_depend_on_how_the_ticks_are_cut():
    trajectory = Trajectory()
    end = 4 * TICK_NS
    cuts_by_run = [[0, end], [0, TICK_NS, 2 * TICK_NS, 3 * TICK_NS, end], [0, SUBSTEP_NS, 13 * SUBSTEP_NS, end]]
    runs = []
    for cuts in cuts_by_run:
        imu = Imu(ImuParams(), np.random.default_rng(7))
        pieces = [imu.samples(trajectory.motion(a, b)) for a, b in zip(cuts[:-1], cuts[1:])]
        runs.append((np.concatenate([p.stamps_ns for p in pieces]), np.vstack([p.accelerometer for p in pieces]),
                     np.vstack([p.gyroscope for p in pieces]), imu.accelerometer_bias, imu.gyroscope_bias))
    for run in runs[1:]:
        for ours, theirs in zip(run, runs[0]):
            assert np.array_equal(ours, theirs)  # bit for bit
    other = Imu(ImuParams(), np.random.default_rng(8)).samples(trajectory.motion(0, end))
    assert not np.array_equal(other.accelerometer, runs[0][1])


def test_ticks_must_follow_each_other():
    trajectory = Trajectory()
    imu = Imu(ImuParams(), np.random.default_rng(0))
    first = imu.samples(trajectory.motion(7 * TICK_NS, 8 * TICK_NS))  # a resumed run may start anywhere
    assert first.stamps_ns[0] == 7 * TICK_NS and len(first) == 10
    with pytest.raises(ValueError, match="must start where the last ended"):
        imu.samples(trajectory.motion(9 * TICK_NS, 10 * TICK_NS))  # a tick skipped


# ------------------------------------------------------------------ preintegration with GTSAM
@pytest.mark.parametrize("rate_hz", [100, 200, 300])
def test_noise_free_preintegration_reproduces_the_closed_form_motion(rate_hz):
    # Exact, not approximate: GTSAM holds each sample over its period and rotates it with the attitude
    # at its start, which turns the point-sampled body-frame specific force back into the constant
    # a_w − g_w. So the agreement is to rounding, far inside mm and mrad, at any rate (300 Hz: uneven
    # 3.33 ms periods, each integrated over its own length).
    trajectory = Trajectory()
    duration = 2.0
    params = msgspec.structs.replace(NOISE_FREE, rate_hz=rate_hz)
    samples = fly(Imu(params, np.random.default_rng(0)), trajectory, duration)
    measurements = preintegrated(samples, int(duration * NS), gtsam.PreintegratedImuMeasurements(
        noise_params(params), gtsam.imuBias.ConstantBias()))
    predicted = measurements.predict(start_state(trajectory), gtsam.imuBias.ConstantBias())
    np.testing.assert_allclose(predicted.position(), trajectory.position_at(duration), rtol=0, atol=1e-9)
    np.testing.assert_allclose(predicted.velocity(), trajectory.velocity_at(duration), rtol=0, atol=1e-9)
    attitude = predicted.attitude()
    assert abs(wrapped(attitude.yaw() - trajectory.heading_at(duration))) < 1e-9
    assert abs(attitude.roll()) < 1e-12 and abs(attitude.pitch()) < 1e-12


def test_noise_free_preintegration_follows_the_simulators_piecewise_motion():
    # As vehicles.py integrates: each 10 ms sub-step its own acceleration and turn. At 200 Hz the samples
    # fall on the sub-step boundaries, so the velocity and heading come out as the simulator's knots
    # and the position as the exact double integral of its piecewise-constant acceleration.
    rng = np.random.default_rng(11)
    substeps = 100  # 1 s
    accelerations = rng.uniform(-4.0, 4.0, (substeps, 3))
    turns = rng.uniform(-0.02, 0.02, substeps)  # up to 2 rad/s
    h = SUBSTEP_NS / NS
    velocities = np.vstack([[1.0, 2.0, -0.5], [1.0, 2.0, -0.5] + np.cumsum(accelerations * h, axis=0)])
    headings = wrapped(np.concatenate([[-3.0], -3.0 + np.cumsum(turns)]))
    positions = np.zeros((substeps + 1, 3))
    for k in range(substeps):
        positions[k + 1] = positions[k] + velocities[k] * h + 0.5 * accelerations[k] * h * h
    stamps = np.arange(substeps + 1) * SUBSTEP_NS
    imu = Imu(NOISE_FREE, np.random.default_rng(0))
    pieces = [imu.samples(TickMotion(stamps[k:k + 6], velocities[k:k + 6], headings[k:k + 6]))
              for k in range(0, substeps, 5)]  # 50 ms ticks of five sub-steps
    samples = ImuSamples(np.concatenate([p.stamps_ns for p in pieces]), np.vstack([p.accelerometer for p in pieces]),
                         np.vstack([p.gyroscope for p in pieces]))
    measurements = preintegrated(samples, NS, gtsam.PreintegratedImuMeasurements(
        noise_params(NOISE_FREE), gtsam.imuBias.ConstantBias()))
    start = gtsam.NavState(gtsam.Rot3.Yaw(headings[0]), positions[0], velocities[0])
    predicted = measurements.predict(start, gtsam.imuBias.ConstantBias())
    np.testing.assert_allclose(predicted.position(), positions[-1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(predicted.velocity(), velocities[-1], rtol=0, atol=1e-9)
    assert abs(wrapped(predicted.attitude().yaw() - headings[-1])) < 1e-9


def prediction_errors_in_sigmas(params: ImuParams, seeds, measurements_type, params_type) -> np.ndarray:
    """(seeds, 7): the error of GTSAM's 1 s prediction from the noisy samples against the closed-form
    motion, in position (3), velocity (3) and yaw, each divided by the σ GTSAM's preintegrated
    covariance gives it. The prediction uses the IMU's true switch-on bias."""
    trajectory = Trajectory()
    duration = 1.0
    rotation = gtsam.Rot3.Yaw(trajectory.heading).matrix()  # the preintegrated deltas are in the start body frame
    errors = []
    for seed in seeds:
        imu = Imu(params, np.random.default_rng(seed))
        bias = gtsam.imuBias.ConstantBias(imu.accelerometer_bias, imu.gyroscope_bias)
        samples = fly(imu, trajectory, duration)
        gtsam_params = noise_params(params, params_type)
        if params_type is gtsam.PreintegrationCombinedParams:
            gtsam_params.setBiasAccCovariance(params.accelerometer_random_walk ** 2 * np.eye(3))
            gtsam_params.setBiasOmegaCovariance(params.gyroscope_random_walk ** 2 * np.eye(3))
        measurements = preintegrated(samples, int(duration * NS), measurements_type(gtsam_params, bias))
        predicted = measurements.predict(start_state(trajectory), bias)
        covariance = measurements.preintMeasCov()[:9, :9]  # rotation, position, velocity
        position_sigma = np.sqrt(np.diag(rotation @ covariance[3:6, 3:6] @ rotation.T))
        velocity_sigma = np.sqrt(np.diag(rotation @ covariance[6:9, 6:9] @ rotation.T))
        yaw_error = wrapped(predicted.attitude().yaw() - trajectory.heading_at(duration))
        errors.append(np.concatenate([(predicted.position() - trajectory.position_at(duration)) / position_sigma,
                                      (predicted.velocity() - trajectory.velocity_at(duration)) / velocity_sigma,
                                      [yaw_error / math.sqrt(covariance[2, 2])]]))
    return np.array(errors)


def assert_standard_normal(errors: np.ndarray) -> None:
    """Each column's mean square ~ χ²(runs) / runs: 1 ± √(2 / runs) (0.14 for 100 runs)."""
    assert np.abs(errors).max() < 5.0
    mean_square = (errors ** 2).mean(axis=0)
    assert np.all((mean_square > 0.5) & (mean_square < 1.7)), mean_square


def test_noisy_preintegration_errors_match_the_white_noise_densities():
    errors = prediction_errors_in_sigmas(WHITE_ONLY, range(100), gtsam.PreintegratedImuMeasurements,
                                         gtsam.PreintegrationParams)
    assert_standard_normal(errors)


def test_noisy_preintegration_errors_match_all_the_noise_with_the_bias_walk():
    # The default IMU: white noise, switch-on bias (given to the prediction) and its random walk,
    # which GTSAM's combined preintegration carries into the covariance of the deltas.
    errors = prediction_errors_in_sigmas(ImuParams(), range(100), gtsam.PreintegratedCombinedMeasurements,
                                         gtsam.PreintegrationCombinedParams)
    assert_standard_normal(errors)
