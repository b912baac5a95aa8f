"""Candidate views of ``FIMSelection``: the raw layout, and one that no longer depends on ``d``.

The env observes every candidate ``k`` whitened in the current information, ``Z_k = G_k L^-T``
(``(m, d)``, ``L L^T`` the current FIM, so the FIM is the identity in these coordinates). A
policy that reads ``Z_k`` entry by entry is tied to the parameter dimension ``d`` (the preset)
and to the basis ``L`` happens to give. :class:`FIMInvariantView` replaces the ``m d`` entries by
``WIDTH`` = 7 statistics that depend only on the Gram matrices ``Z_k Z_l^T`` and on the steps
left, so they are unchanged by any rotation ``Z -> Z Q`` (``Q`` orthogonal) and by padding ``Z``
with zero columns (a larger ``d`` whose extra parameters nothing observes). One checkpoint then
plays every preset (``d`` = 2..8) and budget.

Per candidate ``k`` (``G_k = Z_k Z_k^T``, ``t`` the unselected candidate of largest log-det gain,
``s`` the second largest, ``n_u`` unselected candidates, ``r`` picks left):

====  ==============================================================================
 0    ``log(1 + lambda_1(G_k))``: the larger eigenvalue of the candidate's whitened gram
 1    ``log(1 + lambda_2(G_k))`` (0 when ``m = 1``); ``0 + 1`` is the log-det gain
 2    ``g_{k|t} = log det(I + G_k - C_kt (I + G_t)^-1 C_tk)``, ``C_kt = Z_k Z_t^T``: the gain
      left after greedy's pick ``t`` (Woodbury on Kirchner et al. 2020, eq. 9); for ``t``
      itself, after ``s``
 3    ``g_{k|t} / g_k``: the fraction of the gain that survives greedy's pick (0 if ``g_k = 0``)
 4    ``log det(I + Z_k (I + beta S)^-1 Z_k^T)``, ``S = sum_unselected Z_j^T Z_j``,
      ``beta = r / n_u``: the gain left after ``r`` average candidates of the pool
 5    ``||C_kt||_F^2 / (tr G_k tr G_t)`` in ``[0, 1]``: how aligned ``k`` is with greedy's pick
 6    ``log(1 + r)``
====  ==============================================================================

Selected candidates (and every candidate once nothing is left) get zeros. ``gain``,
``features``, ``selected``, ``budget_left`` and ``action_mask`` are the env's. The view is a pure
function of the observation (``m`` and the budget are fixed when it is built), so it also serves
the native vector env.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces
from scipy.linalg import solve_triangular

from selenv.envs.views import CandidateView, IdentityView, candidate_space

__all__ = ["VIEWS", "FIMInvariantView", "invariant_features"]

#: width of the invariant per-candidate statistics
WIDTH = 7


def _logdet_spd_small(A: np.ndarray) -> np.ndarray:
    """``log det A`` of a stack ``(..., m, m)`` of symmetric positive definite matrices."""
    sign, logdet = np.linalg.slogdet(A)
    return np.where(sign > 0, logdet, 0.0)


def invariant_features(
    Z: np.ndarray, unselected: np.ndarray, steps_left: int, *, closed_form: bool = True
) -> np.ndarray:
    """The ``(N, 7)`` statistics of :class:`FIMInvariantView` (module docstring, rows 0-6).

    Args:
        Z: ``(N, m, d)`` candidates whitened in the current information (float64).
        unselected: ``(N,)`` bool, the candidates still available.
        steps_left: picks left in the episode, ``r >= 0``.
        closed_form: with ``m = 2`` (every Kirchner preset), the 2x2 algebra written out
            entry by entry over the candidate axis (about 3x faster at ``N = 1000``); ``False``
            takes the stacked-matrix path (any ``m``). Both agree to rounding (tested).

    Returns:
        ``(N, 7)`` float64; zero rows for selected candidates.
    """
    N, m, d = Z.shape
    out = np.zeros((N, WIDTH))
    idx = np.flatnonzero(unselected)
    if idx.size == 0:
        return out
    if closed_form and m == 2:
        out[idx] = _features_m2(Z[idx], steps_left)
        return out
    Zu = Z[idx]  # (n_u, m, d)
    eye_m = np.eye(m)
    G = Zu @ Zu.transpose(0, 2, 1)  # (n_u, m, m)
    lam = np.clip(np.linalg.eigvalsh(G)[:, ::-1], 0.0, None)  # descending
    gain = _logdet_spd_small(eye_m + G)
    out[idx, 0] = np.log1p(lam[:, 0])
    if m > 1:
        out[idx, 1] = np.log1p(lam[:, 1])

    order = np.argsort(-gain, kind="stable")
    t = order[0]

    def gain_after(p: int) -> np.ndarray:
        """``g_{k|p}`` for every unselected ``k`` (Woodbury; ``C = Z_k Z_p^T``)."""
        C = Zu @ Zu[p].T  # (n_u, m, m)
        # C_kp (I + G_p)^-1 C_pk, with C_pk = C_kp^T
        X = np.linalg.solve(eye_m + G[p], C.transpose(0, 2, 1))  # (n_u, m, m)
        return _logdet_spd_small(eye_m + G - C @ X)

    after = gain_after(t)
    after[t] = gain_after(order[1])[t] if idx.size > 1 else gain[t]
    out[idx, 2] = after
    out[idx, 3] = np.divide(after, gain, out=np.zeros_like(gain), where=gain > 0)

    S = np.einsum("kmi,kmj->ij", Zu, Zu)  # (d, d) pool information
    beta = steps_left / idx.size
    Lc = np.linalg.cholesky(np.eye(d) + beta * S)
    # Z_k (I + beta S)^-1 Z_k^T = W_k W_k^T with W_k = Z_k Lc^-T: one triangular solve
    W = np.linalg.solve(Lc, Zu.reshape(-1, d).T).T.reshape(idx.size, m, d)
    out[idx, 4] = _logdet_spd_small(eye_m + W @ W.transpose(0, 2, 1))

    C_t = Zu @ Zu[t].T
    tr = np.trace(G, axis1=1, axis2=2)
    denom = tr * tr[t]
    out[idx, 5] = np.divide(
        np.sum(C_t * C_t, axis=(1, 2)), denom, out=np.zeros_like(denom), where=denom > 0
    )
    out[idx, 6] = np.log1p(steps_left)
    return out


def _det2(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``log det [[1 + a, b], [b, 1 + c]]`` (``>= 0`` for the PSD ``[[a, b], [b, c]]`` here)."""
    return np.log((1.0 + a) * (1.0 + c) - b * b)


def _features_m2(Zu: np.ndarray, steps_left: int) -> np.ndarray:
    """:func:`invariant_features` of the unselected candidates ``Zu (n_u, 2, d)``, entry-wise.

    A candidate's gram ``[[a, b], [b, c]]`` and the Woodbury term ``C M C^T`` are written out
    per entry; the products over ``d`` are single GEMMs over the stacked rows.
    """
    n_u, _, d = Zu.shape
    z0, z1 = Zu[:, 0], Zu[:, 1]
    a = np.einsum("ij,ij->i", z0, z0)
    b = np.einsum("ij,ij->i", z0, z1)
    c = np.einsum("ij,ij->i", z1, z1)
    out = np.empty((n_u, WIDTH))
    mid, rad = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    out[:, 0] = np.log1p(np.maximum(mid + rad, 0.0))
    out[:, 1] = np.log1p(np.maximum(mid - rad, 0.0))
    gain = _det2(a, b, c)
    order = np.argsort(-gain, kind="stable")
    t = order[0]
    rows = Zu.reshape(2 * n_u, d)

    def after(p: int) -> tuple[np.ndarray, np.ndarray]:
        """``g_{k|p}`` and ``C_kp`` ``(n_u, 2, 2)`` for every unselected ``k``."""
        C = (rows @ Zu[p].T).reshape(n_u, 2, 2)  # C[k, i, j] = z_i(k) . z_j(p)
        det = (1.0 + a[p]) * (1.0 + c[p]) - b[p] * b[p]
        M = np.array([[1.0 + c[p], -b[p]], [-b[p], 1.0 + a[p]]]) / det  # (I + G_p)^-1
        CM = (C.reshape(2 * n_u, 2) @ M).reshape(n_u, 2, 2)
        q00 = np.einsum("ij,ij->i", CM[:, 0], C[:, 0])
        q01 = np.einsum("ij,ij->i", CM[:, 0], C[:, 1])
        q11 = np.einsum("ij,ij->i", CM[:, 1], C[:, 1])
        return _det2(a - q00, b - q01, c - q11), C

    g_t, C_t = after(t)
    g_t[t] = after(order[1])[0][t] if n_u > 1 else gain[t]
    out[:, 2] = g_t
    out[:, 3] = np.divide(g_t, gain, out=np.zeros_like(gain), where=gain > 0)

    S = rows.T @ rows  # (d, d) pool information
    Lc = np.linalg.cholesky(np.eye(d) + (steps_left / n_u) * S)
    W = solve_triangular(Lc, rows.T, lower=True).T.reshape(n_u, 2, d)  # Z_k Lc^-T
    w0, w1 = W[:, 0], W[:, 1]
    out[:, 4] = _det2(
        np.einsum("ij,ij->i", w0, w0), np.einsum("ij,ij->i", w0, w1), np.einsum("ij,ij->i", w1, w1)
    )
    tr = a + c
    denom = tr * tr[t]
    num = np.einsum("kij,kij->k", C_t, C_t)
    out[:, 5] = np.divide(num, denom, out=np.zeros_like(denom), where=denom > 0)
    out[:, 6] = np.log1p(steps_left)
    return out


class FIMInvariantView(CandidateView):
    """``FIMSelection``: the whitened rows replaced by ``d``-independent statistics.

    Args:
        m: rows per candidate (``env.unwrapped.m``).
        budget: picks per episode (``env.unwrapped.budget``); with the observation's
            ``budget_left`` fraction it gives the picks left.

    Raises:
        ValueError: ``m`` or ``budget`` not a positive integer.
    """

    name = "invariant"

    def __init__(self, m: int, budget: int) -> None:
        for value, what in ((m, "m"), (budget, "budget")):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{what} must be a positive integer, got {value!r}")
        self.m = int(m)
        self.budget = int(budget)

    @classmethod
    def from_env(cls, env: Any) -> FIMInvariantView:
        """The view of a ``FIMSelection`` env (any preset)."""
        base = env.unwrapped
        return cls(int(base.m), int(base.budget))

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        if not isinstance(env_space, spaces.Dict) or "whitened" not in env_space.spaces:
            raise ValueError(f"expected a FIMSelection Dict observation space, got {env_space}")
        n, width = env_space["whitened"].shape or (0, 0)
        if width % self.m:
            raise ValueError(f"whitened width {width} is not a multiple of m = {self.m}")
        return candidate_space(int(n), WIDTH)

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        flat = np.asarray(obs["whitened"], dtype=np.float64)
        n = flat.shape[0]
        Z = flat.reshape(n, self.m, -1)
        unselected = np.asarray(obs["action_mask"]) > 0
        steps_left = round(float(obs["budget_left"][0]) * self.budget)
        return {
            "action_mask": obs["action_mask"],
            "budget_left": obs["budget_left"],
            "features": obs["features"],
            "gain": obs["gain"],
            "selected": obs["selected"],
            "whitened": invariant_features(Z, unselected, steps_left).astype(np.float32),
        }


#: the views of ``FIMSelection`` (the first is the default)
VIEWS: dict[str, Callable[[Any], CandidateView]] = {
    "identity": lambda env: IdentityView(),
    "invariant": FIMInvariantView.from_env,
}
