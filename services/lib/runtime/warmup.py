"""Slow-to-import libraries loaded right after a service is up, on its main thread.

filterpy (with the scipy it pulls in) takes over a second to import, scipy.ndimage half a second. A service that imports it
at module level is that much later to declare its liveliness token — too late for the
launcher's 2 s restart promise on a loaded machine. Such services import it where they use it
and name it in setup with `Node.import_when_up`: the node imports it on its main thread right
after declaring its token, before it serves its first message.

Not on a thread beside start-up: an import on a second thread while the main thread imports (numba
loads modules as it compiles the warm-up kernels) can hang the process for good on CPython 3.11
(python/cpython#82272, the import lock's deadlock detection itself deadlocking), and a service
that never declares its token makes a lockstep run start without it.
"""
from __future__ import annotations

import importlib


def import_modules(names: tuple[str, ...]) -> None:
    for name in names:
        importlib.import_module(name)
