"""Service processes under test over real Zenoh: started and healthy, and what they publish collected."""
from __future__ import annotations

import msgspec

from schemas import keys
from tests.tools.health import wait_healthy


def start_healthy(processes, session, endpoint: str, services: tuple[str, ...], uav: str = "uav1") -> None:
    """Each service of `uav` as its own process on the test's hub, back once every one answers."""
    for service in services:
        processes.start("run", service, "--uav", uav, "--connect", endpoint, "--exit-with-parent")
    wait_healthy(session, [(uav, service) for service in services])


def collect(session, types: dict[str, type], uav: str = "uav1") -> tuple[dict[str, list], list]:
    """(topic -> decoded messages so far, the subscribers: undeclare them when done) for each of the
    UAV's topics in `types` (topic -> message type)."""
    got: dict[str, list] = {topic: [] for topic in types}
    subscribers = [session.declare_subscriber(keys.uav(uav, topic), lambda s, t=topic: got[t].append(
        msgspec.msgpack.decode(s.payload.to_bytes(), type=types[t]))) for topic in types]
    return got, subscribers
