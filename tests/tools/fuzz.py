"""Fuzzing what services receive: hypothesis strategies for every message type, and a harness that
wires a real node on a stand-in for its Zenoh session and hands it samples through the very
subscriber callbacks the node declared (so decode, counting and the handler are the real ones).

Payload families, for one message type:
- `valid`: the documented contract (array dtypes and shapes, shared row counts), values anywhere
  from realistic to NaN, ±inf, extreme and empty;
- `odd`: anything the schema accepts: arrays of any allowed dtype and shape, any int, any text;
- `mutated`: a valid message encoded like the nodes do, then bytes flipped, inserted, deleted or
  cut, or one field given a wrong type or an impossible value;
- `random`: random bytes, or a random msgpack value.
"""
from __future__ import annotations

import collections
import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

import msgspec
import msgspec.inspect as mi
import numpy as np
import pytest
import zenoh
from hypothesis import strategies as st

from schemas import keys
from schemas.arrays import ALLOWED_DTYPES, Array, from_numpy, to_numpy
from schemas.messages import (
    Appearance,
    CameraFrame,
    ColorUpdate,
    Detections,
    FaultCommand,
    GroundTruth,
    Header,
    ImuBatch,
    LabelSet,
    MissionCommand,
    Obstacle,
    Odometry,
    PlanReport,
    PointCloud,
    PointTruth,
    SimClock,
    StepAck,
    TargetTruth,
    Track,
    Tracks,
    TrajectoryReference,
    UavStatus,
    VehicleTruth,
    VoxelMap,
    WorldModel,
)
from services.lib.runtime.node import Node
from services.lib.runtime.typed import _numpy_scalars
from services.lib.runtime.zenoh_config import ZenohSettings
from services.tools.registry import node_class
from tests.tools.samples import concrete

M = TypeVar("M", bound=msgspec.Struct)
REPO = Path(__file__).resolve().parents[2]
FAMILIES = ("valid", "odd", "mutated", "random")
UAV = "uav1"
PARTNER = "uav2"  # whose key a wildcard subscription is given (tests/tools/samples.py, concrete)


@dataclass
class FuzzRun:
    services: list[str]
    cases: collections.Counter = field(default_factory=collections.Counter)  # family -> cases run


# What tests/conftest.py prints at the end of the session: message type -> its run.
CASES_RUN = pytest.StashKey[dict[str, FuzzRun]]()

# What the nodes put on the wire (services/lib/runtime/typed.py, TypedPublisher).
encode = msgspec.msgpack.Encoder(enc_hook=_numpy_scalars).encode


# ------------------------------------------------------------------ harness
class _Publisher:
    def __init__(self, session: FakeSession, key: str) -> None:
        self._session, self._key = session, key

    def put(self, payload: bytes) -> None:
        self._session.published[self._key] = payload

    def undeclare(self) -> None:
        pass


class _Handle:
    def undeclare(self) -> None:
        pass


class _Liveliness:
    def __init__(self, session: FakeSession) -> None:
        self._session = session

    def declare_subscriber(self, key_expr, callback, history=False) -> _Handle:
        self._session.token_callbacks.append((zenoh.KeyExpr(key_expr), callback))
        return _Handle()

    def declare_token(self, key_expr) -> _Handle:
        return _Handle()


class FakeSession:
    """What a Node declares on its session, kept: the subscriber callbacks are Zenoh's entry points."""

    def __init__(self) -> None:
        self.callbacks: list[tuple[zenoh.KeyExpr, Callable]] = []
        self.token_callbacks: list[tuple[zenoh.KeyExpr, Callable]] = []
        self.published: dict[str, bytes] = {}  # key -> the last payload put on it

    def declare_subscriber(self, key_expr: str, callback: Callable) -> _Handle:
        self.callbacks.append((zenoh.KeyExpr(key_expr), callback))
        return _Handle()

    def declare_publisher(self, key_expr: str, **kwargs) -> _Publisher:
        return _Publisher(self, key_expr)

    def declare_queryable(self, key_expr: str, callback: Callable) -> _Handle:
        return _Handle()

    def liveliness(self) -> _Liveliness:
        return _Liveliness(self)


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class FakeSample:
    key_expr: str
    payload: _Payload | None = None
    kind: Any = None  # of a liveliness sample: zenoh.SampleKind


class _LastErrors(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: collections.deque[str] = collections.deque(maxlen=3)

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record.getMessage())


@dataclass
class WiredNode:
    """A node declared on a FakeSession, following a real-time clock (as with `falconry sim`)."""

    node: Node
    session: FakeSession
    errors: _LastErrors
    step: int = 0
    stamp: int = 0
    keys_of: dict[type, str] = field(default_factory=dict)  # message type -> the concrete key it comes on

    def deliver(self, key: str, payload: bytes) -> None:
        """The sample as Zenoh would hand it to every matching subscriber; then the node's loop runs."""
        ke = zenoh.KeyExpr(key)
        for key_expr, callback in self.session.callbacks:
            if key_expr.intersects(ke):
                callback(FakeSample(key, _Payload(payload)))
        while self.node.pump(0.0):
            pass

    def subscriptions(self, key: str) -> int:
        """How many of the node's subscriptions a sample on `key` reaches (each decodes and counts it)."""
        return sum(key_expr.intersects(zenoh.KeyExpr(key)) for key_expr, _ in self.session.callbacks)

    def token(self, key: str, alive: bool) -> None:
        """A liveliness token appearing or vanishing, as Zenoh would tell the node."""
        sample = FakeSample(key, kind=zenoh.SampleKind.PUT if alive else zenoh.SampleKind.DELETE)
        for key_expr, callback in self.session.token_callbacks:
            if key_expr.intersects(zenoh.KeyExpr(key)):
                callback(sample)
        while self.node.pump(0.0):
            pass

    def published(self, msg_type: type[M], key: str) -> M:
        """The last message the node put on `key`."""
        return msgspec.msgpack.decode(self.session.published[key], type=msg_type)

    def subscribed(self) -> set[type]:
        """The message types the service itself subscribes to (the runtime's plumbing aside)."""
        return {sub.decoder.type for sub in self.node._subs if not sub.internal}

    def tick(self, dt_ns: int = 10_000_000) -> None:
        """The next real-time clock tick: on_tick sees what the handlers stored."""
        if self.node._clock_kind == "master":  # the simulator: what its serve() loop does with the references
            self.node.sim.step(dt_ns / 1e9)
            return
        self.step += 1
        self.stamp += dt_ns
        self.deliver(keys.CLOCK, encode(SimClock(header=Header(sender="sim/simulator", seq=self.step,
                                                                 stamp=self.stamp),
                                                   step=self.step, dt=dt_ns / 1e9, lockstep=False)))


def wire(service: str, *, first_tick: bool = True, **options) -> WiredNode:
    """The service's node on a fake session; `options` override the run's (e.g. positioning="lidar").
    Without `first_tick` a follower of the clock is left before its first tick, holding what it is
    given until a tick says real time or lockstep."""
    cls = node_class(service)
    options = SimpleNamespace(**{**dict(scenario="mbzirc", uavs=2, seed=1, duration=60.0, lockstep=False, rtf=1.0,
                                        tick=0.05, detector="classifier"), **options})
    node = cls(None if service in keys.SIM_SERVICES else UAV, ZenohSettings(), options=options)
    errors = _LastErrors()
    logger = logging.Logger(node.sender, logging.ERROR)  # its own: the process's loggers stay as they were
    logger.addHandler(errors)
    node.log = type(node.log)(logger, node)
    session = FakeSession()
    node.session = session
    node.declare()
    wired = WiredNode(node, session, errors)
    for sub in node._subs:
        wired.keys_of.setdefault(sub.decoder.type, concrete(sub.key_expr))
    if node._clock_kind == "sim":
        if first_tick:
            wired.tick()  # the first tick says: real time
    else:
        node._lockstep = False  # the simulator's own serve() does this (run without --lockstep)
    return wired


def subscribers() -> dict[type, list[str]]:
    """Every message type some node subscribes to -> the services to fuzz it in, from the wired nodes.
    A runtime handler every node shares (upstream acks, faults) is fuzzed in the first of them; the
    clock's in every one, since its handler ends in each service's own on_tick."""
    found: dict[type, dict[Any, str]] = collections.defaultdict(dict)
    for service in keys.SERVICES:
        for sub in wire(service).node._subs:
            handler = getattr(sub.handler, "__func__", sub.handler)
            shared = handler is not Node._on_clock and handler.__qualname__.startswith(f"{Node.__name__}.")
            found[sub.decoder.type].setdefault(handler if shared else (handler, service), service)
    return {msg_type: sorted(set(services.values())) for msg_type, services in found.items()}


@functools.cache
def corpus() -> dict[type, msgspec.Struct]:
    """One realistic message of every subscribed type, most of them made by the services themselves
    from the mbzirc scenario's first tick (LiDAR model os0-32-512 to keep scans small): mutation
    seeds, and what a node is given of its other inputs before one of them is fuzzed."""
    sim = wire("simulator")
    sim.node.publish_state(0, 0)
    world = sim.published(WorldModel, keys.WORLD)
    world.sensors = {u: "os0-32-512" for u in world.uavs}
    truth = sim.published(GroundTruth, keys.TRUTH)
    odometry = sim.published(Odometry, keys.uav(UAV, "odometry"))
    made: dict[type, msgspec.Struct] = {WorldModel: world, GroundTruth: truth, Odometry: odometry}
    sim.node.sim.step(0.05)  # a tick's IMU samples (the first batch holds none)
    sim.node.publish_state(1, 50_000_000)
    made[ImuBatch] = sim.published(ImuBatch, keys.uav(UAV, keys.IMU))
    made[SimClock] = SimClock(header=Header(sender="sim/simulator", seq=2, stamp=50_000_000), step=1, dt=0.05,
                              lockstep=True, bounds={keys.uav(UAV, "points"): 1}, alive=[f"{UAV}/sensor_driver"])
    made[StepAck] = StepAck(header=Header(sender=f"{UAV}/sensor_driver", seq=1, stamp=50_000_000), step=1,
                            published={keys.uav(UAV, "points"): 1, keys.uav(UAV, "points_truth"): 1})
    made[FaultCommand] = FaultCommand(header=Header(sender="sim/simulator", seq=1, stamp=50_000_000),
                                      kind="lidar_nan", uav=UAV, duration=0.5)
    made[MissionCommand] = MissionCommand(header=Header(sender=f"{UAV}/job_manager", seq=1, stamp=10_000_000),
                                          command_id=1, action="scan", area=world.arena, height=5.0)
    targets = np.array([t.position for t in truth.targets[:2]])
    n = len(targets)
    made[Detections] = Detections(  # what the classifier sees once the targets are in range
        header=Header(sender=f"{UAV}/classifier", seq=1, stamp=10_000_000), detector="classifier",
        positions=from_numpy(targets), covariances=from_numpy(np.tile(0.05 * np.eye(3), (n, 1, 1))),
        point_counts=from_numpy(np.full(n, 12, dtype=np.int32)), extents=from_numpy(np.ones(n, dtype=np.float32)),
        sensor_position=odometry.pose.position, confidences=from_numpy(np.full(n, 0.9, dtype=np.float32)))
    pipeline = [  # service, what it is given (twice: a tracker confirms a track), what it puts out
        ("sensor_driver", [WorldModel, GroundTruth], [(PointCloud, "points"), (PointTruth, "points_truth")]),
        ("classifier", [PointCloud], [(LabelSet, "labels")]),
        ("mapper", [PointCloud, LabelSet], [(VoxelMap, "map")]),
        ("tracker", [Detections], [(Tracks, "tracks")]),
        ("job_manager", [WorldModel, Odometry, Detections, Tracks], [(UavStatus, "status")]),
        ("planner", [WorldModel, VoxelMap, MissionCommand, Odometry],
         [(TrajectoryReference, "trajectory"), (PlanReport, "plan")]),
    ]
    for service, inputs, outputs in pipeline:
        wired = wire(service)
        for _ in range(2):
            for msg_type in inputs:
                wired.deliver(wired.keys_of[msg_type], encode(made[msg_type]))
            wired.tick(100_000_000)
        for msg_type, topic in outputs:
            made[msg_type] = wired.published(msg_type, keys.uav(UAV, topic))
    made[UavStatus].uav = PARTNER  # a job manager reads its partners' status, not its own
    camera = wire("camera")
    for msg_type in (WorldModel, GroundTruth):
        camera.deliver(camera.keys_of[msg_type], encode(made[msg_type]))
    camera.tick(100_000_000)
    made[CameraFrame] = crop(camera.published(CameraFrame, keys.uav(UAV, "camera")), 24, 40)
    made[ColorUpdate] = ColorUpdate(header=Header(sender="ground/colors", seq=1), name="red",
                                    toml=(REPO / "services/object_detect/colors/red.toml").read_text())
    return made


def crop(frame: CameraFrame, height: int, width: int) -> CameraFrame:
    """The middle of a camera frame, intrinsics kept (Object Detect sees a smaller image)."""
    rows, cols = frame.height // 2 - height // 2, frame.width // 2 - width // 2
    color = to_numpy(frame.color)[rows:rows + height, cols:cols + width]
    depth = None if frame.depth is None else to_numpy(frame.depth)[rows:rows + height, cols:cols + width]
    return msgspec.structs.replace(frame, height=height, width=width, color=from_numpy(color),
                                   depth=None if depth is None else from_numpy(depth))


def sparse(cloud: PointCloud, every_row: int, every_column: int) -> PointCloud:
    """Every n-th row and column of an organised scan (no body mask: it is per column)."""
    points = to_numpy(cloud.points)[::every_row, ::every_column]
    return msgspec.structs.replace(cloud, points=from_numpy(points), height=points.shape[0], width=points.shape[1],
                                   intensity=None, mask=None)


# --------------------------------------------------------------- strategies
def stamps() -> st.SearchStrategy[int]:
    return st.one_of(st.integers(0, 10**11), st.integers(0, 2**63 - 1))


def floats(width: int = 64) -> st.SearchStrategy[float]:
    """Realistic metres and seconds, or anything: NaN, ±inf, ±1e308, subnormals, -0.0."""
    return st.one_of(st.floats(-200.0, 200.0, width=width), st.floats(width=width))


@dataclass(frozen=True)
class Leaves:
    integers: st.SearchStrategy
    floats: st.SearchStrategy
    text: st.SearchStrategy
    array: Callable[[], st.SearchStrategy]  # an Array no field override describes
    overrides: dict[tuple[type, str], st.SearchStrategy] = field(default_factory=dict)
    max_items: int = 4


def from_schema(info: Any, leaves: Leaves, owner: tuple[type, str] | None = None) -> st.SearchStrategy:
    """A strategy for any msgspec type, following its annotations (a new field is fuzzed without a
    line here); `leaves.overrides[(Struct, field)]` replaces the strategy of one field."""
    if isinstance(info, type):
        info = mi.type_info(info)
    if owner is not None and owner in leaves.overrides:
        return leaves.overrides[owner]
    if isinstance(info, mi.StructType):
        if info.cls is Array:
            return leaves.array()
        return st.builds(info.cls, **{f.name: from_schema(f.type, leaves, (info.cls, f.name)) for f in info.fields})
    if isinstance(info, mi.IntType):
        return leaves.integers
    if isinstance(info, mi.FloatType):
        return leaves.floats
    if isinstance(info, mi.StrType):
        return leaves.text
    if isinstance(info, mi.BoolType):
        return st.booleans()
    if isinstance(info, mi.NoneType):
        return st.none()
    if isinstance(info, mi.ListType):
        return st.lists(from_schema(info.item_type, leaves), max_size=leaves.max_items)
    if isinstance(info, mi.TupleType):
        return st.tuples(*(from_schema(t, leaves) for t in info.item_types))
    if isinstance(info, mi.DictType):
        return st.dictionaries(from_schema(info.key_type, leaves), from_schema(info.value_type, leaves),
                               max_size=leaves.max_items)
    if isinstance(info, mi.UnionType):
        return st.one_of(*(from_schema(t, leaves) for t in info.types))
    if isinstance(info, mi.LiteralType):
        return st.sampled_from(info.values)
    if isinstance(info, mi.MemoryViewType):
        return st.binary(max_size=16).map(memoryview)
    raise TypeError(f"no strategy for {info}")


# -- arrays
def _specials(dtype: np.dtype, low: float, high: float, anything: bool) -> list:
    if dtype.kind == "f":
        info = np.finfo(dtype)
        return [math.nan, math.inf, -math.inf, 0.0, -0.0, float(info.max), float(-info.max), float(info.tiny),
                float(info.smallest_subnormal), low, high]
    if anything:
        info = np.iinfo(dtype)
        return [info.min, info.max, 0, -1 if info.min < 0 else 1, low, high]
    return [low, high]


@st.composite
def arrays(draw, dtype: str, shape: st.SearchStrategy[tuple[int, ...]], low: float = -60.0, high: float = 60.0,
           anything: bool = True) -> Array:
    """An array of a documented dtype and shape: values from `low` to `high` (256 steps), or with
    `anything` any bit pattern of the dtype (every float: NaN, ±inf, extremes, subnormals), and then a
    few elements set to the dtype's or the range's special values. The bulk is one `binary` draw: as
    cheap to make, mutate and shrink as one scalar."""
    dt = np.dtype(dtype)
    shape = draw(shape)
    n = math.prod(shape)
    if anything and draw(st.booleans()):
        values = np.frombuffer(draw(st.binary(min_size=n * dt.itemsize, max_size=n * dt.itemsize)), dt).copy()
    else:
        steps = np.frombuffer(draw(st.binary(min_size=n, max_size=n)), np.uint8).astype(np.float64)
        values = low + (high - low) * steps / 255.0
        values = (values if dt.kind == "f" else np.round(values)).astype(dt)
    specials = _specials(dt, low, high, anything)
    for _ in range(draw(st.integers(0, 3)) if n else 0):
        values[draw(st.integers(0, n - 1))] = draw(st.sampled_from(specials))
    return from_numpy(values.reshape(shape))


# Shapes an array of the wrong shape may have (one draw): scalar, empty, short, too many dimensions,
# and empty with a huge dimension (no data: the schema accepts it).
ODD_SHAPES = [[], [0], [1], [5], [0, 3], [1, 3], [4, 3], [2, 2], [3, 3, 3], [1, 1, 1, 1], [0, 2**40], [2**40, 0, 3]]


@st.composite
def any_array(draw) -> Array:
    """Any array the schema accepts: an allowed dtype, a shape of ODD_SHAPES, raw bytes as values."""
    dtype = draw(st.sampled_from(sorted(ALLOWED_DTYPES)))
    shape = draw(st.sampled_from(ODD_SHAPES))
    size = math.prod(shape) * np.dtype(dtype).itemsize
    return Array(dtype=dtype, shape=shape, data=memoryview(draw(st.binary(min_size=size, max_size=size))))


def rows(name: str, most: int) -> st.SearchStrategy[int]:
    """A row count several arrays of one message share (st.shared: the same within one case)."""
    return st.shared(st.integers(0, most), key=name)


def _shape(*dims: st.SearchStrategy[int] | int) -> st.SearchStrategy[tuple[int, ...]]:
    return st.tuples(*(d if isinstance(d, st.SearchStrategy) else st.just(d) for d in dims))


# -- names
# Text within the contract (one draw: a `text` strategy costs as much as a whole array): what services
# send, empty, and odd characters; the odd family has any text.
TEXT = st.sampled_from(["", "world", "uav1/sensor_driver", "sim/simulator", "a" * 300, " ", "\x00", "ü/*?#$"])
SERVICE_NAMES = st.sampled_from(keys.SERVICES)
UAV_NAMES = st.sampled_from([UAV, PARTNER, "uav3", keys.SIM, "", "ü/*?#$"])
LIDAR_NAMES = st.sampled_from(["os0-32-512", "mid360", "os1-32-512", "no-such-lidar", "", "ü/*?#$"])


def _contract_overrides() -> dict[tuple[type, str], st.SearchStrategy]:
    cloud_h, cloud_w = rows("cloud.h", 4), rows("cloud.w", 16)
    truth_h, truth_w = rows("truth.h", 4), rows("truth.w", 16)
    n, m = rows("n", 8), rows("m", 8)
    cov6 = arrays("<f8", _shape(6, 6))
    image_h, image_w = rows("image.h", 12), rows("image.w", 16)
    color = st.tuples(*[st.integers(0, 255)] * 3)
    return {
        (CameraFrame, "height"): image_h,
        (CameraFrame, "width"): image_w,
        (CameraFrame, "color"): arrays("|u1", _shape(image_h, image_w, 3), 0, 255),
        (CameraFrame, "depth"): st.none() | arrays("<u2", _shape(image_h, image_w), 0, 65535),
        (ColorUpdate, "toml"): st.sampled_from(["", "diameter = 0.6", "[thresholds", "x = 1\n",
                                                (REPO / "services/object_detect/colors/green.toml").read_text()]),
        (Obstacle, "color"): st.none() | color,
        (TargetTruth, "color"): color,
        (Appearance, "sky"): color,
        (Appearance, "ground"): color,
        (Appearance, "obstacle"): color,
        (Header, "stamp"): stamps(),
        (PointCloud, "height"): cloud_h,
        (PointCloud, "width"): cloud_w,
        (PointCloud, "points"): arrays("<f4", _shape(cloud_h, cloud_w, 3)),
        (PointCloud, "intensity"): st.none() | arrays("<f4", _shape(cloud_h, cloud_w)),
        (PointCloud, "mask"): st.none() | arrays("|u1", _shape(cloud_h, cloud_w.map(lambda w: -(-w // 8))), 0, 255),
        (PointCloud, "pose_covariance"): st.none() | cov6,
        (PointCloud, "sensor_model"): LIDAR_NAMES,
        (PointTruth, "height"): truth_h,
        (PointTruth, "width"): truth_w,
        (PointTruth, "hits"): arrays("<i4", _shape(truth_h, truth_w), -1, 4, anything=False),
        (Odometry, "covariance"): st.none() | cov6,
        (Detections, "positions"): arrays("<f8", _shape(n, 3)),
        (Detections, "covariances"): arrays("<f8", _shape(n, 3, 3)),
        (Detections, "point_counts"): arrays("<i4", _shape(n), 0, 1000),
        (Detections, "extents"): arrays("<f4", _shape(n)),
        (Detections, "confidences"): st.none() | arrays("<f4", _shape(n)),
        (LabelSet, "points"): arrays("<f4", _shape(n, 3)),
        (LabelSet, "point_labels"): arrays("|u1", _shape(n), 0, 2, anything=False),
        (LabelSet, "voxels"): arrays("<i4", _shape(m, 3), -5, 300),
        (LabelSet, "voxel_labels"): arrays("|u1", _shape(m), 0, 2, anything=False),
        (LabelSet, "voxel_weights"): arrays("<f4", _shape(m)),
        # a small grid, or one too large to hold (MapReplica.MAX_VOXELS, which the test lowers)
        (VoxelMap, "shape"): st.tuples(*[st.integers(0, 40)] * 3) | st.tuples(*[st.integers(2**10, 2**31)] * 3),
        (VoxelMap, "indices"): st.sampled_from(["<i4", "<i8"]).flatmap(
            lambda dtype: arrays(dtype, _shape(n), 0, 64_000)),
        (VoxelMap, "values"): arrays("<f4", _shape(n)),
        (Track, "state"): arrays("<f8", _shape(9)),
        (Track, "covariance"): arrays("<f8", _shape(9, 9)),
        (TrajectoryReference, "positions"): arrays("<f8", _shape(n, 3)),
        (TrajectoryReference, "headings"): arrays("<f8", _shape(n)),
        (UavStatus, "uav"): UAV_NAMES,
        (FaultCommand, "uav"): UAV_NAMES,
        (FaultCommand, "service"): st.just("") | SERVICE_NAMES,
        (VehicleTruth, "name"): UAV_NAMES,
        (WorldModel, "uavs"): st.lists(UAV_NAMES, max_size=3),
        (WorldModel, "sensors"): st.dictionaries(UAV_NAMES, LIDAR_NAMES, max_size=3),
        (SimClock, "bounds"): st.dictionaries(st.sampled_from(_CLOCK_BOUND_KEYS), st.integers(0, 2**63 - 1),
                                              max_size=4),
        (SimClock, "alive"): st.lists(st.builds("{}/{}".format, st.sampled_from([UAV, PARTNER, keys.SIM]),
                                                SERVICE_NAMES), max_size=4),
        (StepAck, "published"): st.dictionaries(st.sampled_from(_CLOCK_BOUND_KEYS), st.integers(0, 2**63 - 1),
                                                max_size=4),
    }


# keys a clock tick or an ack may bound: those the nodes subscribe to, and one nobody does
_CLOCK_BOUND_KEYS = sorted({keys.uav(UAV, t) for t in ("points", "points_truth", "labels", "map", "detections",
                                                       "tracks", "command", "odometry", "trajectory", "camera",
                                                       "camera_detections", "colors")}
                           | {keys.WORLD, keys.TRUTH, keys.FAULTS, keys.uav(PARTNER, "status"), "falconry/x/y"})

VALID = Leaves(integers=st.integers(0, 2**63 - 1), floats=floats(), text=TEXT,
               array=any_array, overrides=_contract_overrides())
ODD = Leaves(integers=st.integers(-2**63, 2**64 - 1), floats=st.floats(), text=st.text(max_size=12),
             array=any_array)


# -- mutations
_WRONG = st.sampled_from([None, "x", -1, 2**64 - 1, -2**63, 1.5, math.nan, [], {}, b"\x00", True,
                          [-1, 3], ["a"], {"dtype": "<f8"}, ">f8", "object", "<f2", [2**40, 2**40]])


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, (*prefix, i))
    return out


def _replace(value: Any, path: tuple, new: Any, delete: bool = False) -> Any:
    if not path:
        return new
    head, rest = path[0], path[1:]
    if isinstance(value, dict):
        value = dict(value)
        if delete and not rest:
            del value[head]
        else:
            value[head] = _replace(value[head], rest, new, delete)
    else:
        value = list(value)
        if delete and not rest:
            del value[head]
        else:
            value[head] = _replace(value[head], rest, new, delete)
    return value


@st.composite
def field_mutation(draw, msg: msgspec.Struct) -> bytes:
    """One field (at any depth) replaced by a wrong type or an impossible value, deleted, or an
    unknown field added; arrays' dtype, shape and data are fields too."""
    tree = msgspec.to_builtins(msg, builtin_types=(bytes, bytearray, memoryview), enc_hook=_numpy_scalars)
    path = draw(st.sampled_from(_paths(tree)))
    how = draw(st.sampled_from(["replace", "delete", "add"]))
    if how == "delete" and path:
        tree = _replace(tree, path, None, delete=True)
    elif how == "add" and isinstance(tree, dict):
        tree = dict(tree, unknown_field=draw(_WRONG))
    else:
        tree = _replace(tree, path, draw(_WRONG))
    return msgspec.msgpack.encode(tree)


@st.composite
def byte_mutation(draw, payload: bytes) -> bytes:
    """Bytes flipped, overwritten, inserted, deleted, or the payload cut short."""
    data = bytearray(payload)
    for _ in range(draw(st.integers(1, 4))):
        where = draw(st.integers(0, max(len(data) - 1, 0)))
        how = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        if how == "flip" and data:
            data[where] ^= 1 << draw(st.integers(0, 7))
        elif how == "set" and data:
            data[where] = draw(st.integers(0, 255))
        elif how == "insert":
            data[where:where] = draw(st.binary(min_size=1, max_size=8))
        elif how == "delete":
            del data[where:where + draw(st.integers(1, 8))]
        elif how == "truncate":
            del data[where:]
    return bytes(data)


_MSGPACK_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@dataclass(frozen=True)
class Case:
    family: str
    payload: bytes

    def __repr__(self) -> str:  # what hypothesis prints for a failing example
        return f"Case({self.family!r}, {self.payload!r})"


def cases(msg_type: type[msgspec.Struct]) -> st.SearchStrategy[Case]:
    """Payloads of all four families for one message type; mutations start from the corpus' message."""
    seed = corpus()[msg_type]
    mutated = st.one_of(byte_mutation(encode(seed)), field_mutation(seed))
    valid = from_schema(msg_type, VALID)
    random = st.one_of(st.binary(max_size=64), _MSGPACK_VALUES.map(msgspec.msgpack.encode))
    return st.one_of(
        valid.map(lambda msg: Case("valid", encode(msg))),
        from_schema(msg_type, ODD).map(lambda msg: Case("odd", encode(msg))),
        mutated.map(lambda payload: Case("mutated", payload)),
        random.map(lambda payload: Case("random", payload)),
    )
