"""Ask running services for their ServiceHealth over Zenoh."""
from __future__ import annotations

import time

import msgspec

from schemas import keys
from schemas.messages import ServiceHealth

_decoder = msgspec.msgpack.Decoder(ServiceHealth)


def health(session, scope: str, service: str, timeout: float = 2.0) -> ServiceHealth | None:
    for reply in session.get(keys.health(scope, service), timeout=timeout):
        if reply.ok is not None:
            return _decoder.decode(reply.ok.payload.to_bytes())
    return None


def wait_healthy(session, names: list[tuple[str, str]], timeout: float = 30.0) -> dict[tuple[str, str], ServiceHealth]:
    found: dict[tuple[str, str], ServiceHealth] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and len(found) < len(names):
        for scope, service in names:
            if (scope, service) not in found and (h := health(session, scope, service, 0.5)) is not None:
                found[(scope, service)] = h
        time.sleep(0.1)
    missing = [n for n in names if n not in found]
    assert not missing, f"no health answer from {missing}"
    return found
