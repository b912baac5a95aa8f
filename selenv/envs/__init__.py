"""What every env shares: action rules, conventions, rendering, candidate views, versions.

The envs themselves live in their family folders (:mod:`selenv.families`), which also registers
the Gymnasium ids; ``ENV_IDS`` and ``ALL_ENV_IDS`` are read from there (kept here for
compatibility).
"""

from __future__ import annotations

from typing import Any

__all__ = ["ALL_ENV_IDS", "ENV_IDS"]


def __getattr__(name: str) -> Any:
    if name in __all__:  # the ids come from the family records (a layer above this one)
        import selenv.families

        return getattr(selenv.families, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
