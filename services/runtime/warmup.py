"""Load slow-to-import libraries beside a service's start-up.

filterpy (with the scipy it pulls in) takes over a second to import. A service that imports it
at module level is that much later to declare its liveliness token — too late for the
launcher's 2 s restart promise on a loaded machine. Such services import it where they use it
and call `preload` in setup, so the import runs on a thread while the node comes up and is
usually done before the first use (which otherwise just waits for it).
"""
from __future__ import annotations

import importlib
import threading


def preload(*modules: str) -> threading.Thread:
    def load() -> None:
        for name in modules:
            importlib.import_module(name)

    thread = threading.Thread(target=load, name="preload", daemon=True)
    thread.start()
    return thread
