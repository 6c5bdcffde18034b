"""Package namespaces whose names are imported on first use (PEP 562), so that importing a command line's module
does not import JAX before its arguments are checked:

    __getattr__, __dir__ = lazy_names(__name__, {"gpd_jax.evaluation.driver": ("run_evaluation", "RenderItem")})
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence


def lazy_names(package: str, where: Mapping[str, Sequence[str]],
               submodules: Sequence[str] = ()) -> tuple[Callable, Callable]:
    """(`__getattr__`, `__dir__`) of `package` exporting each module's names and its `submodules`, imported on
    first access."""
    owner = {name: module for module, names in where.items() for name in names}

    def __getattr__(name: str):
        if name in submodules:
            return importlib.import_module(f"{package}.{name}")
        if name not in owner:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(owner[name]), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(owner) | set(submodules))

    return __getattr__, __dir__
