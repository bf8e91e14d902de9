"""Zenoh configuration profiles.

- embedded: every process is a peer on loopback. One process (the launcher) listens on a
  known port; the others connect to it and listen on an ephemeral loopback port, and gossip
  scouting meshes them directly, so data flows peer to peer. Multicast scouting is off so
  concurrent runs (tests) never see each other.
- router: the process is a client of a zenohd router (compose, onboard).
A JSON5 file (`--zenoh-config` or the ZENOH_CONFIG environment variable) replaces the
profile's base; explicit connect/listen endpoints and the lease are applied on top.
"""
from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from services.runtime.errors import UsageError

PROFILES = ("embedded", "router")
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


class ZenohConfigError(UsageError):
    """A user-supplied Zenoh setting is wrong; the message says which."""


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
        return args


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _insert(config: zenoh.Config, path: str, value) -> None:
    try:
        config.insert_json5(path, json.dumps(value))
    except Exception as exc:  # zenoh raises ZError with the offending value
        raise ZenohConfigError(f"zenoh setting {path}={value!r} rejected: {exc}") from None


def build(settings: ZenohSettings) -> zenoh.Config:
    if settings.profile not in PROFILES:
        raise ZenohConfigError(f"unknown zenoh profile {settings.profile!r} (choose from {', '.join(PROFILES)})")
    config_file = settings.config_file or os.environ.get("ZENOH_CONFIG")
    if config_file:
        path = Path(config_file)
        if not path.is_file():
            raise ZenohConfigError(f"zenoh config file not found: {path}")
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ZenohConfigError(f"zenoh config file {path} is invalid: {exc}") from None
    else:
        config = zenoh.Config()
        if settings.profile == "embedded":
            _insert(config, "mode", "peer")
            _insert(config, "scouting/multicast/enabled", False)
            _insert(config, "listen/endpoints", settings.listen or ["tcp/127.0.0.1:0"])
        else:
            _insert(config, "mode", "client")
            _insert(config, "scouting/multicast/enabled", False)
    if settings.connect:
        _insert(config, "connect/endpoints", settings.connect)
    elif settings.profile == "router" and not config_file:
        _insert(config, "connect/endpoints", [DEFAULT_ROUTER])
    if settings.listen and (config_file or settings.profile != "embedded"):
        _insert(config, "listen/endpoints", settings.listen)
    if settings.shared_memory is not None:
        _insert(config, "transport/shared_memory/enabled", settings.shared_memory)
    if settings.lease_ms:
        _insert(config, "transport/link/tx/lease", settings.lease_ms)
        _insert(config, "transport/link/tx/keep_alive", 4)
    return config


def open_session(settings: ZenohSettings) -> zenoh.Session:
    config = build(settings)
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise ZenohConfigError(f"cannot open zenoh session ({settings.profile}): {exc}") from None


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
