"""Deprecated path of :mod:`selenv.learned.families.landmarks`, removed in the next release.

Importing it warns (``DeprecationWarning``) and re-exports the names of the new module.
"""

from selenv.learned.rl._moved import moved_module

__getattr__, __all__ = moved_module(__name__, "selenv.learned.families.landmarks")
