"""Learning code that serves one family lives in ``selenv.learned.families``; the old paths warn.

The modules that moved keep their old import path for one release as a re-export that warns
(``DeprecationWarning`` naming the new module) when imported; names that left a module that
stays are reachable from it with the same warning. The family-independent RL glue names no
family, and the families never import the learned layer.
"""

from __future__ import annotations

import ast
import importlib
import sys
import warnings
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: old module -> (new module, names it re-exports)
MOVED_MODULES = {
    "selenv.learned.rl.cl_scorer": (
        "selenv.learned.families.cooperative",
        ["CLLearnedScorerAgent", "make_cl_cem", "read_scorer", "CHECKPOINT_FORMAT"],
    ),
    "selenv.learned.rl.search": (
        "selenv.learned.families.landmarks",
        ["LandmarkPolicySearchAgent", "make_landmark_ppo_search"],
    ),
    "selenv.learned.rl.edit_policy": (
        "selenv.learned.families.clustering_edits",
        ["FactorisedEditScorer", "EDIT_EXTRACTOR", "load_edit_policy", "scorer_policy_kwargs"],
    ),
}
#: the class path checkpoints recorded before the edit scorer's module moved
OLD_EDIT_EXTRACTOR = "selenv.learned.rl.edit_policy.FactorisedEditScorer"
#: module that stays -> {name that left it: the module holding it now}
MOVED_NAMES = {
    "selenv.learned.rl.expert": {
        "CL_ID": "selenv.learned.families.cooperative",
        "collect_cl_rollout_labels": "selenv.learned.families.cooperative",
        "LANDMARK_ID": "selenv.learned.families.landmarks",
        "LANDMARK_LABELLERS": "selenv.learned.families.landmarks",
        "collect_landmark_rollout_labels": "selenv.learned.families.landmarks",
    },
    "selenv.learned.rl.ranking": {
        "clustering_edit_deltas": "selenv.learned.families.clustering",
        "collect_clustering_ranking": "selenv.learned.families.clustering",
    },
    "selenv.learned.rl.views": {
        "CLView": "selenv.families.cooperative.view",
        "ClusteringEditView": "selenv.families.clustering.view",
    },
}


def _fresh_import(name: str) -> tuple[object, list[warnings.WarningMessage]]:
    """Import ``name`` anew (its import-time warning fires again), recording the warnings."""
    sys.modules.pop(name, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(name)
    return module, caught


@pytest.mark.parametrize("old", sorted(MOVED_MODULES))
def test_an_old_module_path_warns_and_re_exports_the_same_objects(old: str) -> None:
    new, names = MOVED_MODULES[old]
    module, caught = _fresh_import(old)
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert any(old in m and new in m for m in messages), messages
    target = importlib.import_module(new)
    for name in names:
        assert getattr(module, name) is getattr(target, name), name


@pytest.mark.parametrize(
    ("module_name", "name"), [(m, n) for m, ns in MOVED_NAMES.items() for n in ns]
)
def test_a_name_that_left_a_module_warns_and_is_the_moved_object(
    module_name: str, name: str
) -> None:
    module = importlib.import_module(module_name)
    home = MOVED_NAMES[module_name][name]
    with pytest.warns(DeprecationWarning, match=rf"{module_name}\.{name} .* {home}$"):
        value = getattr(module, name)
    assert value is getattr(importlib.import_module(home), name)


@pytest.mark.parametrize("module_name", sorted(MOVED_NAMES))
def test_an_unknown_name_is_still_an_attribute_error(module_name: str) -> None:
    module = importlib.import_module(module_name)
    with pytest.raises(AttributeError, match="no_such_name"):
        module.no_such_name  # noqa: B018
    assert not hasattr(module, "also_missing")


def test_a_checkpoint_recording_the_old_edit_scorer_path_still_loads(tmp_path: Path) -> None:
    from test_untrusted_metadata import _edit_checkpoint  # a small factorised checkpoint

    from selenv.learned.families.clustering_edits import (
        EDIT_EXTRACTOR,
        FactorisedEditScorer,
        is_edit_architecture,
        load_edit_policy,
    )
    from selenv.learned.resources import current_class_name

    def naming(meta: dict[str, Any], extractor: str) -> dict[str, Any]:
        return {**meta, "architecture": {**meta["architecture"], "features_extractor": extractor}}

    assert EDIT_EXTRACTOR == f"{FactorisedEditScorer.__module__}.FactorisedEditScorer"
    assert current_class_name(OLD_EDIT_EXTRACTOR) == EDIT_EXTRACTOR
    assert current_class_name("learned.rl.edit_policy.FactorisedEditScorer") == EDIT_EXTRACTOR
    checkpoint, meta = _edit_checkpoint(tmp_path)
    assert meta["architecture"]["features_extractor"] == EDIT_EXTRACTOR
    old = naming(meta, OLD_EDIT_EXTRACTOR)
    assert is_edit_architecture(old) and is_edit_architecture(meta)
    assert not is_edit_architecture(naming(meta, OLD_EDIT_EXTRACTOR + " "))
    policy = load_edit_policy(checkpoint, old)
    assert isinstance(policy.pi_features_extractor, FactorisedEditScorer)
    with pytest.raises(ValueError, match="features_extractor"):
        load_edit_policy(checkpoint, naming(meta, "selenv.learned.rl.edit_policy.Other"))


def _imported_modules(path: Path) -> set[str]:
    """Every module an ``import`` / ``from ... import`` statement of ``path`` names."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
    return found


#: the family packages (``selenv.families`` itself and its ``spec`` are family-independent)
FAMILY_PACKAGES = sorted(
    p.parent.name for p in (ROOT / "selenv" / "families").glob("*/__init__.py")
)


def _family_imports(modules: set[str]) -> list[str]:
    """The modules of ``modules`` that belong to one family (its folder or its learned module)."""
    prefixes = [
        f"selenv{layer}.families.{f}" for layer in ("", ".learned") for f in FAMILY_PACKAGES
    ]
    return sorted(m for m in modules if any(m == p or m.startswith(p + ".") for p in prefixes))


@pytest.mark.parametrize("name", ["views.py", "expert.py", "ranking.py"])
def test_the_shared_rl_glue_imports_no_family(name: str) -> None:
    assert len(FAMILY_PACKAGES) >= 4
    assert not _family_imports(_imported_modules(ROOT / "selenv" / "learned" / "rl" / name))


def test_the_generic_learned_layer_imports_no_family_code() -> None:
    # selenv/learned/rl and the learned package's own modules sit below the families' learned
    # code (selenv/learned/families): no static import of it (the moved-name shims import
    # lazily, a family architecture is loaded through safe_load.FAMILY_ARCHITECTURES)
    paths = sorted((ROOT / "selenv" / "learned" / "rl").glob("*.py"))
    paths += sorted((ROOT / "selenv" / "learned").glob("*.py"))
    assert len(paths) > 10
    offenders = {
        str(p.relative_to(ROOT)): sorted(
            m for m in _imported_modules(p) if m.startswith("selenv.learned.families")
        )
        for p in paths
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_a_family_architecture_loads_through_the_generic_loader() -> None:
    # the generic loader finds the clustering family's factorised scorer by the fixed table
    from selenv.learned.families.clustering_edits import EDIT_EXTRACTOR, build_edit_policy
    from selenv.learned.rl.safe_load import FAMILY_ARCHITECTURES, build_policy, builder_for

    assert EDIT_EXTRACTOR in FAMILY_ARCHITECTURES
    meta = {"architecture": {"features_extractor": EDIT_EXTRACTOR}}
    assert builder_for(meta) is build_edit_policy
    assert builder_for({"architecture": {"features_extractor": "x.Other"}}) is build_policy
    assert builder_for({}) is build_policy


def test_the_families_never_import_the_learned_layer() -> None:
    offenders = {
        str(path.relative_to(ROOT)): sorted(
            m for m in _imported_modules(path) if m.startswith("selenv.learned")
        )
        for path in sorted((ROOT / "selenv" / "families").rglob("*.py"))
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_the_import_checker_can_fail(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text(
        "from selenv.families.cooperative.view import CLView\nimport selenv.learned\n"
        "from selenv.families.spec import load_attr\nfrom . import sibling\n"
    )
    found = _imported_modules(bad)
    assert found == {"selenv.families.cooperative.view", "selenv.learned", "selenv.families.spec"}
    assert _family_imports(found) == ["selenv.families.cooperative.view"]
