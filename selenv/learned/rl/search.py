"""Deprecated path of :mod:`selenv.learned.families.landmarks`, removed in the next release.

Importing it warns (``DeprecationWarning``) and re-exports the names it held.
"""

from __future__ import annotations

import warnings

from selenv.learned.families.landmarks import (
    LandmarkPolicySearchAgent,
    make_landmark_ppo_search,
)

__all__ = ["LandmarkPolicySearchAgent", "make_landmark_ppo_search"]

warnings.warn(
    "selenv.learned.rl.search is deprecated and removed in the next release; import from "
    "selenv.learned.families.landmarks",
    DeprecationWarning,
    stacklevel=2,
)
