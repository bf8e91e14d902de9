"""A fully populated instance of any message type, derived from its type annotations so that a
message added to the contract is covered by the round-trip tests without editing them; and a key
that a wildcard subscription matches."""
from __future__ import annotations

import itertools

import msgspec
import msgspec.inspect as mi
import numpy as np

from schemas.arrays import Array, from_numpy


def concrete(key_expr: str) -> str:
    """A key a wildcard subscription matches: uav2's."""
    return key_expr.replace("**", "uav2/x").replace("*", "uav2")


def sample(msg_type: type[msgspec.Struct]) -> msgspec.Struct:
    counter = itertools.count(1)
    return _value(mi.type_info(msg_type), counter)


def _value(info, counter):
    n = next(counter)
    if isinstance(info, mi.StructType):
        if info.cls is Array:
            return from_numpy(np.arange(n, n + 6, dtype=np.float32).reshape(2, 3))
        return info.cls(**{f.name: _value(f.type, counter) for f in info.fields})
    if isinstance(info, mi.IntType):
        return n
    if isinstance(info, mi.FloatType):
        return n + 0.25
    if isinstance(info, mi.StrType):
        return f"text{n}"
    if isinstance(info, mi.BoolType):
        return n % 2 == 0
    if isinstance(info, mi.ListType):
        return [_value(info.item_type, counter), _value(info.item_type, counter)]
    if isinstance(info, mi.TupleType):
        return tuple(_value(t, counter) for t in info.item_types)
    if isinstance(info, mi.DictType):
        return {_value(info.key_type, counter): _value(info.value_type, counter)}
    if isinstance(info, mi.UnionType):
        return _value(next(t for t in info.types if not isinstance(t, mi.NoneType)), counter)
    if isinstance(info, mi.LiteralType):
        return info.values[-1]
    if isinstance(info, mi.MemoryViewType):
        return memoryview(b"payload")
    if isinstance(info, mi.BytesType):
        return b"payload%d" % n
    raise TypeError(f"no sample for {info}")
