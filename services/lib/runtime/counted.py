"""Warnings about refused input that do not flood the log.

A service that drops bad input counts it (in its core) and says so: when a count first moves and
each time it passes a power of ten. Bad input on every scan then costs a handful of log lines,
and the count in each line says how much was lost.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping


class CountedWarnings:
    def __init__(self, log: logging.Logger) -> None:
        self._log = log
        self._next: dict[str, int] = {}  # what -> the count at which to warn again

    def update(self, counts: Mapping[str, int]) -> None:
        """`counts`: what was refused (a phrase) -> how many so far."""
        for what, count in counts.items():
            if count and count >= self._next.get(what, 1):
                self._log.warning("%s so far: %d", what, count)
                self._next[what] = 10 ** len(str(count))
