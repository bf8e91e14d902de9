"""Arrays on the wire: raw little-endian bytes with dtype and shape.

Decoding is zero-copy: msgspec hands the `data` field out as a memoryview into the
received buffer and `to_numpy` wraps it without copying (the result is read-only).
"""
from __future__ import annotations

import math

import msgspec
import numpy as np

# Only fixed-size little-endian numeric types cross the wire, so any language can read them.
ALLOWED_DTYPES = frozenset(
    {"|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f4", "<f8", "|b1"}
)


class Array(msgspec.Struct, frozen=True):
    """An n-dimensional array as raw little-endian bytes (row-major)."""

    dtype: str
    shape: list[int]
    data: memoryview

    def __post_init__(self) -> None:
        if self.dtype not in ALLOWED_DTYPES:
            raise ValueError(f"unsupported array dtype {self.dtype!r}")
        if any(d < 0 for d in self.shape):
            raise ValueError(f"negative array dimension in {self.shape}")
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != expected:
            raise ValueError(
                f"array of shape {self.shape} {self.dtype} needs {expected} bytes, got {len(self.data)}"
            )


def _wire_dtype(dtype: np.dtype) -> np.dtype:
    return dtype.newbyteorder("<") if dtype.byteorder == ">" else dtype


def from_numpy(array: np.ndarray) -> Array:
    """Wrap a numpy array for sending; copies only if it is not contiguous little-endian."""
    array = np.asarray(array)
    wire = _wire_dtype(array.dtype)
    array = np.ascontiguousarray(array, dtype=wire)
    data = memoryview(array).cast("B") if array.size else memoryview(b"")  # cast() rejects empty views
    return Array(dtype=wire.str, shape=list(array.shape), data=data)


def to_numpy(array: Array) -> np.ndarray:
    """A read-only numpy view of a received array (no copy)."""
    return np.frombuffer(array.data, dtype=np.dtype(array.dtype)).reshape(array.shape)


def empty(shape: tuple[int, ...], dtype: str = "<f8") -> Array:
    return from_numpy(np.zeros(shape, dtype=dtype))
