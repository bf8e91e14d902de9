"""`falconry router`: a Zenoh router (what zenohd is, without its plugins) for the router
deployment profile, where every service is a client of one router. `falconry sim --zenoh-profile
router` without `--connect` runs one as a child of the run, which a `router_restart` fault kills
and brings back; on a machine with zenohd, use that instead.

With `--tls DIR` and the team (`--uavs N` or `--team`) it admits only holders of a certificate of
the team's CA and enforces the team's access control (services/lib/runtime/tls.py); with `--connect`
and `--lease-ms` it serves as a UAV's onboard router peering with its partners' routers."""
from __future__ import annotations

import argparse
import json
import os
import sys

import zenoh

from services.tools.launcher.common import CliError, add_team_options, stop_on_signals, team_of
from services.lib.runtime import tls
from services.lib.runtime.zenoh_config import (ZenohConfigError, ZenohUnreachable, check_endpoint, check_tls_endpoints,
                                           default_router, init_logging, load_config_file, pem_file_problem, reason,
                                           tls_files)

POLL_S = 0.2


def add_parser(commands) -> None:
    p = commands.add_parser(
        "router", help="run a Zenoh router (the hub of the router profile) until stopped",
        description="Run a Zenoh router on this machine: services started with `--zenoh-profile router "
                    "--connect ENDPOINT` are its clients. It holds no data and may be restarted at any time; "
                    "clients reconnect by themselves. With --tls and the team it admits only the team's "
                    "certificates and lets each party publish only its own keys (deploy/README.md, \"Security\"). "
                    "SIGTERM or Ctrl-C stops it.")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on (repeatable; default {default_router()}, with --tls "
                        f"{default_router('tls')})")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another router to peer with, e.g. a partner UAV's tls/uav2.radio:7447 (repeatable); "
                        "one that does not answer is retried for ever, never fatal")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="a zenohd-style JSON5 router configuration, e.g. deploy/onboard/uav1/router.json5 (its "
                        "listen and connect endpoints, lease, TLS and access control); --listen, --connect and "
                        "--lease-ms still apply on top, --tls and the team come from the file")
    p.add_argument("--lease-ms", type=int, metavar="MS",
                   help=f"transport lease: a cut link is noticed after about this long (zenoh default 10000; "
                        f"onboard {tls.ONBOARD_LEASE_MS})")
    security = p.add_argument_group("security")
    security.add_argument("--tls", metavar="DIR", default=None,
                          help=f"mutual TLS with the team's certificates in DIR (`falconry certs DIR`) and the "
                               f"team's access control (needs --uavs or --team); every endpoint is then "
                               f"tls/HOST:PORT (default: ${tls.ENV_DIR}, empty or unset = plain tcp, no access "
                               f"control; not read with --zenoh-config, whose file says it all)")
    security.add_argument("--tls-identity", metavar="NAME", default=tls.ROUTER,
                          help=f"whose certificate this router presents: {tls.ROUTER} (default, a hub that only "
                               f"listens) or, for a UAV's onboard router peering with its partners, that UAV's name")
    add_team_options(security, "the team whose access control the router enforces (with --tls)", default=None)
    p.add_argument("--exit-with-parent", action="store_true",
                   help="stop when the parent process (the launcher) is gone")
    p.set_defaults(handler=run_router)


def check_router_options(listen: list[str], connect: list[str], lease_ms: int | None) -> None:
    """A malformed endpoint or lease is a usage error, not a wait."""
    for endpoint in listen:
        check_endpoint(endpoint, listening=True)
    for endpoint in connect:
        check_endpoint(endpoint, listening=False)
    if lease_ms is not None and lease_ms <= 0:
        raise ZenohConfigError(f"--lease-ms must be positive, not {lease_ms}")


def router_config(listen: list[str], connect: list[str] = (), lease_ms: int | None = None, tls_dir: str | None = None,
                  identity: str = tls.ROUTER, team: list[str] | None = None) -> zenoh.Config:
    check_router_options(listen, connect, lease_ms)
    if (tls_dir is None) != (team is None):
        raise ZenohConfigError("--tls DIR and the team (--uavs N or --team) go together: the access control "
                               "identifies each party by its certificate" if tls_dir is None else
                               "--tls switches on the team's access control: give the team (--uavs N or --team "
                               "uav1,uav2,...)")
    files = tls_files(tls_dir, identity) if tls_dir else None
    try:
        inserts = tls.router_inserts(listen, connect, lease_ms, files, team)
    except tls.TlsError as exc:
        raise ZenohConfigError(str(exc)) from None
    config = zenoh.Config()
    for path, value in inserts.items():
        config.insert_json5(path, json.dumps(value))
    if files is not None:
        check_tls_endpoints(config)
    return config


TLS_FILE_SETTINGS = ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
                     "connect_private_key")


def router_config_from_file(path: str, listen: list[str], connect: list[str], lease_ms: int | None) -> zenoh.Config:
    """A router configuration file with the command line's endpoints and lease on top; a file
    that is not a router's, or that names certificate files Zenoh cannot load, is a usage error
    (Zenoh would refuse to open, and a supervisor would restart it for ever)."""
    config = load_config_file(path)
    mode = json.loads(config.get_json("mode") or "null")
    if mode != "router":
        raise CliError(f"--zenoh-config {path}: mode is {mode!r}, a router's configuration says mode: \"router\"")
    for name in TLS_FILE_SETTINGS:
        file = json.loads(config.get_json(f"transport/link/tls/{name}") or "null")
        if file and (problem := pem_file_problem(file)):
            raise CliError(f"--zenoh-config {path}: {name} cannot be read: {problem} (create the "
                           f"certificates with `falconry certs`, readable by this user)")
    check_router_options(listen, connect, lease_ms)
    inserts = {"listen/endpoints": listen, "connect/endpoints": connect}
    if lease_ms:
        inserts.update({"transport/link/tx/lease": lease_ms, "transport/link/tx/keep_alive": tls.KEEP_ALIVE})
    for key, value in inserts.items():
        if value:
            config.insert_json5(key, json.dumps(value))
    return config


def run_router(args: argparse.Namespace) -> int:
    if args.zenoh_config:
        if args.tls or team_of(args):
            raise CliError("--zenoh-config carries its own TLS and access control: leave out --tls, --uavs and --team")
        return serve(router_config_from_file(args.zenoh_config, args.listen, args.connect, args.lease_ms),
                     f"the configuration {args.zenoh_config}", args.exit_with_parent)
    tls_dir = args.tls or os.environ.get(tls.ENV_DIR) or None
    listen = args.listen or [default_router(tls_dir)]
    team = team_of(args)
    if tls_dir:
        try:
            identity = tls.check_identity(args.tls_identity)
        except tls.TlsError as exc:
            raise CliError(str(exc)) from None
        if identity not in (tls.ROUTER, *(team or [])):
            raise CliError(f"--tls-identity {identity}: a router presents the {tls.ROUTER} certificate or, onboard, "
                           f"that of a UAV of the team")
    else:
        identity = tls.ROUTER
    config = router_config(listen, args.connect, args.lease_ms, tls_dir, identity, team)
    secured = f", mutual TLS as {identity}, access control for {','.join(team)}" if tls_dir else ""
    peers = f", peering with {', '.join(args.connect)}" if args.connect else ""
    return serve(config, f"{', '.join(listen)}{peers}{secured}", args.exit_with_parent)


def serve(config: zenoh.Config, where: str, exit_with_parent: bool) -> int:
    """Run the router until SIGTERM/SIGINT (or the parent's end, when asked)."""
    init_logging()
    try:
        session = zenoh.open(config)
    except Exception as exc:  # e.g. the port is busy: worth a restart with back-off
        raise ZenohUnreachable(f"cannot start the router on {where}: {reason(exc)}") from None
    stop = stop_on_signals()
    parent = os.getppid()
    print(f"zenoh router listening on {where} (pid {os.getpid()})", file=sys.stderr, flush=True)
    try:
        while not stop.wait(POLL_S):
            if exit_with_parent and os.getppid() != parent:
                break
    finally:
        session.close()
    return 0
