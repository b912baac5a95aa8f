"""Fusion with unknown cross-correlation: CI, DMV and PECMV (Chen & Kia 2022, eqs. 3-12).

Agent ``i`` (state ``x_i`` in R^{n_i}, covariance ``P_i``) takes a relative measurement of
agent ``j`` (``P_j``): ``z = h(x_i, x_j) + v``, ``v ~ N(0, R)``, with Jacobians ``H_i`` (m, n_i)
and ``H_j`` (m, n_j). Their cross-covariance is unknown, so a plain Kalman update would be
overconfident. The estimators here:

==================================  =======================================================
:func:`covariance_intersection`     CI of two estimates of the same state (optimal, fast,
                                    improved fast, inverse CI)
:func:`dmv_update`                  DMV, eqs. (4)-(6): Kalman update with the discorrelated
                                    bound ``blkdiag(P_i / w, P_j / (1 - w))``, ``w*`` exact
                                    (cubic for m = 1, Newton on the convex cost otherwise)
:func:`pecmv_update`                PECMV, eqs. (7)-(9): update with the admissible
                                    cross-covariance that maximises ``det P_i+``; closed form
                                    for m = 1, exact reduction to m dimensions for m > 1,
                                    cvxpy/Clarabel reference (``method="sdp"``)
:func:`ldmv_update`,                LDMV / LPECMV (Sec. III): the same updates with ``omega`` /
:func:`lpecmv_update`               ``C`` predicted by a learned surrogate (``selenv/learned/``,
                                    loaded lazily through :data:`SURROGATE_HOOK`)
:func:`dmv_omega_batch`,            vectorised labels ``w*`` / ``C*`` for a dataset (LDMV,
:func:`pecmv_batch`                 LPECMV surrogate training)
:func:`dmv_cost`,                   the objectives of eqs. (6) and (8a), and the
:func:`pecmv_objective`,            admissibility test ``[[P_i, X], [X^T, P_j]] >= 0``
:func:`joint_covariance_is_admissible`
==================================  =======================================================

Shapes: ``P_i`` (n_i, n_i), ``P_j`` (n_j, n_j), ``H_i`` (m, n_i), ``H_j`` (m, n_j), ``R``
(m, m), ``x_i`` (n_i,), ``residual = z - z_hat`` (m,). Results are frozen dataclasses with the
fused covariance ``P`` (agent i's), the gain ``K`` (n_i, m), the correction ``dx = K residual``
and posterior mean ``x`` when asked for, the optimiser (``omega`` or ``X`` and
``C = L_i^-1 X L_j^-T``) and ``updated`` (False when the no-update rule applies).
``dmv_update(..., omega=w)`` and ``pecmv_update(..., C=C)`` apply a given (e.g. learned)
optimiser instead of solving for it; ``validate=False`` skips the input checks on hot paths.

Bad input (non-symmetric, not positive definite, NaN/inf, mismatched shapes) raises
``ValueError`` naming the argument. The derivations (Chen & Kia 2022, Sec. III-IV) are
in the docstrings of :mod:`~selenv.core.fusion.dmv` and :mod:`~selenv.core.fusion.pecmv`
(the exact m-dimensional reduction of PECMV). Layout of this subpackage: ``ci``, ``dmv``,
``pecmv``, ``surrogate`` (surrogate-driven updates), ``sdp`` (conic solvers), ``batch``
(vectorised labels) and ``common`` (validation, root finders); the submodules are not public
API, import from ``selenv.core.fusion``.

``selenv.core`` imports nothing from ``learned``: the one plugin point is
:data:`SURROGATE_HOOK` (``"module:attr"`` of a surrogate loader, imported lazily on the first
LDMV / LPECMV call without an explicit ``surrogate=``), which the shipped hook points at
``selenv.learned.surrogates``.
"""

from __future__ import annotations

from selenv.core.fusion.batch import PECMVBatchResult, dmv_omega_batch, pecmv_batch
from selenv.core.fusion.ci import CI_METHODS, CIResult, covariance_intersection
from selenv.core.fusion.common import joint_covariance_is_admissible
from selenv.core.fusion.dmv import DMVResult, dmv_cost, dmv_update
from selenv.core.fusion.pecmv import PECMV_METHODS, PECMVResult, pecmv_objective, pecmv_update
from selenv.core.fusion.surrogate import SURROGATE_HOOK, ldmv_update, load_surrogate, lpecmv_update

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
