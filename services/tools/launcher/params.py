"""Service parameters from a TOML file: one table per service, e.g.

    [tracker]
    radius_max = 5.0

Every table is validated against that service's `params_type`; errors name the file,
the table and the field.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

import msgspec

from schemas import keys
from services.lib.runtime.errors import UsageError


class ParamsError(UsageError):
    pass


def read_tables(path: str | Path | None) -> dict[str, dict]:
    if path is None:
        return {}
    path = Path(path)
    if not path.is_file():
        raise ParamsError(f"config file not found: {path}")
    try:
        tables = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ParamsError(f"{path}: not valid TOML: {exc}") from None
    for name, table in tables.items():
        if name not in keys.SERVICES:
            raise ParamsError(f"{path}: unknown table [{name}] (services are {', '.join(keys.SERVICES)})")
        if not isinstance(table, dict):
            raise ParamsError(f"{path}: [{name}] must be a table")
    return tables


def params_for(service: str, params_type: type[msgspec.Struct], path: str | Path | None) -> msgspec.Struct:
    table = read_tables(path).get(service, {})
    try:
        return msgspec.convert(table, params_type)
    except msgspec.ValidationError as exc:
        text = str(exc).replace("`$.", f"`{service}.").replace("`$`", f"`{service}`")
        raise ParamsError(f"{path}: [{service}] {text}") from None
