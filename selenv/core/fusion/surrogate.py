"""LDMV and LPECMV: DMV / PECMV updates whose optimiser is predicted by a learned surrogate.

Chen & Kia 2022, Sec. III: a network maps the features of eq. (13) to ``omega_hat`` (LDMV,
replacing the minimisation of eq. 6) or to a contraction ``C_hat`` with ``||C_hat||_2 < 1``
(LPECMV, replacing the MAXDET problem eq. 8, with ``X_hat = L_i C_hat L_j^T``, eq. 11). The
update itself is the exact one of :func:`~selenv.core.fusion.dmv.dmv_update` /
:func:`~selenv.core.fusion.pecmv.pecmv_update` with that optimiser plugged in, so the result is
a valid DMV bound (any ``omega`` in [0, 1]) or an admissible joint covariance (Lemma III.1) even
when the prediction is poor; only optimality is learned.

The surrogates live in ``selenv.learned.surrogates`` (torch), above ``selenv`` in the import order.
They are reached through the lazy hook :data:`SURROGATE_HOOK` (``"module:attr"``, imported on
first use only), or passed in explicitly as any object with ``predict_omega`` / ``predict_C``
and a ``meta`` dict holding the training ``"R"``.
"""

from __future__ import annotations

import importlib
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.fusion.common import check_correction, pair
from selenv.core.fusion.dmv import DMVResult, checked_omega, dmv_from_pair
from selenv.core.fusion.pecmv import PECMVResult, checked_C, pecmv_from_pair
from selenv.core.linalg import as_float_array

__all__ = [
    "SHIPPED_KINDS",
    "SURROGATE_HOOK",
    "Surrogate",
    "ldmv_update",
    "load_surrogate",
    "lpecmv_update",
]

#: where the shipped surrogates are loaded from: ``callable(kind) -> Surrogate``
SURROGATE_HOOK = "selenv.learned.surrogates:shipped"


class Surrogate(Protocol):
    """What the fusion layer needs from a learned surrogate (``selenv.learned.surrogates``)."""

    kind: str
    meta: dict[str, Any]

    def predict_omega(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> Any:  # noqa: D102
        ...

    def predict_C(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> Any:  # noqa: D102
        ...


#: shipped surrogate names -> the network kind they hold
SHIPPED_KINDS = {"ldmv": "ldmv", "lpecmv": "lpecmv", "lpecmv_full": "lpecmv"}


def load_surrogate(
    kind: str, surrogate: Surrogate | None = None, R: ArrayLike | None = None
) -> Any:
    """``surrogate`` or the shipped one of ``kind``, checked against the measurement noise ``R``.

    ``kind``: ``"ldmv"``, ``"lpecmv"`` (method 3, diagonal ``C``: the paper's choice) or
    ``"lpecmv_full"`` (method 1, full ``C``, norm-capped below 1 by ``predict_C``).

    The features of eq. (13) do not contain ``R``, so a surrogate is only valid for the ``R``
    it was trained with (``meta["R"]``).

    Raises:
        TypeError: ``kind`` is not a str, or ``R`` is not real numeric.
        ValueError: unknown ``kind``, a surrogate of the other kind, the hook's module is not
            importable, or ``R`` differs from the training ``R`` (the message says how to
            retrain).
    """
    if not isinstance(kind, str):
        raise TypeError(f"kind must be a str, got {type(kind).__name__}")
    if kind not in SHIPPED_KINDS:
        raise ValueError(f"kind must be one of {sorted(SHIPPED_KINDS)}, got {kind!r}")
    if surrogate is None:
        module, attr = SURROGATE_HOOK.split(":")
        try:
            loader = getattr(importlib.import_module(module), attr)
        except ImportError as exc:
            raise ValueError(
                f"fusion {kind!r} needs the learned surrogates ({SURROGATE_HOOK}): {exc}"
            ) from None
        surrogate = loader(kind)
    if getattr(surrogate, "kind", None) != SHIPPED_KINDS[kind]:
        raise ValueError(
            f"surrogate must be an {SHIPPED_KINDS[kind]!r} surrogate, got {surrogate.kind!r}"
        )
    if R is not None:
        R = np.atleast_2d(as_float_array(R, "R"))
        R_trained = np.asarray(surrogate.meta.get("R"), dtype=np.float64)
        if R_trained.shape != R.shape or not np.allclose(R_trained, R):
            raise ValueError(
                f"the {kind} surrogate was trained with R = {R_trained.tolist()}, but R = "
                f"{R.tolist()}; retrain it for this R (python -m selenv.train.train_surrogate)"
            )
    return surrogate


def ldmv_update(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    x_i: ArrayLike | None = None,
    residual: ArrayLike | None = None,
    surrogate: Surrogate | None = None,
    validate: bool = True,
) -> DMVResult:
    """LDMV: the DMV update (eqs. 4-5) with ``omega = surrogate.predict_omega(...)``.

    Shapes and the result as :func:`~selenv.core.fusion.dmv.dmv_update`; ``surrogate``
    defaults to the shipped LDMV checkpoint (:data:`SURROGATE_HOOK`).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: bad input (names the argument), a surrogate trained for another ``R``,
            ``n`` or ``m``, or a predicted ``omega`` outside [0, 1].
    """
    p = pair(P_i, P_j, H_i, H_j, R, validate=validate, x_i=x_i, residual=residual)
    x_v, r_v = check_correction(x_i, residual, p.P_i.shape[0], p.H_i.shape[0])
    sur = load_surrogate("ldmv", surrogate, p.R)
    w = np.asarray(sur.predict_omega(p.P_i, p.P_j, p.H_i, p.H_j))
    if w.size != 1:
        raise ValueError(
            f"the surrogate's predict_omega must return one omega, got shape {w.shape}"
        )
    return dmv_from_pair(p, x_v, r_v, checked_omega(w.reshape(())), check=validate)


def lpecmv_update(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    x_i: ArrayLike | None = None,
    residual: ArrayLike | None = None,
    surrogate: Surrogate | None = None,
    variant: str = "lpecmv",
    validate: bool = True,
) -> PECMVResult:
    """LPECMV: the PECMV update (eq. 9) with ``X = L_i C_hat L_j^T``, ``C_hat`` predicted.

    Shapes and the result as :func:`~selenv.core.fusion.pecmv.pecmv_update`; ``surrogate``
    defaults to the shipped LPECMV checkpoint :data:`SURROGATE_HOOK` of ``variant``:
    ``"lpecmv"`` (method 3, diagonal ``C``) or ``"lpecmv_full"`` (method 1, full ``C``).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: bad input (names the argument), a surrogate trained for another ``R``,
            ``n`` or ``m``, or a predicted ``C`` that is not a contraction.
    """
    if not isinstance(variant, str) or variant not in ("lpecmv", "lpecmv_full"):
        raise ValueError(f"variant must be 'lpecmv' or 'lpecmv_full', got {variant!r}")
    p = pair(P_i, P_j, H_i, H_j, R, validate=validate, x_i=x_i, residual=residual)
    x_v, r_v = check_correction(x_i, residual, p.P_i.shape[0], p.H_i.shape[0])
    sur = load_surrogate(variant, surrogate, p.R)
    C = checked_C(sur.predict_C(p.P_i, p.P_j, p.H_i, p.H_j), p)
    return pecmv_from_pair(p, "auto", C, x_v, r_v, check=validate)
