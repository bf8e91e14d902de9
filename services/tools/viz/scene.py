"""The viewer's core: the fleet's messages in, what to draw out (draw.Log records).

Fed the same way live (from Zenoh) and from a recording (MCAP): `feed(key, payload, received)`
with the payload exactly as it went over the wire. Everything is drawn at the mission time of the
message's header (timeline "mission_time", and "tick" = the mission clock's step); wall-clock
receive times only measure lags. Decisions to thin out (scans, tracks, truth) depend on mission
time alone, so a recording converts to the same picture as the live run drew.

Entities (`UAV_FAMILIES` under each UAV's name; the rest run-wide):
- world/…: arena, ground, obstacles (static); truth/…: the evaluation layer — targets' true
  positions and paths, the UAVs' true positions, destruction and capture markers;
- <uav>/…: what that UAV believes — pose (odometry) and trail, scan coloured by the classifier's
  labels (by height when only raw points exist), map (occupied / unknown voxels), detections and
  tracks with covariance ellipsoids, the camera's compressed frames (1 Hz) and Object Detect's
  detections (balloons by colour), predicted track paths, trajectory reference, working area,
  forbidden zones, the job manager's state (timeline and document), events (faults, restarts,
  commands, state changes);
- plots/…: detections per second (and, with truth, false ones), track uncertainty, CPU per service,
  pipeline lags, the age of the map each scan was classified with, distance to the nearest partner
  (truth), real-time factor; events: every event as a log line.
With truth (a simulation), detections are coloured by services/tools/evaluation/__init__.py's match: green within
1 m of a live target, white otherwise.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import msgspec
import numpy as np

from schemas import keys, voxels
from schemas.arrays import to_numpy
from schemas.catalogue import catalogue_entry
from schemas.messages import (
    CompressedFrame,
    Detections,
    GroundTruth,
    LabelSet,
    MissionCommand,
    Obstacle,
    Odometry,
    PointCloud,
    ServiceHealth,
    SimClock,
    SimEvent,
    Track,
    Tracks,
    TrajectoryReference,
    UavStatus,
    VoxelMap,
    WorldModel,
)
from services.tools import evaluation
from services.lib.geometry import pairwise_gaps
from services.lib.runtime.clock import NS, StampOrigin
from services.lib.tracks import predicted_path, track_positions
from services.tools.viz import draw
from services.tools.viz.geometry import (
    TERRAIN,
    Color,
    closed_polygon,
    cone_mesh,
    covariance_ellipsoids,
    height_colors,
    merge_meshes,
    rectangle_mesh,
    thin_out,
    wxyz_to_xyzw,
)
from services.tools.viz.mapview import MapView
from services.tools.viz.settings import ViewParams
from services.tools.viz.style import (DETECTION_COLOR, FALSE_COLOR, LABEL_COLORS, MATCHED_COLOR, STATE_COLORS, TRUTH_COLOR,
                                uav_color)

UAV_FAMILIES = (
    "pose", "trail", "scan", "map/occupied", "map/unknown", "detections", "camera/image", "camera_detections",
    "tracks/confirmed",
    "tracks/tentative", "tracks/predicted", "trajectory", "working_area", "forbidden_zones", "state",
    "status", "events",
)
WORLD_FAMILIES = ("world/arena", "world/ground", "world/obstacles", "truth/obstacles", "truth/targets",
                  "truth/target_paths", "truth/uavs", "events")

MEMORY_PERIOD = 5.0  # s of mission time between memory points of one service (it changes slowly)
EVENT_LEVELS = {"fault_injected": "WARN", "fault_started": "WARN", "fault_failed": "ERROR",
                "service_restarted": "WARN", "fault_ended": "INFO"}


@dataclass
class _Uav:
    color: Color
    trail: deque = field(default_factory=deque)  # (stamp, (3,) position)
    scans_received: dict[int, int] = field(default_factory=dict)  # scan stamp -> wall ns it arrived
    has_labels: bool = False
    state: str = ""
    status_view: tuple = ()
    command_id: int = -1
    track_set: tuple = ()  # (id, confirmed) of the tracks last drawn
    map: MapView | None = None
    map_seq: int = -1  # header.seq of the last map message
    map_exact: bool = False  # a snapshot and then every message in sequence: snapshots add nothing
    due: dict[str, int] = field(default_factory=dict)  # what -> next mission ns it may be drawn


@dataclass
class _Window:
    start: int  # mission ns of the second's start
    value: float  # what the second has so far


@dataclass
class _Cpu:
    pid: int
    cpu_time: float
    uptime: float


class SceneBuilder:
    def __init__(self, params: ViewParams | None = None) -> None:
        self.params = params or ViewParams()
        self.tick_ns: int | None = None  # the mission clock's step, once a SimClock said it
        self.uavs: dict[str, _Uav] = {}
        self.layout_changed = False  # a new UAV appeared: the output should lay out the views again
        self.decode_errors = 0
        self.messages = 0
        self.mission_ns = 0  # the latest mission time seen
        self.duration = 0.0  # s, from the world model (0: unknown)
        self._origin = StampOrigin()
        self._world_key = b""
        self._unsurveyed: list[Obstacle] = []  # the truth's obstacles drawn last
        self._target_paths: dict[str, deque] = {}
        self._target_last: dict[str, tuple[float, float, float]] = {}
        self._targets_now: np.ndarray | None = None  # (K, 3) live targets' true positions, once truth is seen
        self._destroyed: list[tuple[np.ndarray, str]] = []
        self._cpu: dict[str, _Cpu] = {}
        self._windows: dict[str, _Window] = {}  # plot entity -> the second being folded
        self._due: dict[str, int] = {}
        self._empty: set[str] = set()  # entities whose last drawing was empty
        self._decoders: dict[type, msgspec.msgpack.Decoder] = {}
        self._out: list[draw.Log] = []  # what the message being fed draws
        self._received = 0  # its wall-clock arrival, ns
        self._stamp = 0  # its mission time, ns
        self._handlers = {
            keys.CLOCK: self._on_clock, keys.WORLD: self._on_world, keys.TRUTH: self._on_truth,
            keys.EVENTS: self._on_event,
            "falconry/<uav>/odometry": self._on_odometry, "falconry/<uav>/points": self._on_points,
            "falconry/<uav>/labels": self._on_labels, "falconry/<uav>/detections": self._on_detections,
            "falconry/<uav>/camera_jpeg": self._on_camera_frame,
            "falconry/<uav>/camera_detections": self._on_camera_detections,
            "falconry/<uav>/map": self._on_map, "falconry/<uav>/tracks": self._on_tracks,
            "falconry/<uav>/command": self._on_command, "falconry/<uav>/trajectory": self._on_trajectory,
            "falconry/<uav>/status": self._on_status, "falconry/<scope>/health/<service>": self._on_health,
        }

    # ------------------------------------------------------------------ input
    def feed(self, key: str, payload: bytes, received: int = 0) -> list[draw.Log]:
        """What to draw for one message; undecodable payloads are counted and skipped."""
        entry = catalogue_entry(key)
        handler = self._handlers.get(entry.key) if entry is not None else None
        if handler is None:
            return []
        decoder = self._decoders.get(entry.type)
        if decoder is None:
            decoder = self._decoders[entry.type] = msgspec.msgpack.Decoder(entry.type)
        try:
            msg = decoder.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
            self.decode_errors += 1
            return []
        self.messages += 1
        self._out = []
        self._received = received
        self._stamp = self._origin.mission_ns(msg.header.stamp)
        self.mission_ns = max(self.mission_ns, self._stamp)
        try:
            handler(keys.uav_of(key), msg)
        except (ValueError, IndexError, TypeError):
            self.decode_errors += 1  # well-formed msgpack, impossible content (wrong shapes, …)
        return self._out

    def finish(self) -> list[draw.Log]:
        """What is still held back: the last second of each per-second plot."""
        self._out = []
        for entity, window in sorted(self._windows.items()):
            self._log(entity, draw.Scalar(window.value), stamp=window.start)
        self._windows.clear()
        return self._out

    # ---------------------------------------------------------------- helpers
    def _log(self, entity: str, item, static: bool = False, stamp: int | None = None) -> None:
        """Draw `item` on `entity`; an empty batch after an empty batch is left out (most scans detect
        nothing: saying so once is enough, and each log call costs the viewer's CPU)."""
        if draw.count(item) == 0:
            if entity in self._empty:
                return
            self._empty.add(entity)
        else:
            self._empty.discard(entity)
        at = None if static else (self._stamp if stamp is None else stamp)
        tick = None if at is None or self.tick_ns is None else int(round(at / self.tick_ns))
        self._out.append(draw.Log(entity, item, at, tick, self._received))

    def _due_now(self, table: dict[str, int], what: str, period: float) -> bool:
        """True at most once per `period` s of mission time for `what` (the first time at once)."""
        due = table.get(what)
        if due is not None and self._stamp < due:
            return False
        table[what] = self._stamp + int(period * NS)
        return True

    def _uav(self, name: str) -> _Uav:
        uav = self.uavs.get(name)
        if uav is None:
            uav = self.uavs[name] = _Uav(color=uav_color(len(self.uavs)))
            self.layout_changed = True
            states = list(STATE_COLORS)
            self._log(f"{name}/state", draw.StateStyle(states, [STATE_COLORS[s] for s in states]), static=True)
            self._log(f"{name}/pose/body", draw.Axes(1.0), static=True)
            self._log(f"plots/detections/{name}", draw.SeriesStyle(name, uav.color), static=True)
            pale = tuple(int(c + (255 - c) * 0.6) for c in uav.color[:3]) + (255,)
            self._log(f"plots/false_detections/{name}", draw.SeriesStyle(f"{name} false", pale), static=True)
            self._log(f"plots/map_age_ms/{name}", draw.SeriesStyle(name, uav.color), static=True)
            self._log(f"plots/nearest_partner/{name}", draw.SeriesStyle(name, uav.color), static=True)
        return uav

    # ---------------------------------------------------------------- run-wide
    def _on_clock(self, scope: str, tick: SimClock) -> None:
        if tick.dt > 0:
            self.tick_ns = int(round(tick.dt * NS))
        if self._due_now(self._due, "rtf", 1.0):
            self._log("plots/real_time_factor", draw.Scalar(tick.real_time_factor))

    def _on_world(self, scope: str, world: WorldModel) -> None:
        self.duration = world.duration
        for name in world.uavs:
            self._uav(name)
        shape = msgspec.msgpack.encode([world.arena, world.obstacles])
        if shape == self._world_key:
            return
        self._world_key = shape
        ground = next((o.center[2] for o in world.obstacles if o.kind == "plane"), 0.0)
        self._log("world", draw.ZUp(), static=True)
        self._log("world/arena", draw.Lines([closed_polygon(world.arena, ground + 0.05)], (255, 255, 255, 255), 0.08,
                                            [world.scenario]), static=True)
        arena = np.asarray(world.arena, dtype=np.float64).reshape(-1, 2)
        low, high = arena.min(axis=0) - 10.0, arena.max(axis=0) + 10.0
        vertices, triangles = rectangle_mesh(tuple(low), tuple(high), ground)
        self._log("world/ground", draw.Mesh(vertices, triangles, (90, 110, 80, 255)), static=True)
        self._draw_obstacles(world.obstacles, "world/obstacles")

    def _draw_obstacles(self, obstacles: list[Obstacle], family: str) -> None:
        by_kind: dict[str, list] = {}
        for o in obstacles:
            by_kind.setdefault(o.kind, []).append(o)
        grey: Color = (170, 160, 150, 255)
        if boxes := by_kind.get("box"):
            self._log(f"{family}/boxes", draw.Boxes(
                np.array([o.center for o in boxes]), np.array([o.size for o in boxes]) / 2, grey,
                [o.name for o in boxes], show_labels=False), static=True)
        if cylinders := by_kind.get("cylinder"):
            self._log(f"{family}/cylinders", draw.Cylinders(
                np.array([o.center for o in cylinders]) + np.array([[0, 0, o.height / 2] for o in cylinders]),
                np.array([o.height for o in cylinders]), np.array([o.radius for o in cylinders]),
                (120, 150, 100, 255), [o.name for o in cylinders], show_labels=False), static=True)
        if spheres := by_kind.get("sphere"):
            self._log(f"{family}/spheres", draw.Ellipsoids(
                np.array([o.center for o in spheres]), np.array([[o.radius] * 3 for o in spheres]), None,
                grey, [o.name for o in spheres], solid=True, show_labels=False), static=True)
        if cones := by_kind.get("cone"):
            vertices, triangles = merge_meshes([cone_mesh(np.asarray(o.center), o.radius, o.height) for o in cones])
            self._log(f"{family}/cones", draw.Mesh(vertices, triangles, (60, 120, 60, 255)), static=True)

    def _on_truth(self, scope: str, truth: GroundTruth) -> None:
        """The evaluation layer: drawn as 'truth', never what a UAV believes. The obstacles the
        mission's survey lacks (only the simulated sensors see them) are drawn once, as truth."""
        p = self.params
        if truth.obstacles and truth.obstacles != self._unsurveyed:
            self._unsurveyed = truth.obstacles
            self._draw_obstacles(truth.obstacles, "truth/obstacles")
        self._targets_now = np.array([t.position for t in truth.targets if not t.destroyed]).reshape(-1, 3)
        for target in truth.targets:
            path = self._target_paths.setdefault(target.id, deque())
            if not target.destroyed:
                self._target_last[target.id] = target.position
                if not path or self._stamp - path[-1][0] >= p.trail_spacing * NS:
                    path.append((self._stamp, target.position))
            while path and self._stamp - path[0][0] > p.trail_length * NS:
                path.popleft()
        if self._due_now(self._due, "truth", p.truth_period):
            live = [t for t in truth.targets if not t.destroyed]
            self._log("truth/targets", draw.Ellipsoids(
                np.array([t.position for t in live]).reshape(-1, 3), np.array([[t.radius] * 3 for t in live]).reshape(-1, 3),
                None, TRUTH_COLOR, [f"truth: {t.id}" for t in live], solid=True))
            flying = [v for v in truth.uavs if v.alive]
            self._log("truth/uavs", draw.Points(np.array([v.position for v in flying]).reshape(-1, 3), TRUTH_COLOR,
                                                0.25, [f"truth: {v.name}" for v in flying]))
            self._nearest_partners(truth)
        if self._due_now(self._due, "truth_paths", p.trail_period):
            paths = [(tid, np.array([q for _, q in path])) for tid, path in sorted(self._target_paths.items())
                     if len(path) > 1]
            moving = [(tid, q) for tid, q in paths if np.ptp(q, axis=0).max() > 1.0]  # not a swaying balloon
            self._log("truth/target_paths", draw.Lines([q for _, q in moving], TRUTH_COLOR, 0.05,
                                                       [f"truth: {tid}" for tid, _ in moving]))

    def _nearest_partners(self, truth: GroundTruth) -> None:
        flying = [v for v in truth.uavs if v.airborne and v.alive]
        if len(flying) < 2:
            return
        nearest = pairwise_gaps(np.array([v.position for v in flying])).min(axis=1)
        for v, gap in zip(flying, nearest):
            self._uav(v.name)
            self._log(f"plots/nearest_partner/{v.name}", draw.Scalar(float(gap)))

    def _on_event(self, scope: str, event: SimEvent) -> None:
        level = EVENT_LEVELS.get(event.kind, "INFO")
        line = f"{event.kind} {event.subject}" + (f": {event.detail}" if event.detail else "")
        self._log("events", draw.Text(line, level))
        owner = event.subject.split("/", 1)[0]
        if owner in self.uavs:
            self._log(f"{owner}/events", draw.Text(line, level))
        if event.kind in ("target_destroyed", "target_captured") and event.subject in self._target_last:
            verb = "destroyed" if event.kind == "target_destroyed" else "captured"
            self._destroyed.append((np.asarray(self._target_last[event.subject]),
                                    f"{event.subject} {verb} by {event.detail} t={self._stamp / NS:.1f} s"))
            self._log("truth/destroyed", draw.Points(np.array([p for p, _ in self._destroyed]), (255, 255, 255, 255),
                                                     0.5, [label for _, label in self._destroyed]))

    def _on_health(self, scope: str, health: ServiceHealth) -> None:
        name = f"{health.uav}/{health.service}"
        last = self._cpu.get(name)
        self._cpu[name] = _Cpu(health.pid, health.cpu_time, health.uptime)
        if last is not None and last.pid == health.pid and health.uptime > last.uptime:
            share = 100.0 * (health.cpu_time - last.cpu_time) / (health.uptime - last.uptime)
            self._log(f"plots/cpu/{name}", draw.Scalar(share))
        if health.memory and self._due_now(self._due, f"memory/{name}", MEMORY_PERIOD):
            self._log(f"plots/memory_mb/{name}", draw.Scalar(health.memory / 1e6))

    # ---------------------------------------------------------------- per UAV
    def _on_odometry(self, name: str, odometry: Odometry) -> None:
        uav, p = self._uav(name), self.params
        position = np.asarray(odometry.pose.position, dtype=np.float64)
        if self._due_now(uav.due, "pose", p.pose_period):
            self._log(f"{name}/pose", draw.Pose(position, wxyz_to_xyzw(odometry.pose.orientation)))
        if not uav.trail or self._stamp - uav.trail[-1][0] >= p.trail_spacing * NS:
            uav.trail.append((self._stamp, position))
        while uav.trail and self._stamp - uav.trail[0][0] > p.trail_length * NS:
            uav.trail.popleft()
        if len(uav.trail) > 1 and self._due_now(uav.due, "trail", p.trail_period):
            self._log(f"{name}/trail", draw.Lines([np.array([q for _, q in uav.trail])], uav.color, 0.06))

    def _note_scan(self, uav: _Uav) -> None:
        uav.scans_received[self._stamp] = self._received
        if len(uav.scans_received) > 64:
            uav.scans_received.pop(next(iter(uav.scans_received)))

    def _on_points(self, name: str, cloud: PointCloud) -> None:
        uav = self._uav(name)
        self._note_scan(uav)
        if uav.has_labels or not self._due_now(uav.due, "scan", self.params.scan_period):
            return
        points = to_numpy(cloud.points).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        points = points[thin_out(len(points), self.params.scan_points)]
        self._log(f"{name}/scan", draw.Points(points, height_colors(points[:, 2], 0.0, 12.0), 0.06))

    def _on_labels(self, name: str, labels: LabelSet) -> None:
        uav = self._uav(name)
        uav.has_labels = True
        if labels.map_stamp:  # how old the map was that classified this scan (mission time: deterministic)
            self._per_second(f"plots/map_age_ms/{name}", (labels.header.stamp - labels.map_stamp) / 1e6, max)
        if not self._due_now(uav.due, "scan", self.params.scan_period):
            return
        points = to_numpy(labels.points).reshape(-1, 3)
        codes = to_numpy(labels.point_labels).reshape(-1)
        if len(codes) != len(points):
            raise ValueError("labels and points differ in length")
        background = np.flatnonzero(codes == voxels.BACKGROUND)
        others = np.flatnonzero(codes != voxels.BACKGROUND)  # the interesting ones: always drawn
        keep = np.concatenate([others, background[thin_out(len(background), max(self.params.scan_points - len(others), 0))]])
        colors = LABEL_COLORS[np.clip(codes[keep], 0, len(LABEL_COLORS) - 1)]
        self._log(f"{name}/scan", draw.Points(points[keep], colors, 0.06))

    def _lag(self, name: str, uav: _Uav, what: str) -> None:
        """Wall time from a scan's arrival to the arrival of what was made from it (same stamp);
        the worst of each second is plotted."""
        scan_at = uav.scans_received.get(self._stamp)
        if scan_at and self._received:
            self._per_second(f"plots/lag_ms/{name}/{what}", (self._received - scan_at) / 1e6, max)

    def _per_second(self, entity: str, value: float, combine: Callable[[float, float], float]) -> None:
        """Fold values into one per second of mission time, plotted at the second's start once
        the next second begins (a plot point per scan would cost more than it shows)."""
        second = self._stamp // NS * NS
        window = self._windows.get(entity)
        if window is not None and window.start == second:
            window.value = combine(window.value, value)
            return
        if window is not None:
            self._log(entity, draw.Scalar(window.value), stamp=window.start)
        self._windows[entity] = _Window(second, value)

    def _on_detections(self, name: str, detections: Detections) -> None:
        self._draw_detections(name, detections, "detections", "")
        self._lag(name, self._uav(name), "detections")

    def _on_camera_detections(self, name: str, detections: Detections) -> None:
        self._draw_detections(name, detections, "camera_detections", "camera_", camera=True)

    def _on_camera_frame(self, name: str, frame: CompressedFrame) -> None:
        self._uav(name)
        self._log(f"{name}/camera/image", draw.Image(bytes(frame.jpeg)))

    def _draw_detections(self, name: str, detections: Detections, entity: str, plot_prefix: str,
                         camera: bool = False) -> None:
        """Ellipsoids of the detections' covariances, coloured by the truth where there is one."""
        positions = to_numpy(detections.positions).reshape(-1, 3)
        half, rotations = covariance_ellipsoids(to_numpy(detections.covariances).reshape(-1, 3, 3),
                                                self.params.ellipsoid_sigma)
        counts = to_numpy(detections.point_counts).reshape(-1)
        if not (len(positions) == len(half) == len(counts)):
            raise ValueError("detection arrays differ in length")
        labels = [f"{n} pts" for n in counts.tolist()]
        colors: np.ndarray | Color = DETECTION_COLOR
        if self._targets_now is not None:  # a simulation: truth says which detections were right
            tolerance = (evaluation.camera_tolerance(positions, np.array(detections.sensor_position)) if camera
                         else evaluation.MATCH_DISTANCE)
            right = evaluation.matched(positions, self._targets_now, tolerance)
            colors = np.where(right[:, None], MATCHED_COLOR, FALSE_COLOR).astype(np.uint8).reshape(-1, 4)
            labels = [f"{label}, {'matched' if ok else 'false'}" for label, ok in zip(labels, right.tolist())]
            self._per_second(f"plots/false_detections/{plot_prefix}{name}", float((~right).sum()), lambda a, b: a + b)
        self._log(f"{name}/{entity}", draw.Ellipsoids(positions, half, rotations, colors, labels, show_labels=False))
        plot = f"plots/camera_detections/{name}" if plot_prefix else f"plots/detections/{name}"
        self._per_second(plot, float(len(positions)), lambda a, b: a + b)

    def _on_map(self, name: str, voxel_map: VoxelMap) -> None:
        uav = self._uav(name)
        if uav.map is None:
            uav.map = MapView(self.params.map_cell, self.params.map_layers)
        in_sequence = voxel_map.header.seq == uav.map_seq + 1
        uav.map_seq = voxel_map.header.seq
        void: list[int] = []
        if voxel_map.snapshot and uav.map_exact and in_sequence:
            pass  # every delta since the last applied snapshot arrived: this one repeats them
        else:
            update = uav.map.apply(voxel_map.snapshot, voxel_map.origin, voxel_map.shape, voxel_map.voxel_size,
                                   voxel_map.default_value, to_numpy(voxel_map.indices), to_numpy(voxel_map.values))
            uav.map_exact = update.accepted and ((uav.map_exact and in_sequence) or voxel_map.snapshot)
            void = update.void
        for layer in void:  # the map changed its geometry: what was drawn is no longer it
            self._log(f"{name}/map/occupied/{layer:04d}", draw.Boxes(np.zeros((0, 3)), np.zeros(3), (0, 0, 0, 0)))
            self._log(f"{name}/map/unknown/{layer:04d}", draw.Points(np.zeros((0, 3)), (0, 0, 0, 0), 0.0))
        if not voxel_map.snapshot:
            self._lag(name, uav, "map")
        if not self._due_now(uav.due, "map", self.params.map_period):
            return
        half = uav.map.cell_size() * 0.45
        for layer in uav.map.drain():
            colors = height_colors(layer.occupied[:, 2], 0.0, 10.0, ramp=TERRAIN)
            self._log(f"{name}/map/occupied/{layer.layer:04d}", draw.Boxes(layer.occupied, np.array([half] * 3), colors))
            self._log(f"{name}/map/unknown/{layer.layer:04d}", draw.Points(layer.unknown, (120, 200, 255, 120), half * 0.6))

    def _on_tracks(self, name: str, tracks: Tracks) -> None:
        uav, p = self._uav(name), self.params
        track_set = tuple((t.id, t.confirmed) for t in tracks.tracks)
        due = self._due_now(uav.due, "tracks", p.track_period)
        if not due and track_set == uav.track_set:
            return  # between draws, only a track that appears, goes or is confirmed is drawn at once
        uav.track_set = track_set
        for confirmed in (True, False):
            chosen = [t for t in tracks.tracks if t.confirmed == confirmed]
            covariances = np.array([to_numpy(t.covariance).reshape(9, 9)[:3, :3] for t in chosen]).reshape(-1, 3, 3)
            half, rotations = covariance_ellipsoids(covariances, p.ellipsoid_sigma)
            kind = "confirmed" if confirmed else "tentative"
            color = uav.color if confirmed else (200, 200, 200, 200)
            self._log(f"{name}/tracks/{kind}", draw.Ellipsoids(
                track_positions(chosen), half, rotations, color,
                [_track_label(t) for t in chosen]))
            if confirmed:
                paths = [predicted_path(t, p.prediction_horizon) for t in chosen]
                self._log(f"{name}/tracks/predicted", draw.Lines(paths, uav.color, 0.04, [f"#{t.id}" for t in chosen]))
                for t in chosen:
                    self._log(f"plots/track_uncertainty/{name}/{t.id}", draw.Scalar(t.uncertainty_radius))

    def _on_command(self, name: str, command: MissionCommand) -> None:
        uav = self._uav(name)
        if command.command_id == uav.command_id:
            return  # the 2 s repeat of a command already drawn
        uav.command_id = command.command_id
        target = "" if command.target is None else " to (%.1f, %.1f, %.1f)" % command.target
        self._log(f"{name}/events", draw.Text(f"command {command.command_id}: {command.action}{target}", "DEBUG"))

    def _on_trajectory(self, name: str, trajectory: TrajectoryReference) -> None:
        uav = self._uav(name)
        positions = to_numpy(trajectory.positions).reshape(-1, 3)
        positions = positions[thin_out(len(positions), 400)]
        self._log(f"{name}/trajectory", draw.Lines([positions], uav.color, 0.03,
                                                    [f"command {trajectory.command_id}"], show_labels=False))

    def _on_status(self, name: str, status: UavStatus) -> None:
        uav = self._uav(name)
        if status.state != uav.state:
            uav.state = status.state
            self._log(f"{name}/state", draw.State(status.state))
            self._log(f"{name}/events", draw.Text(f"state {status.state}"))
        view = (status.state, status.flying_normally, status.airborne, status.target, tuple(status.working_area),
                tuple(status.fallen_partners), len(status.forbidden_zones))
        due = self._due_now(uav.due, "status", self.params.status_period)  # zones' remaining life changes
        if not due and view == uav.status_view:
            return
        uav.status_view = view
        self._log(f"{name}/status", draw.Document(status_markdown(name, status)))
        self._log(f"{name}/working_area", draw.Lines([closed_polygon(status.working_area, 0.15)], uav.color, 0.12,
                                                      [f"{name} working area"] if status.working_area else None, show_labels=False))
        zones = status.forbidden_zones
        self._log(f"{name}/forbidden_zones", draw.Ellipsoids(
            np.array([z.center for z in zones]).reshape(-1, 3), np.array([[z.radius] * 3 for z in zones]).reshape(-1, 3),
            None, (255, 60, 60, 90),
            [f"forbidden r={z.radius:g} m, {max(z.expires - status.header.stamp, 0) / NS:.0f} s left ({z.reason})"
             for z in zones]))


def _track_label(track: Track) -> str:
    """A track's label: identity, uncertainty, detections and, once its keeper learnt it, the target's width."""
    width = f", {2 * track.half_width:.2f} m wide" if track.half_width > 0 else ""
    return f"#{track.id} r={track.uncertainty_radius:.1f} m, {track.detections} det{width}"


def status_markdown(name: str, status: UavStatus) -> str:
    """The job manager's status as a short markdown document."""
    xs = [x for x, _ in status.working_area]
    area = f"x {min(xs):.0f}..{max(xs):.0f} m" if xs else "none"
    target = "none" if status.target is None else "(%.1f, %.1f, %.1f)" % status.target
    now = status.header.stamp  # zones expire on the job manager's clock, whatever the viewer counts from
    zones = ", ".join(f"({z.center[0]:.0f}, {z.center[1]:.0f}) {max(z.expires - now, 0) / NS:.0f} s left"
                      for z in status.forbidden_zones) or "none"
    return "\n".join([
        f"## {name}: {status.state}",
        "",
        "| | |",
        "| --- | --- |",
        f"| flying normally | {'yes' if status.flying_normally else 'no'} |",
        f"| airborne | {'yes' if status.airborne else 'no'} |",
        f"| position | ({status.position[0]:.1f}, {status.position[1]:.1f}, {status.position[2]:.1f}) |",
        f"| target | {target} |",
        f"| working area | {area} |",
        f"| fallen partners | {', '.join(status.fallen_partners) or 'none'} |",
        f"| forbidden zones | {zones} |",
    ])
