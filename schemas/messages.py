"""Every message Falconry sends, as msgspec Structs.

Evolution rule: fields are only ever appended, always with defaults, so old readers
ignore new fields and new readers fill in missing ones. `python -m schemas export`
writes the JSON Schema of each message to schemas/json/ (checked by a test).
Vectors are (x, y, z) in metres in the world frame (ENU, z up) unless a frame says otherwise;
quaternions are (w, x, y, z); stamps are integer nanoseconds of mission time.
"""
from __future__ import annotations

from typing import Literal

import msgspec

from schemas.arrays import Array

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
Point2 = tuple[float, float]
Color = tuple[int, int, int]  # sRGB, 0-255 per channel


class Header(msgspec.Struct, kw_only=True):
    """Who sent it, its place in the sender's stream on this key, and when the data is valid."""

    sender: str = ""  # "<uav>/<service>", e.g. "uav1/tracker", or "sim/simulator"
    seq: int = 0  # per publisher and key expression, starts at 1
    stamp: int = 0  # mission time of the data, ns
    frame: str = "world"
    # mission time, ns, of the newest sensor data (a scan or a camera frame) this message derives
    # from, carried along the pipeline (scan -> detections -> tracks -> command -> reference) so its
    # age can be measured at every stage; 0: none (not derived from sensor data, or not known)
    source: int = 0


class Pose(msgspec.Struct):
    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat = (1.0, 0.0, 0.0, 0.0)


class PointCloud(msgspec.Struct, kw_only=True):
    """One organised LiDAR scan: `points` is float32 (height, width, 3) in the world frame,
    NaN where the ray returned nothing. `sensor_pose` is where the scan was taken from."""

    header: Header
    width: int
    height: int
    sensor_pose: Pose
    points: Array
    intensity: Array | None = None  # float32 (height, width)
    sensor_model: str = ""
    min_range: float = 0.0
    max_range: float = 0.0
    frame: int = 0  # the model's beam pattern of this scan (n-th frame since mission time 0; services/lib/lidar)
    # uint8 (height, ceil(width / 8)), each row's bits packed (numpy.packbits): 1 where the ray meets the
    # carrier's own body, so its missing return says nothing about the world (the mapper skips it)
    mask: Array | None = None
    pose_covariance: Array | None = None  # float64 6×6 over (x, y, z, roll, pitch, yaw) of sensor_pose
    # Why the driver's sanity check (services/lib/lidar/sanity.py) failed this scan ("" : it passed). A
    # failed scan is published for the record only: every consumer skips its points.
    sanity: str = ""


class PointTruth(msgspec.Struct, kw_only=True):
    """Evaluation only, never read by perception: what each ray of the PointCloud with the same
    stamp hit. `hits` is int32 (height, width): -1 no return, 0 the static world, k >= 1 the
    target `targets[k - 1]`."""

    header: Header
    width: int
    height: int
    hits: Array
    targets: list[str] = []


class CameraFrame(msgspec.Struct, kw_only=True):
    """One colour image and the depth image aligned with it (a simulated RGB-D camera; onboard,
    a driver). Pixel (u, v): column u from the left, row v from the top; the ray through it in the
    camera frame (x along the optical axis, y left, z up) is (1, (cx - u) / fx, (cy - v) / fy),
    pixel centres at integer + 0.5. Raw frames stay on their UAV: the recorder keeps the compressed
    stream (`CompressedFrame`)."""

    header: Header
    width: int
    height: int
    camera_pose: Pose  # the camera frame in the world at the stamp
    fx: float  # focal lengths and principal point, pixels
    fy: float
    cx: float
    cy: float
    color: Array  # uint8 (height, width, 3), RGB
    depth: Array | None = None  # uint16 (height, width), mm along the optical axis; 0: no depth
    camera_model: str = ""


class CompressedFrame(msgspec.Struct, kw_only=True):
    """A `CameraFrame` small enough for a radio link and a recording: JPEG colour, PNG depth."""

    header: Header
    width: int
    height: int
    camera_pose: Pose
    fx: float
    fy: float
    cx: float
    cy: float
    jpeg: bytes
    depth_png: bytes = b""  # 16-bit PNG of the depth image (mm), empty: none
    camera_model: str = ""


class ColorUpdate(msgspec.Struct, kw_only=True):
    """A colour file for Object Detect, sent live (`falconry colors pick --send`): its TOML text."""

    header: Header
    name: str = ""
    toml: str = ""


# What a LiDAR-inertial localizer says of its own estimate (services/localizer/graph.py): "tracking"
# while the scans' features hold the pose, "degraded" while too few do (the IMU carries it and it
# drifts), "lost" once its uncertainty is beyond use. "" where no localizer stands behind the pose.
PositioningHealth = Literal["", "tracking", "degraded", "lost"]


class Odometry(msgspec.Struct, kw_only=True):
    """Estimated state of one UAV. `covariance` is float64 6×6 over (x, y, z, roll, pitch, yaw).
    `health` is the localizer's when the pose comes from one (GNSS-denied flight), else ""."""

    header: Header
    pose: Pose
    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    covariance: Array | None = None
    health: PositioningHealth = ""


class ImuBatch(msgspec.Struct, kw_only=True):
    """One UAV's IMU samples over one clock tick (onboard, the flight controller's raw IMU), in the
    body frame: x forward, y left, z up (FLU), at the vehicle's centre. Sample j was taken at
    stamps[j]; the stamps lie on the grid k · (1 s / rate_hz) of mission time within [the previous
    batch's stamp, header.stamp), so consecutive batches tile the stream without gap or repeat (tick
    0's batch holds none). `accelerometer` is the specific force, acceleration minus gravity (at rest
    +9.81 m/s² along z, in free fall 0), `gyroscope` the angular rate; both carry the sensor's white
    noise and bias (services/lib/imu.py). Every batch is needed: subscribe without shedding."""

    header: Header  # stamp: the tick's end; frame: the UAV's body frame, named after the UAV ("uav1")
    stamps: Array  # int64 (N,) mission time of each sample, ns
    accelerometer: Array  # float64 (N, 3) specific force, m/s², body frame
    gyroscope: Array  # float64 (N, 3) angular rate, rad/s, body frame
    rate_hz: int  # samples per second of mission time


class Detections(msgspec.Struct, kw_only=True):
    """Flying objects found in one scan: N rows in every array."""

    header: Header
    detector: str  # "classifier" (LiDAR pipeline), "camera" (colour blobs) or "oracle" (evaluation only)
    positions: Array  # float64 (N, 3) cluster centres
    covariances: Array  # float64 (N, 3, 3)
    point_counts: Array  # int32 (N,)
    extents: Array  # float32 (N,) largest cluster dimension, m
    sensor_position: Vec3 = (0.0, 0.0, 0.0)
    # float32 (N,): probability that the centroid's voxel is the true one given the sensor's pose and
    # range uncertainty (seed 000 sec. IV-B); None from a detector that does not say
    confidences: Array | None = None
    # "" when the sensor's data passed its sanity check; else why not (the detector found nothing in it)
    sensor_health: str = ""


class LabelSet(msgspec.Struct, kw_only=True):
    """Classifier output for the mapper: the scan's valid returns with a label each,
    and the voxel label sets with weights. Labels: 0 background, 1 flying object, 2 unknown."""

    header: Header
    sensor_origin: Vec3
    points: Array  # float32 (N, 3) valid returns
    point_labels: Array  # uint8 (N,)
    voxel_size: float
    voxels: Array  # int32 (M, 3) voxel indices relative to map origin
    voxel_labels: Array  # uint8 (M,)
    voxel_weights: Array  # float32 (M,) update weight n of each voxel (eq. 16–18; inf for flying objects)
    map_stamp: int = 0  # stamp of the last map message the classification used: the map's lag behind the scan


class VoxelMap(msgspec.Struct, kw_only=True):
    """The occupancy map G(v): a snapshot lists every voxel whose value differs from
    `default_value`; a delta lists the voxels whose state (schemas/voxels.py, seed 000 eq. 7)
    changed since the previous message, with their value then. Between two state changes a
    voxel's value moves without a message: a replica knows every state exactly, values only as
    of their last state change."""

    header: Header
    snapshot: bool
    voxel_size: float
    origin: Vec3  # world position of voxel (0, 0, 0)'s minimum corner
    shape: tuple[int, int, int]
    indices: Array  # int32 or int64 (N,) flat indices, C order over `shape`
    values: Array  # float32 (N,) G values (±inf: pinned by the a-priori map, seed 000 sec. III-E)
    default_value: float = -740.0


class Track(msgspec.Struct, kw_only=True):
    """One track, predicted to its Tracks' stamp. Consumers read `position`, `velocity` and
    `trajectory`; `state` and `covariance` are the filter's own, in the layout `filter` names (the
    constant-acceleration layout position, velocity, acceleration for every filter so far)."""

    id: int
    state: Array  # float64 (9,) position, velocity, acceleration
    covariance: Array  # float64 (9, 9)
    detections: int
    confirmed: bool
    uncertainty_radius: float
    last_detection: int  # stamp, ns
    # Appended (with defaults, so older recordings still decode):
    filter: str = ""  # kf | adaptive | particle (services/tracker/filters)
    position: Vec3 | None = None
    velocity: Vec3 | None = None
    trajectory_dt: float = 0.0  # s between the predicted positions
    trajectory: Array | None = None  # float64 (K, 3): predicted positions at stamp + (i + 1)·trajectory_dt
    updates: int = 0  # corrections by clouds or detections
    mean_nis: float = 0.0  # mean normalised innovation squared; about 3 for a consistent filter
    last_innovation: float = 0.0  # m, the last correction's innovation length
    primary: bool = False  # the confirmed track with the most detections (seed 000 sec. III-F1)
    source: str = ""  # the UAV whose tracker keeps it ("" in older recordings)
    last_correction: int = 0  # stamp, ns, of its last correction by a scan or a detection (0: none known)
    half_width: float = 0.0  # m, the target's half-width across the line of sight as its keeper learnt it (0: not known)


class Tracks(msgspec.Struct, kw_only=True):
    header: Header
    tracks: list[Track] = []
    # "" while the sender's LiDAR passes its sanity checks; else why its detections are not trusted
    # now (failing, or settling after a failure): partners leave these tracks out of their picture
    sensor_health: str = ""


class ConstraintProfile(msgspec.Struct, kw_only=True):
    name: str = "sweeping"
    max_speed: float = 5.0  # m/s
    max_acceleration: float = 1.5  # m/s²
    max_heading_rate: float = 1.0  # rad/s
    max_vertical_speed: float = 2.0  # m/s


MissionAction = Literal[
    "idle", "takeoff", "scan", "goto", "attack", "hover", "land", "emergency_land",
    "stop", "approach", "intercept",
]


class MissionCommand(msgspec.Struct, kw_only=True):
    """What the job manager wants the planner to do next."""

    header: Header
    command_id: int
    action: MissionAction
    target: Vec3 | None = None
    target_velocity: Vec3 | None = None
    area: list[Point2] = []  # polygon to scan, counter-clockwise
    height: float = 5.0
    spacing: float = 10.0  # lawnmower line spacing, m
    profile: ConstraintProfile = msgspec.field(default_factory=ConstraintProfile)
    # A moving target's predicted path (its tracker's trajectory, re-based to this command's stamp):
    # positions at header.stamp + (i + 1)·target_path_dt; beyond it, straight on. `target` and
    # `target_velocity` hold at header.stamp. None: a straight line from target along target_velocity.
    target_path: Array | None = None  # float64 (K, 3)
    target_path_dt: float = 0.0  # s
    # Appended: when the target was last measured (a scan or detection), ns; 0: at header.stamp. A
    # prediction is only as good as the sighting it starts from (the planner's pursuit_trust).
    target_seen: int = 0


class TrajectoryReference(msgspec.Struct, kw_only=True):
    """Timed reference for the flight controller: sample i is valid at start + i·dt."""

    header: Header
    command_id: int
    start: int  # mission time of sample 0, ns
    dt: float  # s
    positions: Array  # float64 (N, 3)
    headings: Array  # float64 (N,), rad
    profile: ConstraintProfile = msgspec.field(default_factory=ConstraintProfile)


PlanOutcome = Literal["clear", "detour", "clipped", "blocked", "replanned", "braked"]


class PlanReport(msgspec.Struct, kw_only=True):
    """What the planner made of a command, or what its guard did to the reference in flight, against
    the obstacles its UAV knows (the a-priori map and what its mapper learnt).

    outcome: "clear" (the manoeuvre as asked, free), "detour" (free by another route, approach
    direction or height), "clipped" (flown only as far as free space allows: it ends short, at
    rest), "blocked" (no free way: the vehicle holds where it is), "replanned" (the guard found the
    active reference entering occupied or unseen space and a new plan avoids it), "braked" (the
    guard found it too close ahead to avoid: the vehicle brakes to a hold)."""

    header: Header
    command_id: int  # the command planned (-1: none, e.g. the watchdog's hover)
    action: str  # its MissionAction
    outcome: PlanOutcome
    note: str = ""  # one line for the operator: what was in the way, where
    clearance: float | None = None  # m from the body to the nearest known obstacle along the plan (None: none within reach)
    target: Vec3 | None = None  # the command's target, when it had one


class ForbiddenZoneStatus(msgspec.Struct, kw_only=True):
    """A forbidden zone of a job manager (seed 004 §3.5.2): detections inside are ignored until `expires`."""

    center: Vec3
    radius: float  # m
    expires: int  # mission time, ns
    reason: str = ""


class UavStatus(msgspec.Struct, kw_only=True):
    """Heartbeat each UAV's job manager sends to its partners."""

    header: Header
    uav: str
    state: str
    flying_normally: bool
    airborne: bool
    position: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)  # m/s, from the odometry, as `position`: partners predict separation with it
    working_area: list[Point2] = []
    target: Vec3 | None = None
    fallen_partners: list[str] = []  # partners this UAV's job manager counts as fallen (revenge mode)
    forbidden_zones: list[ForbiddenZoneStatus] = []  # this UAV's live forbidden zones
    state_reason: str = ""  # why the job manager entered `state` (e.g. "lost link: ...")
    # The next seconds of this UAV's reference (its planner's trajectory): float64 (K, 3) positions at
    # plan_start + i·plan_dt (ns, s), at rest after the last; partners check their own plans against it
    plan: Array | None = None
    plan_start: int = 0
    plan_dt: float = 0.0


class SimClock(msgspec.Struct, kw_only=True):
    """A mission clock tick. In lockstep mode `bounds` gives, for every key expression,
    the last sequence number published before this tick: a service processes exactly
    those messages, so the run is the same whatever the machine's load."""

    header: Header
    step: int
    dt: float
    lockstep: bool
    real_time_factor: float = 1.0
    bounds: dict[str, int] = {}
    finished: bool = False
    alive: list[str] = []  # "<scope>/<service>" whose liveliness the simulator saw, sorted


class StepAck(msgspec.Struct, kw_only=True):
    """Lockstep: a service has processed tick `step`; `published` is its last seq per key."""

    header: Header
    step: int
    published: dict[str, int] = {}


class Obstacle(msgspec.Struct, kw_only=True):
    """A static primitive: 'plane' (z = center.z), 'box' (center, size), 'cylinder'
    (vertical, base center, radius, height), 'sphere' (center, radius), 'cone' (base center,
    radius, height)."""

    kind: Literal["plane", "box", "cylinder", "sphere", "cone"]
    center: Vec3
    size: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.0
    height: float = 0.0
    name: str = ""
    color: Color | None = None  # what a camera sees of its surface; None: Appearance's default for its kind


class Appearance(msgspec.Struct, kw_only=True):
    """What a simulated camera sees of the world besides the shapes: the sky, the default colours
    of obstacles without one of their own, and the light (a sun and an ambient share)."""

    sky: Color = (150, 190, 235)
    ground: Color = (196, 178, 140)  # the plane: sand
    obstacle: Color = (128, 128, 128)
    sun_elevation: float = 50.0  # degrees above the horizon
    sun_azimuth: float = 135.0  # degrees counter-clockwise from +x
    ambient: float = 0.4  # share of the light that does not depend on the surface's orientation


DEFAULT_UAV_RADIUS = 0.4  # m: a UAV's body radius when the world model names none (WorldModel.uav_radius)


class WorldModel(msgspec.Struct, kw_only=True):
    """The static world and team, published by the simulator at start and every second."""

    header: Header
    scenario: str
    arena: list[Point2]
    min_height: float
    max_height: float
    obstacles: list[Obstacle] = []
    uavs: list[str] = []
    seed: int = 0
    duration: float = 0.0  # s of mission time
    sensors: dict[str, str] = {}  # UAV -> LiDAR model its sensor driver simulates
    appearance: Appearance = msgspec.field(default_factory=Appearance)
    positioning: dict[str, str] = {}  # UAV -> "lidar" when it flies without GNSS, on its localizer; else absent
    # UAV -> the radius of the sphere its body fits in, m: touching an obstacle or a partner with it is
    # a crash (the simulator), and the planner keeps it clear of what the UAV knows is occupied
    uav_radius: dict[str, float] = {}


class VehicleTruth(msgspec.Struct, kw_only=True):
    name: str
    position: Vec3
    velocity: Vec3
    heading: float
    airborne: bool
    alive: bool = True


class TargetTruth(msgspec.Struct, kw_only=True):
    id: str
    kind: Literal["balloon", "drone"]
    position: Vec3
    velocity: Vec3
    radius: float
    destroyed: bool = False
    color: Color = (200, 30, 30)  # what a camera sees of it (sRGB)


class GroundTruth(msgspec.Struct, kw_only=True):
    header: Header
    step: int
    uavs: list[VehicleTruth] = []
    targets: list[TargetTruth] = []
    # static obstacles the mission's survey lacks (WorldModel.obstacles holds the surveyed ones): the
    # simulated sensors see them, evaluation measures clearance to them; no service that flies reads them
    obstacles: list[Obstacle] = []


class SimEvent(msgspec.Struct, kw_only=True):
    """Something that happened: take-off, landing, target destroyed, fault injected, restart."""

    header: Header
    kind: str
    subject: str
    detail: str = ""


FaultKind = Literal[
    "lidar_silent", "lidar_nan", "lidar_garbage", "odometry_jump", "kill", "link_cut", "freeze",
    "duplicate", "reorder", "slow", "clock_jump", "router_restart", "camera_frozen", "camera_saturated",
]


class FaultCommand(msgspec.Struct, kw_only=True):
    """A scheduled fault the simulator injects at its mission time: the sensor driver acts on
    LiDAR faults, the simulator on odometry jumps, the launcher on process and link faults."""

    header: Header
    kind: FaultKind
    uav: str
    service: str = ""  # "kill", "freeze", "slow", "clock_jump": one service, or "" for all of the UAV's processes
    duration: float = 0.0  # s of mission time; 0 = until the end of the run
    offset: Vec3 = (0.0, 0.0, 0.0)  # for "odometry_jump", m
    topic: str = ""  # "duplicate" / "reorder": the UAV's topic (e.g. "detections") whose deliveries are disturbed
    delay: float = 0.0  # "slow": s of extra handling time per message received
    jump: float = 0.0  # "clock_jump": s the system clock steps (negative: back)


class Decision(msgspec.Struct, kw_only=True):
    """A state a service's state machine entered, when (mission time, ns) and why."""

    stamp: int
    state: str
    reason: str = ""


class ServiceHealth(msgspec.Struct, kw_only=True):
    """Answer to a health query on falconry/<uav>/health/<service>."""

    header: Header
    uav: str
    service: str
    pid: int
    uptime: float  # s of wall time
    state: str
    received: dict[str, int] = {}
    published: dict[str, int] = {}
    decode_errors: dict[str, int] = {}
    handler_errors: int = 0
    lockstep_timeouts: int = 0
    subscriptions: list[str] = []
    cpu_time: float = 0.0  # s of CPU the whole process used so far (every thread)
    memory: int = 0  # resident set size, bytes (0 where the platform does not say)
    # a state machine's whole history (the job manager's): what the ground reads after a link cut
    decisions: list[Decision] = []
    # real-time delivery: messages dropped as duplicates or overtaken by a newer one on their key, and
    # messages shed unread because newer ones on their key were queued behind them (a slow consumer)
    dropped_stale: dict[str, int] = {}
    dropped_backlog: dict[str, int] = {}


ALL_MESSAGES: tuple[type[msgspec.Struct], ...] = (
    PointCloud,
    Odometry,
    Detections,
    LabelSet,
    VoxelMap,
    Tracks,
    MissionCommand,
    TrajectoryReference,
    PlanReport,
    UavStatus,
    SimClock,
    StepAck,
    WorldModel,
    GroundTruth,
    SimEvent,
    ServiceHealth,
    PointTruth,
    FaultCommand,
    CameraFrame,
    CompressedFrame,
    ColorUpdate,
    ImuBatch,
)
