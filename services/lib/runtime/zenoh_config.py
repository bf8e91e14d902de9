"""Zenoh configuration profiles.

- embedded: every process is a peer on loopback. One process (the launcher) listens on a
  known port; the others connect to it and listen on an ephemeral loopback port, and gossip
  scouting meshes them directly, so data flows peer to peer. Multicast scouting is off so
  concurrent runs (tests) never see each other.
- router: the process is a client of a zenohd router (compose, onboard).
A JSON5 file (`--zenoh-config` or the ZENOH_CONFIG environment variable) replaces the
profile's base; explicit connect/listen endpoints and the lease are applied on top.

Opening a session tells a bad setting from an unreachable endpoint. A bad setting (unknown
profile, missing or invalid config file, malformed endpoint) is a ZenohConfigError, a usage
error (exit 2). Zenoh refusing to open an otherwise valid configuration (a client whose router
does not answer yet, a listen port still held by a previous instance) is retried with back-off
(0.5 s doubling to 5 s, one log line per attempt) until `connect_timeout` (None: for ever), then
ZenohUnreachable, a runtime failure (exit 75) that supervisors restart. How Zenoh 1.x behaves
with an endpoint that is down:
- client (router profile): `zenoh.open` fails at once ("Unable to connect to any of [...]";
  connect/timeout_ms is 0 for clients), so the retrying is ours. Once connected, a client whose
  router goes away reconnects by itself when it returns: within CLIENT_RETRY_MAX_MS (Zenoh's
  default back-off grows to 4 s, and every message of the UAV waits on it, its LiDAR's included).
- peer (embedded profile): `zenoh.open` succeeds regardless (connect/exit_on_failure is false
  for peers) and Zenoh itself retries the connect endpoints in the background, every 1 s doubling
  to 4 s (connect/retry); only a listen endpoint that cannot be bound makes it fail.
We do not raise connect/timeout_ms instead: Zenoh would then block inside `open`, where neither
SIGTERM nor Ctrl-C can reach the Python loop.

Mutual TLS (`tls_dir`, services/lib/runtime/tls.py): the session trusts only the team CA in that
directory and presents `tls_identity`'s certificate; every endpoint must then be tls/ (the
defaults become tls/ too), and a missing or unreadable certificate file is a usage error
naming it. The access control itself is the router's (`falconry router --tls`).
"""
from __future__ import annotations

import json
import logging
import os
import re
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zenoh

from services.lib.runtime import tls
from services.lib.runtime.errors import RuntimeFailure, UsageError

PROFILES = ("embedded", "router")
CLIENT_RETRY_FIRST_MS, CLIENT_RETRY_MAX_MS = 250, 1000  # a router profile client's reconnection attempts
DEFAULT_ROUTER = f"tcp/127.0.0.1:{tls.ZENOH_PORT}"
RETRY_FIRST_S = 0.5  # back-off between attempts to open a session: doubling up to RETRY_MAX_S
RETRY_MAX_S = 5.0
# Zenoh 1.x link protocols; an endpoint naming another is a typo, not an endpoint that is down.
LINK_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "serial", "unixsock-stream", "unixpipe", "vsock")
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")

log = logging.getLogger("falconry.zenoh")


class ZenohConfigError(UsageError):
    """A user-supplied Zenoh setting is wrong; the message says which."""


class ZenohUnreachable(RuntimeFailure):
    """Zenoh would not open a session with valid settings (no router answers, a port is busy)
    within the connect timeout: the environment's problem, worth a restart."""


class OpenCancelled(Exception):
    """A stop was requested while waiting for Zenoh (SIGTERM, Ctrl-C, the parent gone)."""


@dataclass
class ZenohSettings:
    profile: str = "embedded"
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config_file: str | None = None
    lease_ms: int | None = None  # shorter leases notice a cut link sooner
    # None keeps Zenoh's default (large local messages go through /dev/shm); a long-lived
    # in-process session such as a test's turns it off, since its segments go only at exit.
    shared_memory: bool | None = None
    # How long to keep trying to open the session before ZenohUnreachable; None: for ever.
    connect_timeout: float | None = None
    # False: open connections only to `connect` endpoints, never to peers learnt by gossip (they
    # may still connect to us). The simulator behind per-UAV airframe links must reach each UAV
    # over its own link only, not over the radio a link_cut takes down.
    gossip_connect: bool = True
    # Mutual TLS: the directory of the team's certificates (None: plain tcp) and whose
    # certificate to present (tls.identity_for; None in a child's settings: the child derives it).
    tls_dir: str | None = None
    tls_identity: str | None = None

    def as_args(self) -> list[str]:
        """Command-line arguments that reproduce these settings in a child process."""
        args = ["--zenoh-profile", self.profile]
        for endpoint in self.connect:
            args += ["--connect", endpoint]
        for endpoint in self.listen:
            args += ["--listen", endpoint]
        if self.config_file:
            args += ["--zenoh-config", self.config_file]
        if self.lease_ms:
            args += ["--lease-ms", str(self.lease_ms)]
        if self.connect_timeout is not None:
            args += ["--connect-timeout", f"{self.connect_timeout:g}"]
        if not self.gossip_connect:
            args += ["--no-gossip-connect"]
        if self.tls_dir:
            args += ["--tls", self.tls_dir]
        if self.tls_identity:
            args += ["--tls-identity", self.tls_identity]
        return args

    def describe(self) -> str:
        """Where this session goes, for log lines: its endpoints, or the config file."""
        where = [f"connect {e}" for e in self.connect] + [f"listen {e}" for e in self.listen]
        if not where:
            config_file = self.config_file or os.environ.get("ZENOH_CONFIG")
            scheme = "tls" if self.tls_dir else "tcp"
            where = [f"config {config_file}" if config_file
                     else f"connect {default_router(self.tls_dir)}" if self.profile == "router"
                     else f"listen {scheme}/127.0.0.1:0"]
        secured = f" (mutual TLS as {self.tls_identity})" if self.tls_dir else ""
        return f"{self.profile}: " + ", ".join(where) + secured


def default_router(tls_dir: str | None = None) -> str:
    """The router a client connects to when none is named: tcp/127.0.0.1:7447, or tls/ with TLS."""
    return DEFAULT_ROUTER.replace("tcp/", "tls/", 1) if tls_dir else DEFAULT_ROUTER


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _insert(config: zenoh.Config, path: str, value) -> None:
    try:
        config.insert_json5(path, json.dumps(value))
    except Exception as exc:  # zenoh raises ZError with the offending value
        raise ZenohConfigError(f"zenoh setting {path}={value!r} rejected: {exc}") from None


def check_endpoint(endpoint: str, listening: bool) -> None:
    """A malformed command-line endpoint is a usage error; Zenoh would only report it as
    'Unable to connect', like an endpoint that is down, and be retried for ever."""
    how = "listen" if listening else "connect"
    protocol, slash, address = endpoint.partition("/")
    if not slash or not protocol or not address:
        raise ZenohConfigError(f"--{how} {endpoint!r}: an endpoint is PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447")
    if protocol not in LINK_PROTOCOLS:
        raise ZenohConfigError(f"--{how} {endpoint!r}: unknown protocol {protocol!r} "
                               f"(zenoh knows {', '.join(LINK_PROTOCOLS)})")
    if protocol in _IP_PROTOCOLS:
        hostport = re.split(r"[?#]", address, maxsplit=1)[0]
        host, colon, port = hostport.rpartition(":")
        lowest = 0 if listening else 1
        if not colon or not host or host in ("[", "[]") or not port.isdigit() or not lowest <= int(port) <= 65535:
            raise ZenohConfigError(f"--{how} {endpoint!r}: give HOST:PORT with a port from {lowest} to 65535, "
                                   f"e.g. {protocol}/127.0.0.1:7447")


def pem_file_problem(path: str | Path) -> str | None:
    """Why Zenoh could not load this certificate or key file, naming it (None: it can): Zenoh
    itself says only that the session would not open, which looks like a router that is down."""
    path = Path(path)
    if not path.exists():
        return f"{path} is missing"
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror}"
    return None if b"-----BEGIN" in head else f"{path} is not a PEM certificate or key"


def load_config_file(path: str | Path) -> zenoh.Config:
    """A JSON5 Zenoh configuration file; a missing or invalid one is a usage error."""
    path = Path(path)
    if not path.is_file():
        raise ZenohConfigError(f"zenoh config file not found: {path}")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:
        raise ZenohConfigError(f"zenoh config file {path} is invalid: {reason(exc)}") from None


def tls_files(tls_dir: str, identity: str | None) -> tls.TlsFiles:
    """The certificate files of `identity` in `tls_dir`, each checked readable (a usage error
    naming the file otherwise)."""
    if not identity:
        raise ZenohConfigError("--tls needs the identity whose certificate to present (--tls-identity)")
    try:
        files = tls.files(tls_dir, tls.check_identity(identity))
    except tls.TlsError as exc:
        raise ZenohConfigError(str(exc)) from None
    if not Path(tls_dir).is_dir():
        raise ZenohConfigError(f"--tls {tls_dir}: no such directory (create the team's certificates with "
                               f"`falconry certs {tls_dir}`)")
    for path in files.all():
        if problem := pem_file_problem(path):
            hint = f" (the {identity} certificate, its key and ca.crt come from `falconry certs`)" \
                if not path.exists() else ""
            raise ZenohConfigError(f"--tls {tls_dir}: {problem}{hint}")
    return files


def check_tls_endpoints(config: zenoh.Config) -> None:
    """With TLS every endpoint is tls/: a tcp/ one would bypass the certificates."""
    mode = json.loads(config.get_json("mode") or '"peer"') or "peer"
    for how in ("connect", "listen"):
        endpoints = json.loads(config.get_json(f"{how}/endpoints") or "[]") or []
        if isinstance(endpoints, dict):  # per mode, e.g. Zenoh's default {router: [...], peer: [...]}
            endpoints = endpoints.get(mode) or []
        for endpoint in endpoints:
            if not tls.endpoint_is_tls(endpoint):
                raise ZenohConfigError(f"{how} endpoint {endpoint!r}: with --tls every endpoint is tls/HOST:PORT, "
                                       f"e.g. {endpoint.replace(endpoint.partition('/')[0], 'tls', 1)}")


def build(settings: ZenohSettings) -> zenoh.Config:
    if settings.profile not in PROFILES:
        raise ZenohConfigError(f"unknown zenoh profile {settings.profile!r} (choose from {', '.join(PROFILES)})")
    config_file = settings.config_file or os.environ.get("ZENOH_CONFIG")
    if config_file:
        config = load_config_file(config_file)
    if settings.connect_timeout is not None and not settings.connect_timeout >= 0:
        raise ZenohConfigError(f"--connect-timeout must be 0 or more seconds, not {settings.connect_timeout:g}")
    for endpoint in settings.connect:
        check_endpoint(endpoint, listening=False)
    for endpoint in settings.listen:
        check_endpoint(endpoint, listening=True)
    files = tls_files(settings.tls_dir, settings.tls_identity) if settings.tls_dir else None
    if not config_file:
        config = zenoh.Config()
        if settings.profile == "embedded":
            _insert(config, "mode", "peer")
            _insert(config, "scouting/multicast/enabled", False)
            _insert(config, "listen/endpoints", settings.listen or [f"{'tls' if files else 'tcp'}/127.0.0.1:0"])
        else:
            _insert(config, "mode", "client")
            _insert(config, "scouting/multicast/enabled", False)
            _insert(config, "connect/retry", {"period_init_ms": CLIENT_RETRY_FIRST_MS,
                                              "period_max_ms": CLIENT_RETRY_MAX_MS, "period_increase_factor": 2})
    if settings.connect:
        _insert(config, "connect/endpoints", settings.connect)
    elif settings.profile == "router" and not config_file:
        _insert(config, "connect/endpoints", [default_router(settings.tls_dir)])
    if settings.listen and (config_file or settings.profile != "embedded"):
        _insert(config, "listen/endpoints", settings.listen)
    if settings.shared_memory is not None:
        _insert(config, "transport/shared_memory/enabled", settings.shared_memory)
    if not settings.gossip_connect:
        _insert(config, "scouting/gossip/autoconnect", {"router": [], "peer": []})
    if settings.lease_ms:
        _insert(config, "transport/link/tx/lease", settings.lease_ms)
        _insert(config, "transport/link/tx/keep_alive", tls.KEEP_ALIVE)
    if files is not None:
        for path, value in tls.session_inserts(files).items():
            _insert(config, path, value)
        check_tls_endpoints(config)
    return config


def reason(exc: BaseException) -> str:
    """Zenoh's error without the Rust source locations it carries."""
    return _RUST_LOCATION.sub("", str(exc)).strip() or type(exc).__name__


def open_session(settings: ZenohSettings, wait: Callable[[float], bool] | None = None,
                 logger: logging.Logger | logging.LoggerAdapter | None = None) -> zenoh.Session:
    """Open a session, retrying with back-off while Zenoh refuses (see the module's doc).

    A bad setting raises ZenohConfigError at once. `wait(seconds)` sleeps between attempts and
    returns True when the caller wants to stop (then OpenCancelled); by default a plain sleep,
    which Ctrl-C interrupts with KeyboardInterrupt. After `settings.connect_timeout` seconds of
    failures (0: one attempt only) it raises ZenohUnreachable."""
    config = build(settings)
    logger = logger or log
    started = time.monotonic()
    delay = RETRY_FIRST_S
    attempt = 0
    while True:
        attempt += 1
        try:
            session = zenoh.open(config)
        except Exception as exc:
            why = reason(exc)
        else:
            if attempt > 1:
                logger.info("zenoh session open (%s) after %d attempts in %.1f s", settings.describe(), attempt,
                            time.monotonic() - started)
            return session
        elapsed = time.monotonic() - started
        if settings.connect_timeout is not None and elapsed + 1e-3 >= settings.connect_timeout:
            tried = f" ({attempt} attempts in {elapsed:.1f} s)" if attempt > 1 else ""
            raise ZenohUnreachable(f"cannot open zenoh session ({settings.describe()}){tried}: {why}")
        pause = delay if settings.connect_timeout is None else min(delay, settings.connect_timeout - elapsed)
        logger.warning("waiting for zenoh (%s): %s; attempt %d, next in %.1f s", settings.describe(), why, attempt,
                       pause)
        if wait is not None:
            if wait(pause):
                raise OpenCancelled()
        else:
            time.sleep(pause)
        delay = min(delay * 2, RETRY_MAX_S)


def undeclare_all(handles: list) -> None:
    """Undeclare subscribers, queryables and publishers on the way out; one that is already gone
    (its session closing) must not keep the others declared."""
    for handle in handles:
        try:
            handle.undeclare()
        except Exception:
            pass
    handles.clear()


_logging_initialised = False


def init_logging(level: str = "error") -> None:
    """Zenoh's own (Rust) log: errors only unless RUST_LOG says otherwise."""
    global _logging_initialised
    if not _logging_initialised:
        zenoh.init_log_from_env_or(level)
        _logging_initialised = True
