"""Which numba kernels a piece of code compiles: a warm-up must leave nothing for the real path."""
from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

from numba.core.registry import CPUDispatcher


def signatures(*modules: ModuleType) -> dict[str, int]:
    """Compiled signatures per kernel of the modules."""
    return {f"{module.__name__}.{name}": len(kernel.signatures) for module in modules
            for name, kernel in vars(module).items() if isinstance(kernel, CPUDispatcher)}


def newly_compiled(modules: tuple[ModuleType, ...], run: Callable[[], object]) -> list[str]:
    """The kernels of `modules` that `run` compiled a signature of."""
    before = signatures(*modules)
    run()
    return sorted(name for name, count in signatures(*modules).items() if count > before[name])
