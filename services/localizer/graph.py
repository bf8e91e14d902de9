"""Sensor fusion and precision steps of seed 003's Grape localizer (sec. 2.1): IMU preintegration and
the scans' plane and edge landmarks in one factor graph, solved incrementally by iSAM2 over a fixed
lag, then a rigid re-alignment of the last five scans to the map, weighted by the age of the features.

Seed 003's method, as read here:
(c) Sensor fusion. GTSAM's preintegrated IMU factor links the states of successive scans; planar and
    edge features are landmarks in the graph, as infinite planes and infinite 3-D lines; iSAM2
    optimises the graph incrementally as each scan arrives. Roll and pitch are held by gravity
    through the IMU factor.
(d) Precision. The features of the last five scans are combined and their poses optimised with one
    rigid transform against all earlier features (the map), weighting features by age, old ones
    higher, which "reduces accumulation of errors over time". Its output, "the most accurate pose
    estimate", is fed into the fusion step.

How it is done here, and why:
- One state per scan: pose X(k), world velocity V(k) and IMU bias B(k) at the scan's stamp. Between
  scans a gtsam.ImuFactor from a PreintegratedImuMeasurements (gravity GRAVITY along world −z; body
  FLU, accelerometer = specific force, as services/lib/imu.py) and a bias random-walk
  BetweenFactor with σ = walk · √Δt. The IMU's noise densities and walks default to
  services/lib/imu.py's ImuParams, the bias prior to its switch-on σ.
- IMU samples are held until the next sample's stamp (as GTSAM integrates them, and as
  tests/test_imu.py feeds them); the sample in effect at a scan's stamp is split there and carries on
  into the next interval. add_imu may run ahead of add_scan: samples at or after the scan's stamp wait.
- Planes: gtsam.OrientedPlane3 landmarks with OrientedPlane3Factor. The measurement is the feature's
  (normal, offset) in the body frame: features.py's n·x + d = 0 is GTSAM's convention too.
- Edges: GTSAM has no line landmark in Python, so a line is an anchor point (Point3) plus a
  direction (Unit3), with a gtsam.CustomFactor of four residuals: the observed centre's two
  perpendicular offsets from the line and the two components of the line's direction across the
  observed one, both in the body frame, on the observed direction's fixed tangent basis (signless:
  the line's direction is flipped toward the observation). Centre-on-line alone (2 residuals)
  would leave a single sighting's direction undetermined and needs two scans before the line
  constrains anything; with the direction term one sighting fixes all four degrees of freedom of
  an infinite line, as one plane sighting fixes a plane. The anchor may slide along its line
  without changing the residuals (a fifth, gauge, degree of freedom): a one-row factor pins its
  component along the first sighting's direction, which only fixes where on the line the anchor
  sits (the line is then parametrised by where it crosses that plane) and biases nothing.
  The residual and its Jacobians are one numba-compiled kernel (line_kernel), shared by the factor
  and the precision step: iSAM2 calls the factor back at every relinearisation, and numpy's
  per-call overhead on 3-vectors cost ten times the arithmetic (250 µs a call, against 20 µs).
- A landmark's first sighting initialises it from the state's predicted pose (the best-known
  pose); a first sighting carries no information about that pose, so only sightings of landmarks
  already in the graph ("associated" features) count toward health.
- Measurement factors take a Huber kernel (`huber_threshold` σ): a false association (the
  corridors of the paper's dataset 2) then pulls linearly rather than quadratically. (The Python
  OrientedPlane3Factor takes only a Gaussian model, so a robust plane factor is a CustomFactor
  around GTSAM's own, at the cost of a callback.)
- The start pose defines the map frame: its position and yaw priors are tight (nothing else
  observes them), so the covariance is relative to the map and does not grow as σ_yaw × the
  distance from the start; roll and pitch get a loose prior, as gravity and the planes observe them.
- iSAM2 relinearises a variable once it has moved relinearize_threshold (0.05) from its
  linearisation point, checked every update; 0.01 or an extra iteration per scan cost twice as
  much and change the 10 s test flight by under a millimetre.
- Precision step: a batch Gauss–Newton over ONE rigid correction C applied to the fused poses of
  the last `precision_window` scans, T_j ↦ C·T_j (the paper's "rigid transform"), against the
  landmarks as the smoother currently estimates them, held fixed (the map; a landmark back from
  the fixed-lag window's map is its map estimate, moved by the new sightings only as far as its map
  covariance lets them). C corrects x, y, z and yaw,
  the drift the paper's precision node is for; roll and pitch, which it leaves to gravity through
  the IMU, stay as fused (precision_roll_pitch = True corrects them too: in the tests the window's
  normals then only add noise there). Each sighting is weighted by its landmark's age (scans since
  first sighted), w = clamp(age / precision_full_weight_age, precision_min_weight, 1): old landmarks
  higher, as the seed says. (Not older scans lower: the weight goes by the feature's age, not the
  scan's.) A landmark first seen inside the window was placed from these very poses and cannot tell
  them they have drifted; one seen long ago can. Without a prior C would be unconstrained wherever
  the features are (a floor alone leaves x, y and yaw free), so its prior is the fusion step's
  marginal of the newest pose over the corrected axes: C stays put in directions the map does not see.
  The alternative, re-solving the window's full states (IMU factors and all) with age-scaled
  noise, is larger; the single rigid transform over fixed landmarks has 4 unknowns, runs vectorised
  in about a millisecond, and is what the paper describes.
- "Fed into the fusion step": the corrected newest pose is the reported pose, the pose the next
  state is predicted from (its initial value) and the pose new landmarks are placed from. It is
  NOT added to the graph as a prior factor: it reuses the plane and line measurements already in
  the graph, so a prior would count them twice and make the covariance overconfident. The reported
  covariance is therefore the fusion step's (iSAM2's marginal of the newest pose), which accounts
  for the map's own uncertainty; the Gauss–Newton covariance of C, conditional on a fixed map,
  would be too small.
- What the precision step is worth here: little. With the window's sightings and the map's priors
  in the graph, the smoother's estimate is already about the best the data allow and weighs each
  landmark by what the graph knows of it, which age weighting approximates. On the 10 s noisy test
  flight (seeds 3-6) the step moves the pose by ~3.5 mm (median) and changes the position RMS by
  −6 % to +3 % and the mean yaw error by ±0.01°: neutral within noise. It is kept, on by default,
  because it is the seed's and costs ~1-2 ms.
- Fixed-lag window: seed 003 prunes the oldest features to bound the graph on a Raspberry Pi.
  Here a gtsam.IncrementalFixedLagSmoother (iSAM2 inside) keeps the states of the last
  `smoother_lag` seconds (3 s) and the landmarks sighted in them: every new variable is stamped with
  its scan's time and a landmark is re-stamped at each sighting (the smoother's timestamp map
  updates a key it holds), so a landmark still seen stays however old it is. Whatever is older is
  marginalised: its information stays as a linear prior on what remains (GTSAM's marginal factor,
  fixed at its linearisation point). A landmark leaving the window goes to the map with its last
  estimate and marginal covariance (a line's anchor and direction each, their cross-covariance
  dropped); sighted again, it re-enters the smoother at that estimate with a prior of that
  covariance, counts as associated, and keeps its first sighting, so its age, for the precision
  step. The prior counts some information twice (sightings whose poses' marginal is also on the
  window's oldest state), so returning to old ground is somewhat overconfident; re-entering with
  no prior would make the fusion step forget the map altogether. (The smoother's Python API handles
  landmarks fine: the fall-back of periodically rebuilding a fresh iSAM2 was not needed.)
- Marginalisation in batches: whenever IncrementalFixedLagSmoother marginalises it re-orders the
  leaving variables first and re-eliminates every clique above them, i.e. the whole window when
  landmarks are seen from every state; done every scan (the smoother's own way) that cost ~100 ms
  a scan with 40 features (on the loaded machine below), 2-5 times unbounded iSAM2's. So the lag
  is held infinite (nothing leaves) until the oldest state is twice `smoother_lag` old, then one
  update marginalises all that is older than the lag: the window holds lag to 2·lag seconds of
  states (30 to 60 at 10 Hz), the updates between are plain iSAM2 ones, and one scan in a lag's
  worth (1 in 30), sometimes with the next, pays for the batch.
- Measured: time per add_scan on a 60 s flight with 40 features seen every scan (the tests'
  40-feature world on a slow straight path, default parameters), median / 90th percentile over
  scans 50-150 and 500-600, on a 2-core machine running another heavy benchmark at the same time
  (noisy). The quietest run, then the range over three loaded runs:
                      unbounded iSAM2 (before)          fixed lag, 3 s (now)
      5-15 s          11 / 12 ms   (19 / 36-40 ms)      10 / 11 ms   (10-16 / 11-30 ms)
      50-60 s         28 / 31 ms   (31-107 / 70-163)     9 / 10 ms   (10-16 / 10-27 ms)
  A batch costs its scan (or two) up to ~120 ms (~250 ms loaded): the p99 and maximum. The
  unbounded graph's time grows with the flight; the window's does not. The accuracy is unchanged:
  on the noisy 10 s test flight (seeds 3-6, marginalised from 6 s on) the worst position error is
  the same to 0.1 mm and the RMS within 0.3 mm; the 60 s flight's position RMS is 0.7 cm either way.
- Departure: the LiDAR sits at the body origin, axes aligned (the features are taken in the body
  frame). The paper tilted its lidar forward; a caller with a mounting transform moves the features
  first: association.transform_features(features, R_body_sensor, t_body_sensor).
- Health, beyond the paper (which only reports getting "lost"): "tracking" while iSAM2's position
  σ ≤ tracking_position_sigma and, when max_constraint_sigma is finite (default: not asked), the
  associated features pin the position in all three directions (1/√ of the smallest eigenvalue of
  their translation information ≤ max_constraint_sigma);
  "lost" after lost_after_scans scans in a row with no associated feature or once the position σ
  exceeds lost_position_sigma; "degraded" otherwise (e.g. a floor alone: x and y unobserved). The
  start state counts as constrained by its prior.
- The covariance is in schemas.messages.Odometry's layout, (x, y, z, roll, pitch, yaw): world-frame
  position and ZYX Euler angles, mapped from GTSAM's (body rotation, body translation) tangent.

Pure: numpy and gtsam in, numpy out; no clock, no IO, no globals.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal, Sequence

import gtsam
from gtsam.symbol_shorthand import A, B, D, P, V, X
import msgspec
import numpy as np
from numba import njit

from services.lib.geometry import GRAVITY
from services.localizer.features import EdgeFeature, Features, PlaneFeature
from services.lib.imu import ImuParams
from services.lib.runtime.clock import NS

_IMU = ImuParams()  # the simulated IMU's defaults: the noise the fusion step expects
Health = Literal["tracking", "degraded", "lost"]
_DRIFTING_AXES = np.array([2, 3, 4, 5])  # of a world perturbation (ω, v): yaw, x, y, z
_NO_LAG = 1e12  # s: the smoother's lag between its marginalisation batches (nothing leaves)
_ANCHOR_GAUGE_SIGMA = 1.0  # m: any value; it only says where on its line a line's anchor sits


class GraphParams(msgspec.Struct, forbid_unknown_fields=True):
    gravity: float = GRAVITY  # m/s², along world −z
    # IMU noise, continuous-time densities as ImuParams gives them (the MPU-9250 / PX4 SITL numbers)
    accelerometer_noise_density: float = _IMU.accelerometer_noise_density  # m/s²/√Hz
    gyroscope_noise_density: float = _IMU.gyroscope_noise_density  # rad/s/√Hz
    accelerometer_random_walk: float = _IMU.accelerometer_random_walk  # m/s³/√Hz
    gyroscope_random_walk: float = _IMU.gyroscope_random_walk  # rad/s²/√Hz
    # m/s/√Hz: the position integration's own error (GTSAM's integration covariance); a small floor
    integration_noise_density: float = 1e-4
    # Prior on the start state. Its position and yaw define the map frame (nothing else observes
    # them), so their σ are small: the reported covariance is then relative to the map, and does
    # not grow with the distance from the start as σ_yaw × distance. Gravity and the planes observe
    # roll and pitch, so their prior may be loose. Rotation σ are about the body axes (for a level
    # start: roll, pitch, yaw). The bias prior is the IMU's switch-on σ
    start_position_sigma: float = 0.001  # m
    start_yaw_sigma: float = math.radians(0.01)  # rad
    # rad, roll and pitch: what levelling by the accelerometer at rest leaves, its switch-on bias
    # over g (0.196 / 9.81 ≈ 1.1°)
    start_tilt_sigma: float = math.radians(1.0)
    start_velocity_sigma: float = 0.1  # m/s
    accelerometer_bias_sigma: float = _IMU.accelerometer_bias_sigma  # m/s²
    gyroscope_bias_sigma: float = _IMU.gyroscope_bias_sigma  # rad/s
    # Measurements (reasoned at 1 cm of range noise, flown at the sensor driver's 2 cm: FeatureParams).
    # A plane's normal from a ~1 m patch of 300 returns with 1 cm range noise is good to
    # about half a degree and its offset to millimetres, but real walls are not flat: σ allow for that
    plane_normal_sigma: float = math.radians(1.0)  # rad, each of the normal's two tangent components
    plane_offset_sigma: float = 0.02  # m
    line_distance_sigma: float = 0.03  # m, each perpendicular component of the centre's offset
    line_direction_sigma: float = math.radians(2.0)  # rad, each component across the observed direction
    huber_threshold: float = 3.0  # σ (whitened norm) where a sighting's pull turns linear; 0: none
    # A plane first seen within level_plane_max_tilt_deg of horizontal (the ground, a roof) is taken
    # to be level to level_plane_sigma (rad, each tangent component of its normal); 0: not taken.
    # Without it the world's tilt is unobserved: the first floor is placed from the start's tilt,
    # which the accelerometer's bias leaves uncertain by a degree, and a degree of tilt turns every
    # 10 m flown into 17 cm of height error (measured: 0.7 m after 30 m over the MBZIRC field)
    level_plane_sigma: float = math.radians(0.5)
    level_plane_max_tilt_deg: float = 10.0
    # iSAM2. It relinearises a variable once its estimate has moved this far (rad or m) from where
    # its factors were linearised: 0.05 costs half of 0.01 and changes the 10 s test flight by < 1 mm
    relinearize_threshold: float = 0.05
    relinearize_skip: int = 1  # relinearisation checked every this many updates
    extra_iterations: int = 0  # further iSAM2 updates per scan (each relinearises and re-solves again)
    # s: the fixed-lag smoother's window. States older than this, and landmarks not sighted for this
    # long, are marginalised, in batches once the oldest state is twice this old; the landmarks' last
    # estimates stay as the map (see the docstring). Below the precision window's span (0.5 s at
    # 10 Hz) the precision step leaves out the window's scans whose states are gone
    smoother_lag: float = 3.0
    # Precision step (d)
    precision_window: int = 5  # scans re-aligned together (seed 003: five); 0 turns the step off
    precision_full_weight_age: int = 20  # scans since first sighting at which a landmark weighs fully
    precision_min_weight: float = 0.05  # weight of a landmark first seen in this scan
    precision_iterations: int = 5  # Gauss–Newton steps at most (it converges in 2–3)
    # Correct roll and pitch too. Seed 003's precision node counters drift in x, y, z and yaw; gravity
    # holds roll and pitch through the IMU factor, and the window's normals would only add noise there
    precision_roll_pitch: bool = False
    # Health
    # m, position σ the associated features alone allow, worst direction, for "tracking"; inf: not
    # asked. Off by default: in an open field a scan often sees the floor and one wall, and the IMU
    # bridges the direction they leave open for a while; the position σ says when too long
    max_constraint_sigma: float = math.inf
    # m, iSAM2's position σ (worst direction) for "tracking". The map frame and the detections share
    # the estimate's error, so what a target interception needs is the error's growth over a pass,
    # well under this; the arena's geometry and the team's separation need the absolute σ under a metre
    tracking_position_sigma: float = 0.5
    lost_position_sigma: float = 2.0  # m, beyond this "lost"
    lost_after_scans: int = 10  # scans in a row without an associated feature: "lost" (1 s at 10 Hz)

    def __post_init__(self) -> None:
        for name in ("gravity", "accelerometer_noise_density", "gyroscope_noise_density",
                     "accelerometer_random_walk", "gyroscope_random_walk", "integration_noise_density",
                     "start_position_sigma", "start_yaw_sigma", "start_tilt_sigma", "start_velocity_sigma",
                     "accelerometer_bias_sigma", "gyroscope_bias_sigma", "plane_normal_sigma",
                     "plane_offset_sigma", "line_distance_sigma", "line_direction_sigma",
                     "relinearize_threshold", "smoother_lag", "tracking_position_sigma", "lost_position_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):  # each is a σ of a noise model or a threshold
                raise msgspec.ValidationError(f"{name} must be a finite number > 0, got {value!r}")
        if not (math.isfinite(self.level_plane_sigma) and self.level_plane_sigma >= 0
                and 0.0 <= self.level_plane_max_tilt_deg < 90.0):
            raise msgspec.ValidationError("level_plane_sigma must be finite and >= 0, level_plane_max_tilt_deg "
                                          "from 0 to below 90")
        if not (math.isfinite(self.huber_threshold) and self.huber_threshold >= 0):
            raise msgspec.ValidationError(f"huber_threshold must be a finite number >= 0, got {self.huber_threshold!r}")
        for name, least in (("relinearize_skip", 1), ("extra_iterations", 0), ("precision_window", 0),
                            ("precision_full_weight_age", 1), ("precision_iterations", 1), ("lost_after_scans", 1)):
            if getattr(self, name) < least:
                raise msgspec.ValidationError(f"{name} must be at least {least}, got {getattr(self, name)!r}")
        if not 0.0 < self.precision_min_weight <= 1.0:
            raise msgspec.ValidationError(f"precision_min_weight must be above 0 and at most 1, "
                                          f"got {self.precision_min_weight!r}")
        if not self.max_constraint_sigma > 0:  # inf allowed: not asked
            raise msgspec.ValidationError(f"max_constraint_sigma must be > 0 (inf: not asked), got {self.max_constraint_sigma!r}")
        if self.lost_position_sigma < self.tracking_position_sigma:
            raise msgspec.ValidationError("lost_position_sigma must be at least tracking_position_sigma")


def symmetric_psd(matrix: np.ndarray) -> np.ndarray | None:
    """A square float matrix made symmetric, (M + Mᵀ) / 2, if that is positive semi-definite (its
    smallest eigenvalue above −1e-9, round-off); None otherwise."""
    symmetric = (matrix + matrix.T) / 2
    return symmetric if np.linalg.eigvalsh(symmetric)[0] >= -1e-9 else None


def worst_position_sigma(covariance: np.ndarray) -> float:
    """m, the position's σ in its worst direction: √ of the largest eigenvalue of the covariance's
    position block (the first three rows and columns)."""
    return math.sqrt(max(float(np.linalg.eigvalsh(covariance[:3, :3])[-1]), 0.0))


@dataclass(frozen=True)
class Observation:
    """One feature of a scan, in the body frame, with the global id of the landmark it sights."""

    landmark_id: int  # FeatureMap's id (association.FeatureMap.add_unassociated gives them in order)
    feature: PlaneFeature | EdgeFeature  # body (= sensor) frame


@dataclass(frozen=True)
class PoseEstimate:
    stamp_ns: int
    rotation: np.ndarray  # (3, 3) body → world
    translation: np.ndarray  # (3,) m, world
    velocity: np.ndarray  # (3,) m/s, world
    covariance: np.ndarray  # (6, 6) over (x, y, z, roll, pitch, yaw), as schemas.messages.Odometry
    health: Health
    position_sigma: float  # m, iSAM2's position σ in its worst direction
    constraint_sigma: float  # m, position σ the scan's associated features alone allow (inf: unconstrained)
    associated: int  # sightings of landmarks already in the graph
    # (6,) the precision step's correction C of the fused pose, Log(C): world rotation vector (rad;
    # roll and pitch 0 unless precision_roll_pitch) and translation (m); zeros when the step is off
    correction: np.ndarray


def observations(features: Features, landmark_ids: Sequence[int]) -> list[Observation]:
    """Pairs a scan's body-frame features with their global ids, in the order association gives
    them: planes first, then edges (association.associate, FeatureMap.add_unassociated)."""
    found = (*features.planes, *features.edges)
    if len(landmark_ids) != len(found):
        raise ValueError(f"{len(found)} features but {len(landmark_ids)} landmark ids")
    return [Observation(int(landmark_id), feature) for landmark_id, feature in zip(landmark_ids, found)]


# ---------------------------------------------------------------------------------------------
# Residuals, vectorised over M sightings. Pose Jacobians are for GTSAM's right perturbation of a
# Pose3, ξ = (ω, v): R ↦ R·Exp(ω), t ↦ t + R·v; each row of the stacks is one sighting.


@dataclass(frozen=True)
class _Linearised:
    residual: np.ndarray  # (M, r)
    pose_jacobian: np.ndarray  # (M, r, 6)


@dataclass(frozen=True)
class _LineLinearised(_Linearised):
    anchor_jacobian: np.ndarray  # (M, 4, 3)
    direction_jacobian: np.ndarray  # (M, 4, 3): by the world direction vector (chain with its basis)


def tangent_basis(vectors: np.ndarray) -> np.ndarray:
    """(M, 3, 2): an orthonormal basis of the plane across each unit (M, 3) vector."""
    vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    helper = np.zeros_like(vectors)
    helper[np.arange(len(vectors)), np.abs(vectors).argmin(axis=1)] = 1.0  # least parallel axis
    first = np.cross(vectors, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return np.stack([first, np.cross(vectors, first)], axis=2)


def _skew(vectors: np.ndarray) -> np.ndarray:
    """(M, 3, 3) cross-product matrices [v]×."""
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], 1), np.stack([z, zero, -x], 1), np.stack([-y, x, zero], 1)], 1)


def plane_residuals(normals: np.ndarray, offsets: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                    measured_normals: np.ndarray, measured_offsets: np.ndarray,
                    measured_bases: np.ndarray) -> _Linearised:
    """World planes n·x + d = 0 seen from poses (R, t) against body-frame measurements: the predicted
    normal's two components across the measured one (on its basis), then offset predicted − measured."""
    body_normals = np.einsum("mji,mj->mi", rotations, normals)  # Rᵀ n
    body_offsets = offsets + np.einsum("mi,mi->m", normals, translations)  # d + n·t
    residual = np.concatenate([np.einsum("mik,mi->mk", measured_bases, body_normals),
                               (body_offsets - measured_offsets)[:, None]], axis=1)
    jacobian = np.zeros((len(normals), 3, 6))
    jacobian[:, :2, :3] = np.einsum("mik,mij->mkj", measured_bases, _skew(body_normals))  # δ(Rᵀn) = [Rᵀn]× ω
    jacobian[:, 2, 3:] = body_normals  # δ(n·t) = n·R v
    return _Linearised(residual, jacobian)


def line_residuals(anchors: np.ndarray, directions: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                   measured_directions: np.ndarray, measured_centres: np.ndarray,
                   measured_bases: np.ndarray) -> _LineLinearised:
    """World lines (anchor, unit direction) seen from poses (R, t) against body-frame measurements:
    the measured centre's offset from the line across it (2, on the measured direction's basis), then
    the line's direction across the measured one (2), flipped to the measurement's side."""
    arrays = (anchors, directions, rotations, translations, measured_directions, measured_centres, measured_bases)
    return _LineLinearised(*line_kernel(*(np.ascontiguousarray(a, dtype=np.float64) for a in arrays)))


@njit(cache=True)
def line_kernel(anchors, directions, rotations, translations, measured_directions, measured_centres,
                measured_bases):
    """line_residuals' residual (M, 4) and Jacobians: pose (M, 4, 6), anchor (M, 4, 3) and world
    direction (M, 4, 3). Compiled: the line factor calls it once per linearisation, where numpy's per-call
    overhead on 3-vectors would cost ten times the arithmetic.
    With body anchor p_b = Rᵀ(p − t), body direction d_b = Rᵀd, x = c − p_b, a = d_b·x:
    across = B_mᵀ(x − a·d_b), direction = s·B_mᵀd_b (s = ±1 toward the measured direction);
    ∂across/∂p_b = −B_mᵀ(I − d_b d_bᵀ), ∂across/∂d_b = −B_mᵀ(a·I + d_b xᵀ), ∂direction/∂d_b = s·B_mᵀ;
    δ(Rᵀy) = [Rᵀy]×ω under R ↦ R·Exp(ω), δp_b = −v under t ↦ t + R·v."""
    count = anchors.shape[0]
    residual = np.zeros((count, 4))
    pose_jacobian = np.zeros((count, 4, 6))
    anchor_jacobian = np.zeros((count, 4, 3))
    direction_jacobian = np.zeros((count, 4, 3))
    body_anchor = np.zeros(3)
    body_direction = np.zeros(3)
    offset = np.zeros(3)
    by_anchor = np.zeros((4, 3))  # ∂residual / ∂(body anchor)
    by_direction = np.zeros((4, 3))  # ∂residual / ∂(body direction)
    for m in range(count):
        rotation = rotations[m]
        for i in range(3):
            body_anchor[i] = 0.0
            body_direction[i] = 0.0
            for j in range(3):
                body_anchor[i] += rotation[j, i] * (anchors[m, j] - translations[m, j])
                body_direction[i] += rotation[j, i] * directions[m, j]
        along = 0.0
        side = 0.0
        for i in range(3):
            offset[i] = measured_centres[m, i] - body_anchor[i]
            along += body_direction[i] * offset[i]
            side += measured_directions[m, i] * body_direction[i]
        side = -1.0 if side < 0.0 else 1.0
        basis = measured_bases[m]
        for k in range(2):
            across = 0.0
            tilt = 0.0
            for i in range(3):
                across += basis[i, k] * (offset[i] - along * body_direction[i])
                tilt += basis[i, k] * body_direction[i]
            residual[m, k] = across
            residual[m, 2 + k] = side * tilt
            for j in range(3):
                by_anchor[k, j] = 0.0
                by_direction[k, j] = -basis[j, k] * along
                for i in range(3):
                    projector = (1.0 if i == j else 0.0) - body_direction[i] * body_direction[j]
                    by_anchor[k, j] -= basis[i, k] * projector
                    by_direction[k, j] -= basis[i, k] * body_direction[i] * offset[j]
                by_anchor[2 + k, j] = 0.0
                by_direction[2 + k, j] = side * basis[j, k]
        for r in range(4):
            # pose: rotation block E_d·[d_b]× + E_p·[p_b]×, translation block −E_p
            for j in range(3):
                j1, j2 = (j + 1) % 3, (j + 2) % 3  # (A·[y]×)[r, j] = A[r, j1]·y[j2] − A[r, j2]·y[j1]
                pose_jacobian[m, r, j] = (by_direction[r, j1] * body_direction[j2]
                                          - by_direction[r, j2] * body_direction[j1]
                                          + by_anchor[r, j1] * body_anchor[j2] - by_anchor[r, j2] * body_anchor[j1])
                pose_jacobian[m, r, 3 + j] = -by_anchor[r, j]
                for i in range(3):  # world anchor and direction: ∂/∂p = E_p·Rᵀ, ∂/∂d = E_d·Rᵀ
                    anchor_jacobian[m, r, j] += by_anchor[r, i] * rotation[j, i]
                    direction_jacobian[m, r, j] += by_direction[r, i] * rotation[j, i]
    return residual, pose_jacobian, anchor_jacobian, direction_jacobian


# ---------------------------------------------------------------------------------------------
# Keys and factors


# gtsam's symbol shorthands: state k's pose, velocity and IMU bias; landmark i's plane, line anchor and direction
_pose_key, _velocity_key, _bias_key = X, V, B
_plane_key, _anchor_key, _direction_key = P, A, D


def _landmark_keys(landmark_id: int, kind: type) -> tuple[int, ...]:
    return ((_plane_key(landmark_id),) if kind is PlaneFeature
            else (_anchor_key(landmark_id), _direction_key(landmark_id)))


def _value_at(values: gtsam.Values, key: int):
    kind = chr(gtsam.Symbol(key).chr())
    return (values.atOrientedPlane3(key) if kind == "p" else values.atUnit3(key) if kind == "d"
            else values.atPoint3(key))


def _plane_prior(key: int, plane: gtsam.OrientedPlane3, noise) -> gtsam.CustomFactor:
    """A prior on a plane (GTSAM's Python has none): its local coordinates at `plane`, with a
    numerical Jacobian (a map landmark re-entering the smoother: rare)."""
    def error(_factor, values: gtsam.Values, jacobians) -> np.ndarray:
        estimate = values.atOrientedPlane3(key)
        if jacobians is not None:
            step = 1e-6
            jacobians[0] = np.stack([(plane.localCoordinates(estimate.retract(step * e))
                                      - plane.localCoordinates(estimate.retract(-step * e))) / (2 * step)
                                     for e in np.eye(3)], axis=1)
        return plane.localCoordinates(estimate)

    return gtsam.CustomFactor(noise, [key], error)


def _line_factor(noise, pose_key: int, anchor_key: int, direction_key: int, edge: EdgeFeature) -> gtsam.CustomFactor:
    centre = np.asarray(edge.centre, dtype=np.float64)[None]
    direction = np.asarray(edge.direction, dtype=np.float64)[None]
    basis = tangent_basis(direction)

    def error(_factor, values: gtsam.Values, jacobians) -> np.ndarray:
        pose = values.atPose3(pose_key)
        line_direction = values.atUnit3(direction_key)
        linearised = line_residuals(values.atPoint3(anchor_key)[None], line_direction.point3()[None],
                                    pose.rotation().matrix()[None], pose.translation()[None], direction, centre, basis)
        if jacobians is not None:
            jacobians[0] = linearised.pose_jacobian[0]
            jacobians[1] = linearised.anchor_jacobian[0]
            jacobians[2] = linearised.direction_jacobian[0] @ line_direction.basis()  # Unit3: d + B·δ
        return linearised.residual[0]

    return gtsam.CustomFactor(noise, [pose_key, anchor_key, direction_key], error)


def _anchor_gauge_factor(anchor_key: int, anchor: np.ndarray, direction: np.ndarray) -> gtsam.CustomFactor:
    """Pins a line anchor's component along the first sighting's direction: the one freedom of the
    (anchor, direction) pair that moves no line."""
    anchor, direction = anchor.copy(), direction.copy()

    def error(_factor, values: gtsam.Values, jacobians) -> np.ndarray:
        if jacobians is not None:
            jacobians[0] = direction[None, :]
        return np.array([direction @ (values.atPoint3(anchor_key) - anchor)])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, _ANCHOR_GAUGE_SIGMA), [anchor_key], error)


def odometry_covariance(rotation: np.ndarray, pose_covariance: np.ndarray) -> np.ndarray:
    """(6, 6) over (x, y, z, roll, pitch, yaw) of a pose with attitude `rotation` whose GTSAM Pose3
    covariance (body rotation ω, body translation v) is `pose_covariance`: position = R·v; the ZYX
    Euler rates of the body rate ω (singular at ±90° pitch, which a multirotor never reaches)."""
    roll, pitch, _ = gtsam.Rot3(rotation).rpy()
    sin_roll, cos_roll, tan_pitch, cos_pitch = math.sin(roll), math.cos(roll), math.tan(pitch), math.cos(pitch)
    euler_rates = np.array([[1.0, sin_roll * tan_pitch, cos_roll * tan_pitch],
                            [0.0, cos_roll, -sin_roll],
                            [0.0, sin_roll / cos_pitch, cos_roll / cos_pitch]])
    jacobian = np.zeros((6, 6))
    jacobian[:3, 3:] = rotation
    jacobian[3:, :3] = euler_rates
    covariance = jacobian @ pose_covariance @ jacobian.T
    return (covariance + covariance.T) / 2


# ---------------------------------------------------------------------------------------------
# The graph


@dataclass(frozen=True)
class _Landmark:
    kind: type  # PlaneFeature or EdgeFeature
    first_state: int  # the state that first sighted it


@dataclass(frozen=True)
class _MapEntry:
    """A landmark marginalised out of the smoother: its last estimate and marginal covariances,
    by key (a plane's one key, a line's anchor and direction)."""

    values: dict[int, object]  # key -> OrientedPlane3, Point3 (ndarray) or Unit3
    covariances: dict[int, np.ndarray]


@dataclass(frozen=True)
class _ScanRecord:
    state: int
    observations: tuple[Observation, ...]


@dataclass
class _ImuStream:
    """Samples not yet integrated (at or after the last state's stamp) and the one in effect there."""

    stamps: np.ndarray
    accelerometer: np.ndarray
    gyroscope: np.ndarray
    held: tuple[np.ndarray, np.ndarray] | None = None  # (accelerometer, gyroscope) in effect at the last state
    last_stamp: int | None = None  # of the newest sample received


class LocalizerGraph:
    """Seed 003's fusion (fixed-lag iSAM2 over IMU, plane and line factors) and precision steps, one scan at a
    time: start, then add_imu with the samples as they come and add_scan with each scan's sightings."""

    def __init__(self, params: GraphParams | None = None) -> None:
        self.params = params or GraphParams()
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self.params.relinearize_threshold)
        isam_params.relinearizeSkip = self.params.relinearize_skip
        isam_params.setFactorization("QR")
        self._smoother = gtsam.IncrementalFixedLagSmoother(_NO_LAG, isam_params)
        self._oldest_state = 0  # the oldest state in the smoother
        self._preintegration_params = self._imu_params()
        self._plane_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(
            [self.params.plane_normal_sigma] * 2 + [self.params.plane_offset_sigma]))
        self._robust_plane_noise = self._robust(self._plane_noise)
        self._line_noise = self._robust(gtsam.noiseModel.Diagonal.Sigmas(np.array(
            [self.params.line_distance_sigma] * 2 + [self.params.line_direction_sigma] * 2)))
        self._landmarks: dict[int, _Landmark] = {}  # every landmark ever sighted
        self._active: set[int] = set()  # those in the smoother's window
        self._map: dict[int, _MapEntry] = {}  # those marginalised out: the map
        self._window: deque[_ScanRecord] = deque(maxlen=max(self.params.precision_window, 1))
        self._stamps: list[int] = []  # of each state
        self._scanned_start = False  # the start state has had its scan
        self._best: gtsam.NavState | None = None  # best-known newest state (after the precision step)
        self._bias = gtsam.imuBias.ConstantBias()
        self._pending = (gtsam.NonlinearFactorGraph(), gtsam.Values())  # the start's priors until the first scan
        self._imu = _ImuStream(np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty((0, 3)))
        self._unassociated_scans = 0
        self._frame_covariance = np.zeros((6, 6))  # the start pose's own uncertainty in the world (start)
        self._smoother_stamps: dict[int, float] = {}  # key -> s since the start: the smoother's timestamps

    # ------------------------------------------------------------------ public API
    @property
    def started(self) -> bool:
        return bool(self._stamps)

    def start(self, stamp_ns: int, rotation: np.ndarray, translation: np.ndarray, velocity: np.ndarray,
              frame_covariance: np.ndarray | None = None) -> None:
        """The first state: pose (body → world) and world velocity at `stamp_ns`, with the priors of
        GraphParams. Its pose defines the map frame. `frame_covariance` ((6, 6) as an estimate's;
        default none) is that pose's own uncertainty in the world when it is not a known launch
        point (a localizer restarted in flight starts at the flight controller's belief, its previous
        estimate): every estimate's covariance, position σ and so health then include it, since the
        map frame is only as good as the pose it was started at (to first order: its yaw σ is not
        carried out along the distance flown since)."""
        if self._stamps:
            raise ValueError("the graph has already started")
        stamp = _stamp(stamp_ns, "start stamp")
        rotation = _finite_array(rotation, (3, 3), "start rotation")
        if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
            raise ValueError("the start rotation is not a rotation matrix")
        pose = gtsam.Pose3(gtsam.Rot3(rotation), _finite_array(translation, (3,), "start translation"))
        velocity = _finite_array(velocity, (3,), "start velocity")
        if frame_covariance is not None:
            frame = _finite_array(frame_covariance, (6, 6), "frame covariance")
            symmetric = symmetric_psd(frame)
            if symmetric is None or not np.allclose(frame, frame.T, atol=1e-9):
                raise ValueError("the frame covariance is not symmetric positive semi-definite")
            self._frame_covariance = symmetric
        p = self.params
        factors, values = self._pending
        factors.add(gtsam.PriorFactorPose3(_pose_key(0), pose, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([p.start_tilt_sigma] * 2 + [p.start_yaw_sigma] + [p.start_position_sigma] * 3))))
        factors.add(gtsam.PriorFactorVector(_velocity_key(0), velocity,
                                            gtsam.noiseModel.Isotropic.Sigma(3, p.start_velocity_sigma)))
        factors.add(gtsam.PriorFactorConstantBias(_bias_key(0), self._bias, gtsam.noiseModel.Diagonal.Sigmas(
            np.array([p.accelerometer_bias_sigma] * 3 + [p.gyroscope_bias_sigma] * 3))))
        values.insert(_pose_key(0), pose)
        values.insert(_velocity_key(0), velocity)
        values.insert(_bias_key(0), self._bias)
        self._stamps.append(stamp)
        self._best = gtsam.NavState(pose.rotation(), pose.translation(), velocity)

    def add_imu(self, stamps_ns: np.ndarray, accelerometer: np.ndarray, gyroscope: np.ndarray) -> None:
        """IMU samples (body frame FLU: specific force m/s², angular rate rad/s), stamps strictly
        increasing across calls and not before the last scan's stamp."""
        if not self._stamps:
            raise ValueError("start the graph before adding IMU samples")
        stamps = _stamps_array(stamps_ns)
        accelerometer = _finite_array(accelerometer, (len(stamps), 3), "accelerometer samples")
        gyroscope = _finite_array(gyroscope, (len(stamps), 3), "gyroscope samples")
        if len(stamps) == 0:
            return
        if np.any(np.diff(stamps) <= 0):
            raise ValueError("IMU sample stamps must be strictly increasing")
        imu = self._imu
        if imu.last_stamp is not None and stamps[0] <= imu.last_stamp:
            raise ValueError(f"IMU sample stamped {stamps[0]} ns is not after the previous one ({imu.last_stamp} ns)")
        if stamps[0] < self._stamps[-1]:
            raise ValueError(f"IMU sample stamped {stamps[0]} ns predates the last state ({self._stamps[-1]} ns), "
                             f"whose interval is integrated")
        imu.stamps = np.concatenate([imu.stamps, stamps])
        imu.accelerometer = np.vstack([imu.accelerometer, accelerometer])
        imu.gyroscope = np.vstack([imu.gyroscope, gyroscope])
        imu.last_stamp = int(stamps[-1])

    def add_scan(self, stamp_ns: int, sightings: Sequence[Observation]) -> PoseEstimate:
        """One scan's sightings (body frame, with global landmark ids) at `stamp_ns`: a new state
        linked to the last by the IMU samples between them (the start state itself, for a scan at
        the start's stamp), the sightings' factors, a fixed-lag smoother update and the precision step."""
        if not self._stamps:
            raise ValueError("start the graph before adding scans")
        stamp = _stamp(stamp_ns, "scan stamp")
        sightings = tuple(sightings)
        self._check_sightings(sightings)
        at_start = stamp == self._stamps[0] and not self._scanned_start
        if not at_start:
            self._check_new_state(stamp)
        factors, values = self._pending  # checked: from here on the scan is taken
        self._pending = (gtsam.NonlinearFactorGraph(), gtsam.Values())
        if at_start:
            state, predicted = 0, self._best.pose()
        else:
            state = len(self._stamps)
            predicted = self._add_state(stamp, factors, values)
        self._scanned_start = True
        associated = self._add_sightings(state, predicted, sightings, factors, values)
        self._smoother_update(stamp, sightings, factors, values)
        estimate = self._estimate(_ScanRecord(state, sightings), associated)
        self._window.append(_ScanRecord(state, sightings))
        return estimate

    # ------------------------------------------------------------------ fusion step (c)
    def _smoother_update(self, stamp: int, sightings: tuple[Observation, ...], factors: gtsam.NonlinearFactorGraph,
                         values: gtsam.Values) -> None:
        """The smoother's update with this scan's factors: every new variable and every landmark
        sighted is stamped now (a re-sighting refreshes its landmark's stamp), so what is
        marginalised is the states older than the lag and the landmarks unsighted for as long.
        Those landmarks' estimates and marginal covariances go to the map first."""
        now = (stamp - self._stamps[0]) / NS
        timestamps = {key: now for key in values.keys()}
        for sighting in sightings:
            timestamps.update((key, now) for key in _landmark_keys(sighting.landmark_id, type(sighting.feature)))
        self._smoother_stamps.update(timestamps)
        # Marginalised in batches: once the oldest state is a lag past the lag, everything older
        # than the lag goes in one update; the updates between are plain iSAM2 ones (see the docstring)
        lag = self.params.smoother_lag
        oldest = (self._stamps[self._oldest_state] - self._stamps[0]) / NS
        if now - oldest <= 2 * lag:
            self._smoother.update(factors, values, timestamps)
            for _ in range(self.params.extra_iterations):
                self._smoother.update()
            return
        cutoff = now - lag  # the smoother marginalises what is stamped before this
        leaving = {landmark_id for landmark_id in self._active  # a landmark's keys share their stamp
                   if self._smoother_stamps[_landmark_keys(landmark_id, self._landmarks[landmark_id].kind)[0]]
                   < cutoff}
        if leaving:
            estimate = self._smoother.calculateEstimate()
            for landmark_id in leaving:
                keys = _landmark_keys(landmark_id, self._landmarks[landmark_id].kind)
                self._map[landmark_id] = _MapEntry(
                    {key: _value_at(estimate, key) for key in keys},
                    {key: self._smoother.marginalCovariance(key) for key in keys})
            self._active -= leaving
        self._smoother.setSmootherLag(lag)
        self._smoother.update(factors, values, timestamps)
        self._smoother.setSmootherLag(_NO_LAG)
        for _ in range(self.params.extra_iterations):
            self._smoother.update()
        for key in [key for key, at in self._smoother_stamps.items() if at < cutoff]:
            del self._smoother_stamps[key]
        self._oldest_state = bisect.bisect_left(self._stamps, self._stamps[0] + cutoff * NS)

    def _imu_params(self) -> gtsam.PreintegrationParams:
        p = self.params
        params = gtsam.PreintegrationParams.MakeSharedU(p.gravity)  # gravity along world −z
        params.setAccelerometerCovariance(p.accelerometer_noise_density ** 2 * np.eye(3))
        params.setGyroscopeCovariance(p.gyroscope_noise_density ** 2 * np.eye(3))
        params.setIntegrationCovariance(p.integration_noise_density ** 2 * np.eye(3))
        return params

    def _robust(self, noise):
        if self.params.huber_threshold == 0:
            return noise
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.params.huber_threshold),
                                              noise)

    def _add_state(self, stamp: int, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.Pose3:
        """A new state at `stamp` with its IMU and bias factors; returns its predicted pose."""
        previous, state = len(self._stamps) - 1, len(self._stamps)
        preintegrated = self._preintegrate(stamp)
        factors.add(gtsam.ImuFactor(_pose_key(previous), _velocity_key(previous), _pose_key(state),
                                    _velocity_key(state), _bias_key(previous), preintegrated))
        root_dt = math.sqrt(preintegrated.deltaTij())
        factors.add(gtsam.BetweenFactorConstantBias(
            _bias_key(previous), _bias_key(state), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(
                np.array([self.params.accelerometer_random_walk * root_dt] * 3
                         + [self.params.gyroscope_random_walk * root_dt] * 3))))
        predicted = preintegrated.predict(self._best, self._bias)  # from the precision step's pose
        values.insert(_pose_key(state), predicted.pose())
        values.insert(_velocity_key(state), predicted.velocity())
        values.insert(_bias_key(state), self._bias)
        self._stamps.append(stamp)
        return predicted.pose()

    def _check_new_state(self, stamp: int) -> None:
        if stamp <= self._stamps[-1]:
            raise ValueError(f"scan stamped {stamp} ns is not after the last one ({self._stamps[-1]} ns)")
        if self._imu.held is None and not (len(self._imu.stamps) and self._imu.stamps[0] < stamp):
            raise ValueError(f"no IMU sample before the scan stamped {stamp} ns")

    def predicted_pose(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(rotation (3, 3) body → world, translation (3,)) predicted for `stamp_ns` from the
        best-known newest state by the IMU samples received so far (the pose a scan's features are
        associated from); nothing is consumed. Before any sample, or at the last state's stamp, the
        newest state's pose."""
        if not self._stamps:
            raise ValueError("start the graph before predicting")
        stamp = _stamp(stamp_ns, "prediction stamp")
        imu = self._imu
        if stamp <= self._stamps[-1] or (imu.held is None and not len(imu.stamps)):
            pose = self._best.pose()
        else:
            preintegrated, _ = self._integrate(stamp)
            pose = preintegrated.predict(self._best, self._bias).pose()
        return pose.rotation().matrix(), pose.translation()

    def _preintegrate(self, stamp: int) -> gtsam.PreintegratedImuMeasurements:
        """The samples over [last state, stamp), each held until the next one's stamp; the one in
        effect at the last state's stamp covers the start of the interval (before any sample at all,
        the first sample does). They are consumed: the next interval starts at `stamp`."""
        preintegrated, count = self._integrate(stamp)
        imu = self._imu
        imu.held = (imu.accelerometer[count - 1], imu.gyroscope[count - 1]) if count else \
            (imu.held or (imu.accelerometer[0], imu.gyroscope[0]))
        imu.stamps, imu.accelerometer, imu.gyroscope = (imu.stamps[count:], imu.accelerometer[count:],
                                                         imu.gyroscope[count:])
        return preintegrated

    def _integrate(self, stamp: int) -> tuple[gtsam.PreintegratedImuMeasurements, int]:
        """The preintegration over [last state, stamp) and the count of samples stamped before `stamp`."""
        imu, start = self._imu, self._stamps[-1]
        count = int(np.searchsorted(imu.stamps, stamp, side="left"))  # samples stamped before the scan
        preintegrated = gtsam.PreintegratedImuMeasurements(self._preintegration_params, self._bias)
        bounds = np.concatenate([[start], imu.stamps[:count], [stamp]])
        readings = [imu.held or (imu.accelerometer[0], imu.gyroscope[0])]
        readings += list(zip(imu.accelerometer[:count], imu.gyroscope[:count]))
        for (force, rate), begin, end in zip(readings, bounds[:-1], bounds[1:]):
            if end > begin:  # the held reading spans nothing when a sample falls on the last stamp
                preintegrated.integrateMeasurement(force, rate, (end - begin) / NS)
        return preintegrated, count

    def _plane_factor(self, state: int, landmark_id: int, plane: PlaneFeature) -> gtsam.NonlinearFactor:
        factor = gtsam.OrientedPlane3Factor(np.append(plane.normal, plane.offset), self._plane_noise,
                                            _pose_key(state), _plane_key(landmark_id))
        if self._robust_plane_noise is self._plane_noise:
            return factor
        # The binding takes only a Gaussian model and cannot clone with another: a Huber kernel
        # goes on a CustomFactor that evaluates GTSAM's own plane factor (error and Jacobians).
        def error(_factor, values: gtsam.Values, jacobians) -> np.ndarray:
            return factor.unwhitenedError(values) if jacobians is None else factor.unwhitenedError(values, jacobians)

        return gtsam.CustomFactor(self._robust_plane_noise, [_pose_key(state), _plane_key(landmark_id)], error)

    def _check_sightings(self, sightings: tuple[Observation, ...]) -> None:
        kinds = {landmark_id: landmark.kind for landmark_id, landmark in self._landmarks.items()}
        for sighting in sightings:
            feature, landmark_id = sighting.feature, sighting.landmark_id
            if not isinstance(feature, (PlaneFeature, EdgeFeature)):
                raise ValueError(f"a sighting's feature must be a PlaneFeature or an EdgeFeature, got {type(feature)}")
            if isinstance(landmark_id, bool) or not isinstance(landmark_id, (int, np.integer)) or landmark_id < 0:
                raise ValueError(f"landmark ids are integers >= 0, got {landmark_id!r}")
            is_plane = isinstance(feature, PlaneFeature)
            vector = feature.normal if is_plane else feature.direction
            values = np.concatenate([np.ravel(feature.centre), np.ravel(vector), [feature.offset] if is_plane else []])
            if values.shape != (7 if is_plane else 6,) or not np.isfinite(values).all():
                raise ValueError(f"landmark {landmark_id}: a feature needs a finite (3,) centre and unit vector")
            if abs(np.linalg.norm(vector) - 1.0) > 1e-6:
                raise ValueError(f"landmark {landmark_id}: the feature's normal or direction is not unit")
            kind = kinds.setdefault(int(landmark_id), type(feature))  # also within this scan
            if kind is not type(feature):
                raise ValueError(f"landmark {landmark_id} is a {kind.__name__}, sighted as a {type(feature).__name__}")

    def _add_sightings(self, state: int, predicted: gtsam.Pose3, sightings: tuple[Observation, ...],
                       factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> list[Observation]:
        """Factors for the sightings; landmarks sighted for the first time are placed from the
        predicted pose. Returns the sightings of landmarks already in the graph."""
        associated = []
        rotation, translation = predicted.rotation().matrix(), predicted.translation()
        for sighting in sightings:
            landmark_id, feature = int(sighting.landmark_id), sighting.feature
            known = self._landmarks.get(landmark_id)
            if known is not None and known.first_state < state:
                associated.append(sighting)
            if known is not None and landmark_id not in self._active:
                self._reenter(landmark_id, factors, values)
            if isinstance(feature, PlaneFeature):
                if known is None:
                    normal = rotation @ feature.normal
                    values.insert(_plane_key(landmark_id), gtsam.OrientedPlane3(
                        gtsam.Unit3(normal), float(feature.offset - normal @ translation)))
                    self._level_prior(landmark_id, normal, factors)
                factors.add(self._plane_factor(state, landmark_id, feature))
            else:
                if known is None:
                    anchor, direction = rotation @ feature.centre + translation, rotation @ feature.direction
                    values.insert(_anchor_key(landmark_id), anchor)
                    values.insert(_direction_key(landmark_id), gtsam.Unit3(direction))
                    factors.add(_anchor_gauge_factor(_anchor_key(landmark_id), anchor, direction))
                factors.add(_line_factor(self._line_noise, _pose_key(state), _anchor_key(landmark_id),
                                         _direction_key(landmark_id), feature))
            if known is None:
                self._landmarks[landmark_id] = _Landmark(type(feature), state)
            self._active.add(landmark_id)
        return associated

    def _level_prior(self, landmark_id: int, normal: np.ndarray, factors: gtsam.NonlinearFactorGraph) -> None:
        """A new plane near horizontal is held level (GraphParams.level_plane_sigma)."""
        p = self.params
        if p.level_plane_sigma == 0 or abs(normal[2]) < math.cos(math.radians(p.level_plane_max_tilt_deg)):
            return
        level = np.array([0.0, 0.0, math.copysign(1.0, normal[2]), 0.0])  # the offset is not asked
        factors.add(gtsam.OrientedPlane3DirectionPrior(_plane_key(landmark_id), level,
                                                       gtsam.noiseModel.Isotropic.Sigma(2, p.level_plane_sigma)))

    def _reenter(self, landmark_id: int, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """A landmark of the map sighted again goes back into the smoother at its map estimate, with a
        prior of its marginal covariance when it left."""
        entry = self._map.pop(landmark_id)
        for key, value in entry.values.items():
            values.insert(key, value)
            noise = gtsam.noiseModel.Gaussian.Covariance(entry.covariances[key])
            if isinstance(value, gtsam.OrientedPlane3):
                factors.add(_plane_prior(key, value, noise))
            elif isinstance(value, gtsam.Unit3):
                factors.add(gtsam.PriorFactorUnit3(key, value, noise))
            else:
                factors.add(gtsam.PriorFactorPoint3(key, value, noise))

    # ------------------------------------------------------------------ the estimate
    def _estimate(self, scan: _ScanRecord, associated: list[Observation]) -> PoseEstimate:
        state = scan.state
        estimate = self._smoother.calculateEstimate()
        fused = estimate.atPose3(_pose_key(state))
        velocity = estimate.atVector(_velocity_key(state))
        self._bias = estimate.atConstantBias(_bias_key(state))
        pose_covariance = self._smoother.marginalCovariance(_pose_key(state))
        correction = self._precision(scan, fused, pose_covariance, estimate)
        pose = correction.compose(fused)
        velocity = correction.rotation().rotate(velocity)
        self._best = gtsam.NavState(pose.rotation(), pose.translation(), velocity)
        rotation = pose.rotation().matrix()
        covariance = odometry_covariance(rotation, pose_covariance) + self._frame_covariance
        position_sigma = worst_position_sigma(covariance)
        constraint_sigma = self.params.start_position_sigma if state == 0 else self._constraint_sigma(rotation,
                                                                                                      associated)
        self._unassociated_scans = 0 if associated or state == 0 else self._unassociated_scans + 1
        return PoseEstimate(self._stamps[state], rotation, pose.translation(), velocity, covariance,
                            self._health(position_sigma, constraint_sigma), position_sigma, constraint_sigma,
                            len(associated), gtsam.Pose3.Logmap(correction))

    def _constraint_sigma(self, rotation: np.ndarray, associated: list[Observation]) -> float:
        """Position σ (m, worst direction) the associated sightings alone allow: a plane informs
        along its normal, a line across its direction."""
        information = np.zeros((3, 3))
        for sighting in associated:
            feature = sighting.feature
            if isinstance(feature, PlaneFeature):
                normal = rotation @ feature.normal
                information += np.outer(normal, normal) / self.params.plane_offset_sigma ** 2
            else:
                direction = rotation @ feature.direction
                information += (np.eye(3) - np.outer(direction, direction)) / self.params.line_distance_sigma ** 2
        weakest = np.linalg.eigvalsh(information)[0]
        return 1.0 / math.sqrt(weakest) if weakest > 1e-9 * np.trace(information) > 0 else math.inf

    def _health(self, position_sigma: float, constraint_sigma: float) -> Health:
        p = self.params
        if self._unassociated_scans >= p.lost_after_scans or position_sigma > p.lost_position_sigma:
            return "lost"
        if constraint_sigma > p.max_constraint_sigma or position_sigma > p.tracking_position_sigma:
            return "degraded"
        return "tracking"

    # ------------------------------------------------------------------ precision step (d)
    def _precision(self, scan: _ScanRecord, fused: gtsam.Pose3, pose_covariance: np.ndarray,
                   estimate: gtsam.Values) -> gtsam.Pose3:
        """The rigid correction C of the fused poses of this scan and the window's earlier ones
        (identity when the step is off or nothing was sighted)."""
        if self.params.precision_window == 0:
            return gtsam.Pose3()
        earlier = list(self._window)[-(self.params.precision_window - 1):] if self.params.precision_window > 1 else []
        records = [*earlier, scan]
        problem = self._precision_problem(scan.state, records, estimate)
        if problem is None:
            return gtsam.Pose3()
        adjoint = fused.AdjointMap()  # right (body) perturbation → left (world) perturbation
        return align_rigidly(problem, adjoint @ pose_covariance @ adjoint.T, self.params)

    def _precision_problem(self, state: int, records: list[_ScanRecord],
                           estimate: gtsam.Values) -> "PrecisionProblem | None":
        """The window's sightings against the smoother's landmark estimates. A scan whose state the
        smoother has marginalised (a lag shorter than the window) is left out; the landmarks of the
        others are in the smoother, as they were sighted no earlier than their scan."""
        records = [r for r in records if estimate.exists(_pose_key(r.state))]  # all, unless the lag is short
        if not any(r.observations for r in records):
            return None  # no sightings in the window
        return precision_problem(records, estimate, self._landmarks, state, self.params)


# ---------------------------------------------------------------------------------------------
# Precision step (d) as pure functions


@dataclass(frozen=True)
class _SightingStack:
    """M sightings of one kind stacked: the observing pose, the landmark (world) and the measurement
    (body), with each sighting's age weight."""

    rotations: np.ndarray  # (M, 3, 3)
    translations: np.ndarray  # (M, 3)
    landmark_points: np.ndarray  # (M, 3): plane normals or line anchors
    landmark_values: np.ndarray  # (M,) plane offsets, or (M, 3) line directions
    measured_vectors: np.ndarray  # (M, 3) normals or directions
    measured_values: np.ndarray  # (M,) offsets, or (M, 3) centres
    measured_bases: np.ndarray  # (M, 3, 2)
    weights: np.ndarray  # (M,) by landmark age
    sigmas: np.ndarray  # (r,) per residual row


@dataclass(frozen=True)
class PrecisionProblem:
    planes: _SightingStack | None
    lines: _SightingStack | None


def age_weight(age_scans: np.ndarray, params: GraphParams) -> np.ndarray:
    """Seed 003's age weighting: a landmark weighs more the longer it has been in the map, linearly
    up to full weight at precision_full_weight_age scans (min weight when first seen)."""
    return np.clip(np.asarray(age_scans, dtype=np.float64) / params.precision_full_weight_age,
                   params.precision_min_weight, 1.0)


def precision_problem(records: list[_ScanRecord], estimate: gtsam.Values, landmarks: dict[int, _Landmark],
                      state: int, params: GraphParams) -> PrecisionProblem:
    """The window's sightings stacked against the landmark estimates, with age weights."""
    planes, lines = _Rows(), _Rows()
    for record in records:
        pose = estimate.atPose3(_pose_key(record.state))
        rotation, translation = pose.rotation().matrix(), pose.translation()
        for sighting in record.observations:
            feature, landmark_id = sighting.feature, sighting.landmark_id
            age = state - landmarks[landmark_id].first_state
            if isinstance(feature, PlaneFeature):
                plane = estimate.atOrientedPlane3(_plane_key(landmark_id)).planeCoefficients()
                planes.add(rotation=rotation, translation=translation, landmark_point=plane[:3],
                           landmark_value=plane[3], measured_vector=feature.normal, measured_value=feature.offset,
                           age=age)
            else:
                lines.add(rotation=rotation, translation=translation,
                          landmark_point=estimate.atPoint3(_anchor_key(landmark_id)),
                          landmark_value=estimate.atUnit3(_direction_key(landmark_id)).point3(),
                          measured_vector=feature.direction, measured_value=feature.centre, age=age)
    plane_sigmas = np.array([params.plane_normal_sigma] * 2 + [params.plane_offset_sigma])
    line_sigmas = np.array([params.line_distance_sigma] * 2 + [params.line_direction_sigma] * 2)
    return PrecisionProblem(planes.stack(plane_sigmas, params), lines.stack(line_sigmas, params))


@dataclass
class _Rows:
    """_SightingStack's fields gathered one sighting at a time."""

    rotations: list = field(default_factory=list)
    translations: list = field(default_factory=list)
    landmark_points: list = field(default_factory=list)
    landmark_values: list = field(default_factory=list)
    measured_vectors: list = field(default_factory=list)
    measured_values: list = field(default_factory=list)
    ages: list = field(default_factory=list)

    def add(self, *, rotation, translation, landmark_point, landmark_value, measured_vector, measured_value,
            age: int) -> None:
        for column, value in ((self.rotations, rotation), (self.translations, translation),
                              (self.landmark_points, landmark_point), (self.landmark_values, landmark_value),
                              (self.measured_vectors, measured_vector), (self.measured_values, measured_value),
                              (self.ages, age)):
            column.append(value)

    def stack(self, sigmas: np.ndarray, params: GraphParams) -> _SightingStack | None:
        if not self.ages:
            return None
        measured_vectors = np.array(self.measured_vectors, dtype=np.float64)
        return _SightingStack(
            rotations=np.array(self.rotations, dtype=np.float64),
            translations=np.array(self.translations, dtype=np.float64),
            landmark_points=np.array(self.landmark_points, dtype=np.float64),
            landmark_values=np.array(self.landmark_values, dtype=np.float64),
            measured_vectors=measured_vectors, measured_values=np.array(self.measured_values, dtype=np.float64),
            measured_bases=tangent_basis(measured_vectors), weights=age_weight(np.array(self.ages), params),
            sigmas=sigmas)


def _linearise(stack: _SightingStack, is_plane: bool, correction: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals (M, r) and their Jacobians (M, r, 6) by a world (left) perturbation of the
    correction, at the corrected poses C·T."""
    rotation, translation = correction.rotation().matrix(), correction.translation()
    rotations = rotation @ stack.rotations
    translations = stack.translations @ rotation.T + translation
    residuals = (plane_residuals if is_plane else line_residuals)(
        stack.landmark_points, stack.landmark_values, rotations, translations,
        stack.measured_vectors, stack.measured_values, stack.measured_bases)
    # Exp(δ)·T = T·Exp(Ad(T⁻¹)·δ): Ad(T⁻¹) = [[Rᵀ, 0], [−Rᵀ[t]×, Rᵀ]]
    transposed = rotations.transpose(0, 2, 1)
    inverse_adjoint = np.zeros((len(rotations), 6, 6))
    inverse_adjoint[:, :3, :3] = transposed
    inverse_adjoint[:, 3:, 3:] = transposed
    inverse_adjoint[:, 3:, :3] = -transposed @ _skew(translations)
    jacobians = residuals.pose_jacobian @ inverse_adjoint
    return residuals.residual / stack.sigmas, jacobians / stack.sigmas[None, :, None]


def align_rigidly(problem: PrecisionProblem, prior_covariance: np.ndarray, params: GraphParams) -> gtsam.Pose3:
    """Gauss–Newton for the rigid correction C minimising the age-weighted (and Huber-weighted)
    squared residuals of the window's sightings at C·T_j, plus ξᵀ·Λ·ξ, ξ = Log(C) (world rotation
    vector, translation), Λ the inverse of `prior_covariance` over the axes corrected: x, y, z and
    yaw, or all six with precision_roll_pitch."""
    axes = np.arange(6) if params.precision_roll_pitch else _DRIFTING_AXES
    prior_information = np.linalg.inv(prior_covariance[np.ix_(axes, axes)])  # marginal over the axes
    correction = gtsam.Pose3()
    for _ in range(params.precision_iterations):
        xi = gtsam.Pose3.Logmap(correction)[axes]
        hessian = prior_information.copy()
        gradient = prior_information @ xi
        for stack, is_plane in ((problem.planes, True), (problem.lines, False)):
            if stack is None:
                continue
            residual, jacobian = _linearise(stack, is_plane, correction)
            jacobian = jacobian[:, :, axes]
            weights = stack.weights * _huber_weights(np.linalg.norm(residual, axis=1), params.huber_threshold)
            hessian += np.einsum("m,mri,mrj->ij", weights, jacobian, jacobian)
            gradient += np.einsum("m,mri,mr->i", weights, jacobian, residual)
        step = np.zeros(6)
        step[axes] = -np.linalg.solve(hessian, gradient)
        correction = gtsam.Pose3.Expmap(step).compose(correction)
        if np.linalg.norm(step) < 1e-10:
            break
    return correction


def _huber_weights(norms: np.ndarray, threshold: float) -> np.ndarray:
    if threshold == 0:
        return np.ones_like(norms)
    return np.where(norms <= threshold, 1.0, threshold / np.maximum(norms, 1e-300))


# ---------------------------------------------------------------------------------------------
# Input checks


def _finite_array(values, shape: tuple[int, ...], name: str) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers") from None
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contain NaN or infinity")
    return array


def _stamp(stamp, name: str) -> int:
    if isinstance(stamp, bool) or not isinstance(stamp, (int, np.integer)):
        raise ValueError(f"the {name} must be integer nanoseconds, got {stamp!r}")
    return int(stamp)


def _stamps_array(stamps) -> np.ndarray:
    array = np.asarray(stamps)
    if array.ndim != 1:
        raise ValueError(f"IMU stamps must be a 1-D array, got shape {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"IMU stamps must be integer nanoseconds, got {array.dtype}")
    return array.astype(np.int64)
