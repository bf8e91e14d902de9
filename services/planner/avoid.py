"""Manoeuvres kept clear of what the UAV knows is occupied (pure: numpy in, numpy out).

Every plan is made in three steps, each a small part of its own:
1. **route**: the manoeuvre's polyline (the seed's geometry: scan corners, the approach's level
   leg and descent, ...) has each leg checked against the map; a leg that comes closer than
   `Clearances.plan` to an occupied voxel is replaced by a searched route round it or over it
   (search.py), and a waypoint too close to something moves to the nearest free voxel;
2. **timing**: the polyline is timed as before (timing.py). A plan that starts while the vehicle
   moves across its first leg begins with a lead-in along the velocity it has (`lead_in`): the
   reference velocity stays continuous, which a vehicle can follow; a plan that jumps it does
   not, and the real vehicle swings wide of the reference by metres, into what the plan avoided;
3. **check**: the timed reference is checked again (its rounded corners cut inside); failing,
   it is timed again with corners at most tracking_allowance / 2 from their waypoints, and failing
   that it is clipped: flown up to the last point it can still brake from before the conflict.

Three distances (`Clearances`), all from the body's centre to the nearest occupied voxel's box:
`accept` = body radius + obstacle_margin is the promise (the guard acts below it); `plan` =
accept + tracking_allowance is what routes keep, so the vehicle's tracking error and the
rounded corners (which may cut half the allowance) stay within the promise. A voxel's box is a
lower bound on where its obstacle is, so the body's true clearance is the margin or more.

A balloon's attack passes over its own pole and through the balloon: under a balloon the map
holds both (the pole pinned by the a-priori map, the balloon as background returns), so the
checks of an approach and an attack leave out the voxels in a vertical column of `mount_radius`
round the target, up to `MOUNT_TOP` above it (`mount_exemption`). The attack's hit offset (seed
004's o_h, 0.3 m above the centre, the pole 0.5 m below it) is what keeps the body off the pole.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import ConstraintProfile
from services.lib.geometry import nearest_on_edges, point_in_polygon
from services.planner.freespace import SAMPLE_STEP, FreeSpace
from services.planner.search import FREE_SEARCH_STEPS, Band, nearest_free, route
from services.planner.timing import DT, STOP_ANGLE, Path, fly, speed_caps

MOUNT_TOP = 1.0  # m above a balloon's centre that its exemption column reaches (its top, a voxel, slack)
LEAD_IN_ANGLE = math.radians(5.0)  # a first leg within this of the velocity needs no lead-in
LEAD_IN_SPEED = 0.3  # m/s: slower than this, a plan may start in any direction
LEAD_IN_SLACK = 1.05  # of the shortest lead-in: the timing's rounding is not exact
BARRIER_RETURN = 1.0  # 1/s: a reference inside the clearance is asked out at this many m/s per metre inside
RAY_SLACK = 1.0  # m looked along the velocity beyond the braking distance (speed_barrier)


@dataclass(frozen=True)
class Clearances:
    """Distances a plan keeps from occupied voxels' boxes, body centre to box (see the module)."""

    body: float  # the UAV's radius
    margin: float  # obstacle_margin: what the body keeps
    allowance: float  # tracking_allowance: the vehicle's tracking error and rounded corners

    @property
    def accept(self) -> float:
        return self.body + self.margin

    @property
    def plan(self) -> float:
        return self.accept + self.allowance

    @property
    def hard(self) -> float:
        """Closer than this (half the margin), the guard brakes rather than wait for a re-plan."""
        return self.body + 0.5 * self.margin

    @property
    def timed(self) -> float:
        """What a timed reference keeps: its corners may cut half the allowance."""
        return self.accept + 0.5 * self.allowance


@dataclass(frozen=True)
class Airspace:
    """Where plans may go: above `low` and below `high` (world z), inside the box of the arena
    (routes), and no reference ever beyond `high` or outside the arena polygon (`confine`)."""

    ground_z: float = 0.0
    low: float = -math.inf
    high: float = math.inf
    box_low: tuple[float, float] = (-math.inf, -math.inf)
    box_high: tuple[float, float] = (math.inf, math.inf)
    arena: tuple[tuple[float, float], ...] = ()  # the polygon; () : no arena known
    fence_margin: float = 0.0  # m inside the arena's edge and below `high` that `confine` keeps

    def band(self) -> Band:
        return Band(self.low, self.high, self.box_low, self.box_high)

    def confine(self, points: np.ndarray, across: bool = True) -> Confined:
        """(N, 3) points moved below `high` - fence_margin and, `across`, fence_margin inside the arena
        (from the nearest point of its outline). Landing and take-off go below `low`: not enforced."""
        given = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = given.copy()
        points[:, 2] = np.minimum(points[:, 2], self.high - self.fence_margin)
        if across and len(self.arena) >= 3 and len(points):
            points[:, :2] = self._inside(points[:, :2])
        shift = np.linalg.norm(points - given, axis=1)
        return Confined(points, int((shift > 1e-9).sum()), float(shift.max(initial=0.0)))

    def _inside(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) points at least fence_margin inside the arena: those outside or nearer its edge move
        along the line from the edge's nearest point; where that would not do (a concave corner), onto it."""
        arena = np.asarray(self.arena)
        inside = point_in_polygon(xy, arena)
        nearest, gap = nearest_on_edges(xy, arena)
        move = ~inside | (gap < self.fence_margin)
        if not move.any():
            return xy
        xy = xy.copy()
        away = np.where(inside[:, None], xy - nearest, nearest - xy)[move]
        length = np.linalg.norm(away, axis=1, keepdims=True)
        unit = np.divide(away, length, out=np.zeros_like(away), where=length > 1e-9)
        moved = nearest[move] + self.fence_margin * unit
        fine = point_in_polygon(moved, arena) & (length[:, 0] > 1e-9)
        xy[move] = np.where(fine[:, None], moved, nearest[move])
        return xy


@dataclass(frozen=True)
class Confined:
    """Points moved inside an airspace: how many moved, and the farthest move, m."""

    points: np.ndarray
    moved: int
    farthest: float


def airspace_of(arena, min_height: float, max_height: float, ground_z: float, floor: float,
                fence_margin: float = 0.0) -> Airspace:
    """The airspace of a world model: above `floor` (and the mission's min_height) over the ground,
    below its max_height, in its arena's box. ValueError: a world no plan can be made in."""
    arena = np.asarray(arena, dtype=np.float64).reshape(-1, 2)
    if len(arena) < 3 or not np.isfinite(arena).all() or not math.isfinite(ground_z) \
            or not min_height < max_height < math.inf:
        raise ValueError(f"an arena of {len(arena)} vertices, ground {ground_z} m, heights {min_height}-{max_height} m")
    return Airspace(ground_z, ground_z + max(min_height, floor), ground_z + max_height,
                    tuple(map(float, arena.min(axis=0))), tuple(map(float, arena.max(axis=0))),
                    tuple((float(x), float(y)) for x, y in arena), fence_margin)


@dataclass(frozen=True)
class Surroundings:
    """What a plan is made against: the map, the distances to keep, the airspace."""

    space: FreeSpace
    clearances: Clearances
    airspace: Airspace = field(default_factory=Airspace)
    search_margin: float = 15.0  # m around a leg's ends a search may go

    def conflict(self, positions: np.ndarray, need: float, exempt: np.ndarray | None = None) -> float | None:
        return self.space.path_conflict(positions, need, exempt)

    def free(self, points: np.ndarray, need: float, exempt: np.ndarray | None = None) -> bool:
        """Whether every point is at least `need` from every occupied box."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return bool((self.space.clearance(points, exempt) >= need).all())


@dataclass(frozen=True)
class Polyline:
    """A polyline with the speed caps of its timing, and how it came to be."""

    points: np.ndarray  # (M, 3)
    corner_speeds: np.ndarray  # (M,): cap at each vertex (inf: none; 0: stop)
    segment_speeds: np.ndarray  # (M - 1,)
    outcome: str = "clear"  # a PlanReport outcome
    note: str = ""

    @classmethod
    def of(cls, points, corner_speeds=None, segment_speeds=None) -> "Polyline":
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = len(points)
        corners = np.full(m, np.inf) if corner_speeds is None else np.asarray(corner_speeds, dtype=float)
        segments = np.full(max(m - 1, 0), np.inf) if segment_speeds is None else np.asarray(segment_speeds, dtype=float)
        return cls(points, corners, segments)


@dataclass(frozen=True)
class Cleared:
    """A timed plan and what the check made of it."""

    path: Path
    outcome: str
    note: str = ""
    clearance: float | None = None  # m, body to the nearest occupied box along it (None: nothing near)


def mount_exemption(target: np.ndarray, radius: float) -> np.ndarray:
    """(x, y, radius, top): the column under a balloon that its attack may pass over."""
    target = np.asarray(target, dtype=np.float64).reshape(3)
    return np.array([target[0], target[1], radius, target[2] + MOUNT_TOP])


def vertical_weight(profile: ConstraintProfile) -> float:
    """What a metre up or down costs in metres across: the profile's speed over its vertical speed."""
    return max(profile.max_speed / max(profile.max_vertical_speed, 1e-6), 1.0)


def lead_in(start: np.ndarray, velocity: np.ndarray | None, toward: np.ndarray, profile: ConstraintProfile) -> np.ndarray | None:
    """The point a plan first flies to along the velocity v it starts with, when its first leg
    (towards `toward`) turns away from that velocity by θ: the shortest lead-in L from which the
    timing (timing.py) keeps the start speed. The corner there is rounded within half of the
    lead-in, radius r = L / (2 tan(θ/2)) at speed √(a r) at most, and the rest of the lead-in must
    brake v down to that: L ≥ (v²/a) · 2 tan(θ/2) / (2 tan(θ/2) + 1). A turn sharper than the
    timing's stop angle stops at the corner: L = v²/(2a). None when the turn is negligible."""
    if velocity is None:
        return None
    velocity = np.asarray(velocity, dtype=np.float64).reshape(3)
    speed = float(np.linalg.norm(velocity))
    leg = np.asarray(toward, dtype=np.float64).reshape(3) - start
    length = float(np.linalg.norm(leg))
    if speed < LEAD_IN_SPEED or length < 1e-6:
        return None
    unit = velocity / speed
    turn = math.acos(float(np.clip(np.dot(unit, leg) / length, -1.0, 1.0)))
    if turn <= LEAD_IN_ANGLE:
        return None
    speed = min(speed, float(speed_caps(unit, profile)))
    squared = speed**2 / profile.max_acceleration
    if turn > STOP_ANGLE:
        distance = 0.5 * squared
    else:
        tangent = math.tan(0.5 * turn)
        distance = squared * 2.0 * tangent / (2.0 * tangent + 1.0)
    return start + unit * LEAD_IN_SLACK * distance


def clear_legs(env: Surroundings, line: Polyline, weight: float, exempt: np.ndarray | None = None,
               keep_first: int = 0) -> Polyline:
    """The polyline with every leg that comes too close to something replaced by a route round or
    over it; a waypoint too close moves to the nearest free voxel. A leg no route is found for
    ends the polyline there ("clipped"; "blocked" when that is its first leg). The first
    `keep_first` legs are kept as they are (a lead-in: the way the vehicle's momentum takes it)."""
    need = env.clearances.plan
    points, corners, segments = [line.points[0]], [line.corner_speeds[0]], []
    detoured, notes = False, []
    band = env.airspace.band()
    here = line.points[0]
    for i in range(1, len(line.points)):
        goal = line.points[i]
        if i <= keep_first:
            points.append(goal)
            corners.append(line.corner_speeds[i])
            segments.append(line.segment_speeds[i - 1])
            here = goal
            continue
        found = route(env.space, here, goal, need, band, weight, env.search_margin, exempt)
        if found is None:
            outcome = "blocked" if i == 1 else "clipped"
            notes.append(f"no free way from {fmt(here)} to {fmt(goal)}")
            return _polyline(points, corners, segments, outcome, notes)
        inner = found.points[1:]
        detoured |= found.searched
        if not found.reached:
            notes.append(f"{fmt(goal)} is too close to an obstacle: flying to {fmt(inner[-1])} instead")
        points.extend(inner)
        corners.extend([line.segment_speeds[i - 1]] * (len(inner) - 1) + [line.corner_speeds[i]])
        segments.extend([line.segment_speeds[i - 1]] * len(inner))
        here = inner[-1]
    return _polyline(points, corners, segments, "detour" if detoured or notes else line.outcome, notes)


def _polyline(points, corners, segments, outcome, notes) -> Polyline:
    return Polyline(np.asarray(points, dtype=np.float64).reshape(-1, 3), np.asarray(corners, dtype=float),
                    np.asarray(segments, dtype=float), outcome, "; ".join(notes))


def with_lead_in(line: Polyline, velocity: np.ndarray | None, profile: ConstraintProfile) -> Polyline:
    """The polyline starting with a lead-in along `velocity` when it needs one (see `lead_in`)."""
    if len(line.points) < 2:
        return line
    point = lead_in(line.points[0], velocity, line.points[1], profile)
    if point is None:
        return line
    return Polyline(np.insert(line.points, 1, point, axis=0), np.insert(line.corner_speeds, 1, np.inf),
                    np.insert(line.segment_speeds, 0, line.segment_speeds[0] if len(line.segment_speeds) else np.inf),
                    line.outcome, line.note)


def timed(env: Surroundings | None, line: Polyline, profile: ConstraintProfile, dt: float = DT, *,
          start_velocity=None, start_heading: float | None = None, heading: float | None = None,
          corner_deviation: float = np.inf, exempt: np.ndarray | None = None) -> Cleared:
    """Time the polyline (timing.fly) and check the reference; see the module docstring."""
    kwargs = dict(corner_speeds=line.corner_speeds, segment_speeds=line.segment_speeds,
                  start_velocity=start_velocity, start_heading=start_heading, heading=heading)
    path = fly(line.points, profile, dt, corner_deviation=corner_deviation, **kwargs)
    if env is None or not env.space.known:
        return Cleared(path, line.outcome, line.note)
    need = env.clearances.timed
    conflict = env.conflict(path[0], need, exempt)
    if conflict is not None:
        tight = min(corner_deviation, 0.5 * env.clearances.allowance)
        path = fly(line.points, profile, dt, corner_deviation=tight, **kwargs)
        conflict = env.conflict(path[0], need, exempt)
    if conflict is None:
        return Cleared(path, line.outcome, line.note, body_clearance(env, path[0], exempt))
    clipped = clip(path, conflict, profile, dt)
    where = path[0][min(int(conflict) + 1, len(path[0]) - 1)]
    note = "; ".join(filter(None, [line.note, f"stops short: the reference would pass closer than {need:.1f} m "
                                              f"to an obstacle near {fmt(where)}"]))
    return Cleared(clipped, "clipped", note, body_clearance(env, clipped[0], exempt))


def clip(path: Path, conflict: float, profile: ConstraintProfile, dt: float) -> Path:
    """The reference flown up to the last sample from which braking along it, at the profile's
    acceleration, comes to rest before `conflict` (a fractional sample index), then that braking.
    Along the path, not straight ahead: the path up to its first conflict is clear, and where it
    bends away from an obstacle (the pursuit's speed barrier) a straight braking line does not — in
    street's gap a chaser's plan 1.15 m from a wall, clipped straight ahead, came within 0.67 m."""
    positions, headings = path
    accel = 0.9 * profile.max_acceleration
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    last = len(positions) - 1
    reach = float(np.interp(min(conflict, last), np.arange(len(positions)), along))
    for k in range(min(int(conflict), last - 1), -1, -1):
        speed = float(along[k + 1] - along[k]) / dt
        if along[k] + speed**2 / (2.0 * accel) < reach or k == 0:  # k = 0: too late to stop short, the best left
            tail = braking_along(positions, along, k, speed, accel, dt)
            return np.vstack([positions[:k + 1], tail]), np.concatenate([headings[:k + 1], np.full(len(tail), headings[k])])
    return positions[:1], headings[:1]


def braking_along(positions: np.ndarray, along: np.ndarray, k: int, speed: float, accel: float, dt: float) -> np.ndarray:
    """Samples (every dt, after sample k) of braking to rest from `speed` at `accel` along the
    polyline `positions` (arc lengths `along`), on along its last segment's direction if it ends first."""
    if speed < 1e-9:
        return np.zeros((0, 3))
    stop = speed / accel
    t = np.minimum(np.arange(1, int(np.ceil(stop / dt)) + 1) * dt, stop)
    s = along[k] + speed * t - 0.5 * accel * t**2
    out = np.stack([np.interp(s, along, positions[:, axis]) for axis in range(3)], axis=1)
    beyond = s > along[-1]
    if beyond.any() and len(positions) > 1:
        end = positions[-1] - positions[-2]
        norm = float(np.linalg.norm(end))
        if norm > 1e-12:
            out[beyond] = positions[-1] + (s[beyond] - along[-1])[:, None] * (end / norm)
    return out


def body_clearance(env: Surroundings, positions: np.ndarray, exempt: np.ndarray | None = None) -> float | None:
    """m from the body to the nearest occupied box along the polyline (None: none within reach)."""
    reach = env.space.path_clearance(positions, exempt)
    return None if reach >= env.space.reach else round(reach - env.clearances.body, 3)


def free_overshoot(env: Surroundings, target: np.ndarray, direction: np.ndarray, hit_offset: float,
                   overshoot: float, end_offset: float, exempt: np.ndarray) -> float:
    """How far beyond the target (up to `overshoot`) an attack along `direction` can run and come
    to rest with the plan's clearance (0: not even from the hit point)."""
    hit = target + np.array([0.0, 0.0, hit_offset])
    end = target + overshoot * direction + np.array([0.0, 0.0, end_offset])
    conflict = env.conflict(np.stack([hit, end]), env.clearances.plan, exempt)
    if conflict is None:
        return overshoot
    return max(conflict * overshoot - SAMPLE_STEP, 0.0)


def speed_barrier(env: Surroundings, deceleration: float, top_speed: float):
    """A filter on the velocity a vehicle flown forward in time (the pursuit) asks for: its speed
    towards the nearest occupied box is held to what braking at `deceleration` can still stop before
    the plan's clearance — √(2·a·(d − clearance)) — so the reference slides along an obstacle
    instead of into it and never closes in below the clearance (a control barrier on the distance);
    and its speed along its own direction to what can stop before the first place on that ray
    closer than the clearance. The nearest box alone is not enough: in street's 6 m gap between two
    blocks a chaser coming in past the corner of one (its nearest) flew at the other at 6 m/s, and
    its plans came within 0.2 m of it (benchmarks/pursuit.py --obstacles).
    It looks only as far as the velocity asked for needs to brake (at most what `top_speed` needs):
    nothing farther can limit it, and the search for the nearest box costs with the cube of its
    reach (looking 26 m out at every step made a pursuit near obstacles 40 ms)."""
    need = env.clearances.plan
    top = top_speed**2 / (2.0 * deceleration)

    def limit(position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        watch = need + min(float(velocity @ velocity) / (2.0 * deceleration), top) + RAY_SLACK
        distance, away = env.space.nearest(position, watch)
        if distance >= watch or not away.any():
            return velocity  # nothing within what this speed needs to brake: the ray meets nothing either
        toward = -float(np.dot(velocity, away))
        # inside the clearance: out again at BARRIER_RETURN per metre (one that only stopped closing
        # there held a chaser 1.2 m from a wall, where the vehicle's lag had carried it)
        allowed = (math.sqrt(2.0 * deceleration * (distance - need)) if distance >= need
                   else -BARRIER_RETURN * (need - distance))
        if toward > allowed:
            velocity = velocity + (toward - allowed) * away
        return ahead(position, velocity, distance)

    def ahead(position: np.ndarray, velocity: np.ndarray, nearest: float) -> np.ndarray:
        speed = float(np.linalg.norm(velocity))
        reach = speed**2 / (2.0 * deceleration) + RAY_SLACK
        if speed < 1e-6 or nearest >= need + reach:
            return velocity  # nothing the ray could come within the clearance of
        conflict = env.space.path_conflict(np.stack([position, position + velocity * (reach / speed)]), need)
        if conflict is None:
            return velocity
        allowed = math.sqrt(2.0 * deceleration * conflict * reach)
        return velocity * (allowed / speed) if speed > allowed else velocity

    return limit


def free_points(env: Surroundings, points: np.ndarray) -> np.ndarray:
    """The points, each one closer than the plan's clearance to an occupied box moved to the centre
    of the nearest free voxel of the search grid (within FREE_SEARCH_STEPS voxels; else kept)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    space = env.space
    if not space.known or not len(points):
        return points
    near = space.clearance(points) < env.clearances.plan
    if not near.any():
        return points
    g = space.geometry
    reach = FREE_SEARCH_STEPS + int(math.ceil(space.search_radius / g.voxel_size)) + 1
    cells = g.voxel_of(points[near])
    low = np.clip(cells.min(axis=0) - reach, 0, np.asarray(g.shape) - 1)
    high = np.clip(cells.max(axis=0) + reach + 1, 1, np.asarray(g.shape))
    if np.any(high <= low):
        return points
    blocked = space.blocked(low, high)
    out = points.copy()
    for row, cell in zip(np.flatnonzero(near), cells):
        local = cell - low
        if np.any(local < 0) or np.any(local >= high - low):
            continue
        found = nearest_free(blocked, local, FREE_SEARCH_STEPS)
        if found[0] >= 0:
            out[row] = g.centres((found + low)[None])[0]
    return out


def landing_line(env: Surroundings | None, position: np.ndarray, ground_z: float,
                 profile: ConstraintProfile) -> Polyline:
    """Straight down to the ground; when something is below (a roof, a crown), first across at the
    current height to the nearest spot whose column down is clear (rings of 1 m, 16 bearings; the
    way across is routed like any other leg)."""
    position = np.asarray(position, dtype=np.float64).reshape(3)
    down = np.array([position[0], position[1], ground_z])
    line = Polyline.of([position, down], np.zeros(2))
    if env is None or not env.space.known or env.conflict(line.points, env.clearances.plan) is None:
        return line
    need = env.clearances.plan
    for radius in np.arange(1.0, env.search_margin + 0.5, 1.0):
        for angle in np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False):
            spot = position + radius * np.array([math.cos(angle), math.sin(angle), 0.0])
            column = np.stack([spot, [spot[0], spot[1], ground_z]])
            if env.free(spot, need) and env.conflict(column, need) is None:  # the way there is routed like any leg
                return Polyline(np.vstack([position, column]), np.zeros(3), np.full(2, np.inf), "detour",
                                f"landing {radius:.0f} m aside: something is below {fmt(position)}")
    return Polyline(line.points, line.corner_speeds, line.segment_speeds, "clipped",
                    f"no clear column to land in within {env.search_margin:g} m of {fmt(position)}")


def directions_around(first: np.ndarray, count: int) -> np.ndarray:
    """(count, 3) horizontal unit vectors: `first`, then turned by ±step, ±2·step, ... (nearest first)."""
    angle = math.atan2(first[1], first[0])
    step = 2.0 * math.pi / max(count, 1)
    turns = [0.0] + [sign * k * step for k in range(1, count // 2 + 1) for sign in (1.0, -1.0)]
    turns = turns[:count]
    return np.array([[math.cos(angle + t), math.sin(angle + t), 0.0] for t in turns])


def fmt(v) -> str:
    """A point for a note: (x, y, z) to a decimetre."""
    return f"({v[0]:.1f}, {v[1]:.1f}, {v[2]:.1f})"
