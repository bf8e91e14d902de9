"""`falconry export --format foxglove IN.mcap OUT.mcap`: a recording as JSON Foxglove decodes."""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from services.tools.launcher.common import CliError
from services.tools.recorder.mcap_io import is_mcap

FORMATS = ("foxglove",)


def add_parser(commands) -> None:
    p = commands.add_parser(
        "export", help="convert a recording (falconry record) for another tool: Foxglove",
        description="Convert a recording into an MCAP file Foxglove opens as it is: every message JSON with the "
                    "JSON Schema it follows; LiDAR scans as foxglove.PointCloud, odometry as foxglove.PoseInFrame "
                    "and a FrameTransform per UAV, tracks, detections, ground truth and the world's obstacles as "
                    "foxglove.SceneUpdate, camera JPEGs as foxglove.CompressedImage; every other message as its "
                    "own JSON. Times are the recording's wall-clock receive times; each message's header keeps "
                    "its mission time. A message that cannot be converted is skipped and reported, never lost "
                    "silently. A recording cut short by a crash is exported up to its last complete chunk.",
    )
    p.add_argument("source", metavar="IN.mcap",
                   help="a recording written by `falconry record` or `falconry sim --record`")
    p.add_argument("target", metavar="OUT.mcap", help="the file to write")
    p.add_argument("--format", required=True, choices=FORMATS, help="what to write: foxglove (the only format)")
    p.add_argument("--force", action="store_true", help="replace OUT.mcap if it exists")
    p.add_argument("--progress", type=float, default=5.0, metavar="S",
                   help="print a progress line every S seconds (default 5; 0 = never)")
    p.set_defaults(handler=run_export)


def check_paths(source: Path, target: Path, force: bool) -> None:
    if not source.is_file():
        raise CliError(f"no such recording: {source}")
    if not is_mcap(source):
        raise CliError(f"{source} is not an MCAP file")
    if target.is_dir():
        raise CliError(f"{target} is a directory: give a file name")
    if target.exists() and source.resolve() == target.resolve():
        raise CliError("OUT.mcap is the recording itself: give another file")
    if target.exists() and not force:
        raise CliError(f"{target} exists (add --force to replace it)")
    if not target.parent.is_dir():
        raise CliError(f"no such directory: {target.parent}")


def run_export(args: argparse.Namespace) -> int:
    source, target = Path(args.source), Path(args.target)
    check_paths(source, target, args.force)
    if args.progress < 0:
        raise CliError("--progress must be 0 (never) or positive")
    # imported here: numpy, the Foxglove SDK and the viewer's colours are not needed by the other commands
    from services.tools.viz.foxglove_export import export_recording

    started = time.monotonic()
    next_progress = started + args.progress

    def progress(stats) -> None:
        nonlocal next_progress
        now = time.monotonic()
        if args.progress and now >= next_progress:
            next_progress = now + args.progress
            print(f"exporting: {stats.read} messages read, {stats.skipped_total} skipped, "
                  f"{now - started:.0f} s", flush=True)

    # Written beside the target and renamed when complete: an interrupted export leaves no
    # half-written OUT.mcap, and --force keeps the old one until the new one is whole.
    partial = target.with_name(f".{target.name}.partial")
    try:
        with open(partial, "wb") as file:
            stats = export_recording(str(source), file, progress, source_name=source.name)
        os.replace(partial, target)
    except OSError as exc:
        raise CliError(f"cannot write {target}: {exc.strerror or exc}") from None
    finally:
        partial.unlink(missing_ok=True)
    print("\n".join(summary_lines(source, target, stats, time.monotonic() - started)), flush=True)
    return 0


def summary_lines(source: Path, target: Path, stats, elapsed: float) -> list[str]:
    size = target.stat().st_size / 1e6
    lines = [f"exported {stats.converted} of {stats.read} recorded messages from {source} to {target} "
             f"({size:.1f} MB, {elapsed:.1f} s)"]
    if not stats.source.complete:
        lines.append(f"warning: {stats.source.describe(str(source))}")
    width = max((len(topic) for topic in stats.written), default=0)
    lines += [f"  {topic:<{width}} {count:7d}  {stats.schemas[topic]}"
              for topic, count in sorted(stats.written.items())]
    if stats.skipped:
        lines.append(f"skipped {stats.skipped_total} messages that cannot be converted:")
        lines += [f"  {key} {count:7d}  {reason}" for (key, reason), count in sorted(stats.skipped.items())]
    return lines
