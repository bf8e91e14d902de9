"""Injected clocks. Cores never read time themselves; nodes hand them `clock.now_ns()`.

MissionClock follows the simulator's ticks; WallClock is for onboard runs, where mission
time is the (synchronised) system time; ManualClock is for tests.
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
    def now_ns(self) -> int:
        return time.time_ns()


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
