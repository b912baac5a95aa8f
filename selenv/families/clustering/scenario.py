"""Receiver clustering for multi-receiver GNSS (Greiff, Di Cairano & Berntorp 2022).

``n`` receivers (agents) each have a position and a velocity in R^2 and share one bias
``theta`` in R^2 (eqs. 2-3, step ``h``)::

    x^i = (p^i; v^i; theta),   A^i = [[I, hI, 0], [0, I, 0], [0, 0, I]],
    Q^ii = [[h^3/3 I, h^2/2 I, 0], [h^2/2 I, h I, 0], [0, 0, h I]],
    y^i = C^i x^i + r^i,       C^i = [[I, 0, -I], [I, 0, I]],
    R^ii = diag(sigma_1i^2 I, sigma_2i^2 I),   R^ij = r (R^ii)^1/2 (R^jj)^1/2.

A clustering is an integer label vector ``I`` (n,); cluster ``C_j`` estimates the stacked
unique states of its members plus one copy of ``theta`` (eq. 6), so ``N(C_j) = 4 |C_j| + 2``
states and ``N_y(C_j) = 4 |C_j|`` measurements. Problem 1 requires
``max{N(C_j), N_y(C_j)} <= N_max`` for every cluster, i.e. a cap on the cluster size.

**Per-axis reduction (exact).** Every matrix above is a Kronecker product with ``I_2`` (the east
and north axes never mix and have the same noise), so a cluster's covariance is
``P_axis (x) I_2`` up to a permutation, with ``P_axis`` of size ``2|C| + 1`` (state order
``p_1, v_1, ..., p_s, v_s, theta``; measurement order ``y1_1, y2_1, ..., y1_s, y2_s``). Every
filter in selenv runs on ``P_axis``: 8x fewer flops than the full model, which
:meth:`ClusteringProblem.full_model` still builds (eqs. 3-6) for tests and users.

The cost eq. (10) ``J = a_G J_G + a_C J_C + a_L J_L`` is computed from the per-axis posteriors
(:func:`clustering_cost`); the Kalman forward passes of Algorithm 1 live in
:mod:`selenv.families.clustering.filters`.

**Time-varying noise (our addition).** The paper draws ``sigma`` once; its model (1b) allows
``R_k``. With :class:`MultipathRegimes` each receiver switches between open sky and a degraded
(multipath / urban-canyon) state, a two-state Markov chain whose path is drawn with the rest of
the realisation; ``sigma`` stays the base (open-sky) levels and ``sigma_at(k)`` gives the levels
of step ``k``. ``config.regimes = None`` (the default of :class:`ClusteringConfig`) is the paper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.clustering.batched import (
    axis_model,
    axis_prior,
    correlation,
    noise_covariances,
    regime_paths,
)
from selenv.families.clustering.labels import as_labels, canonical_labels, canonicalize
from selenv.families.clustering.regimes import MultipathRegimes
from selenv.scenarios.validation import (
    ArgumentTypeError,
    check_integer,
    check_real,
    check_reals,
    describe,
    interval,
)

__all__ = [
    "MAX_AGENTS",
    "MAX_CORRELATION",
    "MAX_TAU",
    "MEASUREMENTS_PER_AGENT",
    "RANGES",
    "SHARED_STATES",
    "UNIQUE_STATES",
    "ClusteringConfig",
    "ClusteringProblem",
    "CostBreakdown",
    "MultipathRegimes",
    "axis_to_full",
    "canonical_labels",
    "clustering_cost",
    "make_clustering_problem",
    "make_clustering_problems",
    "n_measurements",
    "n_states",
]

UNIQUE_STATES = 4  #: position and velocity in R^2 per receiver
SHARED_STATES = 2  #: the bias theta in R^2, one copy per cluster
MEASUREMENTS_PER_AGENT = 4  #: y^i in R^4 (eq. 3b)
D = 2  #: positional dimension d of J_C and J_L


def n_states(size: int) -> int:
    """``N(C) = 4 |C| + 2``: states of a cluster of ``size`` receivers (eq. 6a)."""
    return UNIQUE_STATES * size + SHARED_STATES


def n_measurements(size: int) -> int:
    """``N_y(C) = 4 |C|``: measurements of a cluster of ``size`` receivers (eq. 6b)."""
    return MEASUREMENTS_PER_AGENT * size


#: largest number of receivers
MAX_AGENTS = 200
#: largest window of Algorithm 1 (steps)
MAX_TAU = 10_000
#: largest inter-receiver noise correlation (``R`` is singular at ``r = 1``)
MAX_CORRELATION = 0.99
#: valid range of the real-valued :class:`ClusteringConfig` fields: ``(low, high, unit)``
RANGES: dict[str, tuple[float, float, str]] = {
    "sigma": (1e-4, 1e3, "m"),
    "dt": (1e-3, 10.0, "s"),
    "weights": (0.0, 1e6, ""),
    "prior_std": (1e-3, 1e2, ""),
}


@dataclass(frozen=True, kw_only=True)
class ClusteringConfig:
    """Parameters of the receiver-clustering scenario (defaults: Greiff et al. Sec. IV-A).

    Every field is validated: a wrong type is a ``TypeError`` (also a ``ValueError``), a value
    outside its range a ``ValueError``, naming the field and the range.

    Attributes:
        n_agents: number of receivers ``n``, an int in ``[1, MAX_AGENTS]`` (200).
        n_max_states: ``N_max`` of Problem 1, an int >= 6; ``None`` removes the constraint
            (Remark 2).
        sigma: (n_agents, 2) measurement std devs ``(sigma_1i, sigma_2i)``, each in
            ``[1e-4, 1e3]`` (stored as a read-only float array); ``None`` draws them
            ``U(0, 1]`` from the generator given to :func:`make_clustering_problem`.
        noise_correlation: inter-receiver noise correlation ``r`` (eq. 4), in ``[0, 0.99]``
            (``r < 1`` in theory; closer to 1 the noise covariance is numerically singular).
        dt: step ``h`` of eq. (3), in ``[1e-3, 10]`` s.
        tau: window of Algorithm 1 (steps of the forward pass), an int in ``[1, MAX_TAU]``.
        weights: ``(alpha_G, alpha_C, alpha_L)`` of eq. (10), each in ``[0, 1e6]``, not all
            zero.
        prior_std: 1-sigma of the initial belief ``(position, velocity, bias)`` per axis (the
            paper does not give ``P_0|0``), each in ``[1e-3, 1e2]``.
        regimes: time-varying noise (:class:`MultipathRegimes`), ``sigma`` being the base
            levels; ``None`` (the paper) keeps ``sigma`` fixed.

    The ranges keep the Kalman filters of every cluster well conditioned in float64: prior
    variances up to 1e8 times the smallest noise variance, with correlations up to 0.99 and
    degraded noise up to 100 times the base level (wider ratios make ``H P H^T + R`` singular
    to machine precision).
    """

    n_agents: int = 30
    n_max_states: int | None = 14
    sigma: Any = None
    noise_correlation: float = 0.9
    dt: float = 0.1
    tau: int = 20
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    prior_std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    regimes: MultipathRegimes | None = None

    def __post_init__(self) -> None:
        put = object.__setattr__
        n = check_integer(self.n_agents, "n_agents", 1, MAX_AGENTS)
        put(self, "n_agents", n)
        nmax = self.n_max_states
        if nmax is not None:
            if isinstance(nmax, bool | np.bool_) or not isinstance(nmax, int | np.integer):
                raise ArgumentTypeError(
                    f"n_max_states must be an int or None, got {describe(nmax)}"
                )
            need = max(n_states(1), n_measurements(1))
            if nmax < need:
                raise ValueError(
                    f"n_max_states={nmax} is below one receiver's state count "
                    f"N(C)={n_states(1)} (4 unique + 2 shared states): no clustering is feasible"
                )
            put(self, "n_max_states", int(nmax))
        r = self.noise_correlation
        ok = isinstance(r, float | int | np.floating | np.integer) and not isinstance(r, bool)
        if not (ok and 0.0 <= float(r) <= MAX_CORRELATION):
            raise ValueError(
                f"noise_correlation (r) must lie in [0, 1) and be at most {MAX_CORRELATION:g} "
                f"(beyond, the noise covariance is numerically singular), got {describe(r)}"
            )
        put(self, "noise_correlation", float(r))
        low, high, unit = RANGES["dt"]
        put(self, "dt", check_real(self.dt, "dt", low, high, unit=unit))
        put(self, "tau", check_integer(self.tau, "tau", 1, MAX_TAU))
        low, high, _ = RANGES["weights"]
        w = check_reals(self.weights, "weights (alpha_G, alpha_C, alpha_L)", 3, low, high)
        if not any(v > 0 for v in w):
            raise ValueError(
                f"weights must be 3 finite non-negative numbers (alpha_G, alpha_C, alpha_L), "
                f"not all zero; got {self.weights!r}"
            )
        put(self, "weights", w)
        low, high, unit = RANGES["prior_std"]
        put(self, "prior_std", check_reals(self.prior_std, "prior_std", 3, low, high, unit=unit))
        if self.sigma is not None:
            sigma = _check_sigma(self.sigma, n).copy()
            sigma.setflags(write=False)
            put(self, "sigma", sigma)
        if self.regimes is not None and not isinstance(self.regimes, MultipathRegimes):
            raise ArgumentTypeError(
                f"regimes must be a MultipathRegimes or None, got {describe(self.regimes)}"
            )

    @property
    def max_cluster_size(self) -> int:
        """Largest feasible cluster: ``max{4s + 2, 4s} <= N_max``; ``n`` when unconstrained."""
        if self.n_max_states is None:
            return int(self.n_agents)
        return min(int(self.n_agents), (int(self.n_max_states) - SHARED_STATES) // UNIQUE_STATES)


def _check_sigma(sigma: Any, n: int) -> FloatArray:
    """``sigma``: a real ``(n, 2)`` array of standard deviations in ``[1e-3, 1e3]``."""
    low, high, unit = RANGES["sigma"]
    try:
        raw = np.asarray(sigma)
    except ValueError as exc:  # ragged
        raise ValueError(
            f"sigma must be a real (n_agents, 2) array, got {describe(sigma)}"
        ) from exc
    if raw.dtype.kind not in "iuf":
        raise ArgumentTypeError(f"sigma must be a real (n_agents, 2) array, got {describe(sigma)}")
    s = raw.astype(np.float64)
    if s.shape != (n, 2):
        raise ValueError(f"sigma must have shape (n_agents, 2) = ({n}, 2), got {s.shape}")
    bad = ~(np.isfinite(s) & (s > 0))
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"sigma must be finite and > 0 (standard deviations), got sigma[{i}, {j}] = {s[i, j]}"
        )
    bad = (s < low) | (s > high)
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"sigma must lie in {interval(low, high)} {unit} (standard deviations), got "
            f"sigma[{i}, {j}] = {s[i, j]:g}"
        )
    return s


def axis_to_full(P: FloatArray) -> FloatArray:
    """Per-axis covariance (2s+1, 2s+1) -> full covariance (4s+2, 4s+2) in eq. (6a)'s order.

    Inverse of the per-axis reduction: per-axis state ``(p_1, v_1, ..., p_s, v_s, theta)``,
    full state ``(p_1 (2), v_1 (2), ..., theta (2))``; the two axes are independent copies.
    """
    s = (P.shape[0] - 1) // 2
    out = np.zeros((4 * s + 2, 4 * s + 2))
    for a in range(2):
        idx = [
            4 * s + a if j == 2 * s else 4 * (j // 2) + 2 * (j % 2) + a for j in range(2 * s + 1)
        ]
        out[np.ix_(idx, idx)] = P
    return out


@dataclass(frozen=True, eq=False)
class CostBreakdown:
    """Eq. (10) and its terms for one clustering (per-axis posteriors, MSE per state)."""

    J: float
    J_G: float
    J_C: float
    J_L: float


def clustering_cost(
    posteriors: Sequence[FloatArray], weights: Sequence[float] = (1.0, 1.0, 1.0)
) -> CostBreakdown:
    """Cost eq. (10) of a clustering from its clusters' per-axis posterior covariances.

    With ``P_j`` the per-axis covariance of cluster ``j`` (size ``s_j``, position variances
    ``P_j[2a, 2a]``), the full covariance is ``P_j (x) I_2``, so

    * ``J_G = sum_j 2 tr P_j / sum_j N(C_j)`` (total MSE per state),
    * ``J_C = max_j (2 s_j)^-1 sum_a 2 P_j[2a, 2a]`` (worst cluster's positional MSE per state),
    * ``J_L = max_j max_a P_j[2a, 2a]`` (worst receiver's positional MSE per coordinate).

    Args:
        posteriors: one (2 s_j + 1, 2 s_j + 1) per-axis covariance per cluster.
        weights: ``(alpha_G, alpha_C, alpha_L)``.
    """
    # per-cluster statistics computed per size (stacked), then accumulated in cluster order
    # exactly as a loop over the clusters would (each row reduces alone: same bits)
    by_size: dict[int, list[int]] = {}
    for j, P in enumerate(posteriors):
        by_size.setdefault(P.shape[0], []).append(j)
    stats: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)] * len(posteriors)
    for d, idx in by_size.items():
        Ps = np.stack([posteriors[j] for j in idx])  # (B, d, d)
        pos = np.diagonal(Ps, axis1=1, axis2=2)[:, 0 : d - 1 : 2]  # (B, s)
        rows = zip(
            np.trace(Ps, axis1=1, axis2=2).tolist(),
            pos.mean(axis=1).tolist(),
            pos.max(axis=1).tolist(),
            strict=True,
        )
        for j, row in zip(idx, rows, strict=True):
            stats[j] = row
    total_mse = 0.0
    total_states = 0
    J_C = J_L = -np.inf
    for P, (trace, mean, worst) in zip(posteriors, stats, strict=True):
        total_mse += 2.0 * trace
        total_states += n_states((P.shape[0] - 1) // 2)
        J_C = max(J_C, mean)
        J_L = max(J_L, worst)
    J_G = total_mse / total_states
    a_G, a_C, a_L = (float(w) for w in weights)
    return CostBreakdown(a_G * J_G + a_C * J_C + a_L * J_L, J_G, J_C, J_L)


@dataclass(frozen=True, kw_only=True, eq=False)
class ClusteringProblem:
    """One realisation of the scenario: the config and the drawn noise levels.

    Attributes:
        config: the :class:`ClusteringConfig`.
        sigma: (n, 2) std devs ``(sigma_1i, sigma_2i)``; the base (open-sky) levels when the
            noise is time-varying.
        regimes: ``None`` (fixed noise) or ``(K + 1, n)`` state of each receiver at steps
            ``k = 0 .. K`` (needs ``config.regimes``): 1 degraded, 0 open sky, a fraction
            ``q`` in between the expected variance of a forecast
            (:meth:`MultipathRegimes.noise_scale`). Step ``k``'s measurement uses row ``k``.
        sigma_path: derived, ``(K + 1, n, 2)`` levels per step (``None`` when fixed).
    """

    config: ClusteringConfig
    sigma: FloatArray
    regimes: FloatArray | None = None
    sigma_path: FloatArray | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        if self.regimes is None:
            return
        model = self.config.regimes
        if model is None:
            raise ValueError("regimes needs config.regimes (a MultipathRegimes), got None")
        q = np.array(self.regimes, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.n or q.shape[0] < 1:
            raise ValueError(f"regimes must have shape (K + 1, {self.n}), got {q.shape}")
        if not np.all((q >= 0.0) & (q <= 1.0)):
            raise ValueError("regimes must lie in [0, 1] (1: degraded, 0: open sky)")
        path = self.sigma[None, :, :] * model.noise_scale(q)[:, :, None]
        q.setflags(write=False)
        path.setflags(write=False)
        object.__setattr__(self, "regimes", q)
        object.__setattr__(self, "sigma_path", path)

    @property
    def horizon(self) -> int | None:
        """Last step ``K`` of the noise path; ``None`` when the noise is fixed."""
        return None if self.regimes is None else self.regimes.shape[0] - 1

    @property
    def time_varying(self) -> bool:
        """Whether the noise levels change over time (a regime path is set)."""
        return self.regimes is not None

    def _check_step(self, k: Any, name: str = "k") -> int:
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 0:
            raise ValueError(f"{name} must be an int >= 0, got {k!r}")
        if self.regimes is not None and k > self.regimes.shape[0] - 1:
            raise ValueError(
                f"{name}={k} is beyond the drawn noise path (steps 0 .. {self.horizon})"
            )
        return int(k)

    def sigma_at(self, k: int) -> FloatArray:
        """(n, 2) noise levels of step ``k``'s measurement (``sigma`` when fixed)."""
        k = self._check_step(k)
        return self.sigma if self.sigma_path is None else self.sigma_path[k]

    @property
    def n(self) -> int:
        """Number of receivers."""
        return int(self.config.n_agents)

    @property
    def max_cluster_size(self) -> int:
        """Largest feasible cluster (``ClusteringConfig.max_cluster_size``)."""
        return self.config.max_cluster_size

    # -- feasibility ------------------------------------------------------------------------
    def check_clustering(self, labels: Any, name: str = "clustering") -> np.ndarray:
        """Validate a clustering against Problem 1; return it canonically relabelled.

        Raises:
            ValueError: non-integer labels, wrong shape, labels outside [0, n), or a cluster
                whose state or measurement count exceeds ``N_max`` (the message names the
                cluster and its receivers).
        """
        arr = self.check_labels(labels, name)
        canon = canonicalize(arr)
        if np.bincount(canon).max() > self.max_cluster_size:
            raise ValueError(f"{name}: {self.violation(arr)}")
        return canon

    def check_labels(self, labels: Any, name: str = "clustering") -> np.ndarray:
        """Validate the form of a labelling (integers, shape ``(n,)``, values in ``[0, n)``).

        This is membership of the ``MultiDiscrete([n] * n)`` space; feasibility is
        :meth:`violation`. Returns the labels as an int array (not relabelled).

        Raises:
            ValueError: non-integer labels, wrong shape, labels outside ``[0, n)``.
        """
        arr = as_labels(labels, name)
        if arr.shape != (self.n,):
            raise ValueError(f"{name} must have shape ({self.n},), got {arr.shape}")
        if arr.max() >= self.n:
            raise ValueError(f"{name}: labels must lie in [0, {self.n}), got {int(arr.max())}")
        return arr

    def violation(self, labels: np.ndarray) -> str | None:
        """Why a well-formed labelling breaks the state limit of Problem 1, or ``None``.

        The reason names the largest cluster, its receivers and the limit.
        """
        canon = canonical_labels(labels)
        sizes = np.bincount(canon)
        cap = self.max_cluster_size
        if sizes.max() <= cap:
            return None
        j = int(np.argmax(sizes))
        members = np.flatnonzero(canon == j).tolist()
        s = int(sizes[j])
        return (
            f"cluster {int(labels[members[0]])} (receivers {members}) has "
            f"max(N(C), N_y(C)) = {max(n_states(s), n_measurements(s))} > "
            f"n_max_states = {self.config.n_max_states} (at most {cap} receivers per cluster)"
        )

    # -- per-axis model (what the filters run on) -------------------------------------------
    def axis_model(self, members: Sequence[int]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(F, Q, H)`` of a cluster of ``len(members)`` receivers, per axis.

        State ``(p_1, v_1, ..., p_s, v_s, theta)`` (2s + 1), measurements
        ``(y1_1, y2_1, ..., y1_s, y2_s)`` with ``y1 = p - theta``, ``y2 = p + theta`` (eq. 3b).
        """
        return axis_model(float(self.config.dt), len(members))

    def _rho(self, s: int) -> FloatArray:
        return correlation(float(self.config.noise_correlation), s)

    def axis_noise(self, members: Sequence[int], k: int | None = None) -> FloatArray:
        """Per-axis measurement covariance (2s, 2s): ``R[(a,c),(b,c)] = rho_ab s_ca s_cb``.

        ``rho_aa = 1``, ``rho_ab = r`` (eq. 4); channels ``c`` (y1, y2) are uncorrelated. The
        levels ``s`` are those of step ``k`` (:meth:`sigma_at`), or the base ``sigma`` if
        ``k`` is ``None``.
        """
        idx = np.asarray(members, dtype=int)
        s = idx.size
        sigma = self.sigma if k is None else self.sigma_at(k)
        return noise_covariances(sigma[idx], self._rho(s))

    def axis_noise_steps(self, members: Any, k0: int, k1: int) -> FloatArray:
        """Per-step :meth:`axis_noise` of ``B`` clusters of one size, ``(B, k1 - k0, 2s, 2s)``.

        Args:
            members: (B, s) receiver indices, one cluster per row.
            k0: first step, ``>= 0``.
            k1: one past the last step, ``>= k0`` (``k1 - 1`` within the noise path).
        """
        idx = np.asarray(members, dtype=int)
        B, s = idx.shape
        k0, k1 = self._check_step(k0, "k0"), int(k1)
        if k1 < k0:
            raise ValueError(f"k1 must be >= k0={k0}, got {k1}")
        if k1 > k0:
            self._check_step(k1 - 1, "k1 - 1")
        if self.sigma_path is None:
            S = np.broadcast_to(self.sigma[idx][:, None], (B, k1 - k0, s, 2))
        else:
            S = np.moveaxis(self.sigma_path[k0:k1][:, idx], 0, 1)  # (B, T, s, 2)
        return noise_covariances(S, self._rho(s))

    def axis_prior(self, size: int) -> FloatArray:
        """Initial per-axis covariance ``diag(sp^2, sv^2, ..., sb^2)`` of a cluster."""
        return axis_prior(self.config.prior_std, size)

    # -- full model, eqs. (3)-(6): for tests and users --------------------------------------
    def full_model(
        self, members: Sequence[int], k: int | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``(A, Q, C, R)`` of a cluster in the paper's coordinates (eqs. 3, 6).

        State ``x = (p_1; v_1; ...; p_s; v_s; theta)`` in R^{4s+2}, measurement
        ``(y^{l_1}; ...; y^{l_s})`` in R^{4s} with ``y^i = (p^i - theta; p^i + theta)``. ``R``
        uses the levels of step ``k`` (:meth:`sigma_at`), or the base ``sigma`` if ``None``.
        """
        idx = np.asarray(members, dtype=int)
        s = idx.size
        h = float(self.config.dt)
        I2 = np.eye(2)
        N, M = n_states(s), n_measurements(s)
        A, Q, C = np.eye(N), np.zeros((N, N)), np.zeros((M, N))
        th = slice(4 * s, 4 * s + 2)
        for a in range(s):
            p, v = slice(4 * a, 4 * a + 2), slice(4 * a + 2, 4 * a + 4)
            A[p, v] = h * I2
            Q[p, p], Q[p, v], Q[v, p], Q[v, v] = h**3 / 3 * I2, h**2 / 2 * I2, h**2 / 2 * I2, h * I2
            C[4 * a : 4 * a + 2, p], C[4 * a : 4 * a + 2, th] = I2, -I2
            C[4 * a + 2 : 4 * a + 4, p], C[4 * a + 2 : 4 * a + 4, th] = I2, I2
        Q[th, th] = h * I2
        r = float(self.config.noise_correlation)
        sigma = self.sigma if k is None else self.sigma_at(k)
        Rii = [np.diag(np.repeat(sigma[i] ** 2, 2)) for i in idx]  # diag(s1^2 I, s2^2 I)
        R = np.zeros((M, M))
        for a in range(s):
            for b in range(s):
                blk = Rii[a] if a == b else r * np.sqrt(Rii[a]) @ np.sqrt(Rii[b])
                R[4 * a : 4 * a + 4, 4 * b : 4 * b + 4] = blk
        return A, Q, C, R

    def selection_maps(self, labels: Any) -> list[tuple[FloatArray, FloatArray]]:
        """``(M_I^{uj}, M_I^{sj})`` per cluster ``j`` (eq. after 6b), each (N(C_j), 4n + 2).

        Global state (eq. 5a) ``x = (x^1_u; ...; x^n_u; theta)`` with ``x^i_u = (p^i; v^i)``;
        ``M^{uj} x = (x^{uj}; 0)`` and ``M^{sj} x = (0; theta)``. Clusters in canonical order.
        """
        canon = self.check_clustering(labels)
        N = n_states(self.n)
        maps = []
        for j in range(int(canon.max()) + 1):
            members = np.flatnonzero(canon == j)
            s = members.size
            Mu, Ms = np.zeros((n_states(s), N)), np.zeros((n_states(s), N))
            for a, i in enumerate(members):
                Mu[4 * a : 4 * a + 4, 4 * i : 4 * i + 4] = np.eye(4)
            Ms[4 * s :, 4 * self.n :] = np.eye(2)
            maps.append((Mu, Ms))
        return maps


def make_clustering_problem(
    config: ClusteringConfig | None = None,
    rng: np.random.Generator | None = None,
    horizon: int | None = None,
) -> ClusteringProblem:
    """Draw a realisation: ``sigma ~ U(0, 1]`` unless given, then the regime path if any.

    ``sigma`` per receiver and channel first, then (with ``config.regimes``) the regime path of
    steps ``0 .. horizon`` from the same generator, in that order.

    Args:
        config: scenario parameters (default: the paper's Sec. IV-A).
        rng: generator for ``sigma`` and the regime path (required when either is drawn).
        horizon: last step ``K`` of the regime path (required with ``config.regimes``).
    """
    cfg = ClusteringConfig() if config is None else config
    if cfg.sigma is None and rng is None:
        raise ValueError("rng is required to draw sigma ~ U(0, 1] (config.sigma is None)")
    if cfg.regimes is not None:
        if isinstance(horizon, bool) or not isinstance(horizon, int | np.integer) or horizon < 0:
            raise ValueError(
                f"horizon must be an int >= 0 to draw the regime path, got {horizon!r}"
            )
        if rng is None:
            raise ValueError("rng is required to draw the regime path (config.regimes is set)")
    return make_clustering_problems(cfg, [rng], 0 if horizon is None else int(horizon))[0]


def make_clustering_problems(
    config: ClusteringConfig, rngs: Sequence[np.random.Generator | None], horizon: int
) -> list[ClusteringProblem]:
    """One realisation per generator, each drawn exactly as :func:`make_clustering_problem`.

    Generator ``b`` draws ``sigma`` ``(n, 2)`` (unless given), then the regime chain's start
    ``(n,)`` and its uniforms ``(horizon, n)``; the chains of all ``B`` realisations then run
    as one :func:`~selenv.families.clustering.batched.regime_paths` ``(B, horizon + 1, n)``.
    The arguments are not re-validated (a ``None`` generator is allowed only when nothing is
    drawn).
    """
    n = int(config.n_agents)
    fixed = None if config.sigma is None else _check_sigma(config.sigma, n)
    sigmas: list[FloatArray] = []
    starts, uniforms = [], []
    model = config.regimes
    for rng in rngs:
        if fixed is not None:
            sigma = fixed.copy()
        else:
            sigma = 1.0 - rng.random((n, 2))  # type: ignore[union-attr]  # U(0, 1]
        sigma.setflags(write=False)
        sigmas.append(sigma)
        if model is not None:
            starts.append(rng.random(n) < model.degraded_fraction)  # type: ignore[union-attr]
            uniforms.append(rng.random((int(horizon), n)))  # type: ignore[union-attr]
    if model is None:
        return [ClusteringProblem(config=config, sigma=sigma) for sigma in sigmas]
    paths = regime_paths(
        np.array(starts, dtype=float).reshape(len(sigmas), n),
        np.array(uniforms).reshape(len(sigmas), int(horizon), n),
        float(model.p_enter),
        float(model.p_leave),
    )
    return [
        ClusteringProblem(config=config, sigma=sigma, regimes=path)
        for sigma, path in zip(sigmas, paths, strict=True)
    ]
