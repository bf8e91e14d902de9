"""Injected clocks. Cores never read time themselves; nodes hand them `clock.now_ns()`.

MissionClock follows the simulator's ticks; WallClock is for onboard runs, where mission
time is the (synchronised) system time at start carried on by the monotonic clock; ManualClock
is for tests.
"""
from __future__ import annotations

import time
from typing import Protocol

NS = 1_000_000_000


class Clock(Protocol):
    def now_ns(self) -> int: ...


class MissionClock:
    """Mission time as last announced by the simulator's clock ticks."""

    def __init__(self) -> None:
        self._now = 0

    def now_ns(self) -> int:
        return self._now

    def advance_to(self, stamp_ns: int) -> None:
        self._now = max(self._now, stamp_ns)


class WallClock:
    """Mission time onboard: the system time read once at start, carried on by the monotonic
    clock. A step of the system clock in flight (an NTP correction, a hand-set date) would expire
    every timer at once going forward (forbidden zones, a partner's silence: revenge mode on a
    partner that is flying) and freeze them going back; the monotonic clock never steps (NTP slews
    it like the system clock, so processes started on a synchronised clock stay so; one started
    after a step differs by it, hence deploy/README.md's time-sync.target). `system_step_ns` tells how far
    the system clock has moved against it; `inject_step` moves this process's view of the system
    clock (the `clock_jump` fault)."""

    def __init__(self, system_ns=time.time_ns, monotonic_ns=time.monotonic_ns) -> None:
        self._system_ns = system_ns
        self._monotonic_ns = monotonic_ns
        self._injected_ns = 0
        self._start_system = system_ns()
        self._start_monotonic = monotonic_ns()

    def now_ns(self) -> int:
        return self._start_system + self._monotonic_ns() - self._start_monotonic

    def system_ns(self) -> int:
        return self._system_ns() + self._injected_ns

    def system_step_ns(self) -> int:
        return self.system_ns() - self.now_ns()

    def inject_step(self, seconds_: float) -> None:
        self._injected_ns += int(round(seconds_ * NS))


class ManualClock:
    def __init__(self, start_ns: int = 0) -> None:
        self._now = start_ns

    def now_ns(self) -> int:
        return self._now

    def advance_to(self, stamp_ns: int) -> None:
        self._now = stamp_ns

    def advance(self, seconds: float) -> None:
        self._now += int(round(seconds * NS))


EPOCH_NS = 10**18  # a stamp beyond this is wall-clock time (ns since 1970, ~2001 on), not mission time


class StampOrigin:
    """Mission time of message stamps. A simulated run's stamps are mission time already; stamps of
    `--clock wall` services (a real flight) are system time, and count from the first one seen,
    so a flight's recording reads from t = 0 like a simulated one."""

    def __init__(self) -> None:
        self.origin: int | None = None

    def mission_ns(self, stamp: int) -> int:
        if stamp < EPOCH_NS:
            return max(stamp, 0)
        if self.origin is None:
            self.origin = stamp
        return max(stamp - self.origin, 0)


def seconds(stamp_ns: int) -> float:
    return stamp_ns / NS


def to_ns(seconds_: float) -> int:
    return int(round(seconds_ * NS))
