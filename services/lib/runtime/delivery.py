"""How a node takes its messages off the network in real time, and the scheduled faults that
disturb that. Pure: no Zenoh, no clocks; times are mission seconds.

- `Freshness`: per key, a message is handled only when it is newer than the last one handled
  (its seq is higher, or its stamp later: a restarted publisher counts from 1 again). A duplicate,
  or a message overtaken in transit by a newer one, is dropped and counted: every keyed stream
  here but the map deltas is a state ("the newest wins"), and a consumer handed the older state
  after the newer one would step back in time. Of the map deltas only duplicates are dropped.
- `DeliveryFaults`: the `duplicate`, `reorder` and `slow` faults that apply to one node. The first
  two are faults of the network between a topic's publisher and this subscriber (every sample
  twice; a sample held back until the next one on its key has passed it), the third of the node's
  own computer (each message received costs `delay` more seconds).
- `Reorderer`: carries out `reorder`, one held-back sample per key.

Lockstep needs neither this filter nor backlog shedding: its gate holds messages by seq and stamp
(`LockstepGate.hold` drops duplicates and puts overtaken messages back in order) and waits for
every one, so a duplicate or overtaken message changes nothing there, and a slow consumer only
slows the run.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Generic, TypeVar

from schemas import keys

Item = TypeVar("Item")
DELIVERY_FAULTS = ("duplicate", "reorder")
NODE_FAULTS = DELIVERY_FAULTS + ("slow",)
# a `slow` fault beyond this per message is a freeze (use `freeze`); in lockstep a service takes a
# few messages a tick, which must stay well inside the 5 s a downstream waits for its tick
MAX_DELAY_S = 0.1
TOPIC = re.compile(r"[A-Za-z0-9_-]+")  # one chunk of a per-UAV key: "detections", "points_truth"


class Freshness:
    def __init__(self) -> None:
        self._last: dict[str, tuple[int, int]] = {}  # key -> (seq, stamp) of the newest handled

    def fresh(self, key: str, seq: int, stamp: int, ordered: bool = True) -> bool:
        """`ordered` False for a stream of increments (map deltas), where an overtaken message still
        counts (its consumer puts it in order or asks for a snapshot): only a duplicate is dropped."""
        last = self._last.get(key)
        if last is not None and seq <= last[0] and stamp <= last[1]:
            if ordered or (seq, stamp) == last:
                return False  # a duplicate, or older than what was handled already
            return True
        self._last[key] = (seq, stamp)
        return True


@dataclass(frozen=True)
class _Window:
    kind: str
    key: str  # the disturbed key ("" for slow: every message)
    start: float
    end: float
    delay: float = 0.0

    def active(self, now: float) -> bool:
        return self.start <= now < self.end


class DeliveryFaults:
    """The scheduled delivery faults that concern the node `service` of `scope`."""

    def __init__(self, scope: str, service: str) -> None:
        self.scope = scope
        self.service = service
        self._windows: list[_Window] = []

    def add(self, command, subscribed) -> bool:
        """Take a FaultCommand; `subscribed(key)` says whether this node receives the key.
        True when the fault concerns this node."""
        if command.kind not in NODE_FAULTS:
            return False
        start = command.header.stamp / 1e9
        end = start + command.duration if command.duration > 0 else float("inf")
        if command.kind == "slow":
            if command.uav != self.scope or command.service not in ("", self.service) \
                    or not 0 < command.delay <= MAX_DELAY_S:
                return False
            self._windows.append(_Window("slow", "", start, end, command.delay))
            return True
        if not TOPIC.fullmatch(command.topic) or not TOPIC.fullmatch(command.uav):
            return False
        key = keys.uav(command.uav, command.topic)
        if not subscribed(key):
            return False
        self._windows.append(_Window(command.kind, key, start, end))
        return True

    def disturbance(self, key: str, now: float) -> str | None:
        """"duplicate", "reorder" or None for a sample on `key` arriving at `now`."""
        for w in self._windows:
            if w.key == key and w.active(now):
                return w.kind
        return None

    def delay(self, now: float) -> float:
        """Extra seconds the node takes per message received at `now`."""
        return sum(w.delay for w in self._windows if w.kind == "slow" and w.active(now))

    def any_active(self, now: float) -> bool:
        return any(w.active(now) for w in self._windows)


class Reorderer(Generic[Item]):
    """A sample is held back until the next one on its key arrives, which then goes first; a
    sample with no successor in sight is let go when the node has nothing else to read (`flush`),
    so a reorder never loses or stalls anything, it only swaps neighbours."""

    def __init__(self) -> None:
        self._held: dict[str, Item] = {}

    def pass_through(self, key: str, item: Item) -> list[Item]:
        held = self._held.pop(key, None)
        if held is None:
            self._held[key] = item
            return []
        return [item, held]

    def holds(self, key: str) -> bool:
        return key in self._held

    def flush(self) -> list[Item]:
        held, self._held = list(self._held.values()), {}
        return held

    def __bool__(self) -> bool:
        return bool(self._held)


class SimulatedNetwork(Generic[Item]):
    """The network faults a simulation schedules on one service's inputs: each received item goes
    `through` it (duplicated, or held back behind the next of its key), and a `slow` fault's
    `delay` comes before handling it. Only a node that obeys the simulator's fault commands has one
    (Node's `simulated_faults`, on in a simulation and off onboard), so a real UAV's delivery path
    holds no fault code at all."""

    def __init__(self, scope: str, service: str) -> None:
        self._faults = DeliveryFaults(scope, service)
        self._reorderer: Reorderer[Item] = Reorderer()

    def add(self, command, subscribed) -> bool:
        """Take a fault command; True when it disturbs this service's inputs (DeliveryFaults.add)."""
        return self._faults.add(command, subscribed)

    def through(self, key: str, item: Item, now: float) -> list[Item]:
        """What the network hands over of one item of `key` at mission time `now`, in order."""
        disturbance = self._faults.disturbance(key, now)
        if disturbance == "duplicate":
            return [item, item]
        if disturbance == "reorder" or self._reorderer.holds(key):  # one held at the window's end still waits
            return self._reorderer.pass_through(key, item)
        return [item]

    def delay(self, now: float) -> float:
        return self._faults.delay(now)

    def holding(self) -> bool:
        """Whether an item is held back (let go as soon as nothing else waits: `flush`)."""
        return bool(self._reorderer)

    def flush(self) -> list[Item]:
        return self._reorderer.flush()
