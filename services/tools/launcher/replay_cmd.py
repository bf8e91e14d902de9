"""`falconry replay FILE`: feed a recorded run back, paced or in lockstep."""
from __future__ import annotations

import argparse
from pathlib import Path

from services.lib.runtime.zenoh_config import init_logging, open_session
from services.tools.launcher.common import FOREVER, CliError, add_zenoh_options, stop_on_signals, zenoh_settings
from services.tools.launcher.record_cmd import check_key_exprs
from services.tools.recorder.replay import Replayer, ReplayError
from services.tools.recorder.selection import DEFAULT_REPLAY_KEYS


def add_parser(commands) -> None:
    p = commands.add_parser(
        "replay", help="publish a recording (falconry record) back, e.g. to re-run perception on it",
        description="Publish the recorded messages of FILE again, unchanged, on their original keys. By "
                    "default only the sensor stream and what perception needs is replayed "
                    f"({', '.join(DEFAULT_REPLAY_KEYS)}); the services' own outputs and their "
                    "acknowledgements are not, so the services you run produce them afresh. Without "
                    "--lockstep, messages go out in recorded order, paced by their recorded receive times at "
                    "--rate. With --lockstep the replayer is the clock master, like the simulator: it stands "
                    "in for the recorded publishers of the replayed data, orders the messages by the recorded "
                    "lockstep bookkeeping and waits for every live service to acknowledge each tick, so a "
                    "service sees exactly the inputs of the recorded run, tick by tick. A file cut short by a "
                    "crash replays up to its last complete chunk.",
    )
    p.add_argument("file", metavar="FILE", help="an MCAP file written by `falconry record`")
    p.add_argument("--keys", nargs="+", action="extend", metavar="EXPR",
                   help="key expressions to replay, replacing the default set")
    p.add_argument("--also", nargs="+", action="extend", default=[], metavar="EXPR",
                   help="key expressions to replay on top of the default set (or of --keys), "
                        "e.g. falconry/uav1/map to feed a classifier the recorded map")
    p.add_argument("--lockstep", action="store_true",
                   help="drive the services tick by tick and wait for their acknowledgements (deterministic)")
    p.add_argument("--rate", type=float, default=1.0, metavar="F",
                   help="without --lockstep: replay speed relative to the recording (default 1; 0 = as fast as possible)")
    p.add_argument("--wait-for", action="append", default=[], metavar="UAV/SERVICE[,...]",
                   help="wait until these services are alive before the first message, e.g. uav1/classifier")
    p.add_argument("--wait-timeout", type=float, default=30.0, metavar="S",
                   help="give up when a --wait-for service is not alive after S seconds (default 30)")
    p.add_argument("--progress", type=float, default=5.0, metavar="S",
                   help="print a progress line every S seconds (default 5; 0 = never)")
    add_zenoh_options(p, "Give the hub of the services under test, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=FOREVER)
    p.set_defaults(handler=run_replay)


def run_replay(args: argparse.Namespace) -> int:

    if not Path(args.file).is_file():
        raise CliError(f"no such recording: {args.file}")
    if args.zenoh_profile == "embedded" and not (args.connect or args.listen or args.zenoh_config):
        raise CliError("give the services to feed with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    wait_for = [name.strip() for item in args.wait_for for name in item.split(",") if name.strip()]
    for name in wait_for:
        if name.count("/") != 1:
            raise CliError(f"--wait-for takes UAV/SERVICE names such as uav1/classifier, not {name!r}")
    key_exprs = check_key_exprs(list(dict.fromkeys((args.keys or list(DEFAULT_REPLAY_KEYS)) + args.also)))

    stop = stop_on_signals()
    init_logging()
    session = open_session(zenoh_settings(args), wait=stop.wait)
    try:
        replayer = Replayer(session, args.file, key_exprs, lockstep=args.lockstep, rate=args.rate,
                            wait_for=wait_for, wait_timeout=args.wait_timeout, progress_s=args.progress,
                            say=lambda line: print(line, flush=True), stop=stop)
        mode = "lockstep" if args.lockstep else ("as fast as possible" if args.rate == 0 else f"x{args.rate:g}")
        print(f"replaying {args.file} ({mode}): {' '.join(key_exprs)}", flush=True)
        stats = replayer.run()
    except ReplayError as exc:
        raise CliError(str(exc)) from None
    finally:
        session.close()
    total = sum(stats.published.values())
    lines = [f"replayed {total} messages, {stats.ticks} ticks in {stats.wall_s:.1f} s"
             + (" (stopped early)" if stop.is_set() else "")
             + (f"; {stats.ack_timeouts} acknowledgement timeouts" if stats.ack_timeouts else "")]
    width = max((len(k) for k in stats.published), default=0)
    lines += [f"  {key:<{width}} {count:7d}" for key, count in sorted(stats.published.items())]
    print("\n".join(lines), flush=True)
    return 130 if stop.is_set() else 0
