"""Which services exist and how to load their node classes."""
from __future__ import annotations

import importlib

from schemas import keys
from services.lib.runtime.node import Node


def node_class(service: str) -> type[Node]:
    if service not in keys.SERVICES:
        raise ValueError(f"unknown service {service!r} (choose from {', '.join(keys.SERVICES)})")
    module = importlib.import_module(f"services.{service}.node")
    return module.NODE
