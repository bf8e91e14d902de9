"""`python -m services.tools.launcher.run_service [--log-level L] run SERVICE ...`: `falconry run` (run_cmd.py)
without the other commands. The launcher starts every service of a run this way: a run is about
17 processes, and the full command line's imports (analysis, evaluation, OpenCV, ...) cost each of
them some 0.17 s of CPU before its service even starts."""
from __future__ import annotations

import argparse
import sys

from services.tools.launcher import run_cmd
from services.tools.launcher.common import Parser, add_log_level, execute


def build_parser() -> Parser:
    parser = Parser(prog="falconry", description="One Falconry service in this process (falconry run).")
    add_log_level(parser, "info")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    run_cmd.add_parser(commands)
    add_log_level(commands.choices["run"], argparse.SUPPRESS)  # after the command too, as in falconry
    return parser


def main(argv: list[str] | None = None) -> int:
    return execute(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
