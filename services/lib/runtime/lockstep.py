"""Deterministic lockstep: which received messages a service may process at tick k.

Every publisher numbers its messages per key expression (header.seq). At tick k a
service processes exactly:
- for keys its same-UAV upstream services publish, everything up to the seq that
  upstream's acknowledgement of tick k names (dataflow order inside one tick);
- for every other key, everything up to the seq the simulator's clock tick k names
  (what all services had published when tick k-1 was complete; feedback edges).
Messages beyond those bounds wait for a later tick, so the result does not depend on
how fast messages happen to arrive.

A key across a cut radio link (`begin(..., cut=...)`) is neither waited for nor released while
the cut lasts, whatever the network still delivers in the moment before the link really goes
down: the cut starts on the tick the schedule says. When the link is back, the first message
that gets through says where the key's publisher is; what it sent before is gone, as over a real
radio. With the stamp, a message received twice is kept once, and one overtaken on the way goes
back before the newer one (`hold`). Pure logic: no Zenoh, no clocks.

The clock master's side (the simulator, or replay standing in for it) is `TickLedger`, its book
of the live services and their acknowledgements, and `await_acks`, its wait for a tick's.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Callable, Generic, Hashable, Iterable, TypeVar

from schemas import keys

Item = TypeVar("Item")

# How long the lockstep master (the simulator, or replay standing in for it) waits for a live
# service's acknowledgement of a tick before it goes on without it. Going on makes the run another
# than its seed's, so the wait is long: a service compiling its kernels on a loaded machine (a cold
# numba cache) can be busy for many seconds, and must not change the run. A service that is gone
# (its token vanished) or frozen by a fault is not waited for at all.
TICK_RESEND_S = 0.5  # a tick nobody acknowledged is sent again (a service may have joined late)
ACK_WAIT_S = 30.0
# A service waits for an upstream that is still working on the tick (its acknowledgement missing)
# as long as the master would, and at most INPUT_WAIT_S: longer than the master's wait, so the
# master alone decides when a tick goes on without someone (its next tick ends this wait). A
# message the tick names has been published already; one that has not come MESSAGE_WAIT_S after
# the last missing acknowledgement did is lost on the way (a publisher whose session dropped and
# came back, e.g. after a freeze longer than the lease) and is not waited for any longer.
INPUT_WAIT_S = 2 * ACK_WAIT_S
MESSAGE_WAIT_S = 5.0


class LockstepGate(Generic[Item]):
    def __init__(
        self,
        upstream: Iterable[str],
        wants: Callable[[str], bool],
        order: Callable[[str], Hashable] = lambda key: key,
        joining: bool = True,
    ) -> None:
        self.upstream = tuple(upstream)
        self._wants = wants
        self._order = order
        self.step: int | None = None
        self._clock_bounds: dict[str, int] = {}
        self._wanted_clock_bounds: dict[str, int] = {}
        self._acks: dict[str, dict[int, dict[str, int]]] = {}
        self._fifo: dict[str, deque[tuple[int, int | None, Item]]] = {}
        self._released: dict[str, int] = {}
        self._released_mark: dict[str, tuple[int, int]] = {}  # key -> (seq, stamp) of the last released
        # Per key, the bound in force when we (re)joined: messages up to it were sent before we
        # could receive them, so no later tick waits for them either.
        self._floor: dict[str, int] = {}
        # A service joining a run already under way (started late, restarted, or back after
        # missing ticks) cannot have what was sent before: its first tick waits for nothing.
        self.joining = joining
        self._counted = True  # whether the master counted us as there when it sent this tick
        self._cut: Callable[[str], bool] = _never
        self._reconnecting: set[str] = set()  # keys whose link is back but nothing came through yet

    # -- inputs -------------------------------------------------------------
    def hold(self, key: str, seq: int, item: Item, stamp: int | None = None) -> bool:
        """Keep a received message for the tick it belongs to. With its `stamp`, a duplicate (the
        same seq and stamp again) is dropped, a message overtaken in transit (a lower seq and no
        later stamp than one held) goes back before it, and one whose successor was released
        already is too late and dropped. False when dropped. (A restarted publisher counts from 1
        again, but its stamps are later: its messages are news, not stragglers.)"""
        fifo = self._fifo.setdefault(key, deque())
        if stamp is not None:
            last = self._released_mark.get(key)
            if last is not None and seq <= last[0] and stamp <= last[1]:
                return False
            if any(s == seq and t == stamp for s, t, _ in fifo):
                return False
        if key in self._reconnecting and not self._cut(key):
            self._reconnecting.discard(key)  # the first message over the restored link
            self._floor[key] = seq - 1
        if seq < self._floor.get(key, 0) and not fifo:
            del self._floor[key]  # its publisher restarted: the new numbers are all news to us
        at = len(fifo)
        while stamp is not None and at > 0 and fifo[at - 1][0] > seq and fifo[at - 1][1] is not None \
                and fifo[at - 1][1] >= stamp:
            at -= 1
        fifo.insert(at, (seq, stamp, item))
        return True

    def forget_stamps(self) -> None:
        """The clock's master restarted: its mission time, and every publisher's stamps, may start
        again before what was released."""
        self._released_mark.clear()

    def begin(self, step: int, clock_bounds: dict[str, int], cut: Callable[[str], bool] | None = None,
              counted: bool = True) -> None:
        """Tick `step` with the simulator's bounds; `cut(key)`: the key comes over a radio link
        that is down at this tick; `counted`: the master saw us when it sent the tick (not: we
        came up after the run began, even at step 0, when the master stopped waiting for us)."""
        self.step = step
        self._counted = counted
        self._clock_bounds = clock_bounds
        self.rewant()  # the tick names every key of the run; `missing` is asked after each message
        self._cut = cut or _never
        for key in [k for k in self._fifo if self._cut(k)]:
            self._fifo[key].clear()  # delivered in the moment before the link really went down
            self._reconnecting.add(key)
        for key, bound in clock_bounds.items():
            if self._cut(key):
                self._reconnecting.add(key)
                self._floor[key] = max(self._floor.get(key, 0), bound)

    def rewant(self) -> None:
        """The service's subscriptions changed: which of the tick's keys it waits for, again."""
        self._wanted_clock_bounds = {key: bound for key, bound in self._clock_bounds.items() if self._wants(key)}

    def recut(self, cut: Callable[[str], bool]) -> None:
        """A radio fault came in during the tick: the keys it parts from now on (what `begin`
        already let through stays)."""
        self._cut = cut

    def rejoin(self) -> None:
        self.joining = True

    def record_ack(self, service: str, step: int, published: dict[str, int]) -> None:
        acks = self._acks.setdefault(service, {})
        acks[step] = published
        for old in [s for s in acks if s < step - 2]:
            del acks[old]

    # -- decisions ----------------------------------------------------------
    def bounds(self, alive_upstream: set[str]) -> dict[str, int]:
        bounds = dict(self._clock_bounds)
        for service in self.upstream:
            if service in alive_upstream:
                bounds.update(self._acks.get(service, {}).get(self.step, {}))
        return bounds

    def _wanted_bounds(self, alive_upstream: set[str]) -> dict[str, int]:
        """`bounds`, of the keys this service wants only."""
        bounds = dict(self._wanted_clock_bounds)
        for service in self.upstream:
            if service in alive_upstream:
                for key, bound in self._acks.get(service, {}).get(self.step, {}).items():
                    if self._wants(key):
                        bounds[key] = bound
        return bounds

    def missing(self, alive_upstream: set[str]) -> list[str]:
        """What tick `step` still waits for; empty when it can be processed."""
        if self.step is None:
            return ["clock tick"]
        if self._joins_late():
            self._floor.update(self.bounds(alive_upstream))
            return []
        waits = [
            f"ack of {service}"
            for service in self.upstream
            if service in alive_upstream and self.step not in self._acks.get(service, {})
        ]
        for key, bound in self._wanted_bounds(alive_upstream).items():
            if bound == 0 or key in self._reconnecting:
                continue
            # bound == released: nothing new. A bound *below* what we released means the
            # publisher restarted and counts from 1 again: its message `bound` is a new one.
            if bound == self._released.get(key, 0) or bound <= self._floor.get(key, 0):
                continue
            if not any(seq == bound for seq, _, _ in self._fifo.get(key, ())):
                waits.append(f"{key}#{bound}")
        return waits

    def give_up(self, alive_upstream: set[str]) -> None:
        """The messages tick `step` still waits for are lost on the way: no later tick waits for
        them (one that comes after all is released with the tick it comes in)."""
        for key, bound in self.bounds(alive_upstream).items():
            if self._wants(key) and bound and not any(seq == bound for seq, _, _ in self._fifo.get(key, ())):
                self._floor[key] = max(self._floor.get(key, 0), bound)

    def awaiting_upstream(self, alive_upstream: set[str]) -> bool:
        """Whether a live upstream service has yet to acknowledge tick `step` (it is still working
        on it), as against only messages still on their way."""
        return self.step is not None and not self._joins_late() and any(
            service in alive_upstream and self.step not in self._acks.get(service, {}) for service in self.upstream)

    def _joins_late(self) -> bool:
        """Joining a run under way: at step 0 only when the master began without us (at step 0
        everyone it counted was there from the start)."""
        return self.joining and (self.step > 0 or not self._counted)

    def release(self, alive_upstream: set[str]) -> list[tuple[str, Item]]:
        """Pop the messages that belong to this tick, in a deterministic order."""
        bounds = self.bounds(alive_upstream)
        out: list[tuple[str, Item]] = []
        for key in sorted(self._fifo, key=self._order):
            fifo = self._fifo[key]
            bound = bounds.get(key)
            if self._cut(key):
                fifo.clear()
                continue
            if bound is None:  # not from a lockstep participant: nothing to wait for
                take = len(fifo)
            else:
                take = 0
                for i, (seq, _, _) in enumerate(fifo):
                    if seq == bound:
                        take = i + 1  # a restarted publisher counts from 1 again
                if take == 0:
                    while take < len(fifo) and fifo[take][0] <= bound:
                        take += 1
            for _ in range(take):
                seq, stamp, item = fifo.popleft()
                self._released[key] = seq
                if stamp is not None:
                    self._released_mark[key] = (seq, stamp)
                out.append((key, item))
        self.joining = False
        return out


class TickLedger:
    """The lockstep master's book (the simulator's, or replay's standing in for it): which services
    ("<scope>/<service>") are alive, and the newest tick each acknowledged with the sequence numbers
    it had published by then. Thread-safe (replay feeds it from Zenoh's threads while its loop
    reads it); `on_change` is called after every change, e.g. to wake a waiting loop."""

    def __init__(self, on_change: Callable[[], None] = lambda: None) -> None:
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._acks: dict[str, tuple[int, dict[str, int]]] = {}
        self._on_change = on_change

    def seen(self, name: str, alive: bool) -> None:
        """A service's token came (alive) or went: a gone service's acknowledgements go with it."""
        with self._lock:
            if alive:
                self._alive.add(name)
            else:
                self._alive.discard(name)
                self._acks.pop(name, None)
        self._on_change()

    def acknowledged(self, name: str, step: int, published: dict[str, int]) -> None:
        """`name` finished tick `step` having published up to `published` (key -> seq); an older
        acknowledgement overtaken on the way changes nothing."""
        with self._lock:
            old = self._acks.get(name)
            if old is None or step >= old[0]:
                self._acks[name] = (step, published)
        self._on_change()

    def alive(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def waiting(self, step: int, names: Iterable[str]) -> list[str]:
        """Of `names`, the live services that have not acknowledged tick `step` yet (sorted)."""
        with self._lock:
            return sorted(n for n in set(names) if n in self._alive
                          and ((ack := self._acks.get(n)) is None or ack[0] < step))

    def published(self, names: Iterable[str] | None = None) -> dict[str, int]:
        """The sequence numbers the acknowledgements of `names` (all by default) name, merged in
        name order (a key two services both publish takes the later name's)."""
        with self._lock:
            chosen = self._acks.keys() if names is None else set(names) & self._acks.keys()
            merged: dict[str, int] = {}
            for name in sorted(chosen):
                merged.update(self._acks[name][1])
            return merged


def await_acks(ledger: TickLedger, step: int, names: Callable[[], Iterable[str]], pump: Callable[[float], None],
               resend: Callable[[], None], stopping: Callable[[], bool], monotonic: Callable[[], float]) -> list[str]:
    """Wait until every service `names()` lists (asked again each round: a fault may silence one
    meanwhile) has acknowledged tick `step`, sending the tick again every TICK_RESEND_S (a service
    may have joined late) and giving up after ACK_WAIT_S. `pump(s)` waits up to s for news;
`monotonic` is the wall clock the waits are measured on (injected: this module reads no clock).
    Returns the services still waited for when it gave up ([] when all answered, or stopping)."""
    started = monotonic()
    resend_at = started + TICK_RESEND_S
    while not stopping():
        waiting = ledger.waiting(step, names())
        if not waiting:
            return []
        now = monotonic()
        if now - started > ACK_WAIT_S:
            return waiting
        if now > resend_at:
            resend()
            resend_at = now + TICK_RESEND_S
        pump(0.05)
    return []


def _never(key: str) -> bool:
    return False


def _parted(one: str, other: str, down: frozenset[str]) -> bool:
    """Whether UAV scopes `one` and `other` are apart while the radios of `down` are cut: a UAV
    always reaches itself, and the simulator's scope over every UAV's airframe link."""
    return one != other and keys.SIM not in (one, other) and (one in down or other in down)


class FaultWindows:
    """Which services a scheduled fault keeps from acknowledging ticks (killed or frozen), so
    lockstep neither waits for them nor blocks on them, and whose radio link is cut (its
    services still tick over their airframe link, but reach no partner). Times are mission
    seconds."""

    SILENCING = ("kill", "freeze")

    def __init__(self) -> None:
        self._windows: list[tuple[str, str, float, float]] = []  # uav, service ("" = all), start, end
        self._radio: list[tuple[str, float, float]] = []  # uav, start, end of a link_cut

    def add(self, command) -> None:
        start = command.header.stamp / 1e9
        end = start + command.duration if command.duration > 0 else float("inf")
        if command.kind == "link_cut":
            self._radio.append((command.uav, start, end))
        # One killed service is restarted by supervision: liveliness covers its absence.
        elif command.kind in self.SILENCING and not (command.kind == "kill" and command.service):
            self._windows.append((command.uav, command.service, start, end))

    def silencing(self, now: float) -> bool:
        """Whether any service is silenced at `now` (most ticks of most runs: none)."""
        return any(start <= now < end for _, _, start, end in self._windows)

    def silenced(self, uav: str, service: str, now: float) -> bool:
        return any(u == uav and s in ("", service) and start <= now < end
                   for u, s, start, end in self._windows)

    def radios_down(self, now: float) -> frozenset[str]:
        """The UAV scopes whose radio link is cut at `now`."""
        return frozenset(u for u, start, end in self._radio if start <= now < end)

    def parted(self, one: str, other: str, now: float) -> bool:
        """Whether the radio keeps UAV scopes `one` and `other` apart at `now`."""
        return _parted(one, other, self.radios_down(now))

    def cut_off(self, scope: str, now: float) -> Callable[[str], bool]:
        """Whether a key or a "<scope>/<service>" name is parted from `scope` at `now`, the radios
        looked at once for the tick (every service asks it of every key the tick names)."""
        down = self.radios_down(now)
        if not down:
            return _never

        def cut(name: str) -> bool:
            parts = name.split("/")
            return _parted(scope, parts[1] if parts[0] == keys.ROOT and len(parts) > 1 else parts[0], down)
        return cut

    def unaffected(self, names: set[str], now: float) -> set[str]:
        """Of "<uav>/<service>" names, those no fault silences at `now`."""
        if not self.silencing(now):
            return set(names)
        return {n for n in names if not self.silenced(*n.split("/", 1), now)}
