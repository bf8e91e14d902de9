"""Every message type survives a trip through Zenoh to another process and back."""
from __future__ import annotations

import multiprocessing
import queue
import time

import msgspec
import numpy as np
import pytest

from schemas.arrays import Array, from_numpy, to_numpy
from schemas.messages import ALL_MESSAGES, PointCloud
from tests.tools.echo import echo_main
from tests.tools.samples import sample


def wait_for_token(session, key: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if list(session.liveliness().get(key, timeout=0.5)):
            return
    raise AssertionError(f"{key} never appeared")


def test_every_message_type_round_trips_between_processes(hub):
    session, endpoint = hub
    got: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber("test/out/*", lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
    echo = multiprocessing.get_context("spawn").Process(target=echo_main, args=(endpoint,))
    echo.start()
    try:
        wait_for_token(session, "test/alive/echo")
        time.sleep(0.3)  # let the echo's subscription reach us before the first put
        sent = {t.__name__: sample(t) for t in ALL_MESSAGES}
        for name, msg in sent.items():
            session.put(f"test/in/{name}", msgspec.msgpack.encode(msg))
        received = {}
        deadline = time.monotonic() + 10
        while len(received) < len(sent) and time.monotonic() < deadline:
            key, payload = got.get(timeout=max(0.01, deadline - time.monotonic()))
            name = key.rsplit("/", 1)[-1]
            received[name] = msgspec.msgpack.Decoder(type(sent[name])).decode(payload)
        assert sorted(received) == sorted(sent)
        for name, msg in sent.items():
            assert received[name] == msg, name
    finally:
        session.put("test/stop", b"")
        echo.join(timeout=10)
        sub.undeclare()
    assert echo.exitcode == 0


def test_array_decode_is_zero_copy_and_validated():
    cloud = sample(PointCloud)
    cloud.points = from_numpy(np.random.default_rng(0).normal(size=(4, 8, 3)).astype(np.float32))
    wire = msgspec.msgpack.encode(cloud)
    decoded = msgspec.msgpack.Decoder(PointCloud).decode(wire)
    points = to_numpy(decoded.points)
    assert points.shape == (4, 8, 3) and points.dtype == np.float32
    assert np.array_equal(points, to_numpy(cloud.points))
    assert not points.flags.owndata  # a view into the received buffer
    with pytest.raises(ValueError, match="needs 12 bytes"):
        Array(dtype="<f4", shape=[3], data=memoryview(b"short"))
    with pytest.raises(ValueError, match="unsupported"):
        Array(dtype="object", shape=[1], data=memoryview(b"x"))


def test_big_endian_input_is_sent_little_endian():
    arr = np.arange(4, dtype=">f8")
    wire = from_numpy(arr)
    assert wire.dtype == "<f8"
    assert np.array_equal(to_numpy(wire), arr)


def test_empty_arrays_travel():
    empty = from_numpy(np.zeros((0, 3), dtype=np.float64))
    decoded = msgspec.msgpack.Decoder(Array).decode(msgspec.msgpack.encode(empty))
    assert to_numpy(decoded).shape == (0, 3)
