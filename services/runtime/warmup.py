"""Slow-to-import libraries loaded after a service is up, on its own thread of control.

filterpy (with the scipy it pulls in) takes over a second to import. A service that imports it
at module level is that much later to declare its liveliness token — too late for the
launcher's 2 s restart promise on a loaded machine. Such services import it where they use it
and name it in setup with `Node.import_when_up`: the node imports it on its main thread right
after declaring its token, before it serves its first message.

Not on a thread beside start-up: an import on a second thread while the main thread imports (numba
loads modules as it compiles the warm-up kernels) can hang the process for good on CPython 3.11
(python/cpython#82272, the import lock's deadlock detection itself deadlocking). A classifier
started that way never came up in one fresh-clone `make test`: the simulator waited out its
120 s start-up and the seeded run began without it.
"""
from __future__ import annotations

import importlib


def import_modules(names: tuple[str, ...]) -> None:
    for name in names:
        importlib.import_module(name)
