"""`falconry health`: ask every reachable service how it is doing."""
from __future__ import annotations

import argparse

import msgspec

from schemas.messages import ServiceHealth
from services.runtime.zenoh_config import init_logging, open_session


def add_parser(commands) -> None:
    from services.launcher.cli import add_zenoh_options

    p = commands.add_parser(
        "health", help="query the health of every running service",
        description="Query falconry/*/health/* and print one line per service: state, uptime, messages "
                    "received/published, payloads dropped as undecodable, handler errors.",
    )
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for answers (default 2)")
    p.add_argument("--json", action="store_true", help="print the answers as JSON lines")
    add_zenoh_options(p, "Give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.")
    p.set_defaults(handler=run_health)


def query_health(session, timeout: float) -> list[ServiceHealth]:
    decoder = msgspec.msgpack.Decoder(ServiceHealth)
    answers = []
    for reply in session.get("falconry/*/health/*", timeout=timeout):
        if reply.ok is not None:
            try:
                answers.append(decoder.decode(reply.ok.payload.to_bytes()))
            except (msgspec.DecodeError, msgspec.ValidationError):
                pass
    return sorted(answers, key=lambda h: (h.uav, h.service))


def run_health(args: argparse.Namespace) -> int:
    from services.launcher.cli import zenoh_settings

    if args.zenoh_profile == "embedded" and not args.connect and not args.zenoh_config:
        from services.launcher.cli import CliError
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
                  f"in {sum(h.received.values()):7d}  out {sum(h.published.values()):7d}  "
                  f"dropped {errors:4d}  handler errors {h.handler_errors}")
    return 0
