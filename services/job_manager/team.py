"""The team as one job manager sees it (seed 004 §3.5.4): which partners are still working,
revenge mode, who may chase which target, and who yields when two UAVs come close.

Rules (docs/architecture.md, "Mission"):
- A partner has **fallen** when, after it was once seen flying normally, its status says it no
  longer is (landed, emergency landing); or it has been silent for t_s (`partner_timeout`;
  a partner never heard at all counts from this UAV's own take-off). A lost liveliness token
  alone does not make it fall: a cut radio looks the same as a dead UAV, and a cut-off partner
  may still be flying.
- **Lost link** (docs/architecture.md, "Lost link"): a partner is **stale** when silent for
  `lost_link_time`, and **unaccounted** while stale or fallen
  without its last status saying it is on the ground. An unaccounted partner's last known
  position is a no-fly column (`no_fly`). A UAV that finds every partner not seen landed stale is
  **isolated**; it keeps flying the mission only when it is the first in team order among the
  members not seen landed and at most one partner is unaccounted (the two halves of a 2-UAV team
  must not both stop, nor both go on blind); otherwise it lands where it is. Its partners
  therefore find it on the ground, inside its no-fly column, by the time they take over its area
  (t_s after its last status).
- **Revenge mode**: the arena is split into equal working areas among the *active* UAVs (this
  one plus every partner that has not fallen), always in the world's team order, west to east.
  With 2 UAVs a survivor gets the whole arena; with 3 the two survivors share it.
- **Coming back**: a fallen partner is reinstated only after its status has said "flying
  normally" continuously for `rejoin_time` while its job manager's token is alive; the split
  is then recomputed (logged as such by the node). A link that was cut both ways therefore
  ends with both sides back on the original split.
- **One chaser per target**: a partner's claimed target (its status `target`) filters out my
  detections within `claim_radius` of it — unless I claim the same target and am closer to it
  (ties: the UAV earlier in the team order keeps it).
- **Separation, planned ahead** (plans.py): every status carries the next `plan_horizon` s of its
  UAV's reference. When an active partner that is airborne or taking off is closer than
  `safety_distance`, or its plan and this UAV's come closer than that within plan_horizon (the
  partner's plan widened by `plan_widen_rate` m per second of its status's age), the
  lower-priority UAV yields, before the distance breaks (also taking off and landing). Without
  plans on either side the prediction falls back to both UAVs' current velocities over
  `separation_lookahead` (`breach_time`). The yield holds where the UAV's braking ends — on the
  ground while it is not airborne — when the partner's plan stays safety_distance +
  `separation_hysteresis` clear of that spot; else it also climbs to `vertical_separation` above
  the highest point of the partner's plan near it (`hold_spot`). It lasts until the distance
  exceeds safety_distance + hysteresis and no breach is predicted. Priority: a partner that
  does not answer (stale, or its job manager's token gone: killed, it cannot yield) over everyone, then a
  UAV engaging a target (GOING_TO_TARGET, DESTROYING) over one that is not, then the team order. A partner's
  position is its last status's, carried on at its velocity to now (at most for `lost_link_time`:
  beyond that it is unaccounted, a no-fly column). Reacting only inside the safety distance was
  too late: on street (seed 4) a sweeping UAV at 4.5 m/s and an interceptor at 3 m/s met head-on;
  two braking distances at those speeds plus a tick are about 6 m. Reacting to current velocities
  was too late as well: two sweeps turning into each other, two take-offs side by side and two
  chasers converging on one drone came within 4.0-4.6 m (the velocities said nothing of the turn
  ahead).
- **Giving way**: the UAV with priority does not yield, but it must not fly into the one yielding
  to it, which brakes from its own speed before it can climb. A UAV moving towards a partner
  closer than `safety_distance` (faster than GIVE_WAY_SPEED) that is less than
  `vertical_separation` - GIVE_WAY_SLACK above or below it brakes to a hover, until the partner is
  that far above or below or beyond safety_distance + `separation_hysteresis`, judged by the
  mission's plan it paused (core.py `_mission_plan`), not by its braking, and never while it
  still closes on the partner as fast as made it brake. Its velocity counts there only where a
  plan is missing or the plans break safety_distance within plan_horizon. On unmapped's
  first 20 s the interceptor of the circler, aiming ahead along its circle, flew into the partner
  yielding to it on every seed at 3 m/s; on agile with 3 UAVs (seed 1) a sweep flew into a
  partner holding on its line.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.job_manager.plans import PlannedPath, first_breach, straight_on
from services.lib.runtime.clock import NS

ENGAGED_STATES = ("GOING_TO_TARGET", "DESTROYING")
GIVE_WAY_SPEED = 0.5  # m/s towards a partner: slower, a hovering UAV is not flying into it
GIVE_WAY_SLACK = 0.5  # m: the yielding partner climbs to vertical_separation; this much short of it is clear
GIVE_WAY_PLAN_TIME = 1.0  # s: a breach by the plans this soon makes the UAV with priority brake (_flying_into)


@dataclass
class Partner:
    name: str
    heard: int | None = None  # stamp of the last status
    flying_normally: bool = False
    was_flying: bool = False  # seen flying normally at least once
    normal_since: int | None = None  # start of the current run of "flying normally" statuses
    token_alive: bool | None = None  # job manager's liveliness; None: never seen either way
    position: np.ndarray | None = None
    airborne: bool = False
    state: str = ""
    target: np.ndarray | None = None
    fallen_reason: str = ""  # "" while active
    landed_seen: bool = False  # its last status said it is on the ground
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its last status's, m/s
    plan: PlannedPath | None = None  # the next seconds of its reference, from its last status


@dataclass(frozen=True)
class TeamChange:
    partner: str
    fallen: bool  # True: fell; False: came back
    reason: str


@dataclass
class Team:
    me: str
    members: list[str]  # the world's team order
    partner_timeout_ns: int
    rejoin_time_ns: int
    lost_link_ns: int = 1_500_000_000
    partners: dict[str, Partner] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.partners = {m: Partner(m) for m in self.members if m != self.me}

    # ---------------------------------------------------------------- inputs
    def status(self, name: str, stamp: int, *, flying_normally: bool, airborne: bool, position, state: str,
               target, velocity=(0.0, 0.0, 0.0), plan: PlannedPath | None = None) -> None:
        p = self.partners.get(name)
        if p is None:
            return
        p.heard = stamp if p.heard is None else max(p.heard, stamp)
        if flying_normally and (not p.flying_normally or p.normal_since is None):
            p.normal_since = stamp
        p.flying_normally = flying_normally
        p.was_flying |= flying_normally
        p.position = np.asarray(position, dtype=np.float64).reshape(3)
        p.velocity = np.asarray(velocity, dtype=np.float64).reshape(3)
        p.airborne = airborne
        p.landed_seen = not airborne
        p.state = state
        p.target = None if target is None else np.asarray(target, dtype=np.float64).reshape(3)
        p.plan = plan

    def token(self, name: str, alive: bool, stamp: int) -> None:
        p = self.partners.get(name)
        if p is None:
            return
        p.token_alive = alive
        if not alive:
            p.normal_since = None
        elif p.flying_normally:
            p.normal_since = stamp

    # ------------------------------------------------------------------ rules
    def update(self, now: int, my_takeoff: int | None) -> list[TeamChange]:
        """Apply the fall / come-back rules; returns what changed."""
        changes = []
        for p in self.partners.values():
            if not p.fallen_reason:
                reason = self._fall_reason(p, now, my_takeoff)
                if reason:
                    p.fallen_reason = reason
                    p.normal_since = None  # coming back needs rejoin_time of fresh statuses
                    changes.append(TeamChange(p.name, True, reason))
            elif self._back(p, now):
                changes.append(TeamChange(p.name, False, f"flying normally again for "
                                                         f"{(now - p.normal_since) / NS:.1f} s"))
                p.fallen_reason = ""
        return changes

    def _fall_reason(self, p: Partner, now: int, my_takeoff: int | None) -> str:
        if p.was_flying and not p.flying_normally:
            return f"reports not flying normally ({p.state or 'unknown state'})"
        since = p.heard if p.heard is not None else my_takeoff
        if since is not None and now - since > self.partner_timeout_ns:
            what = "silent" if p.heard is not None else "never heard"
            return f"{what} for {(now - since) / NS:.1f} s"
        return ""

    def _back(self, p: Partner, now: int) -> bool:
        return (p.flying_normally and p.token_alive is not False and p.normal_since is not None
                and p.heard is not None and now - p.heard <= self.partner_timeout_ns
                and now - p.normal_since >= self.rejoin_time_ns)

    # --------------------------------------------------------------- lost link
    def stale(self, p: Partner, now: int, my_takeoff: int | None) -> bool:
        """Silent for lost_link_time (its statuses stop when its radio or its token goes; a link
        glitch shorter than that changes nothing)."""
        since = p.heard if p.heard is not None else my_takeoff
        return since is not None and now - since > self.lost_link_ns

    def unanswering(self, p: Partner, now: int) -> bool:
        """Its job manager's token is gone, or it has been silent for lost_link_time: it cannot
        act on the separation rules."""
        return p.token_alive is False or self.stale(p, now, None)

    def unaccounted(self, now: int, my_takeoff: int | None) -> list[Partner]:
        """Partners that may be flying where I cannot know: stale or fallen, not seen landed."""
        return [p for p in self.partners.values()
                if not p.landed_seen and (p.fallen_reason or self.stale(p, now, my_takeoff))]

    def isolated(self, now: int, my_takeoff: int | None) -> bool:
        """Every partner not seen landed is stale (and there is at least one)."""
        up = [p for p in self.partners.values() if not p.landed_seen]
        return bool(up) and all(self.stale(p, now, my_takeoff) for p in up)

    def lands_when_isolated(self, now: int, my_takeoff: int | None) -> bool:
        """Whether an isolated UAV must land: it goes on only as the first in team order among
        the members not seen landed, with at most one of them unaccounted."""
        up = [m for m in self.members if m == self.me or not self.partners[m].landed_seen]
        return up[0] != self.me or len(self.unaccounted(now, my_takeoff)) > 1

    def no_fly(self, now: int, my_takeoff: int | None) -> np.ndarray:
        """(K, 3) last known positions of unaccounted partners: columns to keep out of."""
        spots = [p.position for p in self.unaccounted(now, my_takeoff) if p.position is not None]
        return np.array(spots, dtype=np.float64).reshape(-1, 3)

    @property
    def active(self) -> list[str]:
        return [m for m in self.members if m == self.me or not self.partners[m].fallen_reason]

    @property
    def fallen(self) -> list[str]:
        return [m for m in self.members if m != self.me and self.partners[m].fallen_reason]

    def claimed_targets(self, my_target: np.ndarray | None, my_position: np.ndarray,
                        claim_radius: float) -> np.ndarray:
        """(K, 3) targets active partners have claimed and I must leave to them."""
        keep = []
        for p in self.partners.values():
            if p.fallen_reason or p.target is None:
                continue
            if my_target is not None and np.linalg.norm(p.target - my_target) <= claim_radius:
                mine = np.linalg.norm(my_position - my_target)
                theirs = np.linalg.norm(p.position - p.target) if p.position is not None else np.inf
                if mine < theirs or (mine == theirs and self.members.index(self.me) < self.members.index(p.name)):
                    continue  # I keep it; the partner yields by the same rule
            keep.append(p.target)
        return np.array(keep, dtype=np.float64).reshape(-1, 3)

    def position_now(self, p: Partner, now: int) -> np.ndarray:
        """A partner's last reported position carried on at its velocity to `now` (at most for
        lost_link_time: a partner silent longer is unaccounted)."""
        age = min(max(now - (p.heard if p.heard is not None else now), 0), self.lost_link_ns) / NS
        return p.position + p.velocity * age

    @staticmethod
    def _flying(p: Partner) -> bool:
        """An active partner that is airborne or taking off, where it is known."""
        return not p.fallen_reason and (p.airborne or p.state == "TAKING_OFF") and p.position is not None

    def _near(self, now: int, me: Mover, rule: SeparationRule, radius: float) -> list[tuple[Partner, np.ndarray, float]]:
        """(partner, its offset from me now, distance) of every active partner that is airborne or
        taking off and closer than `radius` now or predicted to be (`predicted_breach`)."""
        found = []
        for p in self.partners.values():
            if not self._flying(p):
                continue
            offset = self.position_now(p, now) - me.position
            distance = float(np.linalg.norm(offset))
            if distance < radius or self.predicted_breach(now, me, p, rule, radius):
                found.append((p, offset, distance))
        return found

    def partner_plan(self, p: Partner, now: int, rule: SeparationRule) -> tuple[PlannedPath, float]:
        """A partner's plan and its age, s (its last status's); without one, its last position carried
        on at its last velocity."""
        heard = p.heard if p.heard is not None else now
        age = max(now - heard, 0) / NS
        if p.plan is not None:
            return p.plan, age
        return straight_on(p.position, p.velocity, heard, rule.plan_horizon + age, rule.plan_step), age

    def predicted_breach(self, now: int, me: Mover, p: Partner, rule: SeparationRule, radius: float) -> bool:
        """Whether the partner and I are predicted to come closer than `radius`: by our plans within
        plan_horizon when either of us has one, else by our velocities within rule.lookahead."""
        if me.plan is None and p.plan is None:
            offset = self.position_now(p, now) - me.position
            return breach_time(offset, p.velocity - me.velocity, radius) <= rule.lookahead
        mine = me.plan if me.plan is not None else straight_on(me.position, me.velocity, now, rule.plan_horizon,
                                                                 rule.plan_step)
        theirs, age = self.partner_plan(p, now, rule)
        approach = first_breach(mine, theirs, now, rule.plan_horizon, rule.plan_step, radius, age, rule.widen_rate)
        if approach.breach <= rule.plan_horizon or not self.unanswering(p, now):
            return approach.breach <= rule.plan_horizon
        # one that does not answer may fly its plan (a cut radio) or have stopped where it was (killed:
        # its autopilot holds or lands there, where its last plan went on towards its target)
        halted = straight_on(self.position_now(p, now), np.zeros(3), now, rule.plan_horizon, rule.plan_step)
        return first_breach(mine, halted, now, rule.plan_horizon, rule.plan_step, radius, age,
                            rule.widen_rate).breach <= rule.plan_horizon

    def hold_spot(self, now: int, me: Mover, p: Partner, rule: SeparationRule, at: np.ndarray | None = None) -> np.ndarray:
        """Where a UAV yielding to `p` holds: where it comes to rest braking from its velocity at
        `rule.braking` (or `at`, the spot it holds at), when the partner's plan keeps safety_distance
        + hysteresis from there over the horizon (and on the ground while it is not airborne);
        else also vertical_separation above the highest point of that plan within that reach. Asked
        again on every tick of a yield: a plan that passes clear now may come through the spot later
        (agile, 3 UAVs, seed 1: a sweep 42 m away). Not where the yield began: braked past it, the
        UAV flew back faster than it climbed, towards the partner braking towards it (intruder,
        3 UAVs, seeds 3435 and 1109: 4.4 and 4.5 m). Level against a partner that does not answer
        and comes after me in team order: cut off, it yields to me too and climbs (`yield_to`)."""
        spot = np.asarray(me.position if at is None else at, dtype=np.float64).copy()
        if at is None and me.airborne:
            speed = float(np.linalg.norm(me.velocity[:2]))
            spot[:2] += me.velocity[:2] * speed / (2.0 * rule.braking)
        theirs, age = self.partner_plan(p, now, rule)
        reach = rule.safety_distance + rule.hysteresis
        here = PlannedPath(now, rule.plan_step, spot[None])
        if not me.airborne:
            return spot  # on the ground, taking off or landing: it stays there (cutclose: one rose 10 m to yield)
        if self.unanswering(p, now) and self.members.index(self.me) < self.members.index(p.name):
            return spot  # level: cut off, it yields to me by the same rule on the same picture and climbs
        if first_breach(here, theirs, now, rule.plan_horizon, rule.plan_step, reach, age, rule.widen_rate).breach == np.inf:
            return spot
        times = now + np.round(np.arange(int(rule.plan_horizon / rule.plan_step) + 1) * rule.plan_step * NS).astype(np.int64)
        path = theirs.at(times)
        close = np.linalg.norm(path[:, :2] - spot[:2], axis=1) < reach + age * rule.widen_rate
        spot[2] = max(spot[2], float(path[close, 2].max(initial=self.position_now(p, now)[2])) + rule.vertical_separation)
        return spot

    def give_way_to(self, now: int, me: Mover, rule: SeparationRule, giving_way_to: str | None) -> Partner | None:
        """The partner a UAV must brake for now (None: no one); see the module docstring. A give-way
        lasts while the partner is near or I am still closing on it as fast as made me brake: it began
        on our velocities, and ending it on our plans alone (the partner's now a braking one) let it
        end on the next tick and begin again on the one after (intruder, 2 UAVs, seed 3545: 16 m apart)."""
        near = self._near(now, me, rule, rule.safety_distance + rule.hysteresis)
        held = self.partners.get(giving_way_to) if giving_way_to is not None else None
        if held is not None and self._flying(held) and all(p is not held for p, _, _ in near):
            offset = self.position_now(held, now) - me.position
            distance = float(np.linalg.norm(offset))
            if self._closing(me, held, offset, distance, rule):
                near.append((held, offset, distance))
        best, best_distance = None, np.inf
        for p, offset, distance in near:
            if abs(offset[2]) >= rule.vertical_separation - GIVE_WAY_SLACK:
                continue
            if p.name != giving_way_to and not self._flying_into(now, me, p, offset, distance, rule):
                continue
            if distance < best_distance:
                best, best_distance = p, distance
        return best

    @staticmethod
    def _closing(me: Mover, p: Partner, offset: np.ndarray, distance: float, rule: SeparationRule) -> bool:
        """Flying towards the partner (faster than GIVE_WAY_SPEED) and inside the safety distance
        within rule.lookahead by our velocities."""
        return float(me.velocity @ offset) > GIVE_WAY_SPEED * distance and \
            breach_time(offset, p.velocity - me.velocity, rule.safety_distance) <= rule.lookahead

    def _flying_into(self, now: int, me: Mover, p: Partner, offset: np.ndarray, distance: float,
                     rule: SeparationRule) -> bool:
        """A new hold: flying towards the partner (now, or by my plan over the next second) and inside
        the safety distance within rule.lookahead by our velocities, or within GIVE_WAY_PLAN_TIME by
        our plans. By velocities alone a plan that starts towards a partner (a sweep taken up after an
        interception) was seen only once under way: agile, 3 UAVs, seed 1, 6.7 m apart, 4.1 m at the
        closest. The plans' horizon is kept short: the partner yielding to me changes its plan in
        answer to mine, and two UAVs acting on each other's plans seconds ahead take turns holding.
        Velocities count only where a plan is missing or the plans break the safety distance within
        plan_horizon: two chases closing fast by their velocities while their plans turned apart both
        braked, again and again, and both targets got away (intruder, 2 UAVs, seed 3545, 15-16 m)."""
        if self._closing(me, p, offset, distance, rule):
            return me.plan is None or p.plan is None or self.predicted_breach(now, me, p, rule, rule.safety_distance)
        if me.plan is None:
            return False
        heading = me.plan.at(np.array([now + NS]))[0] - me.plan.at(np.array([now]))[0]
        if float(heading @ offset) <= GIVE_WAY_SPEED * distance:
            return False
        theirs, age = self.partner_plan(p, now, rule)
        return first_breach(me.plan, theirs, now, GIVE_WAY_PLAN_TIME, rule.plan_step, rule.safety_distance, age,
                            rule.widen_rate).breach <= GIVE_WAY_PLAN_TIME

    def yield_to(self, now: int, me: Mover, rule: SeparationRule, yielding_to: str | None) -> Partner | None:
        """The partner this UAV must give way to now (None: no one). A partner that does not answer
        (stale, or its job manager's token gone) outranks everyone: killed, it cannot yield. Killed
        while engaging, its last status still ranked it below an engaged UAV that flew on at it as
        it came down in its emergency landing (campaign run 11, intruder, 2 UAVs: 2.8 m). Only cut
        off, it still flies by these rules and sees me not answering either, so both yield; only
        the later in team order climbs (`hold_spot`), as in every other yield: both climbing
        alike, two UAVs already closer than the safety distance would stay so."""
        order = self.members.index(self.me)
        engaged = me.state in ENGAGED_STATES
        best, best_distance = None, np.inf
        for p, offset, distance in self._near(now, me, rule, rule.safety_distance + rule.hysteresis):
            if p.name != yielding_to:  # a new yield: inside the safety distance now or predicted to be
                if distance >= rule.safety_distance and not self.predicted_breach(now, me, p, rule, rule.safety_distance):
                    continue
            theirs = p.state in ENGAGED_STATES
            outranked = self.unanswering(p, now) or (theirs if theirs != engaged else self.members.index(p.name) < order)
            if outranked and distance < best_distance:
                best, best_distance = p, distance
        return best


@dataclass(frozen=True)
class Mover:
    """This UAV as the separation rules see it."""
    position: np.ndarray
    velocity: np.ndarray
    state: str
    plan: PlannedPath | None = None  # its own reference (None: not known yet)
    airborne: bool = True


@dataclass(frozen=True)
class SeparationRule:
    safety_distance: float  # m
    vertical_separation: float  # m a yielding UAV climbs above the partner's plan near it
    hysteresis: float  # m beyond safety_distance before a yield or a hold ends
    lookahead: float  # s: a breach predicted from velocities this soon counts as one now
    plan_horizon: float = 6.0  # s of plans compared
    plan_step: float = 0.25  # s between the compared samples
    widen_rate: float = 2.0  # m per s of a partner plan's age added to the distance it must keep
    braking: float = 3.0  # m/s² a yielding UAV brakes at (the attack profile's): its hold is where it stops


def breach_time(offset: np.ndarray, relative_velocity: np.ndarray, radius: float) -> float:
    """Seconds until a partner at `offset` moving at `relative_velocity` (both relative to this
    UAV, constant) first comes closer than `radius`: 0 when it already is, inf when it never will."""
    gap = float(offset @ offset) - radius * radius
    if gap < 0.0:
        return 0.0
    closing = float(offset @ relative_velocity)
    speed2 = float(relative_velocity @ relative_velocity)
    if closing >= 0.0 or speed2 == 0.0:
        return np.inf
    discriminant = closing * closing - speed2 * gap
    if discriminant < 0.0:
        return np.inf
    return (-closing - np.sqrt(discriminant)) / speed2
