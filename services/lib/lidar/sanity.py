"""Is this scan what a working LiDAR gives? (numpy, one compiled pass; the sensor driver asks it of every scan)

A scan fails when
- it has no return at all: over the ground of an arena a working sensor always sees the ground;
- (nearly) every beam that the carrier's body does not block returns (`max_return_share`): the
  sky gives no return, so a sensor whose timing went wrong shows as returns on every beam;
- returns lie outside the sensor's range limits, or are not finite in one coordinate only
  (`max_bad_share` of the returns): corrupted values, not a world;
- its number of returns jumps against the last scan that passed (share of beams by more than
  `max_share_jump`, or by a factor beyond `max_count_ratio`): from one frame to the next (100 ms)
  the world a UAV sees changes a little. Measured on the built-in arenas, every model, from the
  ground to the sweep while turning: the share moved by 0.03 at most and the count by a factor of
  1.4 at most (a mid360's sparse pattern near the ground); garbage (a random range on every beam)
  and an all-NaN scan move them by 0.4 or more, or by a factor of 2.4 or more.

The range distribution's two-sample Kolmogorov-Smirnov distance was tried as a further check and
left out: between consecutive good scans while climbing it reached 0.45, as far as garbage from a
good scan (0.27-0.6), so it separates nothing.

The reference a jump is measured against is the last scan that passed; once no scan has passed
for `rebase_after` s (a long fault, or a start after one), a scan that passes the other checks
becomes the reference again, so one bad reference cannot lock the sensor out for good.

`SensorTrust` is the consumer's side: detections made while the sensor was unhealthy, and for
`settle_time` after, are not to be trusted (neither confirmed by the tracker nor shared with the
fleet nor acted on by the job manager): the scans just after a fault may still be half broken.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from services.lib.runtime.clock import NS

SETTLE_TIME = 1.0  # s after a failing scan before detections are trusted again (tracker, job manager)


@dataclass(frozen=True)
class SanityLimits:
    max_return_share: float = 0.98  # of unblocked beams; above it: "no sky" (set > 1 indoors)
    max_bad_share: float = 0.01  # of returns out of the range limits or half finite
    max_share_jump: float = 0.15  # change of the return share against the reference scan
    max_count_ratio: float = 4.0  # change of the return count (either way) against the reference scan
    min_reference_count: int = 20  # returns the reference needs before the count ratio is tested
    rebase_after: float = 1.0  # s without a passing scan: the next one that passes the other checks is the reference

    def __post_init__(self) -> None:
        for name in ("max_return_share", "max_bad_share", "max_share_jump", "rebase_after"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.max_count_ratio > 1:
            raise ValueError(f"max_count_ratio must be > 1, got {self.max_count_ratio}")


@dataclass(frozen=True)
class ScanFigures:
    """What the checks look at in one scan."""

    beams: int  # beams the body does not block
    returns: int  # of those, with a finite return
    bad: int  # returns out of range or finite in some coordinates only

    @property
    def share(self) -> float:
        return self.returns / self.beams if self.beams else 0.0


def scan_figures(points: np.ndarray, origin, min_range: float, max_range: float,
                 blocked: np.ndarray | None = None) -> ScanFigures:
    """Figures of a (rows, cols, 3) or (N, 3) scan taken from `origin`; `blocked` (same leading
    shape, bool) marks the beams the carrier's body blocks. A return is out of range when it lies
    nearer than `min_range` or farther than `max_range` (by more than the float32 points' and the
    range noise's slack); a `max_range` <= 0 means no limits. Counted in one compiled pass: numpy's
    reductions over each point's three coordinates take some 20 times longer."""
    points = np.asarray(points)
    if points.dtype != np.float32:
        points = points.astype(np.float64)
    points = np.ascontiguousarray(points.reshape(-1, 3))
    blocked = np.zeros(len(points), dtype=np.bool_) if blocked is None else \
        np.ascontiguousarray(np.asarray(blocked, dtype=np.bool_).reshape(-1))
    if len(blocked) != len(points):
        raise ValueError(f"{len(blocked)} blocked flags for {len(points)} beams")
    slack = 1e-3 + 1e-4 * max_range  # float32 points and range noise at the limits
    near, far = (min_range - slack, max_range + slack) if max_range > 0 else (-math.inf, math.inf)
    beams, returns, bad = _count_figures(points, np.asarray(origin, dtype=np.float64).reshape(3), blocked,
                                         float(near), float(far))
    return ScanFigures(beams=int(beams), returns=int(returns), bad=int(bad))


@njit(cache=True)
def _count_figures(points, origin, blocked, near, far):
    """(open beams, returns within [near, far] of origin, returns outside it or finite in some
    coordinates only) of an (N, 3) scan."""
    beams = returns = bad = 0
    for i in range(points.shape[0]):
        if blocked[i]:
            continue
        beams += 1
        x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        fx, fy, fz = math.isfinite(x), math.isfinite(y), math.isfinite(z)
        if fx and fy and fz:
            dx, dy, dz = x - origin[0], y - origin[1], z - origin[2]
            distance = math.sqrt(dx * dx + dy * dy + dz * dz)
            if distance < near or distance > far:
                bad += 1
            else:
                returns += 1
        elif fx or fy or fz:
            bad += 1
    return beams, returns, bad


class ScanSanity:
    """The checks of the module docstring, with the reference scan they need."""

    def __init__(self, limits: SanityLimits = SanityLimits()) -> None:
        self.limits = limits
        self.reference: ScanFigures | None = None
        self.passed_at: int | None = None  # ns: stamp of the reference
        self.failures: dict[str, int] = {}  # scans failed, by check

    def check(self, stamp: int, figures: ScanFigures) -> str:
        """"" when the scan at `stamp` passes (it becomes the reference), else why it fails."""
        failed = self._absolute(figures) or self._jump(stamp, figures)
        if failed is None:
            self.reference, self.passed_at = figures, stamp
            return ""
        check, reason = failed
        self.failures[check] = self.failures.get(check, 0) + 1
        return reason

    def _absolute(self, f: ScanFigures) -> tuple[str, str] | None:
        lim = self.limits
        if f.beams and f.returns + f.bad == 0:
            return "no return", "no return on any beam"
        if f.bad > lim.max_bad_share * max(f.returns + f.bad, 1):
            return "bad returns", f"{f.bad} of {f.returns + f.bad} returns out of range or not finite"
        if f.share > lim.max_return_share:
            return "no sky", f"returns on {100 * f.share:.0f} % of beams (no sky)"
        return None

    def _jump(self, stamp: int, f: ScanFigures) -> tuple[str, str] | None:
        lim, ref = self.limits, self.reference
        if ref is None or stamp - self.passed_at > int(lim.rebase_after * NS):
            return None
        if abs(f.share - ref.share) > lim.max_share_jump:
            return "jump", f"return share jumped from {100 * ref.share:.0f} % to {100 * f.share:.0f} %"
        if ref.returns >= lim.min_reference_count:
            ratio = f.returns / ref.returns
            if not 1 / lim.max_count_ratio <= ratio <= lim.max_count_ratio:
                return "jump", f"return count jumped from {ref.returns} to {f.returns}"
        return None


class SensorTrust:
    """Whether detections of a sensor's data at some stamp can be trusted: not while its data fails
    the sanity checks, nor for `settle_time` s after the last failure."""

    def __init__(self, settle_time: float) -> None:
        if not settle_time >= 0:
            raise ValueError(f"settle_time must be >= 0, got {settle_time}")
        self.settle_ns = int(round(settle_time * NS))
        self.failed_at: int | None = None  # ns: the latest failing scan or frame
        self.failures = 0

    def note(self, stamp: int, healthy: bool) -> None:
        if not healthy:
            self.failures += 1
            self.failed_at = stamp if self.failed_at is None else max(self.failed_at, stamp)

    def trusted(self, stamp: int) -> bool:
        return self.failed_at is None or stamp - self.failed_at > self.settle_ns
