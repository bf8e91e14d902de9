"""`falconry params`: every service's parameters with their defaults, as a TOML file
you can edit and pass back with --config."""
from __future__ import annotations

import argparse

import msgspec

from schemas import keys
from services.tools.launcher.common import CliError
from services.tools.registry import node_class


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def render(services: list[str]) -> str:
    blocks = []
    for service in services:
        params_type = node_class(service).params_type
        blocks.extend(_tables(service, params_type()) or [f"[{service}]\n# (no parameters)"])
    return "\n\n".join(blocks) + "\n"


def _tables(name: str, values: msgspec.Struct) -> list[str]:
    """The table of `values` and, after it, one `[name.field]` table per nested parameter struct."""
    lines, nested = [f"[{name}]"], []
    for field in msgspec.structs.fields(type(values)):
        value = getattr(values, field.name)
        if isinstance(value, msgspec.Struct):
            nested.extend(_tables(f"{name}.{field.name}", value))
        else:
            lines.append(f"{field.name} = {_toml_value(value)}")
    return (["\n".join(lines)] if len(lines) > 1 else []) + nested


def add_parser(commands) -> None:
    p = commands.add_parser(
        "params", help="print every service's parameters and defaults (TOML for --config)",
        description="Print the parameters of the named services (default: all) with their default values, "
                    "as TOML tables. Edit and pass the file to `falconry sim --config` or `falconry run --config`.",
    )
    p.add_argument("services", nargs="*", metavar="SERVICE",
                   help="services to show (default: all): " + ", ".join(keys.SERVICES))
    p.set_defaults(handler=run_params)


def run_params(args: argparse.Namespace) -> int:

    unknown = [s for s in args.services if s not in keys.SERVICES]
    if unknown:
        raise CliError(f"unknown service {unknown[0]!r} (choose from {', '.join(keys.SERVICES)})")
    print(render(args.services or list(keys.SERVICES)), end="")
    return 0
