"""Deprecated path of :mod:`selenv.learned.families.clustering_edits`, removed in the next release.

Importing it warns (``DeprecationWarning``) and re-exports the names it held. Checkpoints that
recorded ``selenv.learned.rl.edit_policy.FactorisedEditScorer`` load under the new name
(:func:`selenv.learned.resources.current_class_name`).
"""

from __future__ import annotations

import warnings

from selenv.learned.families.clustering_edits import (
    EDIT_EXTRACTOR,
    SCORERS,
    FactorisedEditScorer,
    build_edit_policy,
    edit_model_from_checkpoint,
    edit_policy_spec,
    edit_scorer_parameters,
    is_edit_architecture,
    load_edit_policy,
    scorer_policy_kwargs,
)

__all__ = [
    "EDIT_EXTRACTOR",
    "SCORERS",
    "FactorisedEditScorer",
    "build_edit_policy",
    "edit_model_from_checkpoint",
    "edit_policy_spec",
    "edit_scorer_parameters",
    "is_edit_architecture",
    "load_edit_policy",
    "scorer_policy_kwargs",
]

warnings.warn(
    "selenv.learned.rl.edit_policy is deprecated and removed in the next release; import from "
    "selenv.learned.families.clustering_edits",
    DeprecationWarning,
    stacklevel=2,
)
