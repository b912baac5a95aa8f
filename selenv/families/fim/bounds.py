"""A certified bound on a FIMSelection episode's return: the log-det continuous relaxation.

The return of an episode is ``f(S) = log det(Q0 + sum_{k in S} G_k^T G_k) - log det Q0``
(Kirchner et al. 2020, eq. 9) for the ``budget`` picks ``S``, with ``Q0`` the prior at reset.
:func:`~selenv.agents.fim_exact.relaxation_bound_whitened` bounds it over every subset of the
budget's size (Joshi & Boyd 2009's relaxation, certified by its tangent bound).
"""

from __future__ import annotations

from typing import Any

from selenv.agents.fim_exact import relaxation_bound_whitened
from selenv.families.spec import ReturnBound

__all__ = ["return_bound"]


def return_bound(env: Any) -> ReturnBound | None:
    """The relaxation bound of the episode ``env`` (unwrapped, just reset) will play.

    ``None`` for the ``"trace"`` / ``"max_eig"`` objectives (the relaxation bounds log det).
    """
    if env.solver_objective != "logdet":
        return None
    state = env.state
    res = relaxation_bound_whitened(state.information, state.G, env.budget_left)
    return ReturnBound(res.bound, "bound", "continuous relaxation (log det)")
