"""Pure parts of message delivery under faults: the real-time freshness rule, the delivery faults a
node applies to itself, the reorder buffer, the lockstep gate with duplicated and overtaken
messages, the wall clock against a stepped system clock, the planner's job-manager watchdog, and
a node's refusal of overlapping subscriptions."""
from __future__ import annotations

import pytest

from schemas import keys
from schemas.messages import Detections, FaultCommand, Header, UavStatus
from services.lib.runtime.clock import NS, WallClock
from services.lib.runtime.delivery import DeliveryFaults, Freshness, Reorderer
from services.lib.runtime.lockstep import LockstepGate
from services.lib.runtime.node import Node
from services.lib.runtime.zenoh_config import ZenohSettings
from services.planner.watchdog import JobManagerWatchdog

DETECTIONS = "falconry/uav1/detections"


def command(kind: str, at: float, **fields) -> FaultCommand:
    return FaultCommand(header=Header(stamp=int(at * NS)), kind=kind, **{"uav": "uav1", **fields})


def test_the_newest_message_of_a_key_wins_and_a_restarted_publisher_is_news():
    fresh = Freshness()
    assert fresh.fresh(DETECTIONS, 1, 100) and fresh.fresh(DETECTIONS, 2, 200)
    assert not fresh.fresh(DETECTIONS, 2, 200)  # the same message again
    assert fresh.fresh(DETECTIONS, 4, 400)
    assert not fresh.fresh(DETECTIONS, 3, 300)  # overtaken in transit by #4
    assert fresh.fresh(DETECTIONS, 1, 500)  # a restarted publisher: seq from 1, stamps later
    assert fresh.fresh(DETECTIONS, 2, 500)  # same stamp, higher seq: a second message of that tick
    assert fresh.fresh("falconry/uav1/tracks", 1, 0)  # keys are independent


def test_delivery_faults_concern_subscribers_of_the_topic_and_the_slowed_service_only():
    faults = DeliveryFaults("uav1", "tracker")
    subscribed = {DETECTIONS}.__contains__
    assert faults.add(command("duplicate", 10.0, topic="detections", duration=5.0), subscribed)
    assert not faults.add(command("reorder", 10.0, topic="points", duration=5.0), subscribed)  # not ours
    assert not faults.add(command("duplicate", 10.0, topic="*/x", duration=5.0), subscribed)  # not a topic
    assert not faults.add(command("slow", 10.0, service="mapper", delay=0.1), subscribed)
    assert not faults.add(command("slow", 10.0, delay=5.0), subscribed)  # beyond a slow computer: refused
    assert faults.add(command("slow", 12.0, delay=0.1, duration=1.0), subscribed)
    assert faults.disturbance(DETECTIONS, 9.99) is None
    assert faults.disturbance(DETECTIONS, 10.0) == "duplicate"
    assert faults.disturbance(DETECTIONS, 15.0) is None  # the window ended
    assert faults.delay(11.9) == 0 and faults.delay(12.5) == 0.1 and faults.delay(13.0) == 0


def test_a_reorder_swaps_neighbours_and_loses_nothing():
    swap: Reorderer[str] = Reorderer()
    assert swap.pass_through("a", "a1") == [] and swap
    assert swap.pass_through("b", "b1") == []
    assert swap.pass_through("a", "a2") == ["a2", "a1"]
    assert swap.flush() == ["b1"] and not swap


def test_the_gate_drops_duplicates_and_puts_overtaken_messages_back_in_order():
    gate = LockstepGate((), lambda key: True, joining=False)
    assert gate.hold(DETECTIONS, 2, "d2", stamp=200)
    assert gate.hold(DETECTIONS, 1, "d1", stamp=100)  # overtaken by #2 in transit
    assert not gate.hold(DETECTIONS, 2, "d2 again", stamp=200)
    gate.begin(1, {DETECTIONS: 2})
    assert gate.missing(set()) == []
    assert gate.release(set()) == [(DETECTIONS, "d1"), (DETECTIONS, "d2")]
    assert not gate.hold(DETECTIONS, 2, "d2 late copy", stamp=200)
    assert not gate.hold(DETECTIONS, 1, "d1 late copy", stamp=100)  # its successor is processed already
    assert gate.hold(DETECTIONS, 1, "restarted", stamp=900)  # a restarted publisher: later stamps
    gate.begin(2, {DETECTIONS: 1})
    assert gate.release(set()) == [(DETECTIONS, "restarted")]


def test_the_wall_clock_keeps_to_the_monotonic_clock_when_the_system_clock_steps():
    system, monotonic = [1_700_000_000 * NS], [5 * NS]
    clock = WallClock(system_ns=lambda: system[0], monotonic_ns=lambda: monotonic[0])
    start = clock.now_ns()
    system[0] += 2 * NS
    monotonic[0] += 2 * NS
    assert clock.now_ns() == start + 2 * NS and clock.system_step_ns() == 0
    system[0] += 3600 * NS  # NTP steps the system clock an hour ahead
    assert clock.now_ns() == start + 2 * NS and clock.system_step_ns() == 3600 * NS
    clock.inject_step(-3600.0)  # the clock_jump fault: this process's view of the system clock
    assert clock.system_step_ns() == 0


def test_the_watchdog_trips_once_per_silence_and_reports_the_recovery():
    dog = JobManagerWatchdog(timeout_ns=1 * NS)
    assert not dog.silent_too_long(100 * NS)  # nothing heard yet: nothing to watch
    assert not dog.heard(10 * NS)
    assert not dog.silent_too_long(int(10.99 * NS))
    assert dog.silent_too_long(11 * NS) and dog.tripped
    assert not dog.silent_too_long(12 * NS)  # once
    assert dog.heard(13 * NS) and not dog.tripped
    assert not dog.heard(13 * NS)


def test_a_node_refuses_two_subscriptions_that_would_share_a_sample():
    """The duplicate filter and the lockstep gate track a key once per node: a sample matching two
    subscriptions would reach only one handler, so a node subscribes once per key instead."""
    class Listener(Node):
        service = "tracker"

    node = Listener("uav1", ZenohSettings())
    node.subscribe(keys.uav("uav1", "detections"), Detections, lambda msg, key: None)
    node.subscribe(keys.uav("uav1", "status"), UavStatus, lambda msg, key: None)
    with pytest.raises(ValueError, match="overlaps"):
        node.subscribe(keys.ALL_STATUS, UavStatus, lambda msg, key: None)
    node.subscribe_runtime(keys.ALL_STATUS, UavStatus, lambda msg, key: None)  # plumbing is never filtered
