"""Public fusion API (CI, DMV, PECMV, LDMV, LPECMV); a re-export of :mod:`selenv.core.fusion`."""

from __future__ import annotations

from selenv.core.fusion import (
    CI_METHODS,
    PECMV_METHODS,
    SURROGATE_HOOK,
    CIResult,
    DMVResult,
    PECMVBatchResult,
    PECMVResult,
    covariance_intersection,
    dmv_cost,
    dmv_omega_batch,
    dmv_update,
    joint_covariance_is_admissible,
    ldmv_update,
    load_surrogate,
    lpecmv_update,
    pecmv_batch,
    pecmv_objective,
    pecmv_update,
)

__all__ = [
    "CI_METHODS",
    "PECMV_METHODS",
    "SURROGATE_HOOK",
    "CIResult",
    "DMVResult",
    "PECMVBatchResult",
    "PECMVResult",
    "covariance_intersection",
    "dmv_cost",
    "dmv_omega_batch",
    "dmv_update",
    "joint_covariance_is_admissible",
    "ldmv_update",
    "load_surrogate",
    "lpecmv_update",
    "pecmv_batch",
    "pecmv_objective",
    "pecmv_update",
]
