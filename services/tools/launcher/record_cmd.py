"""`falconry record FILE`: write a run's messages (by default all but the raw camera frames) to an MCAP file."""
from __future__ import annotations

import argparse
import datetime
import os
import time
from collections.abc import Callable

import zenoh

from services.lib.runtime.zenoh_config import init_logging, open_session
from services.tools.launcher.common import FOREVER, CliError, add_zenoh_options, stop_on_signals, zenoh_settings
from services.tools.recorder.mcap_io import CHUNK_SIZE, COMPRESSIONS
from services.tools.recorder.record import DEFAULT_KEYS, SKIPPED_BY_DEFAULT, Recorder, summary_lines


def add_parser(commands) -> None:
    p = commands.add_parser(
        "record", help="record a run's messages to an MCAP file (all but the raw camera frames by default)",
        description="Subscribe to falconry/** (or the given key expressions) and write every message to an "
                    "MCAP file, except by default the raw camera frames (falconry/*/camera, 1.2 MB each; the "
                    "compressed falconry/*/camera_jpeg are kept; name them with --keys to record them): one "
                    "channel per key, the raw msgpack payload as message data, the type's JSON "
                    "Schema per channel, log_time = receive time, publish_time = header.stamp; every --health seconds "
                    "the services' health answers too. Chunks are "
                    "closed every --flush seconds, so a crash loses at most that much; Ctrl-C, SIGTERM or "
                    "--duration finish the file properly. Any MCAP reader opens it (`mcap info FILE`, Foxglove: "
                    "channels, schemas, timing; the payloads are msgpack: `falconry export --format foxglove` converts "
                    "them); replay it with `falconry replay FILE`.",
    )
    p.add_argument("file", metavar="FILE",
                   help="the MCAP file to write (replaced if it exists); {start} in the name becomes the UTC start "
                        "time, e.g. flight-{start}.mcap -> flight-20261125T061502Z.mcap, so a recorder that a "
                        "supervisor restarts starts a new file instead of replacing the last")
    p.add_argument("--keys", nargs="+", action="extend", metavar="EXPR",
                   help=f"key expressions to record (default: {' '.join(DEFAULT_KEYS)} but the raw camera frames "
                        f"{' '.join(SKIPPED_BY_DEFAULT)}; the compressed ones are kept)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of wall time (default: until stopped)")
    p.add_argument("--compression", choices=list(COMPRESSIONS), default="zstd", help="chunk compression (default zstd)")
    p.add_argument("--chunk-size", type=int, default=CHUNK_SIZE, metavar="BYTES",
                   help=f"close a chunk once it holds this much (default {CHUNK_SIZE})")
    p.add_argument("--flush", type=float, default=1.0, metavar="S",
                   help="close the chunk in progress at least every S seconds (default 1)")
    p.add_argument("--health", type=float, default=1.0, metavar="S",
                   help="ask every service for its health (CPU, memory, counters) every S seconds and record the "
                        "answers on falconry/<scope>/health/<service> (default 1; 0 = never)")
    p.add_argument("--progress", type=float, default=5.0, metavar="S",
                   help="print a progress line every S seconds (default 5; 0 = never)")
    add_zenoh_options(p, "Give the run's hub, e.g. --connect tcp/127.0.0.1:PORT (or --listen and let the run connect).", connect_timeout=FOREVER)
    p.set_defaults(handler=run_record)


START_PLACEHOLDER = "{start}"


def recording_path(template: str, start: datetime.datetime, exists: Callable[[str], bool] = os.path.exists) -> str:
    """The file name with {start} replaced by the UTC start time (ISO 8601 basic format: no ':' in
    names); a name taken already (a restart within the same second) gets -2, -3, ... before its
    extension, so a {start} name never replaces a recording."""
    path = template.replace(START_PLACEHOLDER, start.astimezone(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ"))
    if START_PLACEHOLDER not in template:
        return path
    stem, dot, extension = path.rpartition(".") if "." in os.path.basename(path) else (path, "", "")
    candidate, number = path, 1
    while exists(candidate):
        number += 1
        candidate = f"{stem}-{number}{dot}{extension}"
    return candidate


def check_key_exprs(exprs: list[str]) -> list[str]:

    for expr in exprs:
        try:
            zenoh.KeyExpr(expr)
        except Exception:  # zenoh's message names a Rust source file: say it plainly
            raise CliError(f"invalid key expression {expr!r}") from None
    return exprs


def run_record(args: argparse.Namespace) -> int:

    if args.zenoh_profile == "embedded" and not (args.connect or args.listen or args.zenoh_config):
        raise CliError("give the run to record with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    if args.duration is not None and args.duration <= 0:
        raise CliError("--duration must be positive")
    if args.flush <= 0 or args.chunk_size <= 0:
        raise CliError("--flush and --chunk-size must be positive")
    if args.health < 0:
        raise CliError("--health must be 0 (never) or positive")
    key_exprs = check_key_exprs(args.keys or list(DEFAULT_KEYS))
    path = recording_path(args.file, datetime.datetime.now(datetime.timezone.utc))

    stop = stop_on_signals()
    init_logging()
    session = open_session(zenoh_settings(args), wait=stop.wait)
    try:
        try:
            recorder = Recorder(session, path, key_exprs, compression=args.compression,
                                chunk_size=args.chunk_size, flush_s=args.flush, health_s=args.health,
                                skip=() if args.keys else SKIPPED_BY_DEFAULT)
        except OSError as exc:
            raise CliError(f"cannot write {path}: {exc.strerror or exc}") from None
        print(f"recording {' '.join(recorder.key_exprs)} to {path} (Ctrl-C to stop)", flush=True)
        started = time.monotonic()
        next_progress = started + args.progress
        while not stop.wait(0.1):
            now = time.monotonic()
            if args.duration is not None and now - started >= args.duration:
                break
            if args.progress and now >= next_progress:
                next_progress += args.progress
                s = recorder.stats
                print(f"recording: {s.messages} messages, {s.bytes / 1e6:.1f} MB, {len(s.per_key)} keys, "
                      f"{now - started:.0f} s" + (f", {recorder.backlog} queued" if recorder.backlog else ""),
                      flush=True)
        stats = recorder.close()
    finally:
        session.close()
    print("\n".join(summary_lines(path, stats, time.monotonic() - started)), flush=True)
    return 0
