"""Pursuit of a moving target: from the vehicle's state onto the target's predicted track,
then along it. Made for re-planning on every update of the prediction — each plan starts
from the current position and velocity, so a target whose straight-line prediction keeps
changing is followed smoothly (the merge of intercept.py instead waits on the predicted path).

The reference is a virtual vehicle flown forward in time under the target's predicted path
p_T(t): the tracker's own prediction (its filter's trajectory, curved for a turning target) when
the command carries one, else the constant-velocity line p + v·t. It demands the target's
predicted velocity plus a closing velocity towards the predicted target of at most √(2·b·gap)
(b = BRAKING·a_max, so it can always brake onto the track without overshooting), and reaches
that demand at up to a_max; speed stays within the profile's total and vertical limits. So
every sample is within the profile by construction, the gap closes as fast as the braking budget
allows, and the reference then lies on the predicted track.
After `horizon` it brakes to rest, in case no newer prediction comes.

BRAKING is 0.2, not the whole a_max: the braking budget is planned as if the target kept its
velocity, and agile's drones do not — they brake or turn towards the UAV at up to 4 m/s² where
the UAV brakes at 3, so the budget must leave room for it. With 0.5 (b = 1.5 m/s²) the UAV
closed at 5-7 m/s from 10 m and went through the random drone at 6-7 m/s relative whenever it
turned back (agile seeds 3 and 4 took 78 and 77 s from first detection to capture); with 0.2
(0.59 m/s²: 3.4 m/s from 10 m, 1.9 m/s from 3 m) 13 and 9 s. With 0.15 the UAV trailed the
figure-eight for 80 s on seed 2, arriving at each pass as the drone turned away. Closing from
far takes longer (22 m from rest: 11 s instead of 9 s); the UAV is still faster than any
target it may catch.

Close in, the closing speed is at most TERMINAL_GAIN·gap (below 2b/k², 0.8 m at the attack
profile). The net takes a drone at a relative speed of at most 2 m/s within 1 m, and the
square-root law alone arrives there with the control lag on top: against agile seed 5's random
manoeuvrer, which flies into the waiting UAV, a law reaching the 1 m radius at 1.7 m/s gave
misses within 0.4-1.3 m at 3-4 m/s relative. The linear law closes the last part at 1.2 m/s per
metre, still onto the track.

A UAV trailing its target aims ahead of it: at the predicted point `behind / LEAD_SPEED` s
(at most LEAD_MAX) further along the prediction, where `behind` is how far the UAV trails along
the target's velocity (0 abreast or ahead, so a target met head-on or from the side is aimed at as
before). Chasing the predicted position itself from behind a turning target asks for more than
the target's speed on the target's own curve: on mast's 4 m circle at 3.2 m/s that is more
centripetal acceleration than the attack profile's 3 m/s², the UAV swung outside, and with
prediction and control lag it never met the drone within the net's 2 m/s (0 of 15 pursuits in
benchmarks/pursuit.py); the lead cuts inside the turn (15 of 15, 6.7 s median). The lead starts
at any gap: leading only beyond 1-2 m caught 3-8 of 15, the last metres of a turn need it most.

A target predicted to turn harder than half of what the law may ask of the UAV (mast's circler:
2.56 m/s² on its 4 m circle at 3.2 m/s, where a plan has 2.5) is not only chased but met: a
rendezvous flies the earliest cubic, within RENDEZVOUS_MAX_S and RENDEZVOUS_SHARE of a_max, to
where the prediction puts it, arriving at its velocity or up to RENDEZVOUS_SLACK off it, closing
no faster than it could brake from; the law takes over from there. Chased, the circler was passed
faster than the net takes, or trailed outside its turn. benchmarks/pursuit.py --obstacles --trust
1.5 (the missions' trust), seeds 1-5 x 6: the circler 21 -> 30 of 30 (mean 16.2 -> 9.1 s); the
cost, not hidden: mast's figure-eight, whose lobes turn as hard and whose prediction carries a lobe
on into the straight, 30 -> 23-25 of 30 (whatever share of a_max gates the meeting), agile's dodger
30 -> 29. In whole missions the circler was missed on mast seed 3 (2 UAVs) and seed 1 (3 UAVs)
without it and caught after 59.4 and 51.8 s with it, the eight after 19.0 and 40.4 s.

Past the tracker's 2 s path the target is carried on round its turn (PredictedPath.turning_on),
not straight on: a meeting planned on the straight line was where the circler never went, the next
update moved it on again, and the UAV trailed 1.3-2 m behind the drone for 40 s, caught or not by
a last-bit difference of floating point (the same code on two BLAS kernels). Round the turn, up to
4 s ahead, the circler is caught in 30 of 30 (mean 8.2 s, worst 27.6 s, identical on both
kernels); the eight 26 of 30 (mean 25.5 s) and the dodger 29 of 30 (mean 18.4 s), where straight
on up to 3 s gave 27 (19.8 s) and 29 (16.3 s) — a lobe carried on round is as wrong as a lobe
carried into the straight. A meeting ends where the law can still stop a descent above the floor.

Nothing is pursued below `floor` (world z): where the prediction goes lower, the reference holds
the floor's height under it. A constant-acceleration prediction of a target diving to brake, or
coasting unseen behind a tree, extrapolates into the ground within seconds; in agile seed 4 the
UAV followed such a prediction down at 7 m/s and hit the ground.

The prediction is followed for `trust` s only; after that the reference waits where it then puts
the target. A target that out-accelerates the interceptor (agile's 4 m/s² manoeuvrer against the
attack profile's 3) is anywhere within ½·a·t² of a prediction t s old: 8 m after 2 s. A command
that is not renewed (the target unseen) would otherwise send the UAV on along a straight line at
up to 8 m/s for the whole horizon.

Near obstacles (commands.py, avoid.py) the caller hands in `free`, which moves the predicted
points the UAV could not be at (too close to an obstacle) to the nearest free voxel, so the
reference aims where the target will be *and* the UAV can fly; and, when the chase would cross an
obstacle, a `route` round it: the virtual vehicle then first follows the route (aiming ROUTE_LOOKAHEAD
ahead of where it is along it, as fast as it can brake before the route's end at ROUTE_BRAKING
of a_max: the obstacle stands still, and braking for the carrot itself held it to 2 m/s while
mast's eight ran round the tower at 5) and turns to the target once it nears the route's end; and a
`barrier` on the velocity it asks for, which holds its speed towards the nearest obstacle to what
it can still brake from before the clearance, so it slides along an obstacle instead of into it
(the acceleration limit still applies to the filtered demand: the reference never jumps).
"""
from __future__ import annotations

import numpy as np

from schemas.messages import ConstraintProfile
from services.lib.tracks import PredictedPath
from services.planner.timing import DT, Path, check_duration, steer

BRAKING = 0.2  # share of max_acceleration the closing speed plans to brake with (see above)
GAIN = 4.0  # 1/s: how fast the velocity demand is taken up (then capped by max_acceleration)
TERMINAL_GAIN = 1.2  # 1/s: the closing speed close in is at most this × the gap (a capture's relative speed)
_MARGIN = 0.98  # of each limit, so differences of the samples stay inside it too
LEAD_SPEED = 3.0  # m/s: a UAV trailing by d m aims d / LEAD_SPEED s further along the prediction ... (see above)
LEAD_MAX = 1.5  # s: ... at most
ROUTE_BRAKING = 0.5  # share of max_acceleration a route round an obstacle is flown to brake with at its end
ROUTE_LOOKAHEAD = 4.0  # m along a route ahead of the vehicle's nearest point on it that it aims at
TAIL_VERTICAL_SHARE = 0.8  # of max_acceleration the braking tail may spend stopping a descent above the floor
RENDEZVOUS_SHARE = 0.8  # of the (margined) max_acceleration a rendezvous may ask for, the rest for tracking it
RENDEZVOUS_SLACK = 1.2  # m/s the velocity a meeting arrives at may differ from the target's (the net takes 2)
RENDEZVOUS_CLOSING = 0.5  # share of max_acceleration the closing speed on the way to a meeting may brake with
RENDEZVOUS_TURN = 0.5  # a meeting is planned for a target predicted to turn harder than this share of what a plan may ask
RENDEZVOUS_MAX_S = 4.0  # s: the latest meeting a rendezvous plans for


def _clip(vector: np.ndarray, limit: float) -> np.ndarray:
    norm = float(np.linalg.norm(vector))
    return vector if norm <= limit else vector * (limit / norm)


def _limit_velocity(velocity: np.ndarray, profile: ConstraintProfile) -> np.ndarray:
    velocity = _clip(velocity, _MARGIN * profile.max_speed)
    vertical = _MARGIN * profile.max_vertical_speed
    return np.array([velocity[0], velocity[1], np.clip(velocity[2], -vertical, vertical)])


def _take_up(change: np.ndarray, dt: float, accel: float, vertical_first: bool) -> np.ndarray:
    """The velocity change of one step of dt towards a demand `change` off: GAIN of it per s, at
    most accel·dt. With `vertical_first` (a descent held up above the floor) the vertical part
    takes what it needs first: shared, a turn took the whole budget and the descent ran on into
    the floor (a hypothesis case: 1.05 m/s down 1.3 m above it, at the floor still 0.63 m/s)."""
    step = GAIN * change * dt
    if not vertical_first:
        return _clip(step, accel * dt)
    vertical = float(np.clip(step[2], -accel * dt, accel * dt))
    level = _clip(step[:2], np.sqrt(max((accel * dt) ** 2 - vertical**2, 0.0)))
    return np.array([*level, vertical])


def _behind(position: np.ndarray, target: np.ndarray, velocity: np.ndarray) -> float:
    """How far the position trails the target along its velocity, m (0 abreast, ahead or still)."""
    speed = float(np.linalg.norm(velocity))
    return 0.0 if speed < 1e-6 else max(0.0, float((target - position) @ velocity) / speed)


def _carrot(route: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, bool, float]:
    """The point ROUTE_LOOKAHEAD along the route beyond the vehicle's nearest point on it, but not
    past the next vertex (a carrot that ran ahead round a corner would pull the vehicle across
    it, towards the obstacle the route goes round); whether to keep following the route (False
    once the vehicle is that close to its end); and how much of the route is left from there, m."""
    a, b = route[:-1], route[1:]
    edge = b - a
    length = np.linalg.norm(edge, axis=1)
    along = np.clip(np.einsum("ij,ij->i", position - a, edge) / np.maximum(length**2, 1e-12), 0.0, 1.0)
    nearest = int(np.argmin(np.linalg.norm(a + along[:, None] * edge - position, axis=1)))
    if nearest == len(edge) - 1 and np.linalg.norm(route[-1] - position) <= ROUTE_LOOKAHEAD:
        return route[-1], False, float(np.linalg.norm(route[-1] - position))
    left = float(length[nearest:].sum() - along[nearest] * length[nearest])
    ahead = min(along[nearest] * length[nearest] + ROUTE_LOOKAHEAD, length[nearest])
    if ahead >= length[nearest] - 1e-9 and np.linalg.norm(b[nearest] - position) < 1.0 and nearest + 1 < len(edge):
        nearest, ahead = nearest + 1, min(ROUTE_LOOKAHEAD, length[nearest + 1])
    return a[nearest] + ahead / max(length[nearest], 1e-12) * edge[nearest], True, left


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.maximum(np.linalg.norm(vectors, axis=-1, keepdims=True), 1e-12)


def _cubic(gap: np.ndarray, v0: np.ndarray, v1: np.ndarray, span: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end accelerations of the cubic covering `gap` in `span` s from velocity v0 to v1."""
    return (6.0 * gap - 4.0 * v0 * span - 2.0 * v1 * span) / span**2, (-6.0 * gap + 2.0 * v0 * span + 4.0 * v1 * span) / span**2


def _meeting_offsets(count: int = 24) -> np.ndarray:
    """Offsets of the meeting velocity from the target's: none, then `count` spread over the
    sphere of radius RENDEZVOUS_SLACK (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / count), np.pi * (1.0 + 5.0**0.5) * i
    sphere = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)
    return np.vstack([np.zeros(3), RENDEZVOUS_SLACK * sphere])


MEETING_OFFSETS = _meeting_offsets()


def _turning(prediction: PredictedPath, last: int, dt: float) -> float:
    """The largest acceleration across its way the target is predicted to make in `last` steps,
    m/s² (of the prediction itself: the floor and the trust end it without a turn)."""
    _, velocities = prediction.state(np.arange(last + 1) * dt)
    change = np.diff(velocities, axis=0) / dt
    along = _unit(velocities[:-1])
    across = change - np.einsum("ij,ij->i", change, along)[:, None] * along
    return float(np.linalg.norm(across, axis=1).max())


def _stops_above(position: np.ndarray, velocity: np.ndarray, floor: float, profile: ConstraintProfile) -> bool:
    """Whether the pursuit law, taking over at (position, velocity), can stop a descent above
    `floor` as it brakes (its vertical demand's bound, less the lag of taking it up)."""
    above = max(position[2] - floor + min(velocity[2], 0.0) / GAIN, 0.0)
    return velocity[2] >= -np.sqrt(2.0 * BRAKING * _MARGIN * profile.max_acceleration * above) - 1e-9


def _rendezvous(p: np.ndarray, v: np.ndarray, targets: np.ndarray, velocities: np.ndarray, last: int, dt: float,
                accel: float, profile: ConstraintProfile, floor: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The earliest meeting with the predicted target: for each step k up to `last`, cubics from
    (p, v) to targets[k] in k·dt arriving at the target's velocity or up to RENDEZVOUS_SLACK off it
    (MEETING_OFFSETS); the first whose acceleration (linear in time, so largest at an end) stays
    within `accel`, whose speeds stay within the profile and which keeps above `floor` (or the
    start's height) and arrives where the law can still stop a descent above it, nearest the
    target's velocity. Its samples after the start and the velocity it arrives at, or None when
    no meeting within `last` steps fits."""
    k = np.arange(1, last + 1)
    if not len(k):
        return None
    span = (k * dt)[:, None, None]
    gap = (targets[k] - p)[:, None, :]
    arrive = velocities[k][:, None, :] + MEETING_OFFSETS[None]
    start, end = _cubic(gap, v, arrive, span)
    peak = np.maximum(np.linalg.norm(start, axis=2), np.linalg.norm(end, axis=2))
    for step, offset in zip(*np.nonzero(peak <= accel)):  # by time, then nearest the target's velocity
        tau = np.arange(1, k[step] + 1)[:, None] * dt
        first, jerk = start[step, offset], (end[step, offset] - start[step, offset]) / (k[step] * dt)
        velocity = v + first * tau + 0.5 * jerk * tau**2
        if np.any(np.linalg.norm(velocity, axis=1) > _MARGIN * profile.max_speed) or \
                np.any(np.abs(velocity[:, 2]) > _MARGIN * profile.max_vertical_speed):
            continue
        samples = p + v * tau + 0.5 * first * tau**2 + jerk * tau**3 / 6.0
        if samples[:, 2].min() < min(floor, p[2]) - 1e-9:
            continue
        if not _stops_above(samples[-1], velocity[-1], floor, profile):
            continue
        apart = np.linalg.norm(targets[1:k[step] + 1] - samples, axis=1)
        closing = np.linalg.norm(velocity - velocities[1:k[step] + 1], axis=1)
        if np.any(closing > np.sqrt(2.0 * RENDEZVOUS_CLOSING * accel * apart) + RENDEZVOUS_SLACK):
            continue
        return samples, velocity[-1]
    return None


def _aims(prediction: PredictedPath, count: int, dt: float, trust: float, floor: float, free) -> tuple[np.ndarray, np.ndarray]:
    """The predicted target's positions and velocities every dt s from now: held where the
    prediction is no longer trusted, no lower than `floor`, moved to free space by `free`."""
    times = np.arange(count) * dt
    targets, velocities = prediction.state(np.minimum(times, max(trust, 0.0)))
    velocities[times > trust] = 0.0
    below = targets[:, 2] < floor
    targets[below, 2] = floor
    velocities[below, 2] = 0.0
    return (targets if free is None else free(targets)), velocities


def _meet(p: np.ndarray, v: np.ndarray, prediction: PredictedPath, steps: int, dt: float, profile: ConstraintProfile,
          floor: float, free) -> tuple[np.ndarray, np.ndarray] | None:
    """The rendezvous with a target predicted to turn harder than RENDEZVOUS_TURN of what the
    pursuit law may ask of the UAV, or None. It may meet the target up to RENDEZVOUS_MAX_S ahead,
    past the trust and the end of the predicted path (round its turn from there): the trust keeps a
    pursuit from following a stale prediction at speed for long (an unseen target out-accelerates
    it), while a rendezvous is planned anew on every update and ends at the target's velocity.
    Within the missions' trust (1.3 s past a sighting 0.2 s old) or the tracker's 2 s path a
    meeting rarely fitted: mast's circler was caught in 21 of 30 pursuits (benchmarks/pursuit.py
    --obstacles --trust 1.5), 30 of 30 with meetings up to 3 s ahead (see the module's words on
    carrying the path on round its turn for the 4 s)."""
    accel = _MARGIN * profile.max_acceleration
    last = int(min(steps, RENDEZVOUS_MAX_S / dt + 1e-9))
    if last < 1 or _turning(prediction, last, dt) < RENDEZVOUS_TURN * accel:
        return None
    targets, velocities = _aims(prediction.turning_on(last * dt), last + 1, dt, np.inf, floor, free)
    return _rendezvous(p, v, targets, velocities, last, dt, RENDEZVOUS_SHARE * accel, profile, floor)


def meeting_length(position, target_position, target_velocity, *, profile: ConstraintProfile, dt: float = DT,
                   start_velocity=None, horizon: float = 12.0, predicted: PredictedPath | None = None,
                   floor: float = -np.inf, free=None, **_) -> int:
    """How many samples of `pursuit`'s reference (with the same arguments, no route) fly the
    rendezvous with the target: 0 when it plans none (the trust does not bound it, see _meet)."""
    p = np.asarray(position, float).reshape(3)
    v = np.zeros(3) if start_velocity is None else _limit_velocity(np.asarray(start_velocity, float).reshape(3), profile)
    prediction = predicted if predicted is not None else PredictedPath(np.asarray(target_position, float).reshape(3),
                                                                      np.asarray(target_velocity, float).reshape(3))
    met = _meet(p, v, prediction, int(np.ceil(horizon / dt)), dt, profile, floor, free)
    return 0 if met is None else len(met[0])


def _braking_tail(p: np.ndarray, v: np.ndarray, accel: float, dt: float, floor: float) -> np.ndarray:
    """Samples braking from (p, v) to rest at up to `accel`: along the velocity, unless that sinks
    below `floor` (braking along a shallow descent stops its vertical part late); then the
    vertical part brakes as hard as stopping above the floor needs (up to TAIL_VERTICAL_SHARE of
    `accel`; the caller's floor clip takes what is left) and the horizontal part with what is
    left, each to rest on its own."""
    speed = float(np.linalg.norm(v))
    if speed <= 1e-9:
        return np.zeros((0, 3))
    deceleration = accel * v / speed
    above = p[2] - floor
    if v[2] < 0.0 and v[2] ** 2 > 2.0 * abs(deceleration[2]) * above:
        vertical = min(v[2] ** 2 / (2.0 * max(above, 1e-9)), TAIL_VERTICAL_SHARE * accel)
        level = float(np.linalg.norm(v[:2]))
        horizontal = np.sqrt(max(accel**2 - vertical**2, 0.0))
        deceleration = np.array([*(horizontal * v[:2] / max(level, 1e-9)), -vertical])
    rest = np.where(np.abs(v) > 1e-9, np.abs(v) / np.maximum(np.abs(deceleration), 1e-9), 0.0)  # s each axis takes
    check_duration(float(rest.max()), "braking")
    stop = np.arange(1, int(np.ceil(rest.max() / dt)) + 1)[:, None] * dt
    stop = np.minimum(stop, rest)
    return p + v * stop - 0.5 * deceleration * stop**2


def pursuit(position, target_position, target_velocity, *, profile: ConstraintProfile, dt: float = DT,
            start_velocity=None, start_heading: float | None = None, horizon: float = 12.0,
            predicted: PredictedPath | None = None, floor: float = -np.inf,
            trust: float = np.inf, free=None, route: np.ndarray | None = None, barrier=None) -> Path | None:
    """Close on the predicted track and fly along it for `horizon` s, then brake to rest; heading
    along the target's velocity. `predicted` (time 0 = now): the target's predicted path, else the
    line from target_position along target_velocity, followed for `trust` s and then waited at;
    pursued no lower than `floor` (world z). None when the target is now faster than the profile
    allows (where only its prediction is, the closing demand is capped by the profile)."""
    accel = _MARGIN * profile.max_acceleration
    pt, vt = np.asarray(target_position, float).reshape(3), np.asarray(target_velocity, float).reshape(3)
    if np.linalg.norm(vt) >= _MARGIN * profile.max_speed or abs(vt[2]) >= _MARGIN * profile.max_vertical_speed:
        return None  # it could never be caught up with
    p = np.asarray(position, float).reshape(3).copy()
    v = np.zeros(3) if start_velocity is None else _limit_velocity(np.asarray(start_velocity, float).reshape(3), profile)
    steps = int(np.ceil(horizon / dt))
    positions = [p.copy()]
    braking = BRAKING * accel
    prediction = predicted if predicted is not None else PredictedPath(pt, vt)
    lead_steps = int(np.ceil(LEAD_MAX / dt))
    targets, target_velocities = _aims(prediction, steps + lead_steps, dt, trust, floor, free)
    following = route is not None and len(route) >= 2
    met = None if following else _meet(p, v, prediction, steps, dt, profile, floor, free)
    first = 0
    if met is not None:
        samples, v = met
        first = len(samples)
        positions.extend(samples)
        p = samples[-1].copy()
    for k in range(first, steps):  # inherently sequential: a vehicle flown forward in time
        lead = min(int(round(_behind(p, targets[k], target_velocities[k]) / (LEAD_SPEED * dt))), lead_steps)
        aim, aim_velocity = targets[k + lead], target_velocities[k + lead]
        to_go = None
        if following:
            aim, following, to_go = _carrot(route, p)
            aim_velocity = np.zeros(3)
        gap = aim - p
        distance = float(np.linalg.norm(gap))
        if to_go is None:
            speed = min(np.sqrt(2.0 * braking * distance), TERMINAL_GAIN * distance)
        else:  # round a still obstacle: brake for the route's end only, not for the carrot running ahead
            speed = np.sqrt(2.0 * ROUTE_BRAKING * accel * to_go)
        closing = speed * gap / distance if distance > 1e-9 else np.zeros(3)
        demand = _limit_velocity(aim_velocity + closing, profile)
        above = max(p[2] - floor + min(v[2], 0.0) / GAIN, 0.0)  # less what the lag of taking up the demand sinks
        lowest = -np.sqrt(2.0 * braking * above)  # can still stop above it
        held_up = min(demand[2], v[2]) < lowest  # the demand, or a descent lagging behind it, would sink too far
        demand[2] = max(demand[2], lowest)
        if barrier is not None:
            demand = barrier(p, demand)
        dv = _take_up(demand - v, dt, accel, vertical_first=held_up)
        v_next = _limit_velocity(v + dv, profile)
        p = p + 0.5 * (v + v_next) * dt
        v = v_next
        positions.append(p.copy())
    positions.extend(_braking_tail(p, v, accel, dt, min(floor, float(positions[0][2]))))
    positions = np.array(positions)
    positions[:, 2] = np.maximum(positions[:, 2], min(floor, float(positions[0, 2])))  # the braking tail too
    facing = vt[:2] if np.linalg.norm(vt[:2]) > 1e-6 else (pt - np.asarray(position, float).reshape(3))[:2]
    heading = float(np.arctan2(facing[1], facing[0])) if np.linalg.norm(facing) > 1e-6 else (start_heading or 0.0)
    return steer(positions, np.full(len(positions), heading), start_heading, profile.max_heading_rate, dt)

