"""The `falconry` command (also `python -m services.launcher`)."""
from __future__ import annotations

import argparse
import logging
import sys

from services.runtime.errors import UsageError
from services.runtime.zenoh_config import PROFILES, ZenohSettings
from services.simulator.scenario import ScenarioError


class CliError(UsageError):
    """A user mistake: reported as one line on stderr with exit code 2."""


class Parser(argparse.ArgumentParser):
    """One-line errors (argparse would print the whole usage first)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def add_zenoh_options(parser: argparse.ArgumentParser, embedded_hint: str) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument("--zenoh-profile", choices=PROFILES, default="embedded",
                       help="embedded: loopback peers, multicast off (default); router: client of a zenohd router")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help=f"endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable). {embedded_hint}")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on (repeatable; default for embedded: tcp/127.0.0.1:0)")
    group.add_argument("--zenoh-config", metavar="FILE",
                       help="JSON5 zenoh configuration replacing the profile's base (also: ZENOH_CONFIG env)")
    group.add_argument("--lease-ms", type=int, metavar="MS",
                       help="transport lease; a cut link is noticed after about this long (zenoh default 10000)")


def zenoh_settings(args: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(profile=args.zenoh_profile, connect=list(args.connect), listen=list(args.listen),
                         config_file=args.zenoh_config, lease_ms=args.lease_ms)


def build_parser() -> argparse.ArgumentParser:
    from services.launcher import health_cmd, params_cmd, record_cmd, replay_cmd, run_cmd, sim_cmd

    parser = Parser(
        prog="falconry",
        description="Falconry: a team of autonomous LiDAR interceptor UAVs as services over Zenoh.",
        epilog="Run `falconry COMMAND --help` for the options of each command.",
    )
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                        help="log verbosity of this process (default: info)")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    sim_cmd.add_parser(commands)
    run_cmd.add_parser(commands)
    health_cmd.add_parser(commands)
    params_cmd.add_parser(commands)
    record_cmd.add_parser(commands)
    replay_cmd.add_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse itself exits 2 with a one-line usage error
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s.%(msecs)03d %(levelname).1s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return args.handler(args)
    except (UsageError, ScenarioError) as exc:
        print(f"falconry {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


