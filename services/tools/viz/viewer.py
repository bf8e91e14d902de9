"""The viewer put together: messages from any source through the scene builder into rerun.

`Viewer.consume` is the one path for live messages and recorded ones alike; the layout (one tab per
UAV) follows the team as it appears in the messages. `convert_recording` turns an MCAP file into
the same recording the live run would have drawn.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

from services.tools.recorder.mcap_io import ReadReport, read_recording
from services.tools.viz.output import RerunOutput
from services.tools.viz.scene import NS, SceneBuilder, ViewParams


@dataclass
class ViewStats:
    messages: int  # messages drawn from
    logged: int  # rerun log calls
    undecodable: int  # payloads (or contents) the builder could not use
    mission_s: float  # the latest mission time drawn
    viewer_problem: str | None = None  # why a live viewer did not take everything (None: it did)


class Viewer:
    def __init__(self, output: RerunOutput, params: ViewParams | None = None,
                 also: Callable[[str, bytes], None] | None = None) -> None:
        self.output = output
        self.builder = SceneBuilder(params)
        self._also = also  # e.g. the run monitor behind a timeline plot

    def consume(self, key: str, payload: bytes, received: int = 0) -> None:
        logs = self.builder.feed(key, payload, received)
        if self.builder.layout_changed:
            self.builder.layout_changed = False
            self.output.layout(sorted(self.builder.uavs))
        self.output.write(logs)
        if self._also is not None:
            self._also(key, payload)

    @property
    def stats(self) -> ViewStats:
        b = self.builder
        return ViewStats(b.messages, self.output.logged, b.decode_errors, b.mission_ns / NS)

    def close(self) -> ViewStats:
        """Draw what the builder still holds back, then finish the outputs."""
        self.output.write(self.builder.finish())
        stats = self.stats
        stats.viewer_problem = self.output.close()
        return stats


def convert_recording(viewer: Viewer, path: str, progress: Callable[[ViewStats, float], None] | None = None,
                      every_s: float = 2.0) -> ReadReport:
    """Draw every message of an MCAP recording (its complete chunks, if it was cut short)."""
    report = ReadReport()
    next_progress = time.monotonic() + every_s
    for message in read_recording(path, report=report):
        viewer.consume(message.key, message.payload, message.log_time)
        if progress is not None and time.monotonic() >= next_progress:
            next_progress += every_s
            progress(viewer.stats, viewer.builder.duration)
    return report
