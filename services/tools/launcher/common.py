"""What every `falconry` command shares: the one-line error parser, user-error type, Zenoh options
and the exit codes' explanation."""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from schemas import keys
from services.lib.runtime import tls
from services.lib.runtime.errors import INTERRUPTED, RUNTIME_FAILURE, USAGE_ERROR, RuntimeFailure, UsageError
from services.lib.runtime.zenoh_config import PROFILES, RETRY_FIRST_S, RETRY_MAX_S, OpenCancelled, ZenohSettings
from services.simulator.scenario import ScenarioError

EXIT_CODES = f"""exit codes:
  0    done (a finished run; a service stopped by SIGTERM or Ctrl-C)
  1    a failed run, or a bug (with a traceback)
  {USAGE_ERROR}    usage error: a bad option, file, parameter or scenario (fix it: a restart
       cannot help)
  {RUNTIME_FAILURE}   runtime failure, e.g. Zenoh unreachable after --connect-timeout (EX_TEMPFAIL):
       restart me, with back-off
  {INTERRUPTED}  interrupted (Ctrl-C)"""
FOREVER = object()  # add_zenoh_options(connect_timeout=FOREVER): keep trying by default
LOG_LEVELS = ("debug", "info", "warning", "error")


class CliError(UsageError):
    """A user mistake: reported as one line on stderr with exit code 2 (USAGE_ERROR)."""


class _Formatter(argparse.HelpFormatter):
    """A text written on several lines (the exit-code table) keeps its lines; one-line texts are wrapped."""

    def _fill_text(self, text, width, indent):
        if "\n" in text:
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)


class Parser(argparse.ArgumentParser):
    """One-line errors (argparse would print the whole usage first)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(USAGE_ERROR, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def add_log_level(parser: argparse.ArgumentParser, default) -> None:
    parser.add_argument("--log-level", default=default, choices=LOG_LEVELS,
                        help="log verbosity of this process (default: info); before or after the command")


def execute(args: argparse.Namespace) -> int:
    """Run a parsed command with its log level; a user error or a runtime failure is one line on
    stderr and its exit code (EXIT_CODES)."""
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s.%(msecs)03d %(levelname).1s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return args.handler(args)
    except (UsageError, ScenarioError) as exc:
        print(f"falconry {args.command}: error: {exc}", file=sys.stderr)
        return UsageError.exit_code
    except RuntimeFailure as exc:  # e.g. Zenoh unreachable: one line too, and a code that asks for a restart
        print(f"falconry {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except (KeyboardInterrupt, OpenCancelled):
        return INTERRUPTED


def add_zenoh_options(parser: argparse.ArgumentParser, embedded_hint: str, connect_timeout=None,
                      tls_identity: str | None = tls.GROUND) -> None:
    """connect_timeout: None offers no --connect-timeout (the session waits for ever), FOREVER
    offers it with no limit as default, a number offers it with that default. tls_identity: the
    identity this command presents with --tls (None: derived from SERVICE and --uav)."""
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
    group.add_argument("--no-gossip-connect", dest="gossip_connect", action="store_false",
                       help="connect only to the --connect endpoints, never to peers learnt by gossip (which may "
                            "still connect to this one): `falconry sim` runs its simulator so with per-UAV links")
    if connect_timeout is not None:
        default = "keep trying" if connect_timeout is FOREVER else f"{connect_timeout:g}"
        group.add_argument(
            "--connect-timeout", type=float, metavar="S",
            default=None if connect_timeout is FOREVER else connect_timeout,
            help=f"while Zenoh will not open the session (no router answers yet, a listen port is busy) try again "
                 f"after {RETRY_FIRST_S:g} s, doubling to {RETRY_MAX_S:g} s, and after S s of this exit with code "
                 f"{RUNTIME_FAILURE}; 0 = one attempt (default: {default}). An embedded peer opens at once and "
                 f"Zenoh retries its --connect endpoints in the background")
    add_tls_options(group, tls_identity)


def add_tls_options(group, tls_identity: str | None) -> None:
    """--tls DIR (default $FALCONRY_TLS_DIR) and --tls-identity NAME."""
    derived = ("derived from the command: SERVICE --uav U presents U's, the simulator sim's"
               if tls_identity is None else f"{tls_identity}")
    group.add_argument("--tls", metavar="DIR", default=os.environ.get(tls.ENV_DIR) or None,
                       help=f"mutual TLS with the team's certificates in DIR (`falconry certs DIR`): trust only "
                            f"DIR/ca.crt, present DIR/IDENTITY.crt and .key; every endpoint is then tls/HOST:PORT "
                            f"(default: ${tls.ENV_DIR}, empty or unset = plain tcp)")
    group.add_argument("--tls-identity", metavar="NAME", default=tls_identity,
                       help=f"whose certificate to present with --tls: a UAV name, {', '.join(tls.ROLES)} "
                            f"(default: {derived})")


def add_team_options(group, what: str, default: int | None) -> None:
    """--uavs N or --team NAME,NAME,... (one of them): the UAVs of a team, for `team_of`."""
    choice = group.add_mutually_exclusive_group()
    choice.add_argument("--uavs", type=int, metavar="N",
                        help=f"{what}: uav1 to uavN" + (f" (default {default})" if default else ""))
    choice.add_argument("--team", metavar="UAV,UAV,...", help=f"{what}, by name, e.g. uav1,uav2,uav3")


def team_of(args: argparse.Namespace, default: int | None = None) -> list[str] | None:
    """The team --uavs or --team names (else `default` UAVs, or None)."""
    try:
        if args.team is not None:
            return tls.parse_team(args.team)
        count = args.uavs if args.uavs is not None else default
        if count is None:
            return None
        if count < 1:
            raise CliError(f"--uavs must be 1 or more, not {count}")
        return tls.check_team(keys.uav_names(count))
    except tls.TlsError as exc:
        raise CliError(f"--team {args.team}: {exc}") from None


def tls_identity(args: argparse.Namespace) -> str | None:
    """The identity this command presents with --tls (None without --tls)."""
    if not getattr(args, "tls", None):
        return None
    try:
        if args.tls_identity:
            return tls.check_identity(args.tls_identity)
        return tls.identity_for(getattr(args, "service", None), getattr(args, "uav", None))
    except tls.TlsError as exc:
        raise CliError(str(exc)) from None


def zenoh_settings(args: argparse.Namespace) -> ZenohSettings:
    return ZenohSettings(profile=args.zenoh_profile, connect=list(args.connect), listen=list(args.listen),
                         config_file=args.zenoh_config, lease_ms=args.lease_ms,
                         connect_timeout=getattr(args, "connect_timeout", None),
                         gossip_connect=getattr(args, "gossip_connect", True),
                         tls_dir=getattr(args, "tls", None) or None, tls_identity=tls_identity(args))


def stop_on_signals() -> threading.Event:
    """An event Ctrl-C (SIGINT) and SIGTERM (`kill`, compose, systemd) set: a long-running command
    polls it and shuts down cleanly instead of dying in the middle of a write."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop
