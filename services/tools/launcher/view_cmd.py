"""`falconry view`: see what every UAV believes, in rerun, live or from a recording.

`falconry view RUN.mcap` converts any MCAP recording (`falconry sim --record`, `falconry record`
on real UAVs) into the same rerun recording a live run draws; `falconry view --connect ENDPOINT`
draws a running system live (what `falconry sim --viz/--rrd` starts for you). The viewer is a
plain subscriber: it never takes part in lockstep and drops scans rather than slow anybody down.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from services.lib.runtime.errors import UsageError
from services.lib.runtime.zenoh_config import init_logging, open_session
from services.tools.launcher.common import FOREVER, CliError, add_zenoh_options, stop_on_signals, zenoh_settings
from services.tools.launcher.monitor import RunMonitor
from services.tools.recorder.mcap_io import is_mcap
from services.tools.viz.settings import WEB_PORT, ViewParams, check_viewer

if TYPE_CHECKING:
    from services.tools.viz.viewer import Viewer, ViewStats

DRAIN_S = 20.0  # after a stop request, at most this long to draw what is still queued


def add_view_options(group, viz_help: str) -> None:
    """--viz, --rrd and --plot, shared with `falconry sim`."""
    group.add_argument("--viz", nargs="?", const="spawn", metavar="MODE",
                       help=f"{viz_help}: 'spawn' (default) opens a native rerun viewer, 'web' serves one to a "
                            f"browser on port {WEB_PORT} (the address to open is printed), or the address of a "
                            "running viewer (rerun+http://HOST:PORT/proxy; start one with `rerun`)")
    group.add_argument("--rrd", metavar="FILE.rrd", help="write the rerun recording to FILE (open it with `rerun FILE`)")
    group.add_argument("--plot", metavar="FILE.png",
                       help="write a PNG timeline of the run: per UAV, state, detections per second and distance "
                            "to the nearest partner, plus every target's detection and destruction")


def check_view_options(args: argparse.Namespace) -> None:
    """Bad viewer modes and unwritable outputs fail before anything starts (one line, exit 2)."""
    try:
        if args.viz is not None:
            check_viewer(args.viz)
    except UsageError as exc:
        raise CliError(str(exc)) from None
    for option, path in (("--rrd", args.rrd), ("--plot", args.plot)):
        if path and Path(path).is_dir():
            raise CliError(f"{option} {path} is a directory: give a file name")
        if path and not Path(path).resolve().parent.is_dir():
            raise CliError(f"{option}: no such directory: {Path(path).resolve().parent}")
    if args.plot and not args.plot.lower().endswith(".png"):
        raise CliError("--plot writes a PNG: give a FILE.png")


def add_parser(commands) -> None:
    p = commands.add_parser(
        "view", help="see a run in rerun: live, or from any MCAP recording",
        description="Draw what every UAV believes — pose and trail, LiDAR scan coloured by label, map voxels, "
                    "detections and tracks with covariance, trajectory, working area, forbidden zones, job "
                    "manager state — with the world, ground truth (marked as such), events and plots of "
                    "detections, track uncertainty, CPU and lag, on the mission-time timeline. From a file: "
                    "`falconry view RUN.mcap --rrd RUN.rrd` (or --viz to watch). Live: `falconry view --connect "
                    "tcp/HOST:PORT --viz web`. Without --rrd or --viz, a native viewer is spawned.",
    )
    p.add_argument("recording", nargs="?", metavar="RECORDING.mcap",
                   help="an MCAP recording to convert (omit it to draw a running system given by --connect)")
    out = p.add_argument_group("output")
    add_view_options(out, "watch in a viewer")
    drawing = p.add_argument_group("what to draw")
    defaults = ViewParams()
    drawing.add_argument("--scan-hz", type=float, default=1.0 / defaults.scan_period, metavar="HZ",
                         help=f"LiDAR scans drawn per second of mission time per UAV (default {1 / defaults.scan_period:g})")
    drawing.add_argument("--scan-points", type=int, default=defaults.scan_points, metavar="N",
                         help=f"at most N points per drawn scan; flying-object and unknown points always "
                              f"(default {defaults.scan_points})")
    drawing.add_argument("--map-hz", type=float, default=1.0 / defaults.map_period, metavar="HZ",
                         help=f"map redraws per second per UAV, changed tiles only (default {1 / defaults.map_period:g})")
    live = p.add_argument_group("live")
    live.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of wall time (live)")
    live.add_argument("--exit-with-parent", action="store_true",
                      help="stop when the launching process dies (falconry sim sets this)")
    live.add_argument("--nice", type=int, default=10, metavar="N",
                      help="run N steps below normal priority, so the services watched get the CPU first "
                           "(default 10; 0 = normal)")
    live.add_argument("--quiet", action="store_true", help="no progress lines")
    add_zenoh_options(p, "Live: give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=FOREVER)
    p.set_defaults(handler=run_view)


def view_params(args: argparse.Namespace) -> ViewParams:
    for option, value in (("--scan-hz", args.scan_hz), ("--map-hz", args.map_hz), ("--scan-points", args.scan_points)):
        if value <= 0:
            raise CliError(f"{option} must be positive")
    return ViewParams(scan_period=1.0 / args.scan_hz, scan_points=args.scan_points, map_period=1.0 / args.map_hz)


def run_view(args: argparse.Namespace) -> int:
    if args.recording and (args.connect or args.listen or args.zenoh_config):
        raise CliError("give either a recording to convert or --connect for a live run, not both")
    if not args.recording and args.zenoh_profile == "embedded" and not (args.connect or args.zenoh_config):
        raise CliError("give a recording (falconry view RUN.mcap) or the run to watch (--connect tcp/HOST:PORT)")
    if args.recording and not Path(args.recording).is_file():
        raise CliError(f"no such recording: {args.recording}")
    if args.recording and not is_mcap(args.recording):
        raise CliError(f"{args.recording} is not an MCAP file (record one with `falconry sim --record` or "
                       f"`falconry record`)")
    if args.duration is not None and args.duration <= 0:
        raise CliError("--duration must be positive")
    if not 0 <= args.nice <= 19:
        raise CliError("--nice takes 0 (normal priority) to 19 (lowest)")
    if args.rrd is None and args.viz is None:
        args.viz = "spawn"
    check_view_options(args)
    params = view_params(args)
    # rerun and scipy load only for this command: every service process starts through this CLI.
    from services.tools.viz.output import RerunOutput
    from services.tools.viz.viewer import Viewer

    name = Path(args.recording).stem if args.recording else "live"
    if not args.recording:
        yield_cpu(args.nice)  # before rerun's and Zenoh's threads start: a thread's niceness is its own
    try:
        output = RerunOutput(rrd=args.rrd, viewer=args.viz, recording_name=name)
    except (OSError, RuntimeError, ValueError) as exc:
        raise CliError(f"cannot open the viewer output: {exc}") from None
    if output.web_address:
        print(f"web viewer: open {output.web_address} in a browser", flush=True)
    monitor = RunMonitor() if args.plot else None
    viewer = Viewer(output, params, also=monitor.handle if monitor else None)
    started = time.monotonic()
    if args.recording:
        _convert(args, viewer)
        if output.web_address:  # the web viewer lives in this process: keep it up until asked to stop
            viewer.output.flush()
            print(f"converted; the web viewer keeps serving on {output.web_address} (Ctrl-C to stop)", flush=True)
            _wait_for_stop()
    else:
        _live(args, viewer)
    stats = viewer.close()
    _report(args, stats, time.monotonic() - started)
    if stats.viewer_problem:
        print(f"falconry view: error: the viewer did not take the whole recording: {stats.viewer_problem}"
              + (f" (the file {args.rrd} is complete)" if args.rrd else ""), file=sys.stderr, flush=True)
    if monitor is not None:
        from services.tools.launcher.plot import plot_timeline  # matplotlib, likewise

        plot_timeline(monitor, args.plot, f"Falconry run: {name}", viewer.builder.duration)
        print(f"timeline plot: {args.plot}", flush=True)
    return 1 if stats.viewer_problem else 0


def _wait_for_stop() -> None:
    stop = stop_on_signals()
    while not stop.wait(0.5):
        pass


def _convert(args: argparse.Namespace, viewer: Viewer) -> None:
    from services.tools.viz.viewer import convert_recording

    def progress(stats: ViewStats, duration: float) -> None:
        if not args.quiet:
            whole = f"/{duration:g}" if duration else ""
            print(f"view: t={stats.mission_s:.1f}{whole} s of mission, {stats.messages} messages", flush=True)

    report = convert_recording(viewer, args.recording, progress)
    if not report.complete:
        print(f"warning: {report.describe(args.recording)}", flush=True)


def _live(args: argparse.Namespace, viewer: Viewer) -> None:
    from services.tools.viz.live import LiveFeed

    stop = stop_on_signals()
    init_logging()
    session = open_session(zenoh_settings(args), wait=stop.wait)
    parent = os.getppid()
    feed = LiveFeed(session)
    started = time.monotonic()
    next_progress = started + 10.0
    try:
        while not stop.is_set():
            item = feed.get(timeout=0.1)
            if item is not None:
                viewer.consume(item.key, item.payload, item.received)
            now = time.monotonic()
            if (args.exit_with_parent and os.getppid() != parent) or \
                    (args.duration is not None and now - started >= args.duration):
                break
            if not args.quiet and now >= next_progress:
                next_progress += 10.0
                s = viewer.stats
                print(f"view: t={s.mission_s:.1f} s of mission, {s.messages} messages, {feed.backlog} queued"
                      + (f", dropped to keep up: {feed.dropped_line()}" if feed.dropped else ""), flush=True)
        feed.close()
        deadline = time.monotonic() + DRAIN_S
        while time.monotonic() < deadline and (item := feed.get(timeout=0.0)) is not None:
            viewer.consume(item.key, item.payload, item.received)
    finally:
        feed.close()
        session.close()
    if feed.dropped:
        print(f"view: dropped to keep up: {feed.dropped_line()}", flush=True)
    if feed.backlog:
        print(f"view: {feed.backlog} messages still queued after {DRAIN_S:g} s of drawing at the end were not drawn",
              flush=True)


def yield_cpu(steps: int) -> None:
    """Lower this process's priority; where the kernel schedules by session (autogroup) and this
    process leads its own session (every process `falconry sim` starts does), lower the session's
    too, since a niceness only counts within it. A viewer started from a terminal leaves the
    terminal's session alone."""
    if steps <= 0:
        return
    try:
        os.nice(steps)
        if os.getsid(0) == os.getpid():  # our own session (falconry sim), not the user's terminal
            Path("/proc/self/autogroup").write_text(str(min(steps, 19)))
    except OSError:
        pass  # not Linux, or no autogroup: the niceness alone


def _report(args: argparse.Namespace, stats: ViewStats, wall_s: float) -> None:
    where = []
    if args.rrd and Path(args.rrd).is_file():
        size = Path(args.rrd).stat().st_size
        per_minute = f", {size / 1e6 / (stats.mission_s / 60):.1f} MB per minute of mission" if stats.mission_s else ""
        where.append(f"{args.rrd} ({size / 1e6:.1f} MB{per_minute})")
    if args.viz:
        where.append(f"viewer {args.viz}")
    print(f"view: drew {stats.messages} messages up to t={stats.mission_s:.1f} s of mission in {wall_s:.1f} s "
          f"({stats.undecodable} unusable) to {' and '.join(where)}", flush=True)
