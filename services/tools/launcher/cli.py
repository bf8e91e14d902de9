"""The `falconry` command (also `python -m services.tools.launcher`)."""
from __future__ import annotations

import argparse
import importlib.metadata
import sys

from services.tools.launcher import (analyze_cmd, campaign_cmd, certs_cmd, colors_cmd, completion_cmd, evaluate_cmd,
                               export_cmd, health_cmd, params_cmd, record_cmd, replay_cmd, router_cmd, run_cmd,
                               sim_cmd, units_cmd, view_cmd)
from services.tools.launcher.common import EXIT_CODES, Parser, add_log_level, execute


def version() -> str:
    """This package's version and the Zenoh it speaks (services must share a Zenoh major version)."""
    package, zenoh = (_installed_version(name) for name in ("falconry", "eclipse-zenoh"))
    return f"falconry {package} (eclipse-zenoh {zenoh}, python {sys.version.split()[0]})"


def _installed_version(distribution: str) -> str:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


class VersionAction(argparse.Action):
    """--version, computed when asked for (not each time the parser is built)."""

    def __init__(self, option_strings, dest, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the version of falconry and of the Zenoh it speaks, and exit")

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(version())
        parser.exit()


def subcommand_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every command's parser, nested ones (`colors pick`) included."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += [sub, *subcommand_parsers(sub)]
    return found


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="falconry",
        description="Falconry: a team of autonomous LiDAR interceptor UAVs as services over Zenoh.",
        epilog="Run `falconry COMMAND --help` for the options of each command.\n\n" + EXIT_CODES,
    )
    parser.add_argument("--version", action=VersionAction)
    add_log_level(parser, "info")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    sim_cmd.add_parser(commands)
    run_cmd.add_parser(commands)
    health_cmd.add_parser(commands)
    params_cmd.add_parser(commands)
    record_cmd.add_parser(commands)
    replay_cmd.add_parser(commands)
    export_cmd.add_parser(commands)
    view_cmd.add_parser(commands)
    analyze_cmd.add_parser(commands)
    evaluate_cmd.add_parser(commands)
    colors_cmd.add_parser(commands)
    campaign_cmd.add_parser(commands)
    router_cmd.add_parser(commands)
    certs_cmd.add_parser(commands)
    units_cmd.add_parser(commands)
    completion_cmd.add_parser(commands, build_parser)
    for command in subcommand_parsers(parser):
        # after the command it overrides the one before it; absent, it leaves that one alone
        add_log_level(command, argparse.SUPPRESS)
    return parser


def main(argv: list[str] | None = None) -> int:
    return execute(build_parser().parse_args(argv))  # argparse itself exits 2 with a one-line usage error


