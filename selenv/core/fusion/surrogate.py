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

Automatic selection: the features of eq. (13) contain neither ``R`` nor anything that tells a
range-only problem from a range + bearing one of the same ``n``, so a network is only valid for
the ``(n, m, R)`` it was trained with. The hook is called as ``hook(kind, R=R, n=n)`` and
returns the shipped checkpoint of that kind whose ``n``, ``m`` and training ``R`` match
(:func:`same_R`): ``checkpoints/ldmv.pt`` / ``lpecmv.pt`` for the range-only scenario
(m = 1, ``R = [[0.1^2]]``), ``ldmv_m2.pt`` / ``lpecmv_m2.pt`` for range + bearing
(m = 2, ``R = diag(0.1^2, (2 deg)^2)``); a problem no checkpoint matches is a ``ValueError``
listing what is shipped (never a mismatched network).
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
    "same_R",
]

#: where the shipped surrogates are loaded from: ``callable(kind, *, R, n) -> Surrogate``
#: (the checkpoint of ``kind`` trained for ``n`` and ``R``; ``R=None``: the range-only one)
SURROGATE_HOOK = "selenv.learned.surrogates:shipped"
#: relative tolerance of :func:`same_R` (a bearing of 2.001 deg instead of 2 deg is 1e-3 off)
R_RTOL = 1e-6


class Surrogate(Protocol):
    """What the fusion layer needs from a learned surrogate (``selenv.learned.surrogates``)."""

    kind: str
    meta: dict[str, Any]

    def predict_omega(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> Any:  # noqa: D102
        ...

    def predict_C(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> Any:  # noqa: D102
        ...


#: shipped surrogate names -> the network kind they hold
SHIPPED_KINDS = {
    "ldmv": "ldmv",
    "lpecmv": "lpecmv",
    "lpecmv_full": "lpecmv",
    "lpecmv_objective": "lpecmv",
}
#: the LPECMV variants of :func:`lpecmv_update`
LPECMV_VARIANTS = ("lpecmv", "lpecmv_full", "lpecmv_objective")


def same_R(R_trained: ArrayLike, R: ArrayLike) -> bool:
    """Whether noise ``R`` (m, m) is the training noise ``R_trained`` (shape and entries).

    Entry ``(k, l)`` may differ by ``R_RTOL sqrt(Rt_kk Rt_ll)`` (``R_RTOL`` = 1e-6): relative
    on the diagonal, in units of the correlation off it, so rows in different units (m^2 for
    a range, rad^2 for a bearing) are each compared at their own scale. ``np.allclose``'s
    absolute 1e-8 would take a bearing noise of 0.006 deg for one of 0.003 deg (variances
    1.1e-8 and 2.7e-9).
    """
    Rt = np.asarray(R_trained, dtype=np.float64)
    Rc = np.asarray(R, dtype=np.float64)
    if Rt.ndim != 2 or Rt.shape != Rc.shape or Rt.size == 0:
        return False
    s = np.sqrt(np.abs(np.diagonal(Rt)))
    return bool(np.all(np.abs(Rt - Rc) <= R_RTOL * np.outer(s, s)))


#: (hook, kind, R shape, R bytes, n) -> the shipped surrogate the hook picked and that passed the
#: checks (one dict lookup per fusion call; explicit surrogates are checked every call)
_CHECKED: dict[tuple[Any, ...], Any] = {}


def load_surrogate(
    kind: str,
    surrogate: Surrogate | None = None,
    R: ArrayLike | None = None,
    n: int | None = None,
) -> Any:
    """``surrogate`` or the shipped one of ``kind`` for ``(n, R)``, checked against ``R``.

    ``kind``: ``"ldmv"``, ``"lpecmv"`` (method 3, diagonal ``C``: the paper's choice),
    ``"lpecmv_full"`` (method 1, full ``C``, norm-capped below 1 by ``predict_C``) or
    ``"lpecmv_objective"`` (method 3 trained on the objective eq. 8a).

    The features of eq. (13) do not contain ``R``, so a surrogate is only valid for the ``R``
    it was trained with (``meta["R"]``, compared by :func:`same_R`). Without ``surrogate`` the
    hook picks the shipped checkpoint trained for this ``n`` (state dimension of agent i) and
    ``R`` (the m = 1 range-only one when ``R`` is ``None``).

    Raises:
        TypeError: ``kind`` is not a str, or ``R`` is not real numeric.
        ValueError: unknown ``kind``, a surrogate of the other kind, the hook's module is not
            importable, no shipped checkpoint is trained for ``(n, R)`` (the message lists the
            shipped ones), or ``R`` differs from the training ``R`` (the message says how to
            retrain).
    """
    if not isinstance(kind, str):
        raise TypeError(f"kind must be a str, got {type(kind).__name__}")
    if kind not in SHIPPED_KINDS:
        raise ValueError(f"kind must be one of {sorted(SHIPPED_KINDS)}, got {kind!r}")
    R_arr = None if R is None else np.atleast_2d(as_float_array(R, "R"))
    key = None
    if R_arr is not None and surrogate is None:
        key = (SURROGATE_HOOK, kind, R_arr.shape, R_arr.tobytes(), n)
        hit = _CHECKED.get(key)
        if hit is not None:
            return hit
    if surrogate is None:
        module, attr = SURROGATE_HOOK.split(":")
        try:
            loader = getattr(importlib.import_module(module), attr)
        except ImportError as exc:
            raise ValueError(
                f"fusion {kind!r} needs the learned surrogates ({SURROGATE_HOOK}): {exc}"
            ) from None
        surrogate = loader(kind) if R_arr is None else loader(kind, R=R_arr, n=n)
    if getattr(surrogate, "kind", None) != SHIPPED_KINDS[kind]:
        raise ValueError(
            f"surrogate must be an {SHIPPED_KINDS[kind]!r} surrogate, got {surrogate.kind!r}"
        )
    if R_arr is not None:
        R_trained = np.asarray(surrogate.meta.get("R"), dtype=np.float64)
        if not same_R(R_trained, R_arr):
            raise ValueError(
                f"the {kind} surrogate was trained with R = {R_trained.tolist()}, but R = "
                f"{R_arr.tolist()}; retrain it for this R (python -m selenv.train.train_surrogate)"
            )
        if key is not None:
            if len(_CHECKED) > 256:  # bounded: many noise levels in one process
                _CHECKED.clear()
            _CHECKED[key] = surrogate
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
    sur = load_surrogate("ldmv", surrogate, p.R, p.P_i.shape[0])
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
    ``"lpecmv"`` (method 3, diagonal ``C``), ``"lpecmv_full"`` (method 1, full ``C``) or
    ``"lpecmv_objective"`` (diagonal ``C`` trained on the objective eq. 8a: consistent where
    method 3 is overconfident; range only).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: bad input (names the argument), a surrogate trained for another ``R``,
            ``n`` or ``m``, or a predicted ``C`` that is not a contraction.
    """
    if not isinstance(variant, str) or variant not in LPECMV_VARIANTS:
        raise ValueError(f"variant must be one of {LPECMV_VARIANTS}, got {variant!r}")
    p = pair(P_i, P_j, H_i, H_j, R, validate=validate, x_i=x_i, residual=residual)
    x_v, r_v = check_correction(x_i, residual, p.P_i.shape[0], p.H_i.shape[0])
    sur = load_surrogate(variant, surrogate, p.R, p.P_i.shape[0])
    C = _checked_C(sur.predict_C(p.P_i, p.P_j, p.H_i, p.H_j), p)
    return pecmv_from_pair(p, "auto", C, x_v, r_v, check=validate)


def _checked_C(C: Any, p: Any) -> Any:
    """:func:`~selenv.core.fusion.pecmv.checked_C`, without its SVD for a diagonal ``C``.

    Method 3 predicts a diagonal ``C``, whose spectral norm is ``max |C_kk|``: a float64
    (n, n) array with no nonzero off the diagonal and every ``|C_kk| <= 1 + 1e-9`` (NaN and
    inf fail the comparison) is accepted as is; anything else goes through ``checked_C``
    (the same acceptance rule, with its error messages).
    """
    n = p.P_i.shape[0]
    if (
        isinstance(C, np.ndarray)
        and C.dtype == np.float64
        and C.shape == (n, n)
        and n == p.P_j.shape[0]
    ):
        d = np.diagonal(C)
        if np.count_nonzero(C) == np.count_nonzero(d) and float(np.max(np.abs(d))) <= 1.0 + 1e-9:
            return C
    return checked_C(C, p)
