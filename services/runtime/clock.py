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


def seconds(stamp_ns: int) -> float:
    return stamp_ns / NS


def to_ns(seconds_: float) -> int:
    return int(round(seconds_ * NS))
