"""Old module paths of the code that moved into the family folders, kept importable.

``import selenv.envs.fim_selection`` (and every other path that moved, :data:`MOVED`) still
works: it returns the module at its new place (the same module object, so ``isinstance`` and
monkeypatching keep working) and emits a ``DeprecationWarning`` naming the new path.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType

__all__ = ["MOVED", "install"]

#: old dotted path -> new dotted path
MOVED: dict[str, str] = {
    "selenv.scenarios.fim_selection": "selenv.families.fim.scenario",
    "selenv.scenarios.kirchner_models": "selenv.families.fim.models",
    "selenv.envs.fim_selection": "selenv.families.fim.env",
    "selenv.agents.fim": "selenv.families.fim.agents",
    "selenv.scenarios.landmarks": "selenv.families.landmarks.scenario",
    "selenv.scenarios.landmark_models": "selenv.families.landmarks.models",
    "selenv.scenarios.landmark_flight": "selenv.families.landmarks.flight",
    "selenv.envs.landmark_selection": "selenv.families.landmarks.env",
    "selenv.agents.landmarks": "selenv.families.landmarks.agents",
    "selenv.scenarios.clustering": "selenv.families.clustering.scenario",
    "selenv.scenarios.clustering_filters": "selenv.families.clustering.filters",
    "selenv.scenarios.clustering_labels": "selenv.families.clustering.labels",
    "selenv.scenarios.clustering_regimes": "selenv.families.clustering.regimes",
    "selenv.envs.receiver_clustering": "selenv.families.clustering.env",
    "selenv.agents.clustering": "selenv.families.clustering.agents",
    "selenv.agents.clustering_ga": "selenv.families.clustering.ga",
    "selenv.agents.clustering_rollout": "selenv.families.clustering.rollout",
    "selenv.scenarios.cooperative": "selenv.families.cooperative.scenario",
    "selenv.scenarios.cooperative_models": "selenv.families.cooperative.models",
    "selenv.envs.cl_scheduling": "selenv.families.cooperative.env",
    "selenv.agents.cl": "selenv.families.cooperative.agents",
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old path of :data:`MOVED` to the module at its new path."""

    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        new = MOVED[spec.name]
        warnings.warn(
            f"{spec.name} moved to {new}; import it from there",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(new)

    def exec_module(self, module: ModuleType) -> None:
        """Nothing to run: the module was imported at its new path."""


_FINDER = _MovedModuleFinder()


def install() -> None:
    """Put the finder on ``sys.meta_path`` (once)."""
    if _FINDER not in sys.meta_path:
        sys.meta_path.append(_FINDER)
