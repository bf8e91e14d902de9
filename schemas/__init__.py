"""Falconry's message contract: typed msgspec Structs and the key expressions they travel on."""
from schemas import keys, messages
from schemas.arrays import Array, from_numpy, to_numpy
from schemas.messages import *  # noqa: F401,F403 - the contract is the package's public face

__all__ = ["keys", "Array", "from_numpy", "to_numpy"] + [
    name for name in dir(messages) if not name.startswith("_") and name[0].isupper()
]
