"""`falconry health`: ask every reachable service how it is doing."""
from __future__ import annotations

import argparse

import msgspec

from services.launcher.common import CliError, add_zenoh_options, zenoh_settings
from services.runtime.health import query_health
from services.runtime.zenoh_config import init_logging, open_session


def add_parser(commands) -> None:
    p = commands.add_parser(
        "health", help="query the health of every running service",
        description="Query falconry/*/health/* and print one line per service: state, uptime, CPU share "
                    "since start, resident memory, messages received/published, payloads dropped as undecodable, handler errors.",
    )
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for answers (default 2)")
    p.add_argument("--json", action="store_true", help="print the answers as JSON lines")
    add_zenoh_options(p, "Give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=0)
    p.set_defaults(handler=run_health)


def run_health(args: argparse.Namespace) -> int:

    if args.zenoh_profile == "embedded" and not args.connect and not args.zenoh_config:
        raise CliError("give the run to ask with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    init_logging()
    session = open_session(zenoh_settings(args))
    try:
        answers = query_health(session, args.timeout)
    finally:
        session.close()
    if not answers:
        print("no service answered")
        return 1
    for h in answers:
        if args.json:
            print(msgspec.json.encode(h).decode())
        else:
            errors = sum(h.decode_errors.values())
            print(f"{h.uav + '/' + h.service:<22} {h.state:<9} up {h.uptime:7.1f} s  "
                  f"cpu {100 * h.cpu_time / max(h.uptime, 1e-9):5.1f} %  mem {h.memory / 1e6:6.0f} MB  "
                  f"in {sum(h.received.values()):7d}  out {sum(h.published.values()):7d}  "
                  f"dropped {errors:4d}  handler errors {h.handler_errors}")
    return 0
