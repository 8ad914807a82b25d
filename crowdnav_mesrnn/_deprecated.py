"""Old import paths of modules and names that moved, kept for one release.

A module that moved leaves a shim at its old path: the shim re-exports the names and calls :func:`warn_moved` when
it is imported. A module that stays but lost names serves them through :func:`moved_attributes` (a module
``__getattr__``). Either way the ``DeprecationWarning`` points at the line that used the old path.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from typing import Any


def warn_moved(old: str, new: str) -> None:
    """Warn that module ``old`` is now ``new``; called at the top level of the shim ``old`` (the warning points
    at the import of the shim, importlib's frames skipped)."""
    warnings.warn(f"{old} moved to {new}: import from {new} instead", DeprecationWarning, stacklevel=3)


def moved_attributes(module: str, moved: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) for ``module``: each name of ``moved`` (name -> the module that now holds
    it, or ``"module:new_name"`` when it was renamed too) is looked up there, with a ``DeprecationWarning`` at every
    use; any other name raises ``AttributeError``."""

    def __getattr__(name: str) -> Any:
        where = moved.get(name)
        if where is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        target, _, new_name = where.partition(":")
        new_name = new_name or name
        warnings.warn(
            f"{module}.{name} moved to {target}.{new_name}: import it from {target} instead",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(target), new_name)

    return __getattr__
