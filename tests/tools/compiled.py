"""Which numba kernels a piece of code compiles: a warm-up must leave nothing for the real path.

Compiled (or cached) signatures stay in the process, so the check runs in a fresh interpreter
(`in_fresh_interpreter`): in the test process every kernel was long compiled by earlier tests."""
from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from numba.core.registry import CPUDispatcher

REPOSITORY = Path(__file__).resolve().parents[2]


def signatures(*modules: ModuleType) -> dict[str, int]:
    """Compiled signatures per kernel of the modules."""
    return {f"{module.__name__}.{name}": len(kernel.signatures) for module in modules
            for name, kernel in vars(module).items() if isinstance(kernel, CPUDispatcher)}


def newly_compiled(modules: tuple[ModuleType, ...], run: Callable[[], object]) -> list[str]:
    """The kernels of `modules` that `run` compiled (or loaded from the cache) a signature of."""
    before = signatures(*modules)
    run()
    return sorted(name for name, count in signatures(*modules).items() if count > before[name])


def in_fresh_interpreter(function: Callable[[], object]) -> object:
    """A module-level function's JSON-able result, computed in a new Python process."""
    code = (f"import importlib, json; print(json.dumps(getattr(importlib.import_module({function.__module__!r}), "
            f"{function.__name__!r})()))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPOSITORY, timeout=300)
    if result.returncode != 0:
        raise AssertionError(f"{function.__name__} failed in a fresh interpreter:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])
