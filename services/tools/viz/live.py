"""The viewer's live input: a plain Zenoh subscriber, never a lockstep participant.

It declares no liveliness token and sends no acknowledgements, so the simulator never waits for it.
Zenoh callbacks only queue what arrives, and never block: when the drawing falls behind, whole
scans are dropped first (past `scan_backlog` queued messages) and anything past `max_backlog`
(a dropped map delta is repaired by the next snapshot: the scene notices the gap in its sequence
numbers). Every drop is counted per topic. Health answers, asked every second, feed the CPU plots.
"""
from __future__ import annotations

import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass

import zenoh

from schemas import keys
from services.lib.runtime.health import HealthPoller
from services.lib.runtime.zenoh_config import undeclare_all

LIVE_KEYS = (keys.CLOCK, keys.WORLD, keys.TRUTH, keys.EVENTS) + tuple(
    keys.uav("*", topic) for topic in
    ("odometry", "points", "labels", "detections", "map", "tracks", "command", "trajectory", "status",
     "camera_jpeg", "camera_detections"))
SCANS = ("/points", "/labels")  # whole scans: the viewer draws one in a few anyway


@dataclass(frozen=True)
class Arrival:
    key: str
    payload: bytes
    received: int  # wall-clock ns


class LiveFeed:
    def __init__(self, session: zenoh.Session, scan_backlog: int = 200, max_backlog: int = 2000,
                 health_period: float = 1.0) -> None:
        self._queue: queue.SimpleQueue[Arrival] = queue.SimpleQueue()
        self.scan_backlog = scan_backlog
        self.max_backlog = max_backlog
        self.dropped: Counter[str] = Counter()  # topic -> messages dropped
        self._lock = threading.Lock()  # callbacks may run on several Zenoh threads at once
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in LIVE_KEYS]
        self._health = HealthPoller(session, self._put, period=health_period)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        backlog = self._queue.qsize()
        if backlog > self.max_backlog or (backlog > self.scan_backlog and key.endswith(SCANS)):
            with self._lock:
                self.dropped[key.rsplit("/", 1)[-1]] += 1
            return
        self._put(key, sample.payload.to_bytes(), time.time_ns())

    def _put(self, key: str, payload: bytes, received: int) -> None:
        self._queue.put(Arrival(key, payload, received))

    def get(self, timeout: float) -> Arrival | None:
        self._health.poll()
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    @property
    def backlog(self) -> int:
        return self._queue.qsize()

    def dropped_line(self) -> str:
        with self._lock:
            return ", ".join(f"{count} {topic}" for topic, count in sorted(self.dropped.items()))

    def close(self) -> None:
        undeclare_all(self._subscribers)
