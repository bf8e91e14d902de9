"""The job manager's mission state machine (seed 004, ch. 3), pure and clock-injected.

Automatic start (§3.6) wraps the seed's five states: PREFLIGHT (every required service alive
and the LiDAR stream heard within `sensor_timeout`: a token says a process is up, not that its
data flows, and a UAV that left the ground before its first scan would be sent straight back
down by the abort below when perception is slow to start, e.g. real time on a loaded computer)
→ TAKING_OFF → the state machine proper — IDLE, GOING_AROUND, CHECKING_TARGET,
GOING_TO_TARGET, DESTROYING (§3.4) — until the mission timer says LANDING → LANDED. The abort
system (§3.5.3) sends any flying state to EMERGENCY_LANDING when the LiDAR stream (one
Detections message per scan) or odometry has been silent for `sensor_timeout`.

Flying without GNSS (`positioning_by_localizer`), the odometry carries the localizer's health
(services/localizer): PREFLIGHT also waits for "tracking"; in flight "degraded" flies every
command slower (profile "degraded", `degraded_speed`), and "lost" holds position (a stop) and,
lost for `sensor_timeout`, is treated as a silent LiDAR: EMERGENCY_LANDING. Not in the seed,
whose UAV had GNSS.

Routines beside the machine (§3.5): state timers T_c, T_g, T_d that forbid the current target
and return to IDLE (T_d for a mover counts from its latest close pass: `_timed_since`);
forbidden zones and the tries counter (targets.py); the detection filter (working area,
forbidden zones, partners' claims); the team rules — revenge mode, one chaser per target,
separation (team.py).

Deviations from the seed, and why: the seed's camera needed the search height and a stop to
see well; a 360° LiDAR does not, so CHECKING_TARGET only waits for the stop manoeuvre and the
approach (planner) handles height. The attack is "done" when the UAV has passed the target and
slowed down at the end of its overshoot; the next decision then starts from IDLE, and a target
that is still there is tried again (n_f tries make a forbidden zone). Moving targets (a
confirmed track faster than `moving_speed`) are intercepted instead of approached, along the
tracker's prediction of that track (its identity followed; the target filter's straight line
only when no confirmed track is at it); static targets are preferred when both are in view.

Every transition is decided in `_next_state`; every command in `_decision_for`; time is
always passed in (int ns of mission time).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace

import numpy as np

from schemas import keys
from services.job_manager.areas import grown_part, split_area
from services.job_manager.params import JobManagerParams
from services.job_manager.plans import PlannedPath
from services.job_manager.sightings import ConfirmedTracks, Sightings
from services.job_manager.targets import NS, ForbiddenZones, TargetFilter, usable_detections
from services.job_manager.team import Mover, SeparationRule, Team
from services.lib.geometry import polygon_area
from services.lib.lidar.sanity import SensorTrust
from services.lib.tracks import PredictedPath


class State(enum.Enum):
    PREFLIGHT = "PREFLIGHT"  # on the ground until every required service is alive
    TAKING_OFF = "TAKING_OFF"
    IDLE = "IDLE"
    GOING_AROUND = "GOING_AROUND"
    CHECKING_TARGET = "CHECKING_TARGET"
    GOING_TO_TARGET = "GOING_TO_TARGET"
    DESTROYING = "DESTROYING"
    LANDING = "LANDING"
    LANDED = "LANDED"
    EMERGENCY_LANDING = "EMERGENCY_LANDING"


MISSION_STATES = (State.IDLE, State.GOING_AROUND, State.CHECKING_TARGET, State.GOING_TO_TARGET, State.DESTROYING)
_WATCHED = (State.TAKING_OFF, *MISSION_STATES)  # the abort system and the mission timer act here
_DESCENDING = (State.LANDING, State.EMERGENCY_LANDING)
REPLAN_LOOKAHEAD = 1.0  # s over which a mover's new prediction is compared with the one sent
TRACK_SEEN_WITHIN = 0.15  # s: a track corrected this recently (a scan period and a half) sees its target
TAKEOVER_SWEEP_MARGIN = 1.5  # × the sweep's straight-line time: turns, and the transfer into the part taken over
DOWN_MARGIN = 1.0  # m above the lowest target height: a mover last seen lower and predicted below it is down
FLEET_SEEN_WITHIN = 0.5  # s: a partner's track corrected this recently is a sighting (its link and tick add lag)
_TIMED = {State.CHECKING_TARGET: "checking_timeout", State.GOING_TO_TARGET: "going_timeout",
          State.DESTROYING: "destroying_timeout"}


# Every stop (and a landing's braking) brakes as hard as the vehicle may: a pursuit at the attack
# profile's speed plans to brake at its acceleration before an obstacle; a stop replacing it at the
# sweeping profile's half of that overshot by the difference (intruder, 2 UAVs, seed 3670: a chase lost from view 2 m before a tree's
# crown ended in the crown at 1.9 m/s).
STOP_PROFILE = "attack"


@dataclass(frozen=True)
class MissionDecision:
    """What the planner should do; a new MissionCommand goes out whenever it changes."""

    action: str  # a schemas.messages.MissionAction
    area: tuple[tuple[float, float], ...] = ()
    height: float = 5.0
    spacing: float = 10.0
    profile: str = "sweeping"  # or "attack"
    target: tuple[float, float, float] | None = None
    target_velocity: tuple[float, float, float] | None = None
    target_path: tuple[tuple[float, float, float], ...] = ()  # a mover's predicted positions every target_path_dt
    target_path_dt: float = 0.0
    target_seen: int = 0  # ns: when the target was last measured (0: not said)
    # ns: when the sighting the target was taken from was made (0: no target); the command's
    # header.source. Not part of the decision: a fresher sighting of the same aim is no new command.
    sighted: int = field(default=0, compare=False)


@dataclass(frozen=True)
class Transition:
    stamp: int
    source: State
    target: State
    reason: str


@dataclass
class Engagement:
    """The locked target b_c, followed by its target filter. A target found to move (its
    filter's velocity, or a fast confirmed track at the lock) is intercepted, never attacked."""

    filter: TargetFilter
    moving: bool = False
    track_id: int | None = None  # the tracker's confirmed track of a mover, followed by its identity
    track_corrected: int = 0  # ns: that track's last correction already taken as a sighting
    close_pass_at: int = 0  # ns: when a mover, just seen, was last within close_pass_distance (restarts T_d)
    attacking: bool = False
    attack_direction: np.ndarray | None = None  # horizontal unit vector
    attack_target: np.ndarray | None = None

    def position(self, now: int) -> np.ndarray:
        return self.filter.predict(now) if self.moving else self.filter.estimate

    def last_seen(self) -> int:
        return self.filter.last_seen

    def last_observed(self) -> int:
        """When the newest sighting taken was really made (a partner's track: its last correction)."""
        return self.filter.last_observed


@dataclass(frozen=True)
class TakeoverSweep:
    """Revenge mode's first sweep: the part taken over from a fallen partner, until when (_note_taken_over)."""

    area: np.ndarray  # (K, 2) polygon
    until: int  # ns


@dataclass(frozen=True)
class Candidates:
    """Detections the machine may act on, each with the stamp of its scan or frame, when it was
    really made (a partner's track: its partner's last correction of it) and its covariance (NaN
    where the detector gave none)."""

    positions: np.ndarray  # (N, 3)
    stamps: np.ndarray  # (N,) int ns
    covariances: np.ndarray  # (N, 3, 3)
    tethered: np.ndarray  # (N,) bool: seen by the camera's balloon detector
    observed: np.ndarray  # (N,) int ns, <= stamps

    def newest(self) -> Candidates:
        """Those of the latest scan or frame."""
        return self.subset(self.stamps == self.stamps.max(initial=0))

    def subset(self, keep: np.ndarray) -> Candidates:
        return Candidates(self.positions[keep], self.stamps[keep], self.covariances[keep], self.tethered[keep],
                          self.observed[keep])


def _rows(covariances: np.ndarray | None, keep: np.ndarray) -> np.ndarray | None:
    return None if covariances is None else covariances[keep]


def _tuple(v) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


@dataclass(frozen=True, slots=True)
class _Step:
    """What one update of the machine sees, for the state rules."""

    now: int
    position: np.ndarray
    velocity: np.ndarray
    airborne: bool
    services_ready: bool


# Pre-flight check (seed 004 §3.6, JobManager.services_ready): the services this UAV's mission
# depends on, and the detectors of which one must run (the classifier, or the evaluation oracle).
REQUIRED_SERVICES = ("sensor_driver", "tracker", "planner")
DETECTORS = ("classifier", keys.ORACLE)


class JobManager:
    def __init__(self, params: JobManagerParams, uav: str) -> None:
        self.params = params
        self.uav = uav
        self.state = State.PREFLIGHT
        self.state_since = 0
        self.working_area: np.ndarray | None = None
        self.arena: np.ndarray | None = None
        self.team: Team | None = None
        self.ground_z = 0.0
        self.duration_ns = 0  # 0: no mission timer
        self.transitions: list[Transition] = []
        self.notes: list[str] = []  # what happened beside transitions, for the node's log (it drains them)
        self.zones = ForbiddenZones(params.forbidden_radius, int(params.forbidden_lifetime * NS), params.forbidden_tries)
        self.engagement: Engagement | None = None
        self.takeoff_at: int | None = None
        self._world_key: tuple | None = None
        self._decision: MissionDecision | None = None
        self._landing_target: tuple[float, float, float] | None = None
        self._candidate_seen: int | None = None
        self._checked: np.ndarray | None = None  # closest candidate while CHECKING_TARGET (b_c before the lock)
        self._stopping = False
        self._climbed = False
        self._yield: tuple[str, tuple[float, float, float]] | None = None
        self._giving_way_to: str | None = None  # the partner this engaged UAV brakes for (team.py)
        self._giving_way_height = 0.0
        self._sent_target: np.ndarray | None = None
        self._sent_prediction: PredictedPath | None = None  # of a mover, with _sent_at
        self._sent_at = 0
        self._sent_seen = 0  # when the mover of the sent prediction was last measured
        self._holding_for_sighting = False  # an interception not taken up on an old sighting (said once)
        self._now = 0
        self.seen = Sightings(params)
        self.reference: PlannedPath | None = None  # the own planner's latest reference
        # a yield's: the mission's reference, since when, and in which state the machine made it
        self._paused: tuple[PlannedPath | None, int, State] | None = None
        self.lidar = SensorTrust(params.sensor_settle_time)  # detections are not acted on while it fails or settles
        self.camera = SensorTrust(params.sensor_settle_time)
        self._previous_target: np.ndarray | None = None  # what was locked before CHECKING_TARGET
        self._no_moving_until = 0  # a moving target that ran out a state timer: movers are skipped till then
        self._unseen_from = 0  # when the locked target last came within reliable range
        self.positioning_by_localizer = False  # flying without GNSS: the odometry's health counts
        self.positioning = ""  # the latest odometry's health ("" when no localizer says any)
        self._positioning_lost_since: int | None = None
        self._sweep_first: TakeoverSweep | None = None
        self._blocked: tuple[int, str] | None = None  # (since, why): the planner finds every way to the target blocked

    # ----------------------------------------------------------------- inputs
    def set_world(self, arena: np.ndarray, uavs: list[str], duration_s: float, ground_z: float = 0.0) -> bool:
        """The arena and team; this UAV's working area is its share among the active UAVs.
        Cheap when nothing changed (the world is re-sent every second); True when it did."""
        arena = np.asarray(arena, dtype=np.float64).reshape(-1, 2)
        key = (arena.tobytes(), tuple(uavs), float(duration_s), float(ground_z))
        if key == self._world_key:
            return False
        if self.uav not in uavs:
            raise ValueError(f"{self.uav} is not in the world's team {uavs}")
        if len(arena) < 3 or not np.isfinite(arena).all():
            raise ValueError(f"the arena needs at least 3 finite vertices, got {len(arena)}")
        if not (0.0 <= duration_s < 1e6 and np.isfinite(ground_z)):  # 1e6 s: 11 days, beyond any battery
            raise ValueError(f"mission duration {duration_s} s or ground height {ground_z} m is impossible")
        self._world_key = key
        self.arena = arena
        p = self.params
        if self.team is None or self.team.members != list(uavs):
            self.team = Team(self.uav, list(uavs), int(p.partner_timeout * NS), int(p.rejoin_time * NS),
                             lost_link_ns=int(p.lost_link_time * NS))
        self.duration_ns = int(round(duration_s * NS))
        self.ground_z = float(ground_z)
        self._split()
        return True

    def _split(self) -> None:
        active = self.team.active
        self.working_area = split_area(self.arena, len(active))[active.index(self.uav)]

    def observe_detections(self, stamp: int, positions: np.ndarray, covariances: np.ndarray | None = None,
                           sensor_health: str = "") -> None:
        """One scan's detections (N, 3), world frame, with their covariances (N, 3, 3) if known;
        also the LiDAR heartbeat of the abort system. A scan that failed its sanity check
        (`sensor_health` says why), and those within sensor_settle_time after, count as heartbeats
        that saw nothing."""
        self.lidar.note(stamp, not sensor_health)
        if not self.lidar.trusted(stamp):
            positions, covariances = np.zeros((0, 3)), None
        positions, covariances = self.seen.scan(stamp, positions, covariances)
        above = positions[:, 2] >= self.ground_z + self.params.min_target_height
        if self.engagement is not None:
            self.engagement.filter.update(positions[above], stamp, _rows(covariances, above))
        mover = self.seen.last_mover
        if mover is not None and (self.engagement is None or mover is not self.engagement.filter):
            mover.update(positions[above], stamp, _rows(covariances, above))  # keep knowing where it is

    def observe_camera(self, stamp: int, positions: np.ndarray, covariances: np.ndarray | None = None,
                       sensor_health: str = "") -> None:
        """One camera frame's detections (N, 3), world frame, with their covariances (N, 3, 3) if
        known (Object Detect: balloons by colour; far ones are metres off along the ray); as
        observe_detections while the frames fail their sanity check or settle."""
        self.camera.note(stamp, not sensor_health)
        if not self.camera.trusted(stamp):
            positions, covariances = np.zeros((0, 3)), None
        positions, covariances = self.seen.camera(stamp, positions, covariances)
        above = positions[:, 2] >= self.ground_z + self.params.min_target_height
        if self.engagement is not None:
            self.engagement.filter.update(positions[above], stamp, _rows(covariances, above), tethered=True)

    def observe_tracks(self, stamp: int, ids: np.ndarray, positions: np.ndarray, velocities: np.ndarray,
                       paths=(), path_dt: float = 0.0, fleet: np.ndarray | None = None,
                       covariances: np.ndarray | None = None, corrected: np.ndarray | None = None) -> None:
        """Confirmed tracks: ids (K,), positions and velocities (K, 3) at `stamp`, and each one's
        predicted path (M, 3) every path_dt s. They tell at the lock whether a target moves (the
        target filter finds out by itself a little later), and a mover is intercepted along them.
        `fleet` (K,) marks the tracks only partners see (their position covariances (K, 3, 3)):
        those count as detections of the fleet (Sightings.fleet) while their partner corrected them
        within FLEET_SEEN_WITHIN. `corrected` (K,): when a scan or a detection last corrected each
        track; a fresh correction of the track a mover is followed by counts as seeing it
        (`_track_sees_the_mover`). Agile seed 4: a partner's track coasting on after the drone
        braked behind a tree, counted as a sighting, kept the UAV chasing the empty prediction."""
        self.seen.confirmed_tracks(ConfirmedTracks.of(stamp, ids, positions, velocities, paths, path_dt))
        if corrected is not None:
            self._track_sees_the_mover(stamp, np.asarray(ids).reshape(-1), np.asarray(positions).reshape(-1, 3),
                                       np.asarray(velocities).reshape(-1, 3), np.asarray(corrected).reshape(-1),
                                       covariances)
        if fleet is None:
            return
        fleet = np.asarray(fleet, dtype=bool).copy()
        if corrected is not None:  # a partner's track coasting unseen is a guess, not a sighting (0: not said)
            age = stamp - np.asarray(corrected, dtype=np.int64).reshape(-1)
            fleet &= (np.asarray(corrected).reshape(-1) == 0) | (age <= int(FLEET_SEEN_WITHIN * NS))
        if not fleet.any():
            return
        made = None
        if corrected is not None:  # 0: not said, so as fresh as the message
            made = np.asarray(corrected, dtype=np.int64).reshape(-1)[fleet]
            made = np.where(made == 0, stamp, made)
        seen, covs, made = self.seen.fleet(stamp, np.asarray(positions, dtype=np.float64).reshape(-1, 3)[fleet],
                                           None if covariances is None else np.asarray(covariances)[fleet], made)
        above = seen[:, 2] >= self.ground_z + self.params.min_target_height
        if self.engagement is not None:
            self.engagement.filter.update(seen[above], stamp, _rows(covs, above), observed=made[above])

    def _track_sees_the_mover(self, stamp: int, ids: np.ndarray, positions: np.ndarray, velocities: np.ndarray,
                              corrected: np.ndarray, covariances: np.ndarray | None) -> None:
        """The tracker's scan updates keep a mover in sight when the detector loses it: near trees
        and walls the classifier calls its cluster background (rule A, d_close 1.5 m), while the
        tracker, which knows it is a target, still takes its returns (occupied_distance 0.8 m).
        Where the target filter's gate refuses the track's fresh position (the drone turned while
        out of sight, away from the line fitted before), the filter starts again from the track."""
        e = self.engagement
        if e is None or not e.moving or e.track_id is None:
            return
        found = np.flatnonzero(ids == e.track_id)
        if not len(found):
            return
        k = int(found[0])
        if corrected[k] <= e.track_corrected or stamp - corrected[k] > int(TRACK_SEEN_WITHIN * NS):
            return
        e.track_corrected = int(corrected[k])
        covariance = _rows(covariances, found[:1])
        if not e.filter.update(positions[k][None], stamp, covariance):
            e.filter.reanchor(positions[k], stamp, velocities[k], None if covariance is None else covariance[0],
                              observed=int(corrected[k]))
            self.notes.append(f"track {e.track_id} seen at {self._fmt(positions[k])}, off the target's predicted "
                              "line: following it from there")

    def plan_report(self, stamp: int, action: str, outcome: str, note: str = "") -> None:
        """What the planner made of the latest command (PlanReport): an approach or attack of a
        static target that it finds blocked by obstacles, and keeps finding so for blocked_time,
        makes the target a forbidden zone (_next_state); any other outcome ends that."""
        engaged = self.engagement is not None and not self.engagement.moving and action in ("approach", "attack")
        if engaged and outcome == "blocked":
            if self._blocked is None:
                self._blocked = (stamp, note)
        else:
            self._blocked = None

    def partner_status(self, name: str, stamp: int, *, flying_normally: bool, airborne: bool = True,
                       position=(0.0, 0.0, 0.0), state: str = "", target=None, velocity=(0.0, 0.0, 0.0),
                       plan: PlannedPath | None = None) -> None:
        if self.team is not None and name != self.uav:
            self.team.status(name, stamp, flying_normally=flying_normally, airborne=airborne,
                             position=position, state=state, target=target, velocity=velocity, plan=plan)

    def observe_reference(self, plan: PlannedPath) -> None:
        """This UAV's own planner's latest reference (the separation rules compare it with the partners')."""
        self.reference = plan

    def shared_plan(self, now: int) -> PlannedPath | None:
        """The next plan_horizon s of the own reference, every plan_step s, for the status (None: none yet)."""
        if self.reference is None:
            return None
        return self.reference.sampled(now, self.params.plan_horizon, self.params.plan_step)

    def partner_token(self, name: str, alive: bool, stamp: int) -> None:
        if self.team is not None and name != self.uav:
            self.team.token(name, alive, stamp)

    def is_airborne(self, z: float) -> bool:
        return bool(z - self.ground_z > self.params.airborne_height)

    def services_ready(self, alive: set[str]) -> bool:
        """The pre-flight check (seed 004 §3.6) on the names of this UAV's services that are alive:
        every service its mission depends on (the localizer too when flying without GNSS) and one
        detector (the classifier, or the evaluation oracle that replaces it)."""
        required = REQUIRED_SERVICES + ((keys.LOCALIZER,) if self.positioning_by_localizer else ())
        return all(s in alive for s in required) and any(d in alive for d in DETECTORS)

    def positioning_health(self, reported: str, localizer_alive: bool) -> str:
        """The odometry's health as the machine takes it: "lost" once the localizer of a UAV flying
        without GNSS is gone (its token vanished), at once and whatever the odometry still says (the
        flight controller carries its last estimate on unchecked, and would notice the silence only
        after its estimate timeout: services/simulator/positioning.py); on the ground it only waits."""
        if self.positioning_by_localizer and not localizer_alive and self.state is not State.PREFLIGHT:
            return "lost"
        return reported

    @property
    def flying_normally(self) -> bool:
        """Seed 004 §3.5.4: False until take-off succeeded, and again once landing."""
        return self.state in MISSION_STATES

    @property
    def target(self) -> tuple[float, float, float] | None:
        """The claimed target b_c (in the status, so partners leave it alone)."""
        if self.engagement is None or self.state not in (State.GOING_TO_TARGET, State.DESTROYING):
            return None
        return _tuple(self.engagement.position(self._now))

    @property
    def decision(self) -> MissionDecision | None:
        return self._decision

    # ------------------------------------------------------------------ step
    def update(self, now_ns: int, position: np.ndarray, airborne: bool, services_ready: bool,
               position_stamp_ns: int | None = None, velocity: np.ndarray | None = None,
               positioning: str = "") -> MissionDecision | None:
        """Advance the machine; returns the new decision when it changed, else None.
        `position_stamp_ns` is the stamp of the odometry `position` came from (default: now);
        `positioning` its health (Odometry.health: "" without a localizer)."""
        self._now = now_ns
        self._note_positioning(positioning, now_ns)
        position = np.asarray(position, dtype=np.float64).reshape(3)
        velocity = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64).reshape(3)
        stamp = now_ns if position_stamp_ns is None else position_stamp_ns
        for zone in self.zones.expire(now_ns):
            self.notes.append(f"forbidden zone at ({zone.center[0]:.1f}, {zone.center[1]:.1f}, "
                              f"{zone.center[2]:.1f}) expired")
        if self.team is not None and self.state in MISSION_STATES:  # revenge only matters while on the mission
            changes = self.team.update(now_ns, self.takeoff_at)
            for change in changes:
                self.notes.append(f"partner {change.partner} {'fell' if change.fallen else 'is back'}: {change.reason}")
            if changes:
                before = self.working_area
                self._split()
                self._note_taken_over(before, now_ns)
                self.notes.append(f"working area now {len(self.team.active)}-way split "
                                  f"(active: {', '.join(self.team.active)}): x {self.working_area[:, 0].min():.1f}"
                                  f"..{self.working_area[:, 0].max():.1f}")
        target, reason = self._next_state(now_ns, position, velocity, airborne, services_ready, stamp)
        if target is not self.state:
            self._enter(target, now_ns, reason, position)
        decision = (self._yielding(now_ns, position, velocity, airborne) or self._giving_way(now_ns, position, velocity)
                    or self._decision_for(now_ns, position))
        decision = self._within_positioning(decision, position)
        if decision == self._decision:
            return None
        self._decision = decision
        return decision

    def _note_taken_over(self, before: np.ndarray | None, now: int) -> None:
        """Revenge mode: a working area that grew is swept first where it grew, the fallen partner's
        part, for as long as one sweep of it takes (its area / (spacing · sweeping speed) times
        TAKEOVER_SWEEP_MARGIN for the turns), then whole. Sweeping the whole area at once started
        from the UAV's own part, which it had swept already. Measured on mbzirc, 2 UAVs, uav2's link
        cut for good at 20 s (uav1 takes over at 35 s): the last two balloons went at 62.2 and
        81.6 s instead of 70.5 and 88.3 s."""
        grown = None if before is None else grown_part(before, self.working_area)
        self._sweep_first = None
        if grown is not None:
            p = self.params
            seconds = TAKEOVER_SWEEP_MARGIN * polygon_area(grown) / (p.scan_spacing * p.sweeping_speed)
            self._sweep_first = TakeoverSweep(grown, now + int(seconds * NS))
            self.notes.append(f"sweeping the part taken over first (x {grown[:, 0].min():.1f}.."
                              f"{grown[:, 0].max():.1f}, {seconds:.0f} s)")

    def _sweep_area(self, now: int) -> np.ndarray:
        if self._sweep_first is not None and now < self._sweep_first.until:
            return self._sweep_first.area
        return self.working_area

    def _note_positioning(self, health: str, now: int) -> None:
        if not self.positioning_by_localizer:
            return
        if health != self.positioning and self.state is not State.PREFLIGHT:
            self.notes.append(f"positioning {health or 'unknown'}" + {
                "degraded": f": flying at {self.params.degraded_speed:g} m/s at most",
                "lost": f": holding position; landing if lost for {self.params.sensor_timeout:g} s"}.get(health, ""))
        self.positioning = health
        if health != "lost":
            self._positioning_lost_since = None
        elif self._positioning_lost_since is None:
            self._positioning_lost_since = now

    def _within_positioning(self, decision: MissionDecision, position: np.ndarray) -> MissionDecision:
        """A flying decision as the localizer's health allows: held while lost, slowed while degraded."""
        if not self.positioning_by_localizer or self.state not in _WATCHED:
            return decision
        if self.positioning == "lost":
            return MissionDecision("stop", height=self.params.search_height, spacing=decision.spacing,
                                   profile=STOP_PROFILE)
        if self.positioning == "degraded" and decision.action != "stop":  # braking never speeds up
            return replace(decision, profile="degraded")
        return decision

    def _enter(self, target: State, now: int, reason: str, position: np.ndarray) -> None:
        self.transitions.append(Transition(now, self.state, target, reason))
        if target is State.TAKING_OFF:
            self.takeoff_at = now
        if target in _DESCENDING:
            self._landing_target = (float(position[0]), float(position[1]), self.ground_z)
        if self.engagement is not None and self.engagement.moving:
            self.seen.last_mover = self.engagement.filter
        if target in (State.IDLE, *_DESCENDING, State.LANDED):
            self.engagement = None
        if target is State.CHECKING_TARGET:
            self._checked = None
            self._previous_target = None if self.engagement is None else self.engagement.position(now)
            self.engagement = None  # a new lock follows; the old target only biases the choice
        if target is State.GOING_TO_TARGET:
            self._unseen_from = 0
        if target not in (State.GOING_TO_TARGET, State.DESTROYING):
            self._blocked = None
        if target is State.GOING_AROUND:
            self._stopping = False
            self._climbed = False
        self.state, self.state_since = target, now

    def _mission_over(self, now: int) -> bool:
        return self.duration_ns > 0 and now >= self.duration_ns - int(self.params.landing_margin * NS)

    def candidates(self, now: int, position: np.ndarray) -> np.ndarray:
        """(N, 3) detections in view that this UAV may act on (seed 004 §3.5.2 filter)."""
        latest = self.seen.in_view(now)
        return np.zeros((0, 3)) if latest is None else self._usable(latest, now, position, self.seen.view_stamp)

    def recent_candidates(self, now: int, position: np.ndarray) -> Candidates:
        """Candidates of the scans and frames of the last t_m, with their stamps and covariances:
        a target far away shows in some scans only, and the stop manoeuvre may carry it out of
        range for a while."""
        fresh = [seen for seen in self.seen.recent if now - seen.stamp <= int(self.params.target_time * NS)]
        keeps = [self._usable_mask(seen.positions, now, position, seen.stamp) for seen in fresh]
        if not fresh:
            return Candidates(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)),
                              np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64))
        return Candidates(np.concatenate([seen.positions[keep] for seen, keep in zip(fresh, keeps)]),
                          np.concatenate([np.full(int(keep.sum()), seen.stamp, dtype=np.int64)
                                          for seen, keep in zip(fresh, keeps)]),
                          np.concatenate([seen.covariances[keep] for seen, keep in zip(fresh, keeps)]),
                          np.concatenate([np.full(int(keep.sum()), seen.tethered) for seen, keep in zip(fresh, keeps)]),
                          np.concatenate([seen.made()[keep] for seen, keep in zip(fresh, keeps)]))

    def _usable(self, detections: np.ndarray, now: int, position: np.ndarray, stamp: int) -> np.ndarray:
        return detections[self._usable_mask(detections, now, position, stamp)]

    def _usable_mask(self, detections: np.ndarray, now: int, position: np.ndarray, stamp: int) -> np.ndarray:
        """(N,) bool: the detections of the scan at `stamp` the machine may act on; while movers
        are skipped (a mover ran out a state timer), the ones that move are left out too."""
        p = self.params
        keep = np.ones(len(detections), dtype=bool)
        if now < self._no_moving_until and len(detections):
            keep = np.array([self.seen.motion(d, now, stamp) is None for d in detections])
        mine = None if self.engagement is None else self.engagement.position(now)
        claimed = self.team.claimed_targets(mine, position, p.claim_radius) if self.team else np.zeros((0, 3))
        keep &= usable_detections(detections, area=self.working_area, zones=self.zones, claimed=claimed,
                                  claim_radius=p.claim_radius, min_z=self.ground_z + p.min_target_height,
                                  area_overlap=p.area_overlap, arena=self.arena)
        no_fly = self._no_fly(now)
        if len(no_fly) and len(detections):  # an unaccounted partner may be there: no attack near it
            apart = np.linalg.norm(detections[:, None, :2] - no_fly[None, :, :2], axis=2)
            keep &= (apart >= p.safety_distance + p.no_fly_margin).all(axis=1)
        return keep

    def _no_fly(self, now: int) -> np.ndarray:
        return self.team.no_fly(now, self.takeoff_at) if self.team is not None else np.zeros((0, 3))

    def _sweep_height(self, now: int) -> float:
        """search_height, or high enough to pass over an unaccounted partner whose no-fly column
        touches the working area (it may hover at its last height; it cannot get out of the way)."""
        p = self.params
        no_fly = self._no_fly(now)
        if not len(no_fly) or self.working_area is None:
            return p.search_height
        reach = p.safety_distance + p.no_fly_margin
        low, high = self.working_area.min(axis=0) - reach, self.working_area.max(axis=0) + reach
        near = no_fly[((no_fly[:, :2] >= low) & (no_fly[:, :2] <= high)).all(axis=1)]
        if not len(near):
            return p.search_height
        # vertical_separation is more than the safety distance: a partner hovering below stays clear
        return max(p.search_height, float(near[:, 2].max()) + p.vertical_separation)

    def _lock(self, found: Candidates, position: np.ndarray, now: int) -> bool:
        """Select b_c among the candidates that may be locked — a LiDAR detection (a 3D cluster of
        returns from a scan that passed its sanity check), a camera blob only once it was seen
        consistently (Sightings.consistent) — the closest static one (a moving one only when none is
        static); the previous target, when it is among them, counts as closest (no flip-flopping
        between two). The LiDAR's are not asked for more sightings: far balloons show in some scans
        only, and three within t_m left two of mbzirc's five standing in a revenge-mode sweep
        (tests/test_mission.py)."""
        agreed = np.array([not tethered or self.seen.consistent(c, cov, now)
                           for c, cov, tethered in zip(found.positions, found.covariances, found.tethered)], dtype=bool)
        if not agreed.any():
            return False
        found = found.subset(agreed)
        candidates, stamps = found.positions, found.stamps
        distance = np.linalg.norm(candidates - position, axis=1)
        if self._previous_target is not None:
            again = np.linalg.norm(candidates - self._previous_target, axis=1) <= self.params.detection_gate
            distance = np.where(again, 0.0, distance)
        order = np.argsort(distance, kind="stable")
        moving = [None if found.tethered[k] else self.seen.motion(candidates[k], now, int(stamps[k])) for k in order]
        static = [k for k, m in zip(order, moving) if m is None]
        if not static and now < self._no_moving_until:
            return False
        p = self.params
        pick = static[0] if static else order[0]
        track = None if static else moving[0]
        self.engagement = Engagement(
            filter=TargetFilter(candidates[pick], int(stamps[pick]), gate=p.detection_gate,
                                measurement_sigma=p.filter_sigma, process_sigma=p.filter_process_sigma,
                                max_gap_ns=int(p.streak_gap * NS), history_ns=int(p.velocity_window * NS),
                                velocity=None if track is None else track.velocity, covariance=found.covariances[pick],
                                tethered=bool(found.tethered[pick]), observed=int(found.observed[pick])),
            moving=track is not None, track_id=None if track is None else track.track_id)
        self._sent_target = None
        self._holding_for_sighting = False
        return True

    def _next_state(self, now: int, position: np.ndarray, velocity: np.ndarray, airborne: bool,
                    services_ready: bool, stamp: int) -> tuple[State, str]:
        """Every transition of the machine: the abort system's and the mission's first (they hold
        in every state they watch), then the state timer, then the state's own rule; the state and
        "" when it stays."""
        step = _Step(now, position, velocity, airborne, services_ready)
        rule = self._RULES.get(self.state)
        return (self._aborted(now, stamp) or self._timed_out(now, position)
                or (rule(self, step) if rule is not None else None) or (self.state, ""))

    def _aborted(self, now: int, stamp: int) -> tuple[State, str] | None:
        """The abort system (silent odometry, LiDAR or positioning), the mission timer and the
        lost-link rule, in the states they watch."""
        p, state = self.params, self.state
        timeout = int(p.sensor_timeout * NS)
        if (state in _WATCHED or state is State.LANDING) and now - stamp > timeout:
            return State.EMERGENCY_LANDING, f"odometry silent {(now - stamp) / NS:.1f} s"
        if state not in _WATCHED:
            return None
        heard = self.seen.scan_stamp if self.seen.scan_stamp is not None else self.takeoff_at
        if heard is not None and now - max(heard, self.takeoff_at) > timeout:
            return State.EMERGENCY_LANDING, f"LiDAR silent {(now - max(heard, self.takeoff_at)) / NS:.1f} s"
        lost = self._positioning_lost_since
        if lost is not None and now - lost > timeout:
            return State.EMERGENCY_LANDING, f"positioning lost {(now - lost) / NS:.1f} s"
        if self._mission_over(now):
            return State.LANDING, "mission timer"
        if (self.team is not None and self.takeoff_at is not None and self.team.isolated(now, self.takeoff_at)
                and self.team.lands_when_isolated(now, self.takeoff_at)):
            return State.LANDING, f"lost link: no partner heard for {p.lost_link_time:g} s, landing where I am"
        return None

    def _timed_out(self, now: int, position: np.ndarray) -> tuple[State, str] | None:
        """Seed 004's state timers: a state that took too long gives its target up (a forbidden zone
        where it was, or no movers for a while) and goes back to IDLE."""
        p, state = self.params, self.state
        if state not in _TIMED or now - self._timed_since(now, position) <= int(getattr(p, _TIMED[state]) * NS):
            return None
        limit = getattr(p, _TIMED[state])
        b_c = self.engagement.position(now) if self.engagement is not None else self._checked
        if self.engagement is not None and self.engagement.moving:
            self._no_moving_until = now + int(p.forbidden_lifetime * NS)  # a zone cannot hold a mover
            self.notes.append(f"no moving targets for {p.forbidden_lifetime:g} s")
        elif b_c is not None:
            zone = self.zones.add(b_c, now, f"{state.value} took over {limit:g} s")
            self.notes.append(f"forbidden zone at ({zone.center[0]:.1f}, {zone.center[1]:.1f}, "
                              f"{zone.center[2]:.1f}): {zone.reason}")
        return State.IDLE, f"state timer {limit:g} s"

    def _from_preflight(self, step: _Step) -> tuple[State, str] | None:
        if self._mission_over(step.now):
            return State.LANDED, "mission over before take-off"
        lidar_heard = self.seen.scan_stamp is not None and \
            step.now - self.seen.scan_stamp <= int(self.params.sensor_timeout * NS)
        positioned = not self.positioning_by_localizer or self.positioning == "tracking"
        if step.services_ready and lidar_heard and positioned and self.working_area is not None:
            return State.TAKING_OFF, "pre-flight check passed"
        return None

    def _from_taking_off(self, step: _Step) -> tuple[State, str] | None:
        p = self.params
        if step.airborne and step.position[2] >= p.search_height - p.height_tolerance:
            return State.IDLE, "in the air: state machine started"
        return None

    def _from_idle(self, step: _Step) -> tuple[State, str] | None:
        if len(self.candidates(step.now, step.position)):
            return State.CHECKING_TARGET, "target in view"
        return State.GOING_AROUND, "nothing in view"

    def _from_going_around(self, step: _Step) -> tuple[State, str] | None:
        p, now = self.params, step.now
        if len(self.candidates(now, step.position)) > 0:
            self._candidate_seen = now
            self._stopping = True
        elif self._stopping and now - self._candidate_seen > int(p.target_time * NS):
            self._stopping = False  # a false alarm: back to the sweep
        if self._stopping and np.linalg.norm(step.velocity) < p.stop_speed:
            return State.CHECKING_TARGET, "stopped with a target in view"
        return None

    def _from_checking_target(self, step: _Step) -> tuple[State, str] | None:
        p, now, position = self.params, step.now, step.position
        latest = self.recent_candidates(now, position).newest()  # the latest scan or frame that saw any
        if len(latest.positions):
            closest = int(np.argmin(np.linalg.norm(latest.positions - position, axis=1)))
            self._checked = latest.positions[closest]
            if np.linalg.norm(step.velocity) < p.stop_speed and self._lock(latest, position, now):
                kind = "moving" if self.engagement.moving else "static"
                return State.GOING_TO_TARGET, f"{kind} target at {self._fmt(self.engagement.position(now))}"
        elif now - self.state_since > int(p.target_time * NS):
            return State.IDLE, f"no target for {p.target_time:g} s"
        return None

    def _from_going_to_target(self, step: _Step) -> tuple[State, str] | None:
        p, e, now, position = self.params, self.engagement, step.now, step.position
        if (blocked := self._forbid_if_blocked(now)):
            return State.IDLE, blocked
        if self._unseen(now, position):
            return State.CHECKING_TARGET, f"target unseen for {p.target_time:g} s"
        if (left := self._left_to_partner(now, position)):
            return State.IDLE, left
        if (drop := self._notice_motion(now) or self._static_in_view(now, position)):
            return State.IDLE, drop
        gap = e.position(now) - position
        filter_ready = e.moving or e.filter.updates >= 2
        if np.linalg.norm(gap[:2]) < p.filter_switch_distance and filter_ready:
            return State.DESTROYING, f"within {p.filter_switch_distance:g} m"
        return None

    def _from_destroying(self, step: _Step) -> tuple[State, str] | None:
        return self._destroying(step.now, step.position, step.velocity)

    def _from_descending(self, step: _Step) -> tuple[State, str] | None:
        return (State.LANDED, "on the ground") if not step.airborne else None

    _RULES = {State.PREFLIGHT: _from_preflight, State.TAKING_OFF: _from_taking_off, State.IDLE: _from_idle,
              State.GOING_AROUND: _from_going_around, State.CHECKING_TARGET: _from_checking_target,
              State.GOING_TO_TARGET: _from_going_to_target, State.DESTROYING: _from_destroying,
              State.LANDING: _from_descending, State.EMERGENCY_LANDING: _from_descending}

    def _timed_since(self, now: int, position: np.ndarray) -> int:
        """Where the state timer counts from: entering the state; for a mover in DESTROYING, its
        latest close pass. T_d (seed 004) gives up a target the UAV cannot get at; a mover that a
        just-seen sighting puts within close_pass_distance is being got at, and one that brakes
        harder than the UAV can (agile's 4 m/s² against 3) may need several passes. Given up, it
        would be skipped with every other mover for forbidden_lifetime while the UAV sweeps."""
        e, p = self.engagement, self.params
        if self.state is not State.DESTROYING or e is None or not e.moving:
            return self.state_since
        fresh = now - e.last_seen() <= int(p.detection_max_age * NS)
        if fresh and np.linalg.norm(e.position(now) - position) <= p.close_pass_distance:
            e.close_pass_at = now
        return max(self.state_since, e.close_pass_at)

    def _destroying(self, now: int, position: np.ndarray, velocity: np.ndarray) -> tuple[State, str]:
        """A mover is "down" (captured: it drops, and detections below the lowest target height
        are no targets) when its prediction is below that height and it was last seen within
        DOWN_MARGIN of it. The prediction alone carries a descent on while the target is unseen:
        agile seed 4's drone, lost behind a tree for 2 s while descending at 3 m, was given up
        as down."""
        p, e = self.params, self.engagement
        if e.moving:
            if now - e.last_seen() > int(p.target_time * NS):
                return State.IDLE, f"moving target gone for {p.target_time:g} s (captured or lost)"
            floor = self.ground_z + p.min_target_height
            if e.position(now)[2] < floor and e.filter.last_position[2] < floor + DOWN_MARGIN:
                return State.IDLE, "moving target down"
            left = self._left_to_partner(now, position) or self._static_in_view(now, position)
            return (State.IDLE, left) if left else (self.state, "")
        if (blocked := self._forbid_if_blocked(now)):
            return State.IDLE, blocked
        if not e.attacking:
            if self._unseen(now, position):
                return State.CHECKING_TARGET, f"target unseen for {p.target_time:g} s"
            left = self._left_to_partner(now, position)
            if left:
                return State.IDLE, left
            drop = self._notice_motion(now)
            if drop:
                return State.IDLE, drop
            if self.engagement.moving:
                return self.state, ""
            # level first: a vehicle still descending onto the hit height sinks below it on the run-in,
            # its acceleration spent on the speed (mbzirc seed 1: 0.25 m above the pole top at 4 m/s)
            if e.filter.confirmed_for(now) >= p.target_time and abs(float(velocity[2])) <= p.attack_level_speed:
                target = e.filter.estimate
                direction = target[:2] - position[:2]
                e.attacking = True
                e.attack_target = target
                e.attack_direction = direction / max(np.linalg.norm(direction), 1e-9)
                self.notes.append(f"attack on {self._fmt(target)}: confirmed for {e.filter.confirmed_for(now):.1f} s")
            return self.state, ""
        past = float(np.dot(position[:2] - e.attack_target[:2], e.attack_direction))
        if past > p.attack_pass_margin and np.linalg.norm(velocity) < p.attack_done_speed:
            zone = self.zones.count_try(e.attack_target, now)
            if zone is not None:
                self.notes.append(f"forbidden zone at {self._fmt(zone.center)}: {zone.reason}")
            return State.IDLE, f"attack flown through ({self.zones.tries_at(e.attack_target)} tries here)"
        return self.state, ""

    def _forbid_if_blocked(self, now: int) -> str:
        """Non-empty when the planner has found every way to the static target blocked for
        blocked_time: the target becomes a forbidden zone (the seed's answer to a target that
        cannot be got at) and the reason is returned."""
        p, e = self.params, self.engagement
        if self._blocked is None or e is None or e.moving or now - self._blocked[0] < int(p.blocked_time * NS):
            return ""
        target = e.attack_target if e.attacking else e.filter.estimate
        zone = self.zones.add(target, now, "every approach blocked by obstacles")
        self.notes.append(f"forbidden zone at {self._fmt(zone.center)}: every approach blocked by obstacles "
                          f"({self._blocked[1]})")
        self._blocked = None
        return f"every approach to the target blocked for {p.blocked_time:g} s"

    def _unseen(self, now: int, position: np.ndarray) -> bool:
        """Lost: not seen for t_m since the lock, counted for a static target only while within
        reliable range (the seed's camera saw a target or not; a LiDAR sees a far 0.6 m balloon in
        some scans); a mover's prediction must not run on unchecked."""
        e, p = self.engagement, self.params
        if not e.moving and np.linalg.norm(e.position(now) - position) > p.reliable_range:
            self._unseen_from = now
            return False
        since = max(e.last_seen(), self.state_since, self._unseen_from)
        return now - since > int(p.target_time * NS)

    def _left_to_partner(self, now: int, position: np.ndarray) -> str:
        """Non-empty when a partner with priority claims my target (team.py: one chaser per target)."""
        if self.team is None:
            return ""
        mine = self.engagement.position(now)
        claimed = self.team.claimed_targets(mine, position, self.params.claim_radius)
        if len(claimed) and (np.linalg.norm(claimed - mine, axis=1) <= self.params.claim_radius).any():
            return "target left to a partner that claimed it and is closer"
        return ""

    def _static_in_view(self, now: int, position: np.ndarray) -> str:
        """Static targets first: non-empty when intercepting while a static one is in view."""
        e = self.engagement
        if not e.moving:
            return ""
        for candidate in self.candidates(now, position):
            if np.linalg.norm(candidate - e.position(now)) > self.params.detection_gate and \
                    self.seen.moving_track(candidate, now) is None and self.seen.held_still(candidate, now):
                return f"a static target in view at {self._fmt(candidate)}: static targets first"
        return ""

    def _notice_motion(self, now: int) -> str:
        """A target locked as static that turns out to move is intercepted from now on (non-empty:
        drop it instead). It moves when its own fit says so, or when a fast confirmed track passed
        through its last sighting (carried back at most target_time): a drone locked far off, seen in
        a scan now and then, leaves the filter's gate between sightings and the fit never learns
        that it moves (mbzirc, 2 UAVs: uav2 flew 12 s at the place its intruder had been)."""
        e, p = self.engagement, self.params
        if e.moving:
            return ""
        track = None
        if not e.filter.tethered and now - e.last_seen() <= int(p.target_time * NS):
            track = self.seen.moving_track(e.filter.last_position, now, e.last_seen())
        if track is None and not e.filter.moves(p.moving_speed, p.motion_sigmas):
            return ""
        if now < self._no_moving_until:
            self.seen.last_mover = e.filter  # so it is known for a mover from now on
            return "the target moves, and moving targets are skipped for now"
        e.moving = True
        if track is not None:
            e.track_id = track.track_id
            e.filter.adopt_velocity(track.velocity)
        self._sent_target = None
        speed = e.filter.speed() if track is None else float(np.linalg.norm(track.velocity))
        by = "" if track is None else f" (track {track.track_id})"
        self.notes.append(f"target at {self._fmt(e.filter.last_position)} moves at {speed:.1f} m/s{by}: intercepting")
        return ""

    # -------------------------------------------------------------- decisions
    def _yielding(self, now: int, position: np.ndarray, velocity: np.ndarray, airborne: bool) -> MissionDecision | None:
        """Separation rule (team.py): hold (and climb above the partner's plan, if it passes near)
        while too close or predicted to be; taking off and landing too (intruder, 3 UAVs, seed 5372:
        two UAVs the mission timer sent down at once landed 4.6 m apart), not in an emergency landing."""
        p = self.params
        if self.team is None or self.state not in (*MISSION_STATES, State.TAKING_OFF, State.LANDING):
            self._yield = None
            return None
        current = self._yield[0] if self._yield else None
        me = Mover(position, velocity, self.state.value, self._mission_plan(now), airborne)
        partner = self.team.yield_to(now, me, self._separation, current)
        if partner is None:
            if self._yield is not None:
                self.notes.append(f"separation from {current} restored")
                self._sent_target = None  # re-issue the mission command
            self._yield = None
            return None
        if self._yield is None or self._yield[0] != partner.name:
            spot = _tuple(self.team.hold_spot(now, me, partner, self._separation))
            if self._yield is None and self._giving_way_to is None:  # not the braking of a give-way
                self._paused = (self.reference, now, self.state)
            self._yield = (partner.name, spot)
            self.notes.append(f"yielding to {partner.name} "
                              f"({np.linalg.norm(self.team.position_now(partner, now) - position):.1f} m apart): "
                              f"holding at {self._fmt(spot)}")
        else:  # the partner's plan may come through the spot now: climb (never down while the yield lasts)
            spot = self.team.hold_spot(now, me, partner, self._separation, at=np.asarray(self._yield[1]))
            if spot[2] > self._yield[1][2] + 1e-6:
                self._yield = (partner.name, _tuple(spot))
                self.notes.append(f"{partner.name}'s plan comes through the hold: climbing to {self._fmt(spot)}")
        # with the attack profile's acceleration: the vehicle's momentum carries it on towards the partner
        # for its whole braking distance (4.7 m/s: 8.7 m at the sweeping profile's, 4.3 m at the attack's)
        return MissionDecision("goto", height=self._yield[1][2], spacing=p.scan_spacing, target=self._yield[1],
                               profile="attack")

    def _mission_plan(self, now: int) -> PlannedPath | None:
        """The own plan the separation rules check: the reference; while yielding or giving way, the
        mission's reference as it would go on if taken up again now (a yield that ended whenever the
        hold itself was clear would end and start again tick by tick while the mission's way is not;
        intruder, 2 UAVs, seed 1943: a chase gave way and engaged again 9 times in 1 s);
        None once the machine has moved on to another state: that reference is no longer the
        mission's (mbzirc, 2 UAVs: a UAV that left a balloon to its partner held 8 s for the
        approach it had given up), and the next command's plan will be checked when it comes."""
        holding = self._yield is not None or self._giving_way_to is not None
        if not holding or self._paused is None or self._paused[0] is None:
            return self.reference
        plan, paused, state = self._paused
        if state is not self.state:
            return None
        p = self.params
        return plan.resumed(paused, now, p.plan_horizon, p.plan_step)

    def _giving_way(self, now: int, position: np.ndarray, velocity: np.ndarray) -> MissionDecision | None:
        """Giving way (team.py): a UAV with priority brakes to a hover rather than fly into a partner."""
        before = self._giving_way_to
        flying = self.team is not None and self.state in (*MISSION_STATES, State.LANDING)
        partner = None if not flying else self.team.give_way_to(
            now, Mover(position, velocity, self.state.value, self._mission_plan(now)), self._separation, before)
        self._giving_way_to = None if partner is None else partner.name
        if partner is None:
            if before is not None:
                self.notes.append(f"{before} is clear: engaging again")
                self._sent_target = None  # re-issue the mission command
            return None
        if before is None and self._yield is None:
            self._paused = (self.reference, now, self.state)
        if before != partner.name:
            offset = self.team.position_now(partner, now) - position
            self.notes.append(f"giving way to {partner.name} ({np.linalg.norm(offset):.1f} m apart, "
                              f"{offset[2]:+.1f} m above): braking to a hover")
            self._giving_way_height = float(position[2])
        # braking as any stop (STOP_PROFILE); one decision for the whole hold, not one per tick
        return MissionDecision("stop", height=self._giving_way_height, spacing=self.params.scan_spacing,
                               profile=STOP_PROFILE)

    @property
    def _separation(self) -> SeparationRule:
        p = self.params
        return SeparationRule(p.safety_distance, p.vertical_separation, p.separation_hysteresis,
                              p.separation_lookahead, p.plan_horizon, p.plan_step, p.plan_widen_rate,
                              p.attack_acceleration)

    def _decision_for(self, now: int, position: np.ndarray) -> MissionDecision:
        p, state = self.params, self.state
        previous = self._decision
        if state is State.TAKING_OFF:
            return MissionDecision("takeoff", height=p.search_height, spacing=p.scan_spacing)
        if state is State.GOING_AROUND:
            if self._stopping:
                return MissionDecision("stop", height=p.search_height, spacing=p.scan_spacing, profile=STOP_PROFILE)
            if not self._climbed and position[2] < p.search_height - p.height_tolerance:
                return MissionDecision("takeoff", height=p.search_height, spacing=p.scan_spacing)
            self._climbed = True
            area = tuple((float(x), float(y)) for x, y in self._sweep_area(now))
            return MissionDecision("scan", area=area, height=self._sweep_height(now), spacing=p.scan_spacing)
        if state in (State.GOING_TO_TARGET, State.DESTROYING):
            return self._engage(now)
        if state is State.LANDING:
            return MissionDecision("land", height=self.ground_z, spacing=p.scan_spacing, target=self._landing_target,
                                   profile=STOP_PROFILE)  # it brakes first (the planner's lead-in)
        if state is State.EMERGENCY_LANDING:
            return MissionDecision("emergency_land", height=self.ground_z, spacing=p.scan_spacing,
                                   target=self._landing_target, profile=STOP_PROFILE)
        if state is State.PREFLIGHT:
            return MissionDecision("idle", height=p.search_height, spacing=p.scan_spacing)
        if state is State.CHECKING_TARGET:  # the stop manoeuvre (a no-op when already at rest)
            return MissionDecision("stop", height=p.search_height, spacing=p.scan_spacing, profile=STOP_PROFILE)
        # IDLE lasts one tick: keep what is flying
        return previous if previous is not None else MissionDecision("hover", spacing=p.scan_spacing)

    def _engage(self, now: int) -> MissionDecision:
        p, e = self.params, self.engagement
        if e.moving:
            return self._intercept(now)
        action, profile = ("attack", "attack") if e.attacking else ("approach", "sweeping")
        target = e.attack_target if e.attacking else e.filter.estimate
        if (self._sent_target is None or self._decision is None or self._decision.action != action
                or np.linalg.norm(self._sent_target - target) > p.replan_distance):
            self._sent_target = target.copy()
            self._sent_seen = min(e.last_observed(), now)
        return MissionDecision(action, height=float(self._sent_target[2]), spacing=p.scan_spacing, profile=profile,
                               target=_tuple(np.round(self._sent_target, 3)), sighted=self._sent_seen)

    def _intercept(self, now: int) -> MissionDecision:
        """Intercept the locked mover along its tracker's prediction (the confirmed track it was
        locked with, or the moving track now at it); without one, along the target filter's
        straight line. A new command goes out when the prediction now differs from the one sent by
        more than intercept_replan_distance (position, or velocity in m/s), and at least every
        intercept_refresh s: the planner follows a prediction for a limited time only (its
        pursuit_trust), since one that is not renewed may be of a target no longer seen."""
        p, e = self.params, self.engagement
        if self._sent_target is None and now - e.last_observed() > int(p.intercept_sighting_age * NS):
            return self._hold_for_sighting(now)
        self._holding_for_sighting = False
        followed = self.seen.followed_track(e.track_id, e.position(now), now)
        if followed is not None:
            e.track_id, prediction = followed
        else:
            prediction = PredictedPath(e.position(now), e.filter.velocity.copy())
        sent = self._sent_prediction if self._sent_target is not None else None
        stale = sent is not None and now - self._sent_at >= int(p.intercept_refresh * NS)
        if sent is None or stale or self._prediction_moved(sent, prediction, now):
            self._sent_prediction, self._sent_at, self._sent_target = prediction, now, prediction.position.copy()
            self._sent_seen = min(e.last_observed(), now)
        s = self._sent_prediction
        return MissionDecision("intercept", height=float(s.position[2]), spacing=p.scan_spacing, profile="attack",
                               target=_tuple(s.position), target_velocity=_tuple(s.velocity),
                               target_path=tuple(_tuple(q) for q in s.path), target_path_dt=s.dt,
                               target_seen=self._sent_seen, sighted=self._sent_seen)

    def _hold_for_sighting(self, now: int) -> MissionDecision:
        """An interception not taken up on an old sighting: a manoeuvring drone is anywhere within
        ½·a·t² of its prediction (agile's 4 m/s²: 2 m after 1 s). Taken up 1.8 s after the last
        sighting when a yield ended, one was aimed 4.9 m from the dodger (intruder, 3 UAVs, seed
        5144); the UAV now holds and looks until the target is seen again or counts as lost. The
        age is the sighting's own: a partner's track counts from the partner's last scan of it, not
        from the message that carried its prediction on (agile, 2 UAVs, seed 1852: a lock on a partner
        track 0.5 s past its correction, taken up 0.65 s later, was aimed 2.9 m from the dodger)."""
        age = (now - self.engagement.last_observed()) / NS
        if not self._holding_for_sighting:
            self.notes.append(f"target last seen {age:.1f} s ago: holding until it is seen again")
        self._holding_for_sighting = True
        return MissionDecision("stop", height=self.params.search_height, spacing=self.params.scan_spacing,
                               profile=STOP_PROFILE)

    def _prediction_moved(self, sent: PredictedPath, prediction: PredictedPath, now: int) -> bool:
        """Whether the sent prediction and the new one part by more than intercept_replan_distance
        anywhere over the next REPLAN_LOOKAHEAD s (compared at a few times: a velocity that differs
        by d m/s shows as d m after a second; a curved path is compared as curved)."""
        ahead = np.linspace(0.0, REPLAN_LOOKAHEAD, 3)
        expected, _ = sent.state(ahead + (now - self._sent_at) / NS)
        predicted, _ = prediction.state(ahead)
        return bool(np.linalg.norm(expected - predicted, axis=1).max() > self.params.intercept_replan_distance)

    @staticmethod
    def _fmt(v) -> str:
        return f"({v[0]:.1f}, {v[1]:.1f}, {v[2]:.1f})"
