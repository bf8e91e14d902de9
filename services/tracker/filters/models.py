"""The constant-acceleration motion and measurement model of seed 000 (sec. III-F1, eq. 24-31),
the uncertainty radius of eq. 26, and the covariance algebra the filters share.

State layout (eq. 24-25): x = [r, v, a], nine components, position first. Pure numpy.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.lib.tracks import manoeuvre_path
from services.tracker.filters.base import NS
from services.tracker.filters.turning import Turn

STATE_SIZE = 9
# Eq. 30: the measurement (a cluster centroid) is the position.
MEASUREMENT_MATRIX = np.hstack([np.eye(3), np.zeros((3, 6))])
MEASUREMENT_MATRIX.flags.writeable = False


def transition(dt: float) -> np.ndarray:
    """State-transition matrix of the constant-acceleration model over `dt` seconds (eq. 27):
    [[I, Δt I, Δt²/2 I], [0, I, Δt I], [0, 0, I]] (filled in place: np.block takes 10x longer,
    and every prediction builds one)."""
    f = np.eye(STATE_SIZE)
    axes = np.arange(6)
    f[axes, axes + 3] = dt  # position from velocity, velocity from acceleration
    f[axes[:3], axes[:3] + 6] = 0.5 * dt * dt  # position from acceleration
    return f


def process_noise(rates: Sequence[float] | np.ndarray, dt: float) -> np.ndarray:
    """Process noise covariance Ξ over `dt` seconds (eq. 31): diag(q_r I, q_v I, q_a I) · dt, with
    `rates` = (q_r, q_v, q_a) the variances each component gains per second.

    The seed prints Ξ without dt: the same covariance for every step. That only holds for a fixed
    scan rate. Our steps are irregular (a detection predicted to the next scan in the buffer may be
    a few ms away, a coasting track a whole second), and a per-step Ξ makes the uncertainty depend
    on how many steps a span was cut into rather than on its length: predicting 0.1 s as ten 10 ms
    steps would add ten times the noise. Noise per second times dt (a random walk in each component)
    adds up the same however the span is cut, and equals the seed's Ξ at its own scan period when
    the rates are Ξ²/period. The seed's implementation defaults (0.01, 0.8, 0.05) are used as
    per-second variances."""
    per_component = np.repeat(np.asarray(rates, dtype=np.float64).reshape(3), 3)
    return np.diag(per_component * dt)


def seconds_between(earlier: int, later: int) -> float:
    """(later - earlier) in s, from int ns stamps."""
    return (later - earlier) / NS


def uncertainty_radius(covariance: np.ndarray, r_min: float, c_r: float) -> float:
    """Eq. 26: r = max(r_min, c_r · cbrt(det(H P Hᵀ))) for a state covariance P (9, 9) (or the
    position block (3, 3) itself). The determinant is clamped at 0: rounding can make that of a
    nearly singular PSD block slightly negative, whose cube root would be a negative radius."""
    position = np.asarray(covariance, dtype=np.float64)[:3, :3]
    det = max(float(np.linalg.det(position)), 0.0)
    return float(max(r_min, c_r * np.cbrt(det)))


# -- covariance algebra --------------------------------------------------------------------------

def symmetrised(matrix: np.ndarray) -> np.ndarray:
    """(M + Mᵀ) / 2: rounding makes products like F P Fᵀ drift from symmetry, which the next
    Cholesky factorisation or eigendecomposition would take as part of the matrix."""
    return 0.5 * (matrix + matrix.T)


def clipped_eigenvalues(matrix: np.ndarray, low: float, high: float = np.inf) -> np.ndarray:
    """The symmetric matrix with its eigenvalues clipped to [low, high] (same eigenvectors): the
    nearest matrix (in the Frobenius norm) with low·I ≤ M ≤ high·I in the Loewner order."""
    values, vectors = np.linalg.eigh(symmetrised(matrix))
    return symmetrised((vectors * np.clip(values, low, high)) @ vectors.T)


def covariance_at_least(covariance: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """A covariance ≥ both `covariance` and `floor` in the Loewner order: floor + the positive part
    of (covariance - floor). Unlike raising only the variances, it keeps every direction at least as
    uncertain as the floor says (a thin detection covariance stays thin only where the floor is)."""
    excess = clipped_eigenvalues(np.asarray(covariance, dtype=np.float64) - floor, 0.0)
    return symmetrised(floor + excess)


def bounded_in_units_of(matrix: np.ndarray, unit: np.ndarray, low: float, high: float) -> np.ndarray:
    """`matrix` with low·unit ≤ M ≤ high·unit in the Loewner order, for a diagonal positive `unit`
    (given as its diagonal): the eigenvalues of unit^-½ M unit^-½ clipped to [low, high]. Symmetric
    and positive semi-definite whatever the input (for low ≥ 0)."""
    scale = np.sqrt(np.asarray(unit, dtype=np.float64))
    normalised = matrix / np.outer(scale, scale)
    return clipped_eigenvalues(normalised, low, high) * np.outer(scale, scale)


def turning_path(mean: np.ndarray, step: float, count: int, manoeuvre_time: float, turn: Turn | None) -> np.ndarray:
    """(count, 3) predicted positions every `step` s ahead of a position-velocity-acceleration
    state turning as `turn` says (filters/turning.py): horizontally a coordinated turn from its
    heading now at a constant rate and the state's horizontal speed, vertically manoeuvre_path.
    Without a turn, manoeuvre_path. On a 4 m circle at 3.2 m/s Singer's model alone, straight on
    after τ, is 2.7 m off 2 s ahead even with the true acceleration; the turn keeps the circle.

    The speed is held through the turn: there the filter's acceleration is a lagging mix of the
    centripetal part and noise (0.8 m/s² along the track on the mast's circle, which the drone
    never had; faded in as Singer's model would, it put the prediction 1.0 m off 2 s ahead
    instead of 0.2 m)."""
    m = np.asarray(mean, dtype=np.float64).reshape(-1)
    straight = manoeuvre_path(m, step, count, manoeuvre_time)
    if turn is None:
        return straight
    t = step * np.arange(1, count + 1, dtype=np.float64)
    speed = float(np.hypot(m[3], m[4]))
    # the arc of radius speed/ω from the heading now, in closed form
    rate = turn.rate
    along = speed * np.sin(rate * t) / rate
    across = speed * (1.0 - np.cos(rate * t)) / rate
    out = straight.copy()
    out[:, 0] = m[0] + along * np.cos(turn.heading) - across * np.sin(turn.heading)
    out[:, 1] = m[1] + along * np.sin(turn.heading) + across * np.cos(turn.heading)
    return out


def manoeuvre_state(mean: np.ndarray, elapsed: float, manoeuvre_time: float) -> np.ndarray:
    """(9,) the position-velocity-acceleration state `elapsed` s after `mean` under the same
    fading-acceleration model as manoeuvre_path: a(t) = a e^(-t/τ), v(t) = v + a τ (1 - e^(-t/τ))."""
    m = np.asarray(mean, dtype=np.float64).reshape(-1)
    t = float(elapsed)
    (position,) = manoeuvre_path(m, t, 1, manoeuvre_time)
    if np.isinf(manoeuvre_time):
        gained, fade = t, 1.0
    else:
        fade = float(np.exp(-t / manoeuvre_time))
        gained = manoeuvre_time * (1.0 - fade)
    return np.concatenate([position, m[3:6] + m[6:9] * gained, m[6:9] * fade])
