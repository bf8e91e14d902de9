"""What a replay publishes (key filter, default keys) and the per-UAV pipeline order it follows."""
from __future__ import annotations

from typing import Callable, Iterable

import zenoh

from schemas import keys
from services.tools.registry import node_class

# The sensor stream and what perception needs; the faults tell a lockstep service when its
# upstream is silenced on purpose (it must not wait for it then).
DEFAULT_REPLAY_KEYS = (keys.CLOCK, keys.WORLD, keys.FAULTS, "falconry/*/points", "falconry/*/odometry")


class KeyFilter:
    def __init__(self, key_exprs: Iterable[str]) -> None:
        self.exprs = [zenoh.KeyExpr(e) for e in key_exprs]
        self._cache: dict[str, bool] = {}

    def __call__(self, key: str) -> bool:
        hit = self._cache.get(key)
        if hit is None:
            ke = zenoh.KeyExpr(key)
            hit = self._cache[key] = any(e.includes(ke) for e in self.exprs)
        return hit


def pipeline_order(say: Callable[[str], None] = print) -> list[str]:
    """Per-UAV services, each after its upstream services (from the node classes' `upstream`)."""
    upstream: dict[str, tuple[str, ...]] = {}
    for service in keys.UAV_SERVICES + (keys.ORACLE,):
        try:
            upstream[service] = tuple(node_class(service).upstream)
        except Exception as exc:
            if service in keys.UAV_SERVICES:
                say(f"warning: cannot load {service} ({exc}); using the default pipeline order")
                return list(keys.UAV_SERVICES)  # listed upstream first
    depth: dict[str, int] = {}

    def depth_of(service: str, seen: tuple[str, ...] = ()) -> int:
        if service not in depth:
            ups = [u for u in upstream.get(service, ()) if u in upstream and u not in seen]
            depth[service] = 1 + max((depth_of(u, seen + (service,)) for u in ups), default=-1)
        return depth[service]

    return sorted(upstream, key=lambda s: (depth_of(s), keys.SERVICES.index(s)))
