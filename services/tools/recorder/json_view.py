"""Any Falconry message as JSON that Foxglove decodes, with the JSON Schema describing it.

msgspec's own JSON and schema (`msgspec.json.encode`, `msgspec.json.schema`) describe a message
exactly, but with constructs Foxglove's JSON decoder refuses: `$ref`/`$defs`, `anyOf` for
optional fields, `prefixItems` for tuples, maps as objects, arrays of arrays; it needs every
property typed, and arrays of scalars or of objects. So the same types map onto that subset:

| msgspec type                         | JSON value                           | JSON Schema                      |
| ------------------------------------ | ------------------------------------ | -------------------------------- |
| Struct (an `Array` too)              | object of its fields                 | object, its fields as properties |
| X or None (a field)                  | the field left out when None         | X's                              |
| int, float, bool, str, Literal       | as is                                | integer, number, boolean, string |
| bytes, memoryview (`Array.data`)     | base64 string                        | string, contentEncoding base64   |
| tuple (Vec3, Quat (w, x, y, z), ...) | array, in the tuple's order          | array with min/maxItems          |
| list of 2- or 3-float tuples         | array of {x, y[, z]}                 | array of objects                 |
| dict[str, V]                         | array of {key, value}                | array of objects                 |

Nothing is required, as in Foxglove's own schemas. JSON has no NaN or infinity: a message
holding one as a number cannot be converted (`json_bytes` says so; the caller counts it).
"""
from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from typing import Any, Callable

import msgspec
import msgspec.inspect as mi

Convert = Callable[[Any], Any]
COORDINATES = "xyz"


@dataclass(frozen=True)
class JsonView:
    """How one message type becomes JSON: its JSON Schema and the conversion of a value."""

    schema: dict
    to_json: Convert


class NotFinite(ValueError):
    """A number is NaN or infinite: JSON cannot carry it."""


def json_bytes(value: Any) -> bytes:
    """Compact JSON; NotFinite where a number is NaN or infinite (json.dumps would write the
    non-JSON `NaN`, msgspec `null`, and neither is the number the schema promises)."""
    try:
        return json.dumps(value, allow_nan=False, separators=(",", ":")).encode()
    except ValueError as exc:
        if "Out of range float" in str(exc):
            raise NotFinite("a number is NaN or infinite (JSON has neither)") from None
        raise


def struct_view(struct_type: type[msgspec.Struct], title: str) -> JsonView:
    """The JSON view of a message type; `title` names its schema (e.g. "falconry.Odometry")."""
    view = _view(mi.type_info(struct_type), struct_type.__name__)
    described = {"title": title, **({"description": struct_type.__doc__.strip()} if struct_type.__doc__ else {})}
    return JsonView({**described, **view.schema}, view.to_json)


def _view(info: mi.Type, where: str) -> JsonView:
    if isinstance(info, mi.StructType):
        return _struct(info, where)
    if isinstance(info, (mi.IntType, mi.FloatType, mi.BoolType, mi.StrType)):
        return _scalar(info)
    if isinstance(info, mi.LiteralType):
        return _literal(info, where)
    if isinstance(info, (mi.BytesType, mi.MemoryViewType)):
        return JsonView({"type": "string", "contentEncoding": "base64"}, base64_text)
    if isinstance(info, mi.TupleType):
        return _tuple(info, where)
    if isinstance(info, mi.ListType):
        return _list(info, where)
    if isinstance(info, mi.DictType):
        return _dict(info, where)
    raise TypeError(f"{where}: {type(info).__name__} has no JSON view (only optional fields may be unions)")


def _struct(info: mi.StructType, where: str) -> JsonView:
    fields: list[tuple[str, str, Convert]] = []
    properties = {}
    for f in info.fields:
        view = _view(_optional_inner(f.type), f"{where}.{f.name}")
        properties[f.encode_name] = view.schema
        fields.append((f.name, f.encode_name, view.to_json))

    def to_json(value: msgspec.Struct) -> dict:
        out = {}
        for name, json_name, convert in fields:
            item = getattr(value, name)
            if item is not None:  # an optional field that is None is left out
                out[json_name] = convert(item)
        return out

    return JsonView({"type": "object", "properties": properties}, to_json)


def _optional_inner(info: mi.Type) -> mi.Type:
    """X for a field typed X | None; the type itself otherwise."""
    if isinstance(info, mi.UnionType):
        inner = [t for t in info.types if not isinstance(t, mi.NoneType)]
        if len(inner) == 1 and len(info.types) == 2:
            return inner[0]
    return info


_SCALARS: dict[type, tuple[str, Convert]] = {
    mi.IntType: ("integer", int), mi.FloatType: ("number", float), mi.BoolType: ("boolean", bool),
    mi.StrType: ("string", str),
}


def _scalar(info: mi.Type) -> JsonView:
    json_type, convert = _SCALARS[type(info)]
    return JsonView({"type": json_type}, convert)


def _literal(info: mi.LiteralType, where: str) -> JsonView:
    if all(isinstance(v, str) for v in info.values):
        return JsonView({"type": "string", "enum": list(info.values)}, str)
    if all(isinstance(v, int) and not isinstance(v, bool) for v in info.values):
        return JsonView({"type": "integer", "enum": list(info.values)}, int)
    raise TypeError(f"{where}: a Literal mixing types has no JSON view")


def base64_text(value: bytes | memoryview) -> str:
    """Bytes as JSON carries them (JSON Schema's contentEncoding base64, Foxglove's bytes)."""
    return base64.b64encode(value).decode("ascii")


def _tuple(info: mi.TupleType, where: str) -> JsonView:
    items = [_view(t, where) for t in info.item_types]
    if not items or any(item.schema != items[0].schema for item in items):
        raise TypeError(f"{where}: only tuples of one item type have a JSON view")
    convert = items[0].to_json
    size = len(items)
    return JsonView({"type": "array", "items": items[0].schema, "minItems": size, "maxItems": size},
                    lambda value: [convert(v) for v in value])


def _list(info: mi.ListType, where: str) -> JsonView:
    if isinstance(info.item_type, mi.TupleType):
        item = _coordinates(info.item_type, where)
    else:
        item = _view(info.item_type, where)
        if item.schema.get("type") == "array":
            raise TypeError(f"{where}: Foxglove cannot show an array of arrays")
    convert = item.to_json
    return JsonView({"type": "array", "items": item.schema}, lambda value: [convert(v) for v in value])


def _coordinates(info: mi.TupleType, where: str) -> JsonView:
    """A point of a polygon, (x, y) or (x, y, z), as {x, y[, z]}: Foxglove shows no array of arrays."""
    size = len(info.item_types)
    if size not in (2, 3) or not all(isinstance(t, mi.FloatType) for t in info.item_types):
        raise TypeError(f"{where}: only lists of 2- or 3-float tuples (points) have a JSON view")
    names = COORDINATES[:size]
    return JsonView({"type": "object", "properties": {name: {"type": "number"} for name in names}},
                    lambda point: {name: float(v) for name, v in zip(names, point)})


def _dict(info: mi.DictType, where: str) -> JsonView:
    if not isinstance(info.key_type, mi.StrType):
        raise TypeError(f"{where}: only maps with string keys have a JSON view")
    value = _view(info.value_type, where)
    convert = value.to_json
    pair = {"type": "object", "properties": {"key": {"type": "string"}, "value": value.schema}}
    return JsonView({"type": "array", "items": pair},
                    lambda mapping: [{"key": k, "value": convert(v)} for k, v in mapping.items()])
