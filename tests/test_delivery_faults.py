"""A real service on the wall clock (an onboard `falconry run`) under the delivery and clock faults:
duplicated messages are dropped and counted, never handled twice; a slow consumer sheds what newer
messages made history instead of falling ever further behind; a step of the system clock moves
none of its stamps. The test publishes the detections and the fault commands itself, as a detector
and a fault injector would. (A reorder needs two messages of a key queued at once, which keep-last
sheds in real time; the lockstep test in test_launcher.py shows the gate putting them in order.)"""
from __future__ import annotations

import queue
import time

import msgspec
import numpy as np
import pytest

from schemas import keys
from schemas.arrays import from_numpy
from schemas.messages import Detections, FaultCommand, Header, Tracks
from tests.tools.health import health, wait_healthy

pytestmark = pytest.mark.alone  # fault windows timed on the wall clock

DETECTIONS = keys.uav("uav1", "detections")
SENDER = "uav1/test_detector"
encode = msgspec.msgpack.Encoder().encode


class Detector:
    """Publishes empty detections with its own seq, stamped with the wall clock."""

    def __init__(self, session) -> None:
        self.session = session
        self.seq = 0

    def send(self, count: int, every: float = 0.0) -> None:
        for _ in range(count):
            self.seq += 1
            self.session.put(DETECTIONS, encode(Detections(
                header=Header(sender=SENDER, seq=self.seq, stamp=time.time_ns()), detector="classifier",
                positions=from_numpy(np.zeros((0, 3))), covariances=from_numpy(np.zeros((0, 3, 3))),
                point_counts=from_numpy(np.zeros(0, np.int32)), extents=from_numpy(np.zeros(0, np.float32)))))
            if every:
                time.sleep(every)


def inject(session, kind: str, seconds: float = 0.0, **fields) -> None:
    session.put(keys.FAULTS, encode(FaultCommand(header=Header(sender="sim/test", stamp=time.time_ns()), kind=kind,
                                                 uav="uav1", duration=seconds, **fields)))
    time.sleep(0.3)  # the command travels on its own key: let it arrive before what it disturbs


def counters(session) -> tuple[int, int, int]:
    """(received, dropped as duplicate or overtaken, shed unread) of the tracker's detections."""
    h = health(session, "uav1", "tracker", timeout=5.0)
    assert h is not None, "the tracker did not answer"
    return h.received.get(DETECTIONS, 0), h.dropped_stale.get(DETECTIONS, 0), h.dropped_backlog.get(DETECTIONS, 0)


def test_duplicates_a_slow_consumer_and_a_clock_step_on_a_wall_clock_service(hub, processes):
    session, endpoint = hub
    stamps: queue.SimpleQueue = queue.SimpleQueue()
    tracks = session.declare_subscriber(keys.uav("uav1", "tracks"), lambda s: stamps.put(
        (time.time_ns(), msgspec.msgpack.decode(s.payload.to_bytes(), type=Tracks).header.stamp)))
    try:
        tracker = processes.start("run", "tracker", "--uav", "uav1", "--clock", "wall", "--simulated-faults", "on",
                                  "--connect", endpoint)
        wait_healthy(session, [("uav1", "tracker")])
        # it answers while its Kalman and assignment libraries still load right after its token
        # (services/lib/runtime/warmup.py): the import holds the interpreter for a moment, long enough to
        # shed one of messages 20 ms apart (0.5-1.8 s here). The counts below are those of a service
        # running steadily.
        time.sleep(2.5)
        detector = Detector(session)

        detector.send(10, every=0.02)
        assert counters(session) == (10, 0, 0)

        inject(session, "duplicate", 1.5, topic="detections")
        detector.send(20, every=0.02)
        received, stale, shed = counters(session)
        print(f"duplicate: 20 sent, {received - 10} received, {stale} dropped")
        assert (received, stale, shed) == (50, 20, 0)  # each twice, the copies dropped
        time.sleep(1.5)  # the window is over

        # a slow consumer with a burst queued behind: without shedding it would be 0.05 s x 300 behind
        inject(session, "slow", 2.0, delay=0.05)
        detector.send(300)
        sent_at = time.monotonic()
        while (counts := counters(session)) and counts[0] - 50 + counts[2] < 300:
            assert time.monotonic() - sent_at < 5.0, f"not through the burst after 5 s: {counts}"
        caught_up = time.monotonic() - sent_at
        received, stale, shed = counts
        print(f"slow consumer: 300 sent at once, {shed} shed, {received - 50} handled; through them "
              f"{caught_up:.2f} s after the burst (handling all would take 15 s)")
        assert shed >= 250 and received - 50 + shed == 300 and caught_up < 1.5
        time.sleep(2.0)

        while not stamps.empty():
            stamps.get()
        inject(session, "clock_jump", jump=3600.0)  # an NTP step of an hour
        wall, stamp = stamps.get(timeout=5)
        wall, stamp = stamps.get(timeout=5)  # one published wholly after the step
        print(f"after a +3600 s system clock step the tracker stamps {abs(stamp - wall) / 1e9:.3f} s off the wall")
        assert abs(stamp - wall) < 1e9
    finally:
        tracks.undeclare()
    tracker.terminate()
    output, _ = tracker.communicate(timeout=10)
    assert "the system clock moved +3600.000 s against the monotonic clock" in output, output[-2000:]
    assert "Traceback" not in output


def test_a_service_on_the_wall_clock_obeys_no_fault_command_unless_told(hub, processes):
    """Onboard (`--clock wall`, simulated faults auto: off) a fault command on the network changes
    nothing: duplicates are not made, so nothing is dropped as one, and the service does not say it
    took the fault."""
    session, endpoint = hub
    tracker = processes.start("run", "tracker", "--uav", "uav1", "--clock", "wall", "--connect", endpoint)
    wait_healthy(session, [("uav1", "tracker")])
    detector = Detector(session)
    detector.send(5, every=0.05)
    time.sleep(0.5)
    before = counters(session)
    inject(session, "duplicate", 2.0, topic="detections")
    detector.send(20, every=0.02)
    time.sleep(0.5)
    received, stale, _ = counters(session)
    assert (received - before[0], stale - before[1]) == (20, 0)  # each once, no copy made
    tracker.terminate()
    output, _ = tracker.communicate(timeout=10)
    assert "fault duplicate" not in output and "Traceback" not in output, output[-2000:]
