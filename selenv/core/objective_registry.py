"""Selection objectives as objects: one registry used by the solvers, the envs and the agents.

An :class:`Objective` is a *cost of a covariance* ``c(M)`` (lower is better) evaluated on a
block ``M = E P E^T`` ``(..., p, p)`` of a posterior covariance (or CRLB) ``P``; ``E`` selects
the parameters the objective scores. The built-ins:

=========== ======================================= ========== ============== ===========
name        ``c(M)``                                submodular unit-invariant solvers use
=========== ======================================= ========== ============== ===========
``logdet``  ``log det M`` (D-optimal; Kirchner      yes        yes            itself
            et al. 2020 eq. 5 / 9, Soubaras eq. 11)
``det``     ``det M`` (Soubaras & Chahbazian eq.    no         yes            ``logdet``
            11; same minimiser as ``logdet``)
``trace``   ``tr M`` (A-optimal, Kirchner eq. 6)    no         no             itself
``max_eig`` ``lambda_max(M)`` (E-optimal, eq. 7)    no         no             itself
=========== ======================================= ========== ============== ===========

*Submodular* gains (``f(S) = c(P0) - c(P_S)``) carry greedy's ``1 - 1/e`` guarantee and make
lazy greedy valid. *Unit-invariant* costs have a minimiser that does not depend on the units of
the state's components (a diagonal rescaling ``D P D`` adds a constant to ``log det``), so they
may score a whole state of mixed units; the others add variances and are scored on a block of
one unit (the position), which the envs choose from this flag.

The one-step marginal gain of a measurement with whitened rows ``G_k`` given ``P`` is a
*downdate*: with ``V_k = C_k^-1 G_k P E^T`` and ``I + G_k P G_k^T = C_k C_k^T`` (Woodbury),
``E P_k E^T = M0 - V_k^T V_k`` and ``gain = c(M0) - c(M0 - V_k^T V_k)``
(:meth:`Objective.downdate_gain`, batched over leading axes of ``V``). An objective may give a
closed form (``trace``: ``||V_k||_F^2``); otherwise the generic form above is used.

Users add their own with :func:`register_objective`; the greedy, swap, brute-force and VNS
solvers and the FIM / landmark / CL envs then accept its name. Every ``objective=`` argument
resolves its name through :func:`check_objective`: an unknown name is a ``ValueError`` that
lists the known ones.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from selenv.core.linalg import FloatArray, logdet_spd

__all__ = [
    "BUILTIN_OBJECTIVES",
    "Objective",
    "check_objective",
    "get_objective",
    "objective_names",
    "register_objective",
    "unregister_objective",
]

CostFn = Callable[[FloatArray], FloatArray]
DowndateFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True, kw_only=True)
class Objective:
    """A selection objective: the cost of a covariance block, lower is better.

    Args:
        name: registry key (what ``objective=`` takes).
        description: one line for listings and error messages.
        cost: ``c(M)``: ``(..., p, p)`` SPD blocks -> ``(...)`` costs, batched over leading axes.
        submodular: whether ``f(S) = c(P0) - c(P_S)`` is submodular in the selection (greedy's
            ``1 - 1/e`` bound; lazy greedy needs it).
        unit_invariant: whether the minimiser of ``c`` is unchanged by a diagonal rescaling of
            the state (``D P D``); if not, envs score a block of one unit (the position).
        solver_proxy: name of the objective whose one-step maximiser equals this one's and which
            the solvers use instead (``det`` -> ``logdet``); ``None``: the objective itself.
        downdate: optional closed form of :meth:`downdate_gain` ``(M0, V) -> gains``.

    Raises:
        TypeError, ValueError: a field of the wrong type (checked on construction).
    """

    name: str
    description: str
    cost: CostFn
    submodular: bool = False
    unit_invariant: bool = False
    solver_proxy: str | None = None
    downdate: DowndateFn | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ValueError(f"Objective name must be an identifier string, got {self.name!r}")
        if not isinstance(self.description, str):
            raise TypeError(f"Objective description must be a str, got {self.description!r}")
        if not callable(self.cost):
            raise TypeError(f"Objective cost must be callable, got {self.cost!r}")
        if self.downdate is not None and not callable(self.downdate):
            raise TypeError(f"Objective downdate must be callable or None, got {self.downdate!r}")
        for flag in ("submodular", "unit_invariant"):
            if not isinstance(getattr(self, flag), bool):
                raise TypeError(f"Objective {flag} must be a bool, got {getattr(self, flag)!r}")
        if self.solver_proxy is not None and not isinstance(self.solver_proxy, str):
            raise TypeError(
                f"Objective solver_proxy must be a str or None, got {self.solver_proxy!r}"
            )

    def value(self, M: FloatArray) -> FloatArray:
        """``c(M)`` ``(...)`` of covariance blocks ``M`` ``(..., p, p)`` as float64."""
        return np.asarray(self.cost(M), dtype=np.float64)

    def downdate_gain(self, M0: np.ndarray, V: np.ndarray) -> FloatArray:
        """``c(M0) - c(M0 - V^T V)`` ``(...)``: the drop of the cost after a Woodbury downdate.

        ``M0`` ``(p, p)`` is ``E P E^T``; ``V`` ``(..., r, p)`` the whitened downdate factors
        (module docstring). Not clipped: rounding can make a zero gain slightly negative.
        """
        if self.downdate is not None:
            return np.asarray(self.downdate(M0, V), dtype=np.float64)
        M = M0 - np.einsum("...ip,...iq->...pq", V, V)  # E P_k E^T
        return self.value(M0) - self.value(M)

    @property
    def solver_name(self) -> str:
        """The objective the one-step solvers maximise for this one (itself or its proxy)."""
        return self.name if self.solver_proxy is None else self.solver_proxy


def _logdet(M: FloatArray) -> FloatArray:
    """``log det M`` by Cholesky (batched)."""
    return np.asarray(logdet_spd(M, "P"))


def _det(M: FloatArray) -> FloatArray:
    """``det M = exp(log det M)`` by Cholesky (batched)."""
    return np.asarray(np.exp(logdet_spd(M, "P")))


def _trace(M: FloatArray) -> FloatArray:
    """``tr M`` (batched)."""
    return np.asarray(np.trace(M, axis1=-2, axis2=-1))


def _trace_downdate(M0: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``tr(V^T V) = ||V||_F^2``: the trace's drop after the downdate, without forming it."""
    return np.einsum("...ip,...ip->...", V, V)


def _max_eig(M: FloatArray) -> FloatArray:
    """``lambda_max(M)`` (batched, symmetric eigenvalues)."""
    return np.asarray(np.linalg.eigvalsh(M)[..., -1])


def _max_eig_downdate(M0: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``lambda_max(M0) - lambda_max(M0 - V^T V)``, ``lambda_max(M0)`` computed once."""
    lam0 = float(np.linalg.eigvalsh(M0)[-1])
    M = M0 - np.einsum("...ip,...iq->...pq", V, V)
    return lam0 - np.linalg.eigvalsh(M)[..., -1]


#: the objectives that ship with selenv (not removable)
BUILTIN_OBJECTIVES: tuple[Objective, ...] = (
    Objective(
        name="logdet",
        description="log det of the covariance (D-optimal)",
        cost=_logdet,
        submodular=True,
        unit_invariant=True,
    ),
    Objective(
        name="det",
        description="det of the covariance (same minimiser as logdet)",
        cost=_det,
        unit_invariant=True,
        solver_proxy="logdet",
    ),
    Objective(
        name="trace",
        description="trace of the covariance block: mean-square error (A-optimal)",
        cost=_trace,
        downdate=_trace_downdate,
    ),
    Objective(
        name="max_eig",
        description="largest eigenvalue of the covariance block: worst-axis variance (E-optimal)",
        cost=_max_eig,
        downdate=_max_eig_downdate,
    ),
)

_REGISTRY: dict[str, Objective] = {o.name: o for o in BUILTIN_OBJECTIVES}
_BUILTIN_NAMES = frozenset(_REGISTRY)


def objective_names() -> tuple[str, ...]:
    """Names of every registered objective, built-ins first, in registration order."""
    return tuple(_REGISTRY)


def register_objective(objective: Objective, *, replace: bool = False) -> Objective:
    """Add ``objective`` to the registry (its ``name`` becomes valid for every ``objective=``).

    Raises:
        TypeError: ``objective`` not an :class:`Objective`.
        ValueError: the name is taken (and ``replace`` is false, or it is a built-in), or its
            ``solver_proxy`` names no registered objective.
    """
    if not isinstance(objective, Objective):
        raise TypeError(f"objective must be an Objective, got {type(objective).__name__}")
    if objective.name in _BUILTIN_NAMES:
        raise ValueError(f"objective {objective.name!r} is a built-in and cannot be replaced")
    if objective.name in _REGISTRY and not replace:
        raise ValueError(
            f"objective {objective.name!r} is already registered (pass replace=True to replace it)"
        )
    proxy = objective.solver_proxy
    if proxy is not None and proxy not in _REGISTRY:
        raise ValueError(f"solver_proxy must name a registered objective, got {proxy!r}")
    _REGISTRY[objective.name] = objective
    return objective


def unregister_objective(name: str) -> None:
    """Remove a user-registered objective.

    Raises:
        ValueError: ``name`` is a built-in or not registered.
    """
    if name in _BUILTIN_NAMES:
        raise ValueError(f"objective {name!r} is a built-in and cannot be removed")
    if name not in _REGISTRY:
        raise ValueError(f"objective {name!r} is not registered; known: {objective_names()}")
    del _REGISTRY[name]


def check_objective(
    objective: object, *, name: str = "objective", allowed: tuple[str, ...] | None = None
) -> str:
    """``objective`` if it names a registered objective (and one of ``allowed``, if given).

    Raises:
        TypeError: not a str.
        ValueError: a str that is not registered (or not in ``allowed``); the message lists the
            known names.
    """
    known = objective_names() if allowed is None else allowed
    if not isinstance(objective, str):
        raise TypeError(f"{name} must be one of {known}, got {type(objective).__name__}")
    if objective not in _REGISTRY or objective not in known:
        raise ValueError(f"{name} must be one of {known}, got {objective!r}")
    return objective


def get_objective(objective: object, *, name: str = "objective") -> Objective:
    """The registered :class:`Objective` named ``objective``.

    Raises:
        TypeError, ValueError: as :func:`check_objective`.
    """
    return _REGISTRY[check_objective(objective, name=name)]
