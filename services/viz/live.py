"""The viewer's live input: a plain Zenoh subscriber, never a lockstep participant.

It declares no liveliness token and sends no acknowledgements, so the simulator never waits for it.
Zenoh callbacks only queue (key, payload, receive time); when the drawing falls behind, scans are
the first thing dropped (counted), so publishers never block on the viewer. Health answers, asked
every second, feed the CPU plots.
"""
from __future__ import annotations

import queue
import time

import zenoh

from schemas import keys
from services.runtime.health import HealthPoller
from services.runtime.zenoh_config import undeclare_all

LIVE_KEYS = (keys.CLOCK, keys.WORLD, keys.TRUTH, keys.EVENTS) + tuple(
    f"{keys.ROOT}/*/{topic}" for topic in
    ("odometry", "points", "labels", "detections", "map", "tracks", "command", "trajectory", "status"))
DROPPABLE = ("/points", "/labels")  # whole scans: the viewer draws one in a few anyway


class LiveFeed:
    def __init__(self, session: zenoh.Session, max_backlog: int = 200, health_period: float = 1.0) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.max_backlog = max_backlog
        self.dropped = 0
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in LIVE_KEYS]
        self._health = HealthPoller(session, self._put, period=health_period)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key.endswith(DROPPABLE) and self._queue.qsize() > self.max_backlog:
            self.dropped += 1
            return
        self._put(key, sample.payload.to_bytes(), time.time_ns())

    def _put(self, key: str, payload: bytes, received: int) -> None:
        self._queue.put((key, payload, received))

    def get(self, timeout: float) -> tuple[str, bytes, int] | None:
        self._health.poll()
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    @property
    def backlog(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        undeclare_all(self._subscribers)
