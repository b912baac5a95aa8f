"""Deprecated path of :mod:`selenv.learned.families.clustering_edits`, removed in the next release.

Importing it warns (``DeprecationWarning``) and re-exports the names of the new module.
Checkpoints that recorded ``selenv.learned.rl.edit_policy.FactorisedEditScorer`` load under
the new name (:func:`selenv.learned.resources.current_class_name`).
"""

from selenv.learned.rl._moved import moved_module

__getattr__, __all__ = moved_module(__name__, "selenv.learned.families.clustering_edits")
