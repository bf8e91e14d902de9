"""What Falconry's typed messages cost over Zenoh, between two real processes.

Two spawned processes (never forked) open Zenoh sessions with the project's embedded
profile: the echo listens on tcp/127.0.0.1:<free port>, the pinger connects; this process
only orchestrates and opens no session. Each figure is a ping-pong round trip halved; both
directions do the same work, and both sides receive the way `Node` does: the Zenoh callback
calls payload.to_bytes() and queues it, the loop thread decodes.

  bare    bytes in, payload.to_bytes() out: Zenoh alone.
  typed   the project's path: TypedPublisher.put (header fill + msgspec msgpack encode +
          put); on receive to_bytes, Decoder(T).decode and schemas.arrays.to_numpy.
  typed+into (diagnostic) TypedPublisher with msgspec Encoder.encode_into one reused
          bytearray instead of a fresh bytes object per message.

Every case runs twice: over the profile as is (Zenoh moves payloads above 3 KB through its
shared-memory pool when both ends are on one host) and with shared memory off (all bytes
over TCP, as between containers or UAVs).

Goal: the typed path of a 1.5 MB cloud costs at most 10 % more than bare Zenoh.
Usage: .venv/bin/python benchmarks/transport.py [--quick]
"""
from __future__ import annotations

import argparse
import importlib.metadata
import multiprocessing
import os
import queue
import re
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too

import msgspec  # noqa: E402
import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from schemas.arrays import from_numpy, to_numpy  # noqa: E402
from schemas.messages import Header, PointCloud, Pose, SimEvent  # noqa: E402
from services.lib.runtime import shm as shm_segments  # noqa: E402
from services.lib.runtime.node import TypedPublisher  # noqa: E402
from services.lib.runtime.zenoh_config import ZenohSettings, free_port, init_logging, open_session  # noqa: E402

ROOT = "bench"
REPLY_TIMEOUT_S = 2.0
GOAL_OVERHEAD = 0.10
SHM_PATH = re.compile(r"(/dev/shm/\S*zenoh\S*)")
LINKS = {
    "shm": "embedded profile as is: Zenoh moves payloads > 3 KB through shared memory on one host",
    "tcp": "shared memory off: every byte crosses TCP, as between containers or UAVs",
}


@dataclass(frozen=True)
class Case:
    name: str  # key segment and table label
    size: str  # "small" or "cloud"
    typed: bool
    reuse_buffer: bool = False


CASES = (
    Case("small-bare", "small", typed=False),
    Case("small-typed", "small", typed=True),
    Case("cloud-bare", "cloud", typed=False),
    Case("cloud-typed", "cloud", typed=True),
    Case("cloud-typed+into", "cloud", typed=True, reuse_buffer=True),
)
MSG_TYPES = {"small": SimEvent, "cloud": PointCloud}


@dataclass(frozen=True)
class Plan:
    """Samples are taken in interleaved blocks so machine noise hits every case alike."""

    warmup: int
    rounds: int
    block: int


FULL = {"small": Plan(warmup=200, rounds=10, block=200), "cloud": Plan(warmup=20, rounds=10, block=20)}
QUICK = {"small": Plan(warmup=50, rounds=3, block=100), "cloud": Plan(warmup=5, rounds=3, block=10)}


def small_message() -> SimEvent:
    return SimEvent(header=Header(stamp=1), kind="target_destroyed", subject="balloon3")


def cloud_message() -> PointCloud:
    """One organised 128×1024 scan, a third of the rays without return (NaN)."""
    rng = np.random.default_rng(7)
    points = rng.uniform(-50.0, 50.0, size=(128, 1024, 3)).astype(np.float32)
    points[rng.random((128, 1024)) < 0.3] = np.nan
    return PointCloud(header=Header(stamp=1), width=1024, height=128, sensor_pose=Pose(),
                      points=from_numpy(points), sensor_model="os1-128", max_range=100.0)


MESSAGES = {"small": small_message, "cloud": cloud_message}


def publisher_host(session: zenoh.Session, sender: str) -> SimpleNamespace:
    """The few Node attributes TypedPublisher reads, so the benchmark runs the real publish code."""
    return SimpleNamespace(session=session, sender=sender, clock=SimpleNamespace(now_ns=lambda: 1),
                           counters=SimpleNamespace(published={}))


class ReusedBufferEncoder:
    """Swapped in for a TypedPublisher's encoder (diagnostic): msgspec encodes into one
    bytearray kept for every message. Safe: zenoh-python copies the payload before put returns."""

    def __init__(self) -> None:
        self._encoder = msgspec.msgpack.Encoder()
        self._buffer = bytearray()

    def encode(self, msg: Any) -> bytearray:
        self._encoder.encode_into(msg, self._buffer)
        return self._buffer


def _typed_receiver(msg_type: type) -> Callable[[bytes], Any]:
    decoder = msgspec.msgpack.Decoder(msg_type)

    def receive(payload: bytes) -> Any:
        msg = decoder.decode(payload)
        if msg_type is PointCloud:
            to_numpy(msg.points)
        return msg

    return receive


class Endpoint:
    """One side of every case: a publisher on bench/<case>/<out>, a wildcard subscriber on
    bench/*/<in> whose callback does exactly what Node's does (to_bytes, queue)."""

    def __init__(self, session: zenoh.Session, out: str, into: str) -> None:
        host = publisher_host(session, f"bench/{out}")
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.send: dict[str, Callable[[Any], None]] = {}
        self.receive: dict[str, Callable[[bytes], Any]] = {}
        self._handles: list[Any] = []
        for case in CASES:
            key = f"{ROOT}/{case.name}/{out}"
            if case.typed:
                publisher = TypedPublisher(host, key, MSG_TYPES[case.size])
                if case.reuse_buffer:
                    publisher._encoder = ReusedBufferEncoder()
                self.receive[case.name] = _typed_receiver(MSG_TYPES[case.size])
            else:
                publisher = session.declare_publisher(key)
                self.receive[case.name] = lambda payload: payload
            self.send[case.name] = publisher.put
            self._handles.append(publisher)
        inbox = self.inbox
        self._handles.append(session.declare_subscriber(
            f"{ROOT}/*/{into}", lambda sample: inbox.put((str(sample.key_expr), sample.payload.to_bytes()))
        ))
        self.stop_publisher = session.declare_publisher(f"{ROOT}/stop/{out}")
        self._handles.append(self.stop_publisher)

    def undeclare(self) -> None:
        for handle in self._handles:
            handle.undeclare()


# --------------------------------------------------------------- processes
def open_link(settings: ZenohSettings, link: str) -> zenoh.Session:
    """The embedded profile as is ("shm") or with Zenoh's shared-memory transport off ("tcp")."""
    settings.shared_memory = None if link == "shm" else False
    return open_session(settings)


def mapped_shm_files() -> list[str]:
    """Zenoh shared-memory segments this process has mapped (to check they are gone later)."""
    with open("/proc/self/maps") as maps:
        return sorted({m.group(1) for m in map(SHM_PATH.search, maps) if m})


def echo_main(port: int, link: str, conn) -> None:
    """Child process: send every ping straight back after the case's receive work."""
    session = endpoint = None
    try:
        init_logging()
        session = open_link(ZenohSettings(profile="embedded", listen=[f"tcp/127.0.0.1:{port}"]), link)
        endpoint = Endpoint(session, out="pong", into="ping")
        conn.send(("ready", None))
        while True:
            try:
                key, payload = endpoint.inbox.get(timeout=0.5)
            except queue.Empty:
                if conn.poll():
                    return  # the orchestrator says stop (the pinger failed)
                continue
            case = key.split("/")[1]
            if case == "stop":
                return
            endpoint.send[case](endpoint.receive[case](payload))
    except Exception:
        conn.send(("error", traceback.format_exc()))
    finally:
        _close(session, endpoint, conn)


def pinger_main(port: int, link: str, plans: dict[str, Plan], conn) -> None:
    """Child process: interleaved ping blocks per case; sends the one-way samples back."""
    session = endpoint = None
    try:
        init_logging()
        typed = {size: make() for size, make in MESSAGES.items()}
        encoded_len = {size: len(msgspec.msgpack.encode(msg)) for size, msg in typed.items()}
        rng = np.random.default_rng(3)
        bare = {size: rng.integers(0, 256, n, dtype=np.uint8).tobytes() for size, n in encoded_len.items()}
        session = open_link(ZenohSettings(profile="embedded", connect=[f"tcp/127.0.0.1:{port}"]), link)
        endpoint = Endpoint(session, out="ping", into="pong")
        wait_for_echo(endpoint)
        samples: dict[str, list[tuple[float, float, float]]] = {case.name: [] for case in CASES}
        lost = {name: [0, 0] for name in samples}  # [no answer in time, answered late]
        for size, plan in plans.items():
            cases = [case for case in CASES if case.size == size]
            for case in cases:
                ping(endpoint, case, typed[size] if case.typed else bare[size], plan.warmup, [])
            for _ in range(plan.rounds):
                for case in cases:
                    missed, late = ping(endpoint, case, typed[size] if case.typed else bare[size],
                                        plan.block, samples[case.name])
                    lost[case.name][0] += missed
                    lost[case.name][1] += late
        endpoint.stop_publisher.put(b"stop")
        conn.send(("result", (samples, lost, encoded_len)))
    except Exception:
        conn.send(("error", traceback.format_exc()))
    finally:
        _close(session, endpoint, conn)


def _close(session, endpoint, conn) -> None:
    shm = mapped_shm_files()
    if endpoint is not None:
        endpoint.undeclare()
    if session is not None:
        session.close()
    conn.send(("shm", shm))


def _drain(inbox: queue.SimpleQueue) -> int:
    """Empties the inbox; returns how many (late) replies were in it."""
    count = 0
    while True:
        try:
            inbox.get_nowait()
            count += 1
        except queue.Empty:
            return count


def wait_for_echo(endpoint: Endpoint, deadline_s: float = 15.0) -> None:
    """Routes appear asynchronously after connect: ping until the first answer."""
    payload = b"x" * 64
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        endpoint.send["small-bare"](payload)
        try:
            endpoint.inbox.get(timeout=0.2)
            _drain(endpoint.inbox)
            return
        except queue.Empty:
            continue
    raise RuntimeError("the echo process never answered")


def ping(endpoint: Endpoint, case: Case, message: Any, count: int, samples: list[tuple[float, float, float]]
         ) -> tuple[int, int]:
    """Appends (one-way = round trip / 2, time in send, time in receive), µs. Returns how many
    pings got no answer within REPLY_TIMEOUT_S, and how many of those answers came later."""
    send, receive, inbox = endpoint.send[case.name], endpoint.receive[case.name], endpoint.inbox
    lost = late = in_a_row = 0
    clock = time.perf_counter_ns
    for _ in range(count):
        late += _drain(inbox)
        start = clock()
        send(message)
        sent = clock()
        try:
            _, payload = inbox.get(timeout=REPLY_TIMEOUT_S)
        except queue.Empty:
            lost += 1
            in_a_row += 1
            if in_a_row == 3:
                raise RuntimeError(f"{case.name}: 3 pings in a row unanswered; the echo process is gone")
            continue
        in_a_row = 0
        arrived = clock()
        receive(payload)
        done = clock()
        samples.append(((done - start) / 2e3, (sent - start) / 1e3, (done - arrived) / 1e3))
    return lost, late


@dataclass
class LinkResult:
    samples: dict[str, np.ndarray]  # per case, rows of (one-way, send, receive) µs
    lost: dict[str, list[int]]  # per case: [no answer within REPLY_TIMEOUT_S, of which answered late]
    encoded_len: dict[str, int]
    port: int
    shm_mapped: list[str]  # zenoh segments the two processes had mapped
    shm_removed: list[str]  # of those, orphans this run deleted


def _receive(conn, kind: str, timeout_s: float, shm: list[str]) -> Any:
    """The next message of `kind` from a child; remembers the shm files it reports."""
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0 and conn.poll(remaining):
        got, value = conn.recv()
        if got == "shm":
            shm.extend(value)
        if got == kind:
            return value
        if got == "error":
            raise RuntimeError(f"a benchmark process failed:\n{value}")
    raise RuntimeError(f"no {kind!r} from a benchmark process within {timeout_s:.0f} s")


def run_link(link: str, plans: dict[str, Plan]) -> LinkResult:
    """One echo and one pinger process; this process opens no Zenoh session."""
    ctx = multiprocessing.get_context("spawn")
    port = free_port()
    echo_conn, echo_child = ctx.Pipe()
    ping_conn, ping_child = ctx.Pipe()
    echo = ctx.Process(target=echo_main, args=(port, link, echo_child), name="bench-echo", daemon=True)
    pinger = ctx.Process(target=pinger_main, args=(port, link, plans, ping_child), name="bench-ping", daemon=True)
    shm: list[str] = []
    try:
        echo.start()
        _receive(echo_conn, "ready", 30.0, shm)
        pinger.start()
        samples, lost, encoded_len = _receive(ping_conn, "result", 120.0, shm)
        for conn in (ping_conn, echo_conn):
            _receive(conn, "shm", 10.0, shm)
    finally:
        for process, conn in ((pinger, ping_conn), (echo, echo_conn)):
            if process.pid is None:
                continue
            try:
                conn.send("stop")
            except OSError:
                pass
            process.join(timeout=10.0)
            if process.is_alive():
                process.terminate()
                process.join(timeout=5.0)
            while conn.poll(0):  # a failed run still reports its segments on the way out
                got, value = conn.recv()
                if got == "shm":
                    shm.extend(value)
        removed = shm_segments.remove_orphans({Path(p) for p in shm})
    return LinkResult({name: np.asarray(s).reshape(-1, 3) for name, s in samples.items()}, lost, encoded_len, port, sorted(set(shm)), removed)


# ----------------------------------------------------------- in-process parts
def _median_us(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - start)
    return float(np.median(times)) / 1e3


def measure_parts(repeat: int) -> list[tuple[str, float]]:
    """Where one direction's time could go, for the 1.5 MB cloud, without the network."""
    msg = cloud_message()
    encoder = msgspec.msgpack.Encoder()
    decoder = msgspec.msgpack.Decoder(PointCloud)
    encoded = encoder.encode(msg)
    reused = bytearray()
    as_bytearray = bytearray(encoded)
    zbytes = zenoh.ZBytes(encoded)
    parts = [
        ("msgpack encode -> new bytes (typed send)", lambda: encoder.encode(msg)),
        ("msgpack encode_into reused bytearray", lambda: encoder.encode_into(msg, reused)),
        ("zenoh.ZBytes(bytes) (every put copies)", lambda: zenoh.ZBytes(encoded)),
        ("zenoh.ZBytes(bytearray)", lambda: zenoh.ZBytes(as_bytearray)),
        ("ZBytes.to_bytes() (every receive copies)", lambda: zbytes.to_bytes()),
        ("Decoder(PointCloud).decode + to_numpy", lambda: to_numpy(decoder.decode(encoded).points)),
    ]
    return [(label, _median_us(fn, repeat)) for label, fn in parts]


# ------------------------------------------------------------------- report
def print_link(link: str, result: LinkResult) -> None:
    print(f"[{link}] {LINKS[link]} (tcp/127.0.0.1:{result.port})")
    print(f"  {'case':<18} {'bytes':>9} {'n':>5} {'lost':>4} {'median':>8} {'p90':>8} {'p99':>8} "
          f"{'send':>7} {'recv':>7}")
    for case in CASES:
        rows = result.samples[case.name]
        size = result.encoded_len[case.size]
        if rows.shape[0] == 0:
            print(f"  {case.name:<18} {size:>9} {0:>5} {result.lost[case.name][0]:>4}  no samples")
            continue
        p50, p90, p99 = np.percentile(rows[:, 0], [50, 90, 99])
        send, recv = np.median(rows[:, 1]), np.median(rows[:, 2])
        print(f"  {case.name:<18} {size:>9} {rows.shape[0]:>5} {result.lost[case.name][0]:>4} "
              f"{p50:>8.1f} {p90:>8.1f} {p99:>8.1f} {send:>7.1f} {recv:>7.1f}")
    print("  (µs: one-way = round trip / 2; send = put() incl. encode, recv = decode after to_bytes, medians)")
    missed = sum(m for m, _ in result.lost.values())
    if missed:
        late = sum(late for _, late in result.lost.values())
        print(f"  {missed} pings unanswered within {REPLY_TIMEOUT_S:.0f} s, {late} answered later: the rest were dropped "
              f"(Zenoh's default congestion control drops a message it cannot queue in time)")

    def ratio(typed: str, bare: str) -> float:
        return float(np.median(result.samples[typed][:, 0]) / np.median(result.samples[bare][:, 0]))

    cloud = ratio("cloud-typed", "cloud-bare")
    verdict = "met" if cloud - 1 <= GOAL_OVERHEAD else "NOT met"
    print(f"  cloud typed/bare = {cloud:.2f}x (overhead {100 * (cloud - 1):.0f} %), goal <= {100 * GOAL_OVERHEAD:.0f} %: "
          f"{verdict}")
    into = ratio("cloud-typed+into", "cloud-bare")
    print(f"  cloud typed+into/bare = {into:.2f}x (overhead {100 * (into - 1):.0f} %)")
    small = ratio("small-typed", "small-bare")
    print(f"  small typed/bare = {small:.2f}x (overhead {100 * (small - 1):.0f} %)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (smoke test)")
    args = parser.parse_args(argv)
    plans = QUICK if args.quick else FULL
    began = time.monotonic()
    results = {link: run_link(link, plans) for link in LINKS}
    parts = measure_parts(repeat=10 if args.quick else 50)

    print(f"Falconry transport: 2 spawned processes, Zenoh {importlib.metadata.version('eclipse-zenoh')}, "
          f"embedded profile; one-way = round trip / 2")
    for link, result in results.items():
        print()
        print_link(link, result)
    print()
    print("one direction of the 1.5 MB cloud, in-process parts (median µs):")
    for label, us in parts:
        print(f"  {label:<44} {us:>8.1f}")
    removed = [path for result in results.values() for path in result.shm_removed]
    leftovers = [path for result in results.values() for path in result.shm_mapped if os.path.exists(path)]
    print()
    print(f"sessions closed, processes joined in {time.monotonic() - began:.1f} s; orphaned zenoh segments "
          f"removed: {len(removed)}; left in /dev/shm: {leftovers or 'none'}")
    return 1 if leftovers else 0


if __name__ == "__main__":
    sys.exit(main())
