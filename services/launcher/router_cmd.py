"""`falconry router`: a Zenoh router (what zenohd is, without its plugins) for the router
deployment profile, where every service is a client of one router. `falconry sim --zenoh-profile
router` without `--connect` runs one as a child of the run, which a `router_restart` fault kills
and brings back; on a machine with zenohd, use that instead."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

import zenoh

from services.runtime.zenoh_config import (DEFAULT_ROUTER, ZenohUnreachable, check_endpoint, init_logging,
                                           reason)

POLL_S = 0.2


def add_parser(commands) -> None:
    p = commands.add_parser(
        "router", help="run a Zenoh router (the hub of the router profile) until stopped",
        description="Run a Zenoh router on this machine: services started with `--zenoh-profile router "
                    "--connect ENDPOINT` are its clients. It holds no data and may be restarted at any time; "
                    "clients reconnect by themselves. SIGTERM or Ctrl-C stops it.")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on (repeatable; default {DEFAULT_ROUTER})")
    p.add_argument("--exit-with-parent", action="store_true",
                   help="stop when the parent process (the launcher) is gone")
    p.set_defaults(handler=run_router)


def router_config(listen: list[str]) -> zenoh.Config:
    for endpoint in listen:
        check_endpoint(endpoint, listening=True)  # a malformed one is a usage error, not a wait
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", "[" + ", ".join(f'"{e}"' for e in listen) + "]")
    return config


def run_router(args: argparse.Namespace) -> int:
    listen = args.listen or [DEFAULT_ROUTER]
    config = router_config(listen)
    init_logging()
    try:
        session = zenoh.open(config)
    except Exception as exc:  # e.g. the port is busy: worth a restart with back-off
        raise ZenohUnreachable(f"cannot start the router on {', '.join(listen)}: {reason(exc)}") from None
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    parent = os.getppid()
    print(f"zenoh router listening on {', '.join(listen)} (pid {os.getpid()})", file=sys.stderr, flush=True)
    try:
        while not stop.wait(POLL_S):
            if args.exit_with_parent and os.getppid() != parent:
                break
    finally:
        session.close()
    return 0
