"""Service health: what a process reports about itself, and the queries that collect the reports.

Every Node answers `falconry/<scope>/health/<service>` with a ServiceHealth (runtime/node.py).
`query_health` asks once and waits (`falconry health`); `HealthPoller` asks every period without
ever blocking the caller, for the recorder and the viewer, which turn the answers into CPU plots.
"""
from __future__ import annotations

import os
import time
from typing import Callable

import msgspec
import zenoh

from schemas import keys
from schemas.messages import ServiceHealth

ALL_HEALTH = keys.health("*", "*")
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def process_usage() -> tuple[float, int]:
    """(CPU seconds this process used in every thread, resident set size in bytes; 0 if unknown)."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            resident = int(statm.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        resident = 0
    return time.process_time(), resident


def query_health(session: zenoh.Session, timeout: float,
                 key_exprs: list[str] | None = None) -> list[ServiceHealth]:
    """Ask every reachable service once (or those of `key_exprs`); the answers sorted by (scope, service)."""
    decoder = msgspec.msgpack.Decoder(ServiceHealth)
    answers = []
    for key_expr in key_exprs or [ALL_HEALTH]:
        for reply in session.get(key_expr, timeout=timeout):
            if reply.ok is not None:
                try:
                    answers.append(decoder.decode(reply.ok.payload.to_bytes()))
                except (msgspec.DecodeError, msgspec.ValidationError):
                    pass
    return sorted(answers, key=lambda h: (h.uav, h.service))


class HealthPoller:
    """Sends a health query every `period` s of wall time when `poll` is called; every answer goes
    to `on_reply(key, payload, receive_ns)` on a Zenoh thread (so it must only queue)."""

    def __init__(self, session: zenoh.Session, on_reply: Callable[[str, bytes, int], None],
                 period: float = 1.0, timeout: float = 0.8) -> None:
        self._session = session
        self._on_reply = on_reply
        self.period = period
        self._timeout = timeout
        self._next = time.monotonic()

    def _reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._on_reply(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), time.time_ns())

    def poll(self) -> None:
        now = time.monotonic()
        if self.period > 0 and now >= self._next:
            self._next = now + self.period
            try:
                self._session.get(ALL_HEALTH, self._reply, timeout=self._timeout)
            except Exception:
                pass  # a closing session: the next poll (if any) tries again
