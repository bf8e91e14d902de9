"""A simulated IMU per UAV: the true motion over one simulator tick in, the accelerometer and gyroscope
samples of that tick out (seed 003 sec. 2.1's "Grape" system fused a Pixhawk Mini's IMU with GTSAM's
preintegrated IMU factor).

Pure: numpy in, numpy out; the noise comes from an injected `numpy.random.Generator`.

Measurement model (the one GTSAM's preintegration and Kalibr assume):
    accelerometer = R_wbᵀ (a_w − g_w) + b_a + η_a      (specific force, m/s²)
    gyroscope     = ω_b + b_g + η_g                    (angular rate, rad/s)
g_w = (0, 0, −g) in the simulator's world frame (z up), so a vehicle at rest reads +g along body z and
one falling freely reads 0. η is discrete white noise, σ_d = density · √rate_hz. b starts at
N(0, σ₀²) per axis and random-walks: each sample steps it by N(0, (density · √Δt)²), Δt = 1 / rate_hz.

Frames: body x forward, y left, z up (FLU) at the vehicle's point mass (no lever arm); world z up with
the heading as yaw about it, as vehicles.py and the simulator node's pose quaternion have it. The
vehicles are point masses that fly level with a heading only, so roll and pitch are taken as 0:
R_wb = Rz(heading) and ω_b = (0, 0, heading rate). A real multirotor tilts to accelerate and feels a
horizontal manoeuvre mostly along its body z; this level IMU feels it along body x and y.

The true motion of a tick (TickMotion) is given at its knots, the start of the tick and the end of each
physics sub-step, as world velocity and heading; between knots the acceleration and the yaw rate are
constant, as in the simulator's integrator. Each sample is the true value at its stamp (point sampling:
no anti-aliasing filter, no averaging over the period), stamped on a fixed grid of mission time,
j · (1 s / rate_hz). GTSAM's preintegration holds a sample over [t_j, t_j + Δt] and rotates it with the
attitude at t_j; for a world acceleration and a yaw rate constant over that period this is exact: the
specific force turns with the body, but rotated back with the attitude at t_j it is a_w − g_w again. The
simulator's 10 ms sub-steps end on the grid when rate_hz is a multiple of 100, so preintegrating the
noise-free samples then reproduces its velocity and heading to rounding; at other rates a sample that
straddles a knot holds the earlier sub-step's acceleration past it (velocity off by at most
|Δa| · Δt per knot). Positions are another matter: the simulator's semi-implicit Euler moves a
sub-step by v_end · h, not by the exact v_start · h + a h² / 2, so its position differs from the double
integral of its own acceleration by h (v − v_0) / 2 (a few cm at 10 ms and 10 m/s).

Reproducibility: the same generator seed and the same true motion give bit-identical samples however
the motion is cut into ticks, as long as the cuts fall on its knots (a tick always ends on a sub-step),
because (1) each sample's stamp comes from the absolute grid and falls in exactly one tick's half-open
window [start, end); (2) each sample draws exactly SAMPLE_DRAWS normals, in stamp order, and numpy's
Generator yields the same stream whether drawn in one call or several; (3) the biases are a left fold
(np.cumsum is sequential) continued from where the last tick left them. Not guaranteed: when anything
else draws from the injected generator (give each UAV's IMU its own, keyed like the odometry noise:
default_rng([seed, uav index, salt])); after a simulator restart (`resume`: a new stream and new
biases); when a tick is cut inside a sub-step (its acceleration is re-derived with other rounding).

Where this departs from the paper: the paper gives no IMU numbers. The white-noise densities are the
datasheet's for the Pixhawk Mini's primary IMU, the InvenSense MPU-9250 (PX4's Pixhawk Mini page; its
second IMU is an ICM-20608). The ICM-20602 is rated quieter (4 mdps/√Hz, 100 µg/√Hz): taking the
MPU-9250 errs on the side of the localizer. Datasheets give no bias
random walk, so the walks and the switch-on biases are the ones PX4's own simulator gives its Pixhawk
quadrotor (PX4-SITL_gazebo-classic, models/iris/iris.sdf.jinja), which models the in-run bias as a
Gauss-Markov process (τ = 1000 s gyroscope, 300 s accelerometer) where this is a pure random walk
(GTSAM's and Kalibr's model): the same over the localizer's horizons of seconds to minutes. The
paper's IMU data came through MAVROS from ArduCopter, as a flight controller sends it (calibrated,
low-pass filtered, at a MAVLink stream rate); these samples have no filter, vibration, scale-factor or
misalignment error, quantisation, clipping, temperature drift or time offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np

from services.lib.geometry import GRAVITY, rotate_yaw  # GRAVITY: also the unit "g" of the datasheets' µg
from services.lib.runtime.clock import NS

MIN_RATE_HZ = 100  # at least 10 samples between two of the localizer's 10 Hz LiDAR scans
MAX_RATE_HZ = 8000  # the MPU-9250's fastest gyroscope output rate
SAMPLE_DRAWS = 12  # normals per sample: accelerometer noise, gyroscope noise, then each bias step (3 each)


class ImuParams(msgspec.Struct, forbid_unknown_fields=True):
    rate_hz: int = 200  # samples per second, an integer: stamps sit on the grid j · (1 s / rate_hz)
    gravity: float = GRAVITY  # m/s²
    # White noise densities: MPU-9250 Product Specification PS-MPU-9250A-01 rev 1.0, tables 1 and 2.
    # Gyroscope "rate noise spectral density" 0.01 °/s/√Hz, in rad/s/√Hz (1.745e-4).
    gyroscope_noise_density: float = 0.01 * math.pi / 180.0
    # Accelerometer "noise power spectral density" (low-noise mode) 300 µg/√Hz, in m/s²/√Hz (2.942e-3).
    accelerometer_noise_density: float = 300e-6 * GRAVITY
    # Bias random walks: PX4-SITL_gazebo-classic models/iris/iris.sdf.jinja, the IMU plugin of PX4's
    # simulated Pixhawk quadrotor (gyroscopeRandomWalk, accelerometerRandomWalk): rad/s²/√Hz, m/s³/√Hz.
    gyroscope_random_walk: float = 3.8785e-5
    accelerometer_random_walk: float = 6.0e-3
    # Switch-on biases, σ per axis: the same file's gyroscopeTurnOnBiasSigma (0.5 °/s, in rad/s) and
    # accelerometerTurnOnBiasSigma (20 mg, in m/s²). The MPU-9250's datasheet tolerances (±5 °/s,
    # ±60-80 mg) are for the bare part; a flight controller calibrates most of that away.
    gyroscope_bias_sigma: float = 0.0087
    accelerometer_bias_sigma: float = 0.196

    def __post_init__(self) -> None:
        if isinstance(self.rate_hz, bool) or not isinstance(self.rate_hz, int) or \
                not MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ:
            raise msgspec.ValidationError(f"rate_hz must be an integer from {MIN_RATE_HZ} to {MAX_RATE_HZ} Hz, "
                                          f"got {self.rate_hz!r}")
        if not (math.isfinite(self.gravity) and self.gravity > 0):
            raise msgspec.ValidationError(f"gravity must be a positive number of m/s², got {self.gravity!r}")
        for name in ("gyroscope_noise_density", "accelerometer_noise_density", "gyroscope_random_walk",
                     "accelerometer_random_walk", "gyroscope_bias_sigma", "accelerometer_bias_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):  # 0 is allowed: a noise-free IMU for tests
                raise msgspec.ValidationError(f"{name} must be a finite number >= 0, got {value!r}")

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def white_noise_sigmas(self) -> tuple[float, float]:
        """(accelerometer m/s², gyroscope rad/s): σ of one sample's white noise, density · √rate."""
        root_rate = math.sqrt(self.rate_hz)
        return self.accelerometer_noise_density * root_rate, self.gyroscope_noise_density * root_rate

    @property
    def bias_step_sigmas(self) -> tuple[float, float]:
        """(accelerometer m/s², gyroscope rad/s): σ of the bias's step between samples, density · √Δt."""
        root_period = math.sqrt(self.period_s)
        return self.accelerometer_random_walk * root_period, self.gyroscope_random_walk * root_period


@dataclass(frozen=True)
class TickMotion:
    """The true motion of one vehicle over one tick, at its knots: the tick's start, then the end of
    each physics sub-step. Acceleration and yaw rate are constant between knots; a sub-step turns by
    less than π (the heading rate limit times 10 ms is far less)."""

    stamps_ns: np.ndarray  # (K + 1,) int64 mission time, strictly increasing, K >= 1
    velocities: np.ndarray  # (K + 1, 3) m/s, world frame
    headings: np.ndarray  # (K + 1,) rad, yaw about world z (wrapped or not)

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        velocities = np.asarray(self.velocities, dtype=np.float64).reshape(-1, 3)
        headings = np.asarray(self.headings, dtype=np.float64).reshape(-1)
        if len(stamps) < 2 or len(velocities) != len(stamps) or len(headings) != len(stamps):
            raise ValueError(f"a tick's motion needs K + 1 >= 2 stamps, velocities and headings, "
                             f"got {len(stamps)}, {len(velocities)} and {len(headings)}")
        if not np.all(np.diff(stamps) > 0):
            raise ValueError("a tick's motion needs strictly increasing stamps")
        if not (np.isfinite(velocities).all() and np.isfinite(headings).all()):
            raise ValueError("a tick's motion contains non-finite velocities or headings")
        object.__setattr__(self, "stamps_ns", stamps)  # frozen: store the validated arrays
        object.__setattr__(self, "velocities", velocities)
        object.__setattr__(self, "headings", headings)

    @property
    def start_ns(self) -> int:
        return int(self.stamps_ns[0])

    @property
    def end_ns(self) -> int:
        return int(self.stamps_ns[-1])

    def accelerations(self) -> np.ndarray:
        """(K, 3) m/s², world frame: each sub-step's constant acceleration."""
        return np.diff(self.velocities, axis=0) / self._durations()[:, None]

    def yaw_rates(self) -> np.ndarray:
        """(K,) rad/s: each sub-step's constant heading rate (the short way round)."""
        turns = (np.diff(self.headings) + math.pi) % (2 * math.pi) - math.pi
        return turns / self._durations()

    def _durations(self) -> np.ndarray:
        return np.diff(self.stamps_ns) / NS


@dataclass(frozen=True)
class ImuSamples:
    """One tick's IMU samples, body frame (FLU)."""

    stamps_ns: np.ndarray  # (N,) int64 mission time of each sample
    accelerometer: np.ndarray  # (N, 3) m/s², specific force
    gyroscope: np.ndarray  # (N, 3) rad/s, angular rate

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @classmethod
    def empty(cls) -> ImuSamples:
        """No samples: what an IMU gives over no time."""
        return cls(np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty((0, 3)))


class Imu:
    """One UAV's IMU: its biases and its own generator. Feed it every tick's motion in order."""

    def __init__(self, params: ImuParams, rng: np.random.Generator) -> None:
        self.params = params
        self._rng = rng
        switch_on = rng.standard_normal(6)  # the generator's first draws, before any sample's
        self._accelerometer_bias = params.accelerometer_bias_sigma * switch_on[:3]
        self._gyroscope_bias = params.gyroscope_bias_sigma * switch_on[3:]
        self._end_ns: int | None = None  # where the last tick's motion ended

    @property
    def accelerometer_bias(self) -> np.ndarray:
        """(3,) m/s²: the bias the next sample carries."""
        return self._accelerometer_bias.copy()

    @property
    def gyroscope_bias(self) -> np.ndarray:
        """(3,) rad/s: the bias the next sample carries."""
        return self._gyroscope_bias.copy()

    def samples(self, motion: TickMotion) -> ImuSamples:
        """The samples stamped in [motion start, motion end). Ticks must follow each other without gap
        or overlap: a skipped tick would shift every later sample's noise."""
        if self._end_ns is not None and motion.start_ns != self._end_ns:
            raise ValueError(f"the IMU's next motion must start where the last ended ({self._end_ns} ns), "
                             f"got {motion.start_ns} ns")
        params = self.params
        stamps = grid_stamps(motion.start_ns, motion.end_ns, params.rate_hz)
        specific_force, angular_rate = true_readings(motion, stamps, params.gravity)
        draws = self._rng.standard_normal((len(stamps), SAMPLE_DRAWS))
        accelerometer_sigma, gyroscope_sigma = params.white_noise_sigmas
        accelerometer_step, gyroscope_step = params.bias_step_sigmas
        accelerometer_biases = _random_walk(self._accelerometer_bias, accelerometer_step * draws[:, 6:9])
        gyroscope_biases = _random_walk(self._gyroscope_bias, gyroscope_step * draws[:, 9:12])
        accelerometer = specific_force + accelerometer_biases[:-1] + accelerometer_sigma * draws[:, 0:3]
        gyroscope = angular_rate + gyroscope_biases[:-1] + gyroscope_sigma * draws[:, 3:6]
        self._accelerometer_bias, self._gyroscope_bias = accelerometer_biases[-1], gyroscope_biases[-1]
        self._end_ns = motion.end_ns
        return ImuSamples(stamps, accelerometer, gyroscope)


def grid_stamps(start_ns: int, end_ns: int, rate_hz: int) -> np.ndarray:
    """(N,) int64: the stamps floor(j · NS / rate_hz) that lie in [start_ns, end_ns). Half-open, so
    consecutive ticks share no sample and miss none."""
    first = -(-start_ns * rate_hz // NS)  # ceil(start · rate / NS): floor(j · NS / rate) >= start from here
    stop = -(-end_ns * rate_hz // NS)
    j = np.arange(first, stop, dtype=np.int64)
    return (j // rate_hz) * NS + (j % rate_hz) * NS // rate_hz  # = floor(j · NS / rate) without overflow


def true_readings(motion: TickMotion, stamps_ns: np.ndarray, gravity: float) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (specific force (N, 3) m/s², angular rate (N, 3) rad/s), body frame, at stamps inside
    the motion's span: the values of the sub-step each stamp starts (a knot begins the next one)."""
    segment = np.searchsorted(motion.stamps_ns, stamps_ns, side="right") - 1
    yaw_rates = motion.yaw_rates()[segment]
    elapsed = (stamps_ns - motion.stamps_ns[segment]) / NS
    headings = motion.headings[segment] + yaw_rates * elapsed
    world_force = motion.accelerations()[segment] + np.array([0.0, 0.0, gravity])  # a_w − g_w
    specific_force = rotate_yaw(world_force, -headings)  # R_wbᵀ f_w: a level body turned by its heading
    angular_rate = np.zeros((len(stamps_ns), 3))
    angular_rate[:, 2] = yaw_rates  # level flight: the body rate is the heading rate about z
    return specific_force, angular_rate


def _random_walk(start: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N + 1, 3): start, then start plus the steps added one at a time. np.cumsum is a sequential
    left fold, so a walk cut into pieces and continued from each end gives the same floats."""
    return np.cumsum(np.vstack([start[None, :], steps]), axis=0)
