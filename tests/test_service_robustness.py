"""Garbage on every key a running service subscribes to is counted and survived."""
from __future__ import annotations

import os
import time

import msgspec
import pytest

from schemas import keys
from schemas.catalogue import CATALOGUE
from schemas.messages import Header, SimClock
from tests.tools.health import health, wait_healthy
from tests.tools.samples import concrete

pytestmark = pytest.mark.alone  # real-time services given one tick and fixed sleeps to handle it

GARBAGE = (b"\x00\xffnot msgpack at all", b"", msgspec.msgpack.encode({"header": "wrong shape"}),
           os.urandom(256))


def test_services_count_garbage_and_keep_working(hub, processes):
    session, endpoint = hub
    services = keys.UAV_SERVICES + keys.CAMERA_SERVICES
    for service in services:
        processes.start("run", service, "--uav", "uav1", "--connect", endpoint, "--exit-with-parent")
    names = [("uav1", s) for s in services]
    before = wait_healthy(session, names)
    time.sleep(0.5)  # every service's subscriptions reach this session

    targets = {name: [concrete(k) for k in h.subscriptions] for name, h in before.items()}
    for name, subscribed in targets.items():
        assert keys.CLOCK in subscribed, f"{name} does not follow the clock"
    for key in sorted({k for subscribed in targets.values() for k in subscribed}):
        for junk in GARBAGE:
            session.put(key, junk)
    # then a valid real-time tick: every service must still process it
    tick = SimClock(header=Header(sender="sim/simulator", seq=1, stamp=1_000_000_000), step=20, dt=0.05,
                    lockstep=False)
    time.sleep(0.5)
    session.put(keys.CLOCK, msgspec.msgpack.encode(tick))
    time.sleep(1.0)

    for name, subscribed in targets.items():
        after = health(session, *name)
        assert after is not None and after.state == "running", f"{name} stopped answering after garbage"
        for key in subscribed:
            assert after.decode_errors.get(key, 0) >= len(GARBAGE) - 1, (name, key, after.decode_errors)
        assert after.received.get(keys.CLOCK, 0) >= 1, f"{name} did not process a valid tick after garbage"
        assert after.handler_errors == 0, name
        assert_catalogued(name[1], after.subscriptions)
        print(f"{name[0]}/{name[1]}: {sum(after.decode_errors.values())} bad payloads counted on "
              f"{len(subscribed)} keys, still running")


def assert_catalogued(service: str, subscriptions: list[str]) -> None:
    """The README's catalogue (generated from schemas.catalogue) names this service as a subscriber."""
    for key in subscriptions:
        if "/ack/" in key or key in (keys.CLOCK, keys.FAULTS):  # runtime plumbing, not the service's own
            continue
        pattern = key.replace("/uav1/", "/<uav>/").replace("/*/", "/<uav>/")
        entry = next((e for e in CATALOGUE if e.key == pattern), None)
        assert entry is not None, f"{service} subscribes to {key}, which the catalogue does not list"
        assert service in entry.subscribers, f"catalogue: {entry.key} does not list {service} as a subscriber"
