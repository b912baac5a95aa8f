"""Names that moved out of a module, kept reachable from it for one release with a warning."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from typing import Any

__all__ = ["moved_attr", "moved_module"]


def moved_attr(module: str, name: str, moved: dict[str, str]) -> Any:
    """``moved[name]``'s attribute ``name``, warning that ``module.name`` is deprecated.

    For a module's ``__getattr__``: ``moved`` maps each name that left ``module`` to the module
    that holds it now; the import happens on first use, so ``module`` does not import it.

    Raises:
        AttributeError: ``name`` is not one of the moved names (the usual message).
    """
    if name not in moved:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    warnings.warn(
        f"{module}.{name} is deprecated and removed in the next release; import it from "
        f"{moved[name]}",
        DeprecationWarning,
        stacklevel=3,
    )
    return getattr(importlib.import_module(moved[name]), name)


def moved_module(old: str, new: str) -> tuple[Callable[[str], Any], list[str]]:
    """For a module that moved: warn that ``old`` is deprecated; its ``__getattr__``, ``__all__``.

    The old module is then a thin re-export of ``new``::

        __getattr__, __all__ = moved_module(__name__, "selenv.learned.families.cooperative")

    The ``DeprecationWarning`` is emitted once, when ``old`` is first imported.
    """
    warnings.warn(
        f"{old} is deprecated and removed in the next release; import from {new}",
        DeprecationWarning,
        stacklevel=3,
    )
    module = importlib.import_module(new)

    def attribute(name: str) -> Any:
        return getattr(module, name)

    return attribute, list(module.__all__)
