"""What the launcher watches during `falconry sim`: it writes the ground-truth log and
builds the progress line and the end-of-run summary from messages alone (truth, events,
status, tracks, detections, commands, the world model, liveliness).

Clearance: at every truth tick, each alive, airborne UAV's body (its radius from the world model,
DEFAULT_UAV_RADIUS where it names none) is measured against every static obstacle, the world
model's and the truth's unsurveyed ones (not the ground): the closest approach, which obstacle,
when. While the UAV's latest mission command is an attack, the pole of the balloon attacked (the
`<balloon>_pole` whose axis is horizontally nearest the command's target, within
ATTACKED_POLE_WITHIN) is measured apart, as its `attack_pole`: an attack flies close over that
pole's top by design. The pass does not end with the command: a command that follows an attack
(a stop once the balloon is down, a yield) starts where the attack left the UAV, over the pole's
top (street seed 2: a yield 0.05 s after the hit, 0.50 m from the pole's top 0.2 s later), or on
its way there: a UAV giving way to a partner mid-attack brakes along the attack's line, towards
the pole (street, 3 UAVs, seed 5: a stop 0.55 s before the hit, 0.83 m from the pole 0.45 s later).
So the pole stays the attack's until the UAV is PASS_CLEAR from it and no longer closing on it
faster than PASS_CLOSING: once the attack's momentum is spent, any later approach is measured as
an obstacle's.

Geofence: an alive, airborne UAV more than GEOFENCE_SLACK outside the world model's arena polygon
or above its ground + max_height starts a breach episode (uav, start, end, how far out at most),
as a real range's geofence would trip."""
from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator, NamedTuple

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import (DEFAULT_UAV_RADIUS, Detections, GroundTruth, MissionCommand, Obstacle, PointTruth,
                              SimClock, SimEvent, Tracks, TrajectoryReference, UavStatus, WorldModel)
from services.tools import evaluation
from services.lib.geometry import distance_to_edges, pairwise_gaps, point_in_polygon
from services.lib.runtime.clock import StampOrigin, seconds
from services.simulator import contact
from services.simulator.specs import pole_name
from services.tracker.fleet import FLEET_ID_BASE
from services.lib.tracks import track_positions

_LENGTH = struct.Struct("<I")
DETECTED_WITHIN = 1.5  # m between a detection and a target's true position for "first detected"
NEAREST_PERIOD = 0.25  # s of mission time between samples of each UAV's distance to its nearest partner
ATTACKED_POLE_WITHIN = 1.5  # m from an attack command's target to the axis of the pole it attacks
PASS_CLEAR = 1.0  # m (the obstacle margin) from the attacked pole that ends an attack's pass over it
PASS_CLOSING = 0.1  # m/s: closing on the attacked pole slower than this, the attack's momentum is spent
GEOFENCE_SLACK = 0.5  # m beyond the arena's edge or ceiling a tracking error may carry the body


def write_record(stream: BinaryIO, payload: bytes) -> None:
    stream.write(_LENGTH.pack(len(payload)) + payload)


def read_truth_log(path: str | Path) -> Iterator[GroundTruth]:
    """Ground-truth log: each record is a little-endian u32 length then a msgpack GroundTruth."""
    decoder = msgspec.msgpack.Decoder(GroundTruth)
    data = Path(path).read_bytes()
    offset = 0
    while offset + 4 <= len(data):
        (length,) = _LENGTH.unpack_from(data, offset)
        offset += 4
        if offset + length > len(data):
            break  # a record cut short by a crash
        yield decoder.decode(data[offset:offset + length])
        offset += length


class Sample(NamedTuple):
    t: float  # mission time, s
    value: float


@dataclass
class UavSummary:
    distance: float = 0.0
    max_height: float = 0.0
    takeoff: float | None = None
    landed: float | None = None
    state: str = "?"
    airborne: bool = False
    alive: bool = True
    detections: int = 0
    confirmed_tracks: set[int] = field(default_factory=set)
    last_position: tuple[float, float, float] | None = None
    states: list[tuple[float, str]] = field(default_factory=list)  # (mission time, job manager state) changes
    decisions: list[tuple[float, str, str]] = field(default_factory=list)  # the same with the job manager's reason
    detection_counts: list[Sample] = field(default_factory=list)  # detections per scan
    nearest_partner: list[Sample] = field(default_factory=list)  # m to the nearest flying partner (truth), 4 Hz
    perception: evaluation.PerceptionScore = field(default_factory=evaluation.PerceptionScore)
    camera: evaluation.PerceptionScore = field(default_factory=evaluation.PerceptionScore)  # Object Detect's
    engagements: list[evaluation.Engagement] = field(default_factory=list)
    last_action: str = ""  # of the job manager's latest command
    attacking: tuple[float, float, float] | None = None  # the target of the latest command, an attack
    leaving: tuple[float, float, float] | None = None  # the target of an attack whose pole the UAV is still over
    pole_gap: tuple[float, float] | None = None  # (m, mission time) to the attacked pole at the last truth
    team_view: tuple | None = None  # (working area x-range, fallen partners) last reported
    clearance: tuple[float, str, float] | None = None  # (m, obstacle, mission time) of the closest approach
    attack_pole: tuple[float, str, float] | None = None  # the same to the pole of the balloon it attacked


class RunMonitor:
    def __init__(self, truth_log: BinaryIO | None = None, digests: bool = False,
                 safety_distance: float | None = None) -> None:
        self.truth_log = truth_log
        # the job manager's safety_distance: two flying UAVs closer than this break the invariant
        self.safety_distance = safety_distance
        self.violations: list[dict] = []  # one per episode below safety_distance: start, end, pair, closest m
        self.digests: dict[str, tuple[int, "hashlib._Hash"]] | None = {} if digests else None
        self.step = -1
        self.truth_step = -1
        self.last_truth: bytes | None = None  # what a restarted simulator resumes from
        self.mission_time = 0.0
        self.rtf = 0.0
        self.finished = False  # the clock's last tick went out
        self.over = False  # ... and the simulator saw every service acknowledge it
        self.uavs: dict[str, UavSummary] = {}
        self.targets: dict[str, tuple[str, bool]] = {}
        self._target_positions: dict[str, tuple[float, float, float]] = {}
        self._down: dict[str, tuple[float, tuple[float, float, float]]] = {}  # target -> (t down, where), s
        self.first_detected: dict[str, tuple[float, str]] = {}  # target → (mission time, UAV)
        self.min_separation: tuple[float, float, str] | None = None  # (m, mission time, "uavA-uavB")
        self.destroyed: list[tuple[float, str, str]] = []
        self.events: list[SimEvent] = []
        self.restarts: list[str] = []
        self.started_without: list[str] = []  # services the simulator gave up waiting for at start-up
        self.team_changes: list[dict] = []  # a UAV's working area or fallen partners changed (revenge mode)
        self.faults: list[str] = []
        self.collisions: list[dict] = []  # t, uav, with (the other party), detail
        self.geofence: list[dict] = []  # breach episodes: uav, start, end (None: still out), m out at most
        self._fence: tuple[np.ndarray, float] | None = None  # the arena polygon and the ceiling's world z
        self._surveyed: list[Obstacle] | None = None  # the world model's obstacles (None: no world model yet)
        self._unsurveyed: list[Obstacle] = []  # the truth's
        self._solids: list[Obstacle] = []  # both, as contact.shapes orders them (the ground left out)
        self._shapes = contact.shapes([])
        self.uav_radius: dict[str, float] = {}
        self.decode = {
            keys.CLOCK: msgspec.msgpack.Decoder(SimClock),
            keys.TRUTH: msgspec.msgpack.Decoder(GroundTruth),
            keys.EVENTS: msgspec.msgpack.Decoder(SimEvent),
            keys.WORLD: msgspec.msgpack.Decoder(WorldModel),
        }
        self._origin = StampOrigin()
        self.latest = 0.0  # the latest mission time any message carried, s
        self._status = msgspec.msgpack.Decoder(UavStatus)
        self._tracks = msgspec.msgpack.Decoder(Tracks)
        self._points_truth = msgspec.msgpack.Decoder(PointTruth)
        self._truth_history: dict[int, dict[str, tuple[float, float, float]]] = {}  # stamp -> standing targets
        self._sight_pending: dict[str, dict[int, list]] = {}  # uav -> scan stamp -> [detections, in sight]
        self._detections = msgspec.msgpack.Decoder(Detections)
        self._command = msgspec.msgpack.Decoder(MissionCommand)
        self._reference = msgspec.msgpack.Decoder(TrajectoryReference)
        # the age of sensor data at each stage: arrival is the latest tick's mission time, carried on
        # by the wall clock at `speed` mission seconds a second in a real-time run (0: lockstep)
        self.ages = evaluation.PipelineAges()
        self.speed = 0.0
        self._tick_anchor: tuple[int, int] | None = None  # (monotonic ns the tick arrived, its stamp)
        self._received_ns: int | None = None  # when the message being handled arrived

    def handle(self, key: str, payload: bytes, received_ns: int | None = None) -> None:
        """One message; `received_ns` (time.monotonic_ns when it arrived, taken on Zenoh's thread)
        dates its arrival for the data ages of a real-time run."""
        self._received_ns = received_ns
        # the clock and acknowledgements are plumbing whose repetitions depend on timing: a tick
        # re-sent after 0.5 s without every acknowledgement is acknowledged again
        if self.digests is not None and key != keys.CLOCK and not keys.is_ack(key):
            count, digest = self.digests.get(key) or (0, hashlib.sha256())
            digest.update(payload)
            self.digests[key] = (count + 1, digest)
        try:
            if key in self.decode:
                msg = self.decode[key].decode(payload)
                if key == keys.TRUTH:
                    self.last_truth = payload
                    if self.truth_log is not None:
                        write_record(self.truth_log, payload)
                getattr(self, f"_on_{key.rsplit('/', 1)[-1]}")(msg)
                return
            uav, topic = keys.uav_of(key), keys.topic_of(key)
            if topic == "status":
                self._on_status(uav, self._status.decode(payload))
            elif topic == "tracks":
                self._on_tracks(uav, self._tracks.decode(payload))
            elif topic == "detections":
                self._on_detections(uav, self._detections.decode(payload))
            elif topic == "points_truth":
                self._on_points_truth(uav, self._points_truth.decode(payload))
            elif topic == "camera_detections":
                self._on_camera_detections(uav, self._detections.decode(payload))
            elif topic == "command":
                self._on_command(uav, self._command.decode(payload))
            elif topic == "trajectory":
                self._age(uav, "sighting → reference", self._reference.decode(payload).header.source)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
            pass  # not ours to police: the services count their own decode errors

    # ------------------------------------------------------------ perception (evaluation)
    def _targets_at(self, stamp: int) -> dict[str, tuple[float, float, float]]:
        """The standing targets' true positions at a stamp (the latest known if that tick's truth is gone)."""
        return self._truth_history.get(stamp, self._target_positions)

    def _arrival_ns(self, source_ns: int) -> int | None:
        """Mission time, ns, at which the message being handled arrived (see `speed` in __init__);
        None before the first tick (a recording begun mid-run: nothing to date it by)."""
        if self._tick_anchor is None:
            return None
        received, stamp = self._tick_anchor
        if self.speed <= 0 or self._received_ns is None:
            # lockstep: the tick's time; a message may overtake its tick's clock message on the way
            # here, and it cannot have arrived before the data it derives from
            return max(stamp, source_ns)
        return stamp + int((self._received_ns - received) * self.speed)

    def _age(self, uav: str, stage: str, source_ns: int) -> None:
        arrival = self._arrival_ns(source_ns)
        if arrival is not None:
            self.ages.add(uav, stage, source_ns, arrival / 1e9)

    def _on_detections(self, uav: str, det: Detections) -> None:
        self._age(uav, "scan → detections", det.header.source)
        positions = to_numpy(det.positions).reshape(-1, 3)
        u, t = self._uav(uav), self._seconds(det.header.stamp)
        u.detections += len(positions)
        u.detection_counts.append(Sample(t, len(positions)))
        self._note_first_detections(uav, det)
        targets = np.array(list(self._targets_at(det.header.stamp).values())).reshape(-1, 3)
        u.perception.add_detections(t, positions, targets)
        self._pair_sight(uav, det.header.stamp, detections=positions)

    def _on_camera_detections(self, uav: str, det: Detections) -> None:
        self._age(uav, "frame → camera detections", det.header.source)
        positions = to_numpy(det.positions).reshape(-1, 3)
        t = self._seconds(det.header.stamp)
        self._note_first_detections(uav, det)
        targets = np.array(list(self._targets_at(det.header.stamp).values())).reshape(-1, 3)
        self._uav(uav).camera.add_detections(t, positions, targets,
                                             evaluation.camera_tolerance(positions, np.array(det.sensor_position)))

    def _on_command(self, uav: str, command: MissionCommand) -> None:
        """An engagement starts with the first attack or intercept command after any other one
        (re-plans and re-sends of the same engagement follow it). It is judged against the standing
        targets and those down less than UNSEEN_BEFORE_GONE before, where they went down: a UAV
        learns that its target is down only when it has not seen it for that long, and a chase
        taken up again meanwhile (after giving way) aims where the drone was captured."""
        self._age(uav, "sighting → command", command.header.source)
        u = self._uav(uav)
        previous, action = u.last_action, command.action
        u.last_action = action
        if action != "attack" and u.attacking is not None:
            u.leaving = u.attacking
        u.attacking = tuple(command.target) if action == "attack" and command.target is not None else None
        if action not in ("attack", "intercept") or command.target is None or action == previous:
            return
        t = self._seconds(command.header.stamp)
        aimable = dict(self._targets_at(command.header.stamp))
        aimable.update({tid: where for tid, (down, where) in self._down.items()
                        if 0.0 <= t - down <= evaluation.UNSEEN_BEFORE_GONE})
        target, miss = evaluation.aimed_at(command.target, aimable)
        u.engagements.append(evaluation.Engagement(t, action, tuple(command.target), target, miss))

    def _on_points_truth(self, uav: str, truth: PointTruth) -> None:
        where = self._targets_at(truth.header.stamp)
        hit = evaluation.in_sight(to_numpy(truth.hits), len(truth.targets))
        seen = [tid for tid, ok in zip(truth.targets, hit.tolist()) if ok and tid in where]
        self._pair_sight(uav, truth.header.stamp, seen=(np.array([where[tid] for tid in seen]).reshape(-1, 3),
                                                         [self.targets.get(tid, ("?",))[0] for tid in seen]))

    def _pair_sight(self, uav: str, stamp: int, detections: np.ndarray | None = None,
                    seen: tuple[np.ndarray, list[str]] | None = None) -> None:
        """A scan's targets in sight meet its detections (they travel on different keys)."""
        pending = self._sight_pending.setdefault(uav, {})
        entry = pending.setdefault(stamp, [None, None])
        if detections is not None:
            entry[0] = detections
        if seen is not None:
            entry[1] = seen
        if entry[0] is not None and entry[1] is not None:
            self._uav(uav).perception.add_sight(*entry[1], entry[0])
            del pending[stamp]
        while len(pending) > 64:  # a scan whose other half never came
            pending.pop(min(pending))

    def _on_tracks(self, uav: str, tracks: Tracks) -> None:
        self._age(uav, "sensor → tracks", tracks.header.source)
        u = self._uav(uav)
        confirmed = [track for track in tracks.tracks if track.confirmed]
        u.confirmed_tracks.update(track.id for track in confirmed)
        if confirmed:
            positions = track_positions(confirmed)
            targets = np.array(list(self._targets_at(tracks.header.stamp).values())).reshape(-1, 3)
            u.perception.add_tracks(self._seconds(tracks.header.stamp), [track.id for track in confirmed],
                                    positions, targets, [_origin(uav, track) for track in confirmed])

    def _seconds(self, stamp: int) -> float:
        """Mission time of a stamp (a flight's wall-clock stamps count from the first one)."""
        t = seconds(self._origin.mission_ns(stamp))
        self.latest = max(self.latest, t)
        return t

    def _uav(self, name: str) -> UavSummary:
        return self.uavs.setdefault(name, UavSummary())

    def _on_status(self, uav: str, status: UavStatus) -> None:
        u, t = self._uav(uav), self._seconds(status.header.stamp)
        u.state = status.state
        if not u.states or u.states[-1][1] != status.state:
            u.states.append((t, status.state))
            u.decisions.append((t, status.state, status.state_reason))
        xs = [x for x, _ in status.working_area]
        view = ((round(min(xs), 1), round(max(xs), 1)) if xs else None, tuple(status.fallen_partners))
        if view != u.team_view:
            if u.team_view is not None:
                self.team_changes.append({"t": round(t, 2), "uav": uav, "x": list(view[0]) if view[0] else None,
                                          "fallen": list(view[1])})
            u.team_view = view

    def _on_world(self, world: WorldModel) -> None:
        self.uav_radius = dict(world.uav_radius)
        ground = next((o.center[2] for o in world.obstacles if o.kind == "plane"), 0.0)
        if len(world.arena) >= 3:
            self._fence = (np.asarray(world.arena, dtype=np.float64), ground + world.max_height)
        if world.obstacles != self._surveyed:
            self._surveyed = world.obstacles
            self._rebuild_solids()

    def _rebuild_solids(self) -> None:
        self._solids = [o for o in [*(self._surveyed or []), *self._unsurveyed] if o.kind in contact.KINDS]
        self._shapes = contact.shapes(self._solids)

    def _note_clearance(self, t: float, truth: GroundTruth) -> None:
        """Each flying UAV's closest approach to an obstacle so far (see the module's docstring)."""
        flying = [v for v in truth.uavs if v.airborne and v.alive]
        if not flying or self._surveyed is None or not len(self._shapes):  # no world model yet: obstacles unknown
            return
        radius = np.array([self.uav_radius.get(v.name, DEFAULT_UAV_RADIUS) for v in flying])
        gaps = contact.signed_distance(np.array([v.position for v in flying]), self._shapes) - radius[:, None]
        for v, row in zip(flying, gaps):
            u = self._uav(v.name)
            pole = self._attacked_pole(u.attacking or u.leaving)
            if u.attacking is None and (pole is None or self._pass_over(u, float(row[pole]), t)):
                u.leaving, pole = None, None  # the pass is over: the pole is an obstacle like any other
            u.pole_gap = None if pole is None else (float(row[pole]), t)
            if pole is not None:
                u.attack_pole = _closer(u.attack_pole, (float(row[pole]), self._shapes.names[pole], t))
                row = row.copy()
                row[pole] = np.inf
            k = int(np.argmin(row))
            if np.isfinite(row[k]):
                u.clearance = _closer(u.clearance, (float(row[k]), self._shapes.names[k], t))

    @staticmethod
    def _pass_over(u: UavSummary, gap: float, t: float) -> bool:
        """Whether the pass over the attacked pole, `gap` m from the UAV's body now, has ended."""
        if gap < PASS_CLEAR:
            return False
        if u.pole_gap is None or t <= u.pole_gap[1]:
            return True
        before, then = u.pole_gap
        return (before - gap) / (t - then) <= PASS_CLOSING

    def _attacked_pole(self, target: tuple[float, float, float] | None) -> int | None:
        """The index of the balloon pole an attack on `target` goes for, if any."""
        if target is None:
            return None
        names = {pole_name(tid) for tid, (kind, _) in self.targets.items() if kind == "balloon"}
        poles = [(math.dist(o.center[:2], target[:2]), k) for k, o in enumerate(self._solids)
                 if o.kind == "cylinder" and o.name in names]
        nearest = min(poles, default=None)
        return nearest[1] if nearest is not None and nearest[0] <= ATTACKED_POLE_WITHIN else None

    def _on_clock(self, tick: SimClock) -> None:
        self.step = max(self.step, tick.step)
        self.mission_time = seconds(tick.header.stamp)
        if self._tick_anchor is None or tick.header.stamp > self._tick_anchor[1]:  # not a repeat of an older tick
            self._tick_anchor = (self._received_ns if self._received_ns is not None else 0, tick.header.stamp)
        self.rtf = tick.real_time_factor
        self.finished = self.finished or tick.finished

    def digest_summary(self) -> dict[str, list]:
        return {key: [count, digest.hexdigest()] for key, (count, digest) in sorted((self.digests or {}).items())}

    def _on_truth(self, truth: GroundTruth) -> None:
        self.truth_step = max(self.truth_step, truth.step)
        t = self._seconds(truth.header.stamp)
        if truth.obstacles != self._unsurveyed:
            self._unsurveyed = truth.obstacles
            self._rebuild_solids()
        for v in truth.uavs:
            u = self._uav(v.name)
            if u.last_position is not None:
                u.distance += math.dist(u.last_position, v.position)
            u.last_position = v.position
            u.max_height = max(u.max_height, v.position[2])
            u.airborne, u.alive = v.airborne, v.alive
            if v.airborne and u.takeoff is None:
                u.takeoff = t
            if not v.airborne and u.takeoff is not None and u.landed is None:
                u.landed = t
        for target in truth.targets:
            self.targets[target.id] = (target.kind, target.destroyed)
            if not target.destroyed:
                self._target_positions[target.id] = target.position
            elif target.id in self._target_positions:
                self._down[target.id] = (t, self._target_positions.pop(target.id))
        self._truth_history[truth.header.stamp] = dict(self._target_positions)
        while len(self._truth_history) > 64:
            self._truth_history.pop(min(self._truth_history))
        self._note_clearance(t, truth)
        flying = [v for v in truth.uavs if v.airborne and v.alive]
        self._note_geofence(t, flying)
        if len(flying) < 2:
            self._note_separation(t, None, "")
            return
        gaps = pairwise_gaps(np.array([v.position for v in flying]))
        i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
        a, b = sorted((i, j))
        pair = f"{flying[a].name}-{flying[b].name}"
        if self.min_separation is None or gaps[i, j] < self.min_separation[0]:
            self.min_separation = (float(gaps[i, j]), t, pair)
        self._note_separation(t, float(gaps[i, j]), pair)
        for v, gap in zip(flying, gaps.min(axis=1)):
            series = self._uav(v.name).nearest_partner
            if not series or t - series[-1].t >= NEAREST_PERIOD:
                series.append(Sample(t, float(gap)))

    def _note_geofence(self, t: float, flying: list) -> None:
        """Episodes in which a flying UAV was out of the arena or above its ceiling (module docstring)."""
        if self._fence is None:
            return
        arena, ceiling = self._fence
        open_episodes = {e["uav"]: e for e in self.geofence if e["end"] is None}
        for v in flying:
            p = np.asarray(v.position, dtype=np.float64)
            out = max(p[2] - ceiling, 0.0)
            if not point_in_polygon(p[:2], arena):
                out = max(out, float(distance_to_edges(p[:2], arena)[0]))
            episode = open_episodes.pop(v.name, None)
            if out > GEOFENCE_SLACK and episode is None:
                self.geofence.append({"uav": v.name, "start": round(t, 2), "end": None, "m": round(out, 2)})
            elif out > GEOFENCE_SLACK:
                episode["m"] = max(episode["m"], round(out, 2))
            elif episode is not None:
                episode["end"] = round(t, 2)
        for episode in open_episodes.values():  # landed or lost while out
            episode["end"] = round(t, 2)

    def _note_separation(self, t: float, closest: float | None, pair: str) -> None:
        """Episodes in which two flying UAVs were closer than the safety distance."""
        if self.safety_distance is None:
            return
        inside = closest is not None and closest < self.safety_distance
        episode = self.violations[-1] if self.violations and self.violations[-1]["end"] is None else None
        if inside and episode is None:
            self.violations.append({"start": round(t, 2), "end": None, "pair": pair, "m": round(closest, 2)})
        elif inside:
            episode["m"] = min(episode["m"], round(closest, 2))
        elif episode is not None:
            episode["end"] = round(t, 2)

    def _note_first_detections(self, uav: str, det: Detections) -> None:
        """When each target was first detected by anyone: a detection within DETECTED_WITHIN of its
        latest true position (an evaluation figure; no service ever sees it)."""
        if not det.positions.shape or not det.positions.shape[0]:
            return
        positions = to_numpy(det.positions).reshape(-1, 3)
        t = self._seconds(det.header.stamp)
        for tid, where in self._target_positions.items():
            if tid not in self.first_detected:
                if any(math.dist(where, p) <= DETECTED_WITHIN for p in positions.tolist()):
                    self.first_detected[tid] = (t, uav)

    def _on_events(self, event: SimEvent) -> None:
        self.events.append(event)
        if event.kind == "mission_finished":
            self.over = True
        elif event.kind in ("target_destroyed", "target_captured"):
            self.destroyed.append((self._seconds(event.header.stamp), event.subject, event.detail))
        elif event.kind == "collision":
            self.collisions.append({"t": round(self._seconds(event.header.stamp), 2), "uav": event.subject,
                                    "with": event.detail.rsplit(" at ", 1)[0], "detail": event.detail})
        elif event.kind == "started_without":
            self.started_without = event.detail.split(", ")
        elif event.kind == "service_restarted":
            self.restarts.append(f"{event.subject} ({event.detail})")
        elif event.kind.startswith("fault_"):
            self.faults.append(f"t={self._seconds(event.header.stamp):.1f} s {event.kind} {event.subject}: {event.detail}")

    def progress(self, duration: float) -> str:
        airborne = sum(u.airborne for u in self.uavs.values())
        tracks = sum(len(u.confirmed_tracks) for u in self.uavs.values())
        return (f"t={self.mission_time:6.1f}/{duration:.0f} s  rtf {self.rtf:4.1f}x  "
                f"airborne {airborne}/{len(self.uavs)}  destroyed {len(self.destroyed)}/{len(self.targets)}  "
                f"confirmed tracks {tracks}")

    def summary(self) -> dict:
        matched_anywhere = set().union(*(u.perception.matched_origins() for u in self.uavs.values()))
        return {
            "finished": self.finished,
            "mission_time": round(self.mission_time, 3),
            "real_time_factor": round(self.rtf, 2),
            "targets": len(self.targets),
            "destroyed": [{"t": round(t, 2), "target": tid, "kind": self.targets.get(tid, ("?", True))[0], "by": uav,
                           "first_detected": None if tid not in self.first_detected
                           else round(self.first_detected[tid][0], 2)}
                          for t, tid, uav in self.destroyed],
            "target_kinds": {tid: kind for tid, (kind, _) in sorted(self.targets.items())},
            "first_detected": {tid: {"t": round(t, 2), "by": uav} for tid, (t, uav) in sorted(self.first_detected.items())},
            "min_separation": None if self.min_separation is None else {
                "m": round(self.min_separation[0], 2), "t": round(self.min_separation[1], 2),
                "pair": self.min_separation[2]},
            "safety_distance": self.safety_distance,
            "separation_violations": [dict(v) for v in self.violations],
            "collisions": [dict(c) for c in self.collisions],
            "geofence_breaches": [dict(e) for e in self.geofence],
            "clearance": {name: {**_approach(u.clearance), "attack_pole": None if u.attack_pole is None
                                 else _approach(u.attack_pole)}
                          for name, u in sorted(self.uavs.items())},
            "restarts": list(self.restarts),
            "started_without": list(self.started_without),
            "team_changes": list(self.team_changes),
            "faults": list(self.faults),
            "uavs": {
                name: {"distance_m": round(u.distance, 1), "max_height_m": round(u.max_height, 2),
                       "takeoff_s": u.takeoff, "landed_s": u.landed, "final_state": u.state,
                       "detections": u.detections, "confirmed_tracks": len(u.confirmed_tracks),
                       "states": [[round(t, 2), state] for t, state in u.states],
                       "decisions": [[round(t, 2), state, reason] for t, state, reason in u.decisions],
                       "perception": u.perception.summary(matched_anywhere),
                       "camera": {key: value for key, value in u.camera.summary().items()
                                  if key in ("detections", "matched", "false", "false_per_minute")},
                       "engagements": [e.summary() for e in u.engagements]}
                for name, u in sorted(self.uavs.items())
            },
            "events": [f"{seconds(self._origin.mission_ns(e.header.stamp)):.2f} {e.kind} {e.subject} {e.detail}".rstrip()
                       for e in self.events],
            "data_age": {"real_time": self.speed > 0, "stages": self.ages.summary()},
        }


def _origin(uav: str, track) -> evaluation.TrackOrigin:
    """Whose tracker keeps the track, and its id there: a partner's track in the fleet picture
    carries the fleet id partner number x FLEET_ID_BASE + the partner's own id."""
    if track.source in ("", uav):
        return uav, int(track.id)
    return track.source, int(track.id) % FLEET_ID_BASE


def _closer(best: tuple[float, str, float] | None, sample: tuple[float, str, float]) -> tuple[float, str, float]:
    return sample if best is None or sample[0] < best[0] else best


def _approach(closest: tuple[float, str, float] | None) -> dict:
    """{"m", "to", "t"} of a closest approach (None each when there was none)."""
    if closest is None:
        return {"m": None, "to": None, "t": None}
    return {"m": round(closest[0], 2), "to": closest[1], "t": round(closest[2], 2)}
