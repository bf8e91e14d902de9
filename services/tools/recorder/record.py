"""`Recorder`: every message on the recorded key expressions into an MCAP file.

Zenoh callbacks only queue (key, payload, receive time); one writer thread encodes the file and
closes a chunk at least every `flush_s` seconds, so a crash loses at most that much. The caller
may also feed messages it receives itself (`handle`), e.g. the launcher from its hub session.
Every `health_s` seconds the writer also asks every service for its health and records the
answers on their own keys (falconry/<scope>/health/<service>), so a recording carries CPU and
memory use for the viewer's plots.
The recorder is no lockstep participant (no liveliness token, no acknowledgements): it never
slows a run down except by the CPU it uses.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Any, Iterable

import zenoh

from services.lib.runtime.health import HealthPoller
from services.lib.runtime.zenoh_config import undeclare_all
from services.tools.recorder.mcap_io import CHUNK_SIZE, McapRecordWriter, WriteStats

DEFAULT_KEYS = ("falconry/**",)
# Raw camera frames stay on their UAV (1.2 MB each, 10 a second); a recording keeps the
# compressed stream (falconry/<uav>/camera_jpeg). Name them with --keys to record them anyway.
SKIPPED_BY_DEFAULT = ("falconry/*/camera",)


def without_overlaps(key_exprs: Iterable[str]) -> list[str]:
    """Drop expressions another one already includes, so no message is written twice."""
    kept: list[zenoh.KeyExpr] = []
    for expr in key_exprs:
        ke = zenoh.KeyExpr(expr)  # a bad expression fails here, before any file is created
        if any(k.includes(ke) for k in kept):
            continue
        kept = [k for k in kept if not ke.includes(k)] + [ke]
    return [str(k) for k in kept]


class Recorder:
    def __init__(self, session: zenoh.Session | None, path: str, key_exprs: Iterable[str] = DEFAULT_KEYS,
                 compression: str = "zstd", chunk_size: int = CHUNK_SIZE, flush_s: float = 1.0,
                 health_s: float = 1.0, skip: Iterable[str] = SKIPPED_BY_DEFAULT) -> None:
        self.key_exprs = tuple(without_overlaps(key_exprs))
        self._skip = [zenoh.KeyExpr(e) for e in skip]
        self._skipped: dict[str, bool] = {}
        self.path = str(path)
        self._writer = McapRecordWriter(self.path, self.key_exprs, compression, chunk_size)
        self._flush_s = flush_s
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._received = 0
        self._error: BaseException | None = None
        self._health = None
        if session is not None and health_s > 0:
            self._health = HealthPoller(session, self.handle, period=health_s)
        self._thread = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._thread.start()
        self._subscribers: list[Any] = []
        if session is not None:
            for expr in self.key_exprs:
                self._subscribers.append(session.declare_subscriber(expr, self._on_sample))
        self.started = time.monotonic()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        skipped = self._skipped.get(key)
        if skipped is None:
            skipped = self._skipped[key] = any(e.includes(zenoh.KeyExpr(key)) for e in self._skip)
        if self._error is None and not skipped:  # after a write error (disk full) nothing would drain the queue
            self._queue.put((key, sample.payload.to_bytes(), time.time_ns()))

    def handle(self, key: str, payload: bytes, receive_ns: int | None = None) -> None:
        """Record one message received by the caller (thread-safe)."""
        if self._error is None:  # after a write error (disk full) nothing would drain the queue
            self._queue.put((key, bytes(payload), receive_ns if receive_ns is not None else time.time_ns()))

    @property
    def stats(self) -> WriteStats:
        return self._writer.stats

    @property
    def backlog(self) -> int:
        return self._queue.qsize()

    def _write_loop(self) -> None:
        writer = self._writer
        next_flush = time.monotonic() + self._flush_s
        try:
            while True:
                try:
                    item = self._queue.get(timeout=max(0.0, min(0.2, next_flush - time.monotonic())))
                except queue.Empty:
                    item = ()
                if item is None:
                    break
                if item:
                    writer.write(*item)
                if self._health is not None:
                    self._health.poll()
                if time.monotonic() >= next_flush:
                    writer.flush()
                    next_flush = time.monotonic() + self._flush_s
        except BaseException as exc:  # reported by close(); the file keeps its complete chunks
            self._error = exc

    def close(self) -> WriteStats:
        """Stop receiving, write what is queued, finish the file (summary, footer)."""
        undeclare_all(self._subscribers)
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._writer.close()
        if self._error is not None:
            raise RuntimeError(f"recording to {self.path} failed: {self._error}") from self._error
        return self._writer.stats


def summary_lines(path: str, stats: WriteStats, wall_s: float) -> list[str]:
    lines = [f"recorded {stats.messages} messages ({stats.bytes / 1e6:.1f} MB of payload) on "
             f"{len(stats.per_key)} keys in {wall_s:.1f} s to {path}"]
    width = max((len(k) for k in stats.per_key), default=0)
    lines += [f"  {key:<{width}} {count:7d}" for key, count in sorted(stats.per_key.items())]
    return lines
