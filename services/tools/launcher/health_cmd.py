"""`falconry health`: ask every reachable service how it is doing; with `--service`, say by the
exit status whether the named ones are up (compose health checks, monitoring, scripts)."""
from __future__ import annotations

import argparse
from dataclasses import dataclass

import msgspec

from schemas import keys
from schemas.messages import ServiceHealth
from services.lib.runtime.errors import RuntimeFailure
from services.lib.runtime.health import query_health
from services.lib.runtime.zenoh_config import init_logging, open_session
from services.tools.launcher.common import CliError, add_zenoh_options, zenoh_settings

HEALTHY_STATE = "running"  # a node is "starting" until its subscriptions and token are declared
UNHEALTHY = 1  # what Docker's HEALTHCHECK (and any script) reads as "not healthy"


@dataclass(frozen=True)
class ServiceName:
    """One service of a run: `uav1/tracker`, or `sim/simulator` (a run-wide service)."""
    scope: str
    service: str

    def __str__(self) -> str:
        return f"{self.scope}/{self.service}"


def parse_service_name(text: str) -> ServiceName:
    scope, slash, service = text.partition("/")
    if not slash:
        scope, service = (keys.SIM, text) if text in keys.SIM_SERVICES else ("", text)
    if service not in keys.SERVICES:
        raise CliError(f"--service {text!r}: unknown service {service!r} (choose from {', '.join(keys.SERVICES)})")
    if service in keys.SIM_SERVICES and scope != keys.SIM:
        raise CliError(f"--service {text!r}: {service} is run-wide: give {keys.SIM}/{service}")
    if service not in keys.SIM_SERVICES:
        try:
            keys.check_name(scope, "UAV name")
        except ValueError as exc:
            raise CliError(f"--service {text!r}: {exc}; give UAV/SERVICE, e.g. uav1/{service}") from None
    return ServiceName(scope, service)


def service_name_argument(text: str) -> ServiceName:
    """parse_service_name for argparse, which shows an ArgumentTypeError's own words."""
    try:
        return parse_service_name(text)
    except CliError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix(f"--service {text!r}: ")) from None


def verdicts(wanted: list[ServiceName], answers: list[ServiceHealth]) -> dict[ServiceName, str]:
    """Why each wanted service is not healthy; an empty dict when all are."""
    states = {ServiceName(h.uav, h.service): h.state for h in answers}
    problems = {}
    for name in wanted:
        state = states.get(name)
        if state is None:
            problems[name] = "no answer"
        elif state != HEALTHY_STATE:
            problems[name] = f"state {state}"
    return problems


def add_parser(commands) -> None:
    p = commands.add_parser(
        "health", help="query the health of running services (exit status for health checks)",
        description="Query falconry/*/health/* and print one line per service: state, uptime, CPU share "
                    "since start, resident memory, messages received/published, payloads dropped as undecodable, "
                    f"handler errors. With --service, ask only those and exit 0 when every one answers in state "
                    f"'{HEALTHY_STATE}', {UNHEALTHY} otherwise, a router out of reach included (the compose stack's "
                    f"health check; monitoring, scripts; the onboard systemd units run none); a usage mistake is 2, "
                    f"as for every command.",
    )
    p.add_argument("--service", action="append", default=[], metavar="UAV/SERVICE", type=service_name_argument,
                   help="a service that must be up, e.g. uav1/tracker or sim/simulator (repeatable)")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for answers (default 2)")
    p.add_argument("--json", action="store_true", help="print the answers as JSON lines")
    add_zenoh_options(p, "Give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=0)
    p.set_defaults(handler=run_health)


def run_health(args: argparse.Namespace) -> int:
    if args.zenoh_profile == "embedded" and not args.connect and not args.zenoh_config:
        raise CliError("give the run to ask with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    if not args.timeout > 0:
        raise CliError(f"--timeout must be positive, not {args.timeout:g}")
    init_logging()
    try:
        session = open_session(zenoh_settings(args))
    except RuntimeFailure as exc:
        if not args.service:
            raise
        # a health check's question is "are they up?": a router out of reach says no
        print(f"unhealthy: {exc}")
        return UNHEALTHY
    try:
        key_exprs = [keys.health(name.scope, name.service) for name in args.service] or None
        answers = query_health(session, args.timeout, key_exprs)
    finally:
        session.close()
    for h in answers:
        print(msgspec.json.encode(h).decode() if args.json else describe(h))
    if args.service:
        problems = verdicts(args.service, answers)
        for name, why in problems.items():
            print(f"{str(name):<22} unhealthy: {why}")
        return UNHEALTHY if problems else 0
    if not answers:
        print("no service answered")
        return UNHEALTHY
    return 0


def describe(h: ServiceHealth) -> str:
    errors = sum(h.decode_errors.values())
    return (f"{h.uav + '/' + h.service:<22} {h.state:<9} up {h.uptime:7.1f} s  "
            f"cpu {100 * h.cpu_time / max(h.uptime, 1e-9):5.1f} %  mem {h.memory / 1e6:6.0f} MB  "
            f"in {sum(h.received.values()):7d}  out {sum(h.published.values()):7d}  "
            f"dropped {errors:4d}  handler errors {h.handler_errors}")
