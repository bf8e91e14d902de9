"""Runtime behaviour of a single service process: profiles, clocks, shutdown."""
from __future__ import annotations

import json
import logging
import queue
import signal
import time

import msgspec
import pytest

from schemas import keys
from schemas.messages import Tracks
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.zenoh_config import ZenohConfigError, ZenohSettings, build
from tests.tools.health import wait_healthy

pytestmark = pytest.mark.alone  # services stopped within 2 s of the wall clock


def test_profiles_and_overrides(tmp_path, monkeypatch):
    embedded = build(ZenohSettings(connect=["tcp/127.0.0.1:7000"]))
    assert json.loads(embedded.get_json("mode")) == "peer"
    assert json.loads(embedded.get_json("scouting/multicast/enabled")) is False
    assert json.loads(embedded.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7000"]
    router = build(ZenohSettings(profile="router"))
    assert json.loads(router.get_json("mode")) == "client"
    assert json.loads(router.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    leased = build(ZenohSettings(lease_ms=1500))
    assert json.loads(leased.get_json("transport/link/tx/lease")) == 1500

    custom = tmp_path / "zenoh.json5"
    custom.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.1.2.3:7447"] } }')
    monkeypatch.setenv("ZENOH_CONFIG", str(custom))
    from_env = build(ZenohSettings())
    assert json.loads(from_env.get_json("mode")) == "client"
    assert json.loads(from_env.get_json("connect/endpoints")) == ["tcp/10.1.2.3:7447"]
    monkeypatch.delenv("ZENOH_CONFIG")

    custom.write_text("{ this is not json5")
    with pytest.raises(ZenohConfigError, match="invalid"):
        build(ZenohSettings(config_file=str(custom)))
    with pytest.raises(ZenohConfigError, match="unknown zenoh profile"):
        build(ZenohSettings(profile="mesh"))


def test_wall_clock_service_ticks_without_a_simulator_and_stops_within_2s(hub, processes):
    session, endpoint = hub
    tracks: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber(keys.uav("uav1", "tracks"), lambda s: tracks.put(s.payload.to_bytes()))
    try:
        proc = processes.start("run", "tracker", "--uav", "uav1", "--clock", "wall", "--connect", endpoint)
        wait_healthy(session, [("uav1", "tracker")])
        # with no detections the tracker still says it is alive once per second of (wall) time
        first = msgspec.msgpack.Decoder(Tracks).decode(tracks.get(timeout=5))
        assert first.tracks == [] and abs(first.header.stamp / 1e9 - time.time()) < 5
        started = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=5)
        took = time.monotonic() - started
        print(f"tracker stopped {took * 1000:.0f} ms after SIGTERM, exit code {code}")
        assert code == 0 and took < 2.0
    finally:
        sub.undeclare()


@pytest.mark.parametrize("service", ["simulator", "classifier", "job_manager"])
def test_sigint_stops_a_service_within_2s(hub, processes, service):
    session, endpoint = hub
    uav = [] if service == "simulator" else ["--uav", "uav1"]
    proc = processes.start("run", service, *uav, "--connect", endpoint)
    wait_healthy(session, [("sim" if service == "simulator" else "uav1", service)])
    started = time.monotonic()
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=5)
    assert code == 0 and time.monotonic() - started < 2.0


def test_counted_warnings_speak_at_the_first_refusal_and_at_each_power_of_ten(caplog):
    warnings = CountedWarnings(logging.getLogger("test.counted"))
    with caplog.at_level(logging.WARNING, logger="test.counted"):
        for count in (0, 1, 2, 9, 10, 11, 99, 250, 250, 1000):
            warnings.update({"scans refused": count, "points dropped": 2 * count})
    said = [r.getMessage() for r in caplog.records]
    assert [m for m in said if m.startswith("scans refused")] == [
        "scans refused so far: 1", "scans refused so far: 10", "scans refused so far: 250", "scans refused so far: 1000"]
    assert [m for m in said if m.startswith("points dropped")] == [
        "points dropped so far: 2", "points dropped so far: 18", "points dropped so far: 198",
        "points dropped so far: 2000"]


def detections_listener(endpoint: str):
    """A tracker node of uav1 subscribed to its detections over a real session to `endpoint`, its
    subscription declared as the node declares it: (node, key)."""
    from schemas.messages import Detections
    from services.lib.runtime.node import Node
    from services.lib.runtime.zenoh_config import open_session

    class Listener(Node):
        service = "tracker"

    key = keys.uav("uav1", "detections")
    node = Listener("uav1", ZenohSettings(connect=[endpoint], shared_memory=False))
    node.subscribe(key, Detections, lambda msg, k: None)
    node.session = open_session(ZenohSettings(connect=[endpoint], shared_memory=False))
    node._declare_subscriber(node._subs[0])
    return node, key


def test_a_subscription_a_lockstep_wait_gave_up_on_is_declared_again_and_receives(hub):
    """A subscription that no longer reaches its publisher (here undeclared behind the node's back,
    as a declaration lost on the way would be) delivers nothing; declared again after a give-up, it
    does, and the old declaration is gone. Not more than once per REDECLARE_EVERY_S."""
    from services.lib.runtime.zenoh_config import undeclare_all

    session, endpoint = hub
    node, key = detections_listener(endpoint)
    try:
        lost = node._subscribers[0]
        lost.undeclare()
        payload = b"any bytes: the inbox holds them undecoded"

        def heard() -> bool:
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                session.put(key, payload)
                try:
                    return node._inbox.get(timeout=0.2)[2] == key
                except queue.Empty:
                    pass
            return False

        assert not heard()
        node._declare_again([key])
        assert node._subscribers[0] is not lost and lost not in node._zenoh_handles
        assert heard()
        again = node._subscribers[0]
        node._declare_again([key])  # within REDECLARE_EVERY_S: left alone
        node._declare_again(["falconry/uav1/status"])  # another key: not this subscription's
        assert node._subscribers[0] is again and len(node._zenoh_handles) == 1
    finally:
        undeclare_all(node._zenoh_handles)
        node.session.close()


def test_the_old_subscription_is_gone_from_the_network_before_the_new_one_is_declared(hub):
    """Zenoh sends nothing for a second subscriber on a key the session already subscribes, nor for
    undeclaring one of two; so a re-declaration made beside the old subscriber never leaves the
    process. At the moment the new one is declared, the publisher must already see no subscriber
    (polled, so no two declarations can arrive as one), and afterwards see it again."""
    from services.lib.runtime.zenoh_config import undeclare_all

    session, endpoint = hub
    publisher = session.declare_publisher(keys.uav("uav1", "detections"))
    node, key = detections_listener(endpoint)

    def publisher_sees(matching: bool) -> bool:
        deadline = time.monotonic() + 3.0
        while publisher.matching_status.matching != matching:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    seen_when_declared: list[bool] = []
    declare = node._declare_subscriber

    def declare_watched(sub) -> None:
        seen_when_declared.append(publisher_sees(False))
        declare(sub)

    try:
        assert publisher_sees(True)
        node._declare_subscriber = declare_watched
        node._declare_again([key])
        assert seen_when_declared == [True], "the old subscriber was still declared on the network"
        assert publisher_sees(True)
    finally:
        publisher.undeclare()
        undeclare_all(node._zenoh_handles)
        node.session.close()
