"""What every `falconry` command shares: the one-line error parser, user-error type and Zenoh options."""
from __future__ import annotations

import argparse

from services.runtime.errors import UsageError
from services.runtime.zenoh_config import PROFILES, ZenohSettings


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
