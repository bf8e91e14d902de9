"""The job manager's mission state machine (seed 004, ch. 3) — FIRST VERSION.

Walking skeleton: after the pre-flight check (every service of this UAV alive: seed 004
§3.6, automatic start) the UAV takes off, sweeps its working area with a lawnmower
(GOING_AROUND) and lands when the mission timer runs out. Odometry silent for longer than
`sensor_timeout` triggers EMERGENCY_LANDING (placeholder of the abort system, §3.5.3).

Later issues deepen it: CHECKING_TARGET / GOING_TO_TARGET / DESTROYING driven by tracks,
state timers and forbidden zones (§3.5.1–2), the abort system on the LiDAR stream, and
revenge mode (§3.5.4: a silent or landed partner's area is taken over). Partner
bookkeeping already exists so that can plug in. The structure is meant to grow: the
states are an explicit enum, every transition is decided in `_next_state`, the command
each state wants is built in `_decision_for`, and time is always passed in (int ns).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import msgspec
import numpy as np

from services.job_manager.areas import split_area

NS = 1_000_000_000


class JobManagerParams(msgspec.Struct, forbid_unknown_fields=True):
    """Defaults from design §6 / seed 004 Table 3.1."""

    search_height: float = 5.0  # m, world z of the sweep
    scan_spacing: float = 10.0  # m between lawnmower lines
    landing_margin: float = 15.0  # s before the mission's end at which to land
    partner_timeout: float = 15.0  # s without a partner's status before it counts as silent (t_s)
    status_rate_hz: float = 5.0
    sensor_timeout: float = 1.0  # s of silent odometry before an emergency landing
    height_tolerance: float = 0.3  # m below search_height that counts as "at height"
    airborne_height: float = 0.3  # m above the ground that counts as airborne
    command_repeat: float = 2.0  # s between re-sends of the current command (0: only on change)


class State(enum.Enum):
    IDLE = "IDLE"  # on the ground, waiting for the pre-flight check
    TAKING_OFF = "TAKING_OFF"
    GOING_AROUND = "GOING_AROUND"  # sweeping the working area
    LANDING = "LANDING"
    LANDED = "LANDED"
    EMERGENCY_LANDING = "EMERGENCY_LANDING"


# States in which the UAV is (or should be) in the air and the mission clock can stop it.
_FLYING = (State.TAKING_OFF, State.GOING_AROUND)
_DESCENDING = (State.LANDING, State.EMERGENCY_LANDING)
_SWEEPING_PROFILE = "sweeping"


@dataclass(frozen=True)
class MissionDecision:
    """What the planner should do; a new MissionCommand goes out whenever it changes."""

    action: str  # a schemas.messages.MissionAction
    area: tuple[tuple[float, float], ...] = ()
    height: float = 5.0
    spacing: float = 10.0
    profile: str = _SWEEPING_PROFILE
    target: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Transition:
    stamp: int
    source: State
    target: State
    reason: str


class JobManager:
    def __init__(self, params: JobManagerParams, uav: str) -> None:
        self.params = params
        self.uav = uav
        self.state = State.IDLE
        self.state_since = 0
        self.working_area: np.ndarray | None = None
        self.arena: np.ndarray | None = None
        self.ground_z = 0.0
        self.duration_ns = 0  # 0: no mission timer
        self.transitions: list[Transition] = []
        self._world_key: tuple | None = None
        self._decision: MissionDecision | None = None
        self._landing_target: tuple[float, float, float] | None = None
        self._partners: dict[str, tuple[int, bool]] = {}  # name → (last heard, flying normally)
        self._confirmed_tracks: set[int] = set()

    # ----------------------------------------------------------------- inputs
    def set_world(self, arena: np.ndarray, uavs: list[str], duration_s: float, ground_z: float = 0.0) -> bool:
        """Working area = this UAV's equal-area share of the arena. Cheap when nothing
        changed (the world is re-sent every second); returns True when it did change."""
        arena = np.asarray(arena, dtype=np.float64).reshape(-1, 2)
        key = (arena.tobytes(), tuple(uavs), float(duration_s), float(ground_z))
        if key == self._world_key:
            return False
        if self.uav not in uavs:
            raise ValueError(f"{self.uav} is not in the world's team {uavs}")
        self._world_key = key
        self.arena = arena
        self.working_area = split_area(arena, len(uavs))[uavs.index(self.uav)]
        self.duration_ns = int(round(duration_s * NS))
        self.ground_z = float(ground_z)
        return True

    def partner_status(self, name: str, now_ns: int, flying_normally: bool) -> None:
        if name != self.uav:
            self._partners[name] = (now_ns, flying_normally)

    def partners_silent(self, now_ns: int) -> list[str]:
        """Partners heard at least once but not within partner_timeout (seed 004 t_s)."""
        limit = int(self.params.partner_timeout * NS)
        return sorted(name for name, (heard, _) in self._partners.items() if now_ns - heard > limit)

    def partners_grounded(self) -> list[str]:
        return sorted(name for name, (_, flying) in self._partners.items() if not flying)

    def note_confirmed_tracks(self, track_ids: list[int]) -> list[int]:
        """Confirmed track ids not seen confirmed before (first version: only logged)."""
        new = sorted(set(track_ids) - self._confirmed_tracks)
        self._confirmed_tracks.update(new)
        return new

    def is_airborne(self, z: float) -> bool:
        return bool(z - self.ground_z > self.params.airborne_height)

    @property
    def flying_normally(self) -> bool:
        """Seed 004 §3.5.4: False until take-off succeeded, and again once landing."""
        return self.state is State.GOING_AROUND

    @property
    def airborne_state(self) -> bool:
        return self.state in _FLYING or self.state in _DESCENDING

    # ------------------------------------------------------------------ step
    def update(
        self,
        now_ns: int,
        position: np.ndarray,
        airborne: bool,
        services_ready: bool,
        position_stamp_ns: int | None = None,
    ) -> MissionDecision | None:
        """Advance the state machine; returns the new decision when it changed, else None.
        `position_stamp_ns` is the stamp of the odometry `position` came from (default: now)."""
        position = np.asarray(position, dtype=np.float64).reshape(3)
        stamp = now_ns if position_stamp_ns is None else position_stamp_ns
        target, reason = self._next_state(now_ns, position, airborne, services_ready, stamp)
        if target is not self.state:
            self.transitions.append(Transition(now_ns, self.state, target, reason))
            self.state, self.state_since = target, now_ns
            if target in _DESCENDING:
                self._landing_target = (float(position[0]), float(position[1]), self.ground_z)
        decision = self._decision_for(self.state)
        if decision == self._decision:
            return None
        self._decision = decision
        return decision

    @property
    def decision(self) -> MissionDecision | None:
        return self._decision

    def _mission_over(self, now_ns: int) -> bool:
        if self.duration_ns <= 0:
            return False
        return now_ns >= self.duration_ns - int(self.params.landing_margin * NS)

    def _next_state(
        self, now_ns: int, position: np.ndarray, airborne: bool, services_ready: bool, stamp: int
    ) -> tuple[State, str]:
        """Every transition of the machine, in one place."""
        p = self.params
        state = self.state
        if state in _FLYING or state is State.LANDING:
            if now_ns - stamp > int(p.sensor_timeout * NS):
                return State.EMERGENCY_LANDING, f"odometry silent {(now_ns - stamp) / NS:.1f} s"
        if state is State.IDLE:
            if self._mission_over(now_ns):
                return State.LANDED, "mission over before take-off"
            if services_ready and self.working_area is not None:
                return State.TAKING_OFF, "pre-flight check passed"
        elif state is State.TAKING_OFF:
            if self._mission_over(now_ns):
                return State.LANDING, "mission timer"
            if airborne and position[2] >= p.search_height - p.height_tolerance:
                return State.GOING_AROUND, "at search height"
        elif state is State.GOING_AROUND:
            if self._mission_over(now_ns):
                return State.LANDING, "mission timer"
        elif state in _DESCENDING:
            if not airborne:
                return State.LANDED, "on the ground"
        return state, ""

    def _decision_for(self, state: State) -> MissionDecision:
        p = self.params
        if state is State.LANDED and self._decision is not None:
            return self._decision  # once down, nothing new goes out
        if state is State.TAKING_OFF:
            return MissionDecision("takeoff", height=p.search_height, spacing=p.scan_spacing)
        if state is State.GOING_AROUND:
            area = tuple((float(x), float(y)) for x, y in self.working_area)
            return MissionDecision("scan", area=area, height=p.search_height, spacing=p.scan_spacing)
        if state is State.LANDING:
            return MissionDecision("land", height=self.ground_z, spacing=p.scan_spacing, target=self._landing_target)
        if state is State.EMERGENCY_LANDING:
            return MissionDecision("emergency_land", height=self.ground_z, spacing=p.scan_spacing,
                                   target=self._landing_target)
        return MissionDecision("idle", height=p.search_height, spacing=p.scan_spacing)
