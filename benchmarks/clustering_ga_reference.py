"""A straightforward implementation of the receiver-clustering GA, the benchmark's reference.

The operators and :class:`GeneticClustering` of ``selenv/families/clustering/ga.py`` written
plainly (every operator call validated), with plain label helpers (``canonical_labels`` by
``np.unique``, ``cluster_keys`` by a stable argsort) and :func:`old_evaluate`, a plain
``ClusterFilterBank.evaluate`` (one ``check_clustering`` and ``cluster_keys`` per candidate, no
caches). ``benchmarks/bench_clustering.py`` times it against the current code in
one process; ``tests/clustering/test_clustering_speed_identity.py`` holds the recorded outputs both
give.
Not part of the package; do not import it from ``selenv``.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment

from selenv.core.linalg import FloatArray
from selenv.core.riccati import riccati_pass
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.labels import (
    IntArray,
    as_labels,
    check_int,
    cluster_sizes,
    is_feasible,
    random_feasible_clustering,
)
from selenv.scenarios.validation import (
    ArgumentTypeError,
    as_generator,
    check_bool,
    check_generator,
    check_real,
    describe,
)

#: batched cost: ``evaluate(candidates (B, n) int) -> J (B,) float``
Evaluate = Callable[[IntArray], ArrayLike]

#: largest population ``N_S`` (the paper uses 20; every member is evaluated each generation)
MAX_POPULATION = 10_000
#: largest ``max_tries`` (random draws per operator call before falling back to the parent)
MAX_TRIES = 10_000
#: largest selection spread ``alpha`` (beyond ~1 the partner rank is already near uniform)
MAX_ALPHA = 100.0
#: operator variants of :class:`GAConfig` (``variant``): ours, and Table I as printed
VARIANTS = ("improved", "literal")

__all__ = [
    "MAX_ALPHA",
    "MAX_POPULATION",
    "MAX_TRIES",
    "VARIANTS",
    "GAConfig",
    "GeneticClustering",
    "align_labels",
    "canonical_labels",
    "cluster_sizes",
    "draw_rank",
    "is_feasible",
    "o1c",
    "o1c_literal",
    "o1m",
    "o1m_literal",
    "o2c",
    "o2c_literal",
    "o2m",
    "o2m_literal",
    "o3m",
    "old_ensure",
    "old_evaluate",
    "random_feasible_clustering",
]


def _check_alpha(alpha: object) -> float:
    return check_real(alpha, "alpha", 0.0, MAX_ALPHA, low_open=True)


def _check_caps(max_size: object, max_tries: object) -> tuple[int, int]:
    """The ``max_size`` and ``max_tries`` of an operator call, validated."""
    return check_int(max_size, "max_size", 1), check_int(max_tries, "max_tries", 1, MAX_TRIES)


def _label_counts(x: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """``(labels in use (sorted), index of each agent's label among them, cluster sizes)``.

    ``np.bincount`` for compact labels (the GA's canonical ones), ``np.unique`` otherwise, so
    that a label like ``10**12`` allocates nothing.
    """
    if int(x.max()) < 4 * x.size + 64:
        all_counts = np.bincount(x)
        used = all_counts > 0
        uniq = np.flatnonzero(used)
        return uniq, (np.cumsum(used) - 1)[x], all_counts[uniq]
    uniq, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    return uniq, inverse.reshape(-1), counts


def _fits(labels: IntArray, max_size: int) -> bool:
    """Every cluster of ``labels`` has at most ``max_size`` members (any label values)."""
    return bool(_label_counts(labels)[2].max() <= max_size)


def align_labels(a: ArrayLike, b: ArrayLike) -> IntArray:
    """Rename the clusters of ``b`` ``(n,)`` to agree with ``a`` ``(n,)`` on most agents.

    Maximises the matched mass of the contingency table ``T[i, j] = |A_i ∩ B_j|`` with
    :func:`scipy.optimize.linear_sum_assignment`; clusters of ``b`` left unmatched get the
    smallest labels unused by ``a``. The result ``(n,)`` is the partition of ``b``; if ``b`` is
    a relabelling of ``a`` it equals ``a``. Our addition to Greiff et al. 2022 (Table I crosses
    raw label vectors): it makes crossover meaningful despite label-permutation symmetry.
    """
    x, y = as_labels(a, "a"), as_labels(b, "b")
    if x.shape != y.shape:
        raise ValueError(f"a and b must have the same shape, got {x.shape} and {y.shape}")
    ua, ia = np.unique(x, return_inverse=True)
    ub, ib = np.unique(y, return_inverse=True)
    ia, ib = ia.reshape(-1), ib.reshape(-1)
    T = np.bincount(ia * ub.size + ib, minlength=ua.size * ub.size).reshape(ua.size, ub.size)
    rows, cols = linear_sum_assignment(T, maximize=True)
    mapping = np.empty(ub.size, dtype=np.int64)
    mapping[cols] = ua[rows]
    unmatched = np.setdiff1d(np.arange(ub.size), cols)
    mapping[unmatched] = np.setdiff1d(np.arange(x.size + ub.size), ua)[: unmatched.size]
    return mapping[ib]


def _retry(draw: Callable[[], IntArray], x: IntArray, max_size: int, max_tries: int) -> IntArray:
    """First feasible ``draw()`` out of ``max_tries`` (validated), else a copy of the parent."""
    for _ in range(max_tries):
        child = draw()
        if _fits(child, max_size):
            return child
    return x.copy()


def o1c(
    a: ArrayLike, b: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O1C (Table I): one-point crossover ``a[:j] ++ b'[j:]``, ``j ~ U{1..n-1}``.

    Args:
        a: ``(n,)`` first parent; a copy of it is the fallback.
        b: ``(n,)`` second parent, relabelled to ``b'`` by :func:`align_labels` first.
        rng: source of randomness.
        max_size: cluster-size cap, an int >= 1.
        max_tries: random draws (here cut points) before falling back to a copy of ``a``, an
            int in ``[1, MAX_TRIES]``.

    Returns:
        ``(n,)`` feasible child in ``a``'s label space, or a copy of ``a``.

    Raises:
        TypeError, ValueError: naming the bad argument (labels, ``rng`` not a ``Generator``,
            ``max_size`` / ``max_tries`` not an int in range).
    """
    x = as_labels(a, "a")
    y = align_labels(x, b)
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)

    def draw() -> IntArray:
        j = int(rng.integers(1, x.size)) if x.size > 1 else 1  # cut point
        return np.concatenate([x[:j], y[j:]])

    return _retry(draw, x, max_size, max_tries)


def o2c(
    a: ArrayLike, b: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O2C (Table I): uniform crossover, each element from ``a`` or aligned ``b'`` w.p. 1/2.

    Arguments and result as :func:`o1c`.
    """
    x = as_labels(a, "a")
    y = align_labels(x, b)
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    return _retry(lambda: np.where(rng.random(x.size) < 0.5, x, y), x, max_size, max_tries)


def o1m(
    a: ArrayLike, n_labels: int, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O1M (Table I): set one element of ``a`` ``(n,)`` to another label in ``[0, n_labels)``.

    Enumerates the feasible moves ``(agent i, label l != a[i])`` that change the partition and
    picks one uniformly. Every unused label gives the same partition (``i`` alone in a new
    cluster), so they count as one move, to the smallest unused label; a singleton moved to an
    unused label is no change and is excluded. ``max_tries`` is accepted for the common
    signature and not used. Returns an ``(n,)`` child differing from ``a`` in exactly one
    element, or a copy of ``a`` when no feasible move exists.
    """
    x = as_labels(a, "a")
    n_labels = check_int(n_labels, "n_labels", 1)
    check_generator(rng)
    max_size, _ = _check_caps(max_size, max_tries)
    # cluster sizes from the labels in use (no array of length n_labels or max(a) + 1)
    uniq, inverse, counts = _label_counts(x)
    size_x = counts[inverse]  # (n,) size of each agent's cluster
    used = uniq[uniq < n_labels]
    # the smallest label in [0, n_labels) not in use is at most len(uniq)
    unused = np.setdiff1d(np.arange(min(n_labels, uniq.size + 1)), uniq)[:1]
    targets = np.append(used, unused)  # (L,)
    size_t = np.append(counts[uniq < n_labels], np.zeros(unused.size, np.int64))
    over = counts > max_size
    over_x = over[inverse]
    # the source cluster of agent i shrinks by one: fine unless another cluster is over the cap
    src_ok = (over.sum() == 0) | ((over.sum() == 1) & over_x & (size_x - 1 <= max_size))
    ok = (targets[None, :] != x[:, None]) & (size_t < max_size)[None, :] & src_ok[:, None]
    if unused.size:
        ok[:, -1] &= size_x > 1  # a singleton moved to a new cluster: same partition
    agents, cols = np.nonzero(ok)  # (n, L) -> feasible moves
    child = x.copy()
    if agents.size:
        k = int(rng.integers(agents.size))
        child[agents[k]] = targets[cols[k]]
    return child


def o2m(a: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20) -> IntArray:
    """O2M (Table I): swap the labels of two agents of ``a`` ``(n,)`` in different clusters.

    The pair is uniform over pairs with different labels; cluster sizes are preserved, so the
    child is feasible iff ``a`` is. Returns a copy of ``a`` if it has a single cluster.
    """
    x = as_labels(a, "a")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    i, j = np.nonzero(np.triu(x[:, None] != x[None, :]))
    if i.size == 0:
        return x.copy()

    def draw() -> IntArray:
        k = int(rng.integers(i.size))
        child = x.copy()
        child[[i[k], j[k]]] = x[[j[k], i[k]]]
        return child

    return _retry(draw, x, max_size, max_tries)


def o3m(a: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20) -> IntArray:
    """O3M (Table I): O2C on two random clusters of ``a`` ``(n,)``.

    Each try picks two distinct clusters and reassigns each of their members to one of the two
    w.p. 1/2. Returns a copy of ``a`` if it has a single cluster or no try was feasible.
    """
    x = as_labels(a, "a")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    clusters = np.unique(x)
    if clusters.size < 2:
        return x.copy()

    def draw() -> IntArray:
        l1, l2 = rng.choice(clusters, size=2, replace=False)
        members = np.flatnonzero((x == l1) | (x == l2))
        child = x.copy()
        child[members] = np.where(rng.random(members.size) < 0.5, l1, l2)
        return child

    return _retry(draw, x, max_size, max_tries)


# -- Table I as printed (GAConfig(variant="literal")) -------------------------------------------
def o1c_literal(
    a: ArrayLike, b: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O1C as printed in Table I: ``a[:j] ++ b[j:]`` on the raw labels, ``j ~ U{1..n}``.

    No :func:`align_labels`: label ``l`` of ``b`` is read as label ``l`` of ``a``. Table I
    prints "randomize ``j`` in {1, ..., n}; combine the first ``l`` elements of ``I^A`` with
    the last ``j - l`` elements of ``I^B``"; we read it as the first ``j`` of ``a`` and the
    last ``n - j`` of ``b`` with ``j`` uniform on ``{1..n}`` as printed (``j = n`` gives a copy
    of ``a``; :func:`o1c` draws ``j`` from ``{1..n-1}``). Arguments, retries and result as
    :func:`o1c`.
    """
    x, y = as_labels(a, "a"), as_labels(b, "b")
    if x.shape != y.shape:
        raise ValueError(f"a and b must have the same shape, got {x.shape} and {y.shape}")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)

    def draw() -> IntArray:
        j = int(rng.integers(1, x.size + 1))  # cut point, j in {1..n}
        return np.concatenate([x[:j], y[j:]])

    return _retry(draw, x, max_size, max_tries)


def o2c_literal(
    a: ArrayLike, b: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O2C as printed in Table I: each element from ``a`` or raw ``b`` (no alignment) w.p. 1/2.

    The same draws as :func:`o2c` (one ``rng.random(n)`` per try); arguments as :func:`o1c`.
    """
    x, y = as_labels(a, "a"), as_labels(b, "b")
    if x.shape != y.shape:
        raise ValueError(f"a and b must have the same shape, got {x.shape} and {y.shape}")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    return _retry(lambda: np.where(rng.random(x.size) < 0.5, x, y), x, max_size, max_tries)


def o1m_literal(
    a: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O1M as printed in Table I: set a random element of ``a`` to a number in ``[1, |C|]``.

    ``[1, |C|]`` is read as the ``|C|`` labels present in ``a`` (the GA's canonical labels are
    ``0..|C|-1``), so no new cluster is ever opened; a cluster may empty, so ``|C|`` may drop.
    Each try draws the element and the label uniformly and independently; the label may be
    the element's own (Table I does not exclude it: that child equals ``a``). Infeasible
    draws (target cluster already at ``max_size``) are retried up to ``max_tries`` times, then
    a copy of ``a`` is returned, as for the other operators. Unlike :func:`o1m`, no
    ``n_labels``.
    """
    x = as_labels(a, "a")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    present = _label_counts(x)[0]  # (|C|,) labels in use, sorted

    def draw() -> IntArray:
        child = x.copy()
        child[int(rng.integers(x.size))] = present[int(rng.integers(present.size))]
        return child

    return _retry(draw, x, max_size, max_tries)


def o2m_literal(
    a: ArrayLike, rng: np.random.Generator, max_size: int, max_tries: int = 20
) -> IntArray:
    """O2M as printed in Table I: swap the labels of two random elements of ``a`` ``(n,)``.

    The two positions are distinct and uniform over all pairs (Table I does not require
    different clusters: swapping two members of one cluster returns ``a`` unchanged, where
    :func:`o2m` draws only pairs from different clusters). Sizes are preserved, so the child is
    feasible iff ``a`` is. Returns a copy of ``a`` if ``n < 2``.
    """
    x = as_labels(a, "a")
    check_generator(rng)
    max_size, max_tries = _check_caps(max_size, max_tries)
    if x.size < 2:
        return x.copy()

    def draw() -> IntArray:
        i, j = rng.choice(x.size, size=2, replace=False)
        child = x.copy()
        child[[i, j]] = x[[j, i]]
        return child

    return _retry(draw, x, max_size, max_tries)


def draw_rank(rng: np.random.Generator, alpha: float, population_size: int) -> int:
    """Selection of Alg. 2, steps 4-5: rank ``r`` of the partner, the ``(r+1)``-th best.

    Returns ``r = clip(round(|r̄|), 1, N_S - 1)`` with ``r̄ ~ N(0, (alpha (N_S - 1))^2)``: the
    index of the partner in the population sorted by cost. ``rng`` must be a ``Generator``,
    ``alpha`` in ``(0, MAX_ALPHA]``, ``population_size`` an int in ``[2, MAX_POPULATION]``.
    """
    check_generator(rng)
    N_S = check_int(population_size, "population_size", 2, MAX_POPULATION)
    r_bar = rng.normal(0.0, _check_alpha(alpha) * (N_S - 1))  # r̄ ~ N(0, (α(N_S - 1))²)
    return min(max(round(abs(r_bar)), 1), N_S - 1)  # nearest integer in [1, N_S - 1]


@dataclass(frozen=True, kw_only=True)
class GAConfig:
    """Parameters of :class:`GeneticClustering` (defaults: the paper's alpha 0.1, N_S 20).

    Attributes:
        population_size: ``N_S``, an int in ``[2, MAX_POPULATION]`` (10 000).
        alpha: selection spread (:func:`draw_rank`), in ``(0, MAX_ALPHA]`` (100).
        operators: the ``O`` vector of Table II: 0/1 flags for (O1C, O2C, O1M, O2M, O3M), at
            least one set. With no crossover enabled the crossover half of a generation is
            filled by mutations; with no mutation enabled the mutation half by crossovers.
        max_tries: random draws per operator call before falling back to the parent, an int
            in ``[1, MAX_TRIES]`` (10 000).
        n_labels: label range of O1M, an int >= 1 (``None``: ``n``).
        redraw_partner: draw a new partner rank for every crossover (``False``: once per
            generation, as Alg. 2 does); a bool.
        variant: which Table I operators, one of :data:`VARIANTS`: ``"improved"`` (ours:
            crossovers on aligned labels, O1M may open a singleton, see the module docstring)
            or ``"literal"`` (Table I as printed: :func:`o1c_literal`, :func:`o2c_literal`,
            :func:`o1m_literal`, :func:`o2m_literal`, :func:`o3m`). Named ``variant`` because
            ``operators`` is already Table II's O vector (the paper's Table II calls it
            ``operators="literal"``); the O vector selects among the chosen variant's five.
            ``n_labels`` only applies to the improved O1M and must be ``None`` with literal.

    Raises:
        TypeError, ValueError: naming the field (wrong type, or outside its range).
    """

    population_size: int = 20
    alpha: float = 0.1
    operators: tuple[int, ...] = (1, 1, 1, 1, 1)
    max_tries: int = 20
    n_labels: int | None = None
    redraw_partner: bool = False
    variant: str = "improved"

    def __post_init__(self) -> None:
        check_int(self.population_size, "population_size", 2, MAX_POPULATION)
        _check_alpha(self.alpha)
        ops = tuple(self.operators) if isinstance(self.operators, tuple | list) else None
        if ops is None or len(ops) != 5 or any(isinstance(o, str) or o not in (0, 1) for o in ops):
            raise ValueError(
                "operators must be 5 flags in {0, 1} (O1C, O2C, O1M, O2M, O3M), got "
                f"{describe(self.operators)}"
            )
        if not any(ops):
            raise ValueError("operators must enable at least one operator, got all zeros")
        object.__setattr__(self, "operators", tuple(int(o) for o in ops))
        check_int(self.max_tries, "max_tries", 1, MAX_TRIES)
        if self.n_labels is not None:
            check_int(self.n_labels, "n_labels", 1)
        check_bool(self.redraw_partner, "redraw_partner")
        if not isinstance(self.variant, str) or self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {describe(self.variant)}")
        if self.variant == "literal" and self.n_labels is not None:
            raise ValueError(
                "n_labels applies to the improved O1M only; the literal O1M draws from the "
                f"labels present, so n_labels must be None with variant='literal', got "
                f"{describe(self.n_labels)}"
            )


class GeneticClustering:
    """Genetic algorithm for clustering under a size cap (Greiff et al. 2022, Alg. 2 / Table I).

    Each :meth:`generation` keeps the best member (elitism; it is re-evaluated because the cost
    may drift in time), adds crossovers of (best, partner at :func:`draw_rank`) with a uniformly
    random enabled O_C until ``ceil(N_S / 2)`` members, then mutations of uniformly random
    members of the new population so far with a random enabled O_M until ``N_S``, evaluates all
    ``N_S`` in one batched ``evaluate`` call and sorts them by cost (stable: ties keep the elite
    first). With a time-invariant cost the best cost never increases.

    Args:
        evaluate: batched cost, ``(B, n)`` canonical labels -> ``(B,)`` float, lower is better
            (a callable; NaN costs are refused).
        initial_labels: ``(n,)`` feasible clustering; the initial population is it plus
            ``N_S - 1`` mutations of it (random feasible clusterings if no O_M is enabled).
        max_size: cluster-size cap (Problem 1), an int >= 1.
        config: :class:`GAConfig`, default ``GAConfig()``.
        rng: generator, int seed >= 0 or ``None``.

    Attributes:
        population: ``(N_S, n)`` canonical labels sorted by cost.
        costs: ``(N_S,)`` costs, increasing.
        n_generations: generations run.
        n_evaluations: candidates passed to ``evaluate`` in total, duplicates included.

    Raises:
        TypeError, ValueError: naming the bad argument: ``evaluate`` not callable or
            returning a wrong shape, non-numbers or NaN; ``initial_labels`` not a label vector
            or infeasible (naming the cluster and its size); ``config`` not a
            :class:`GAConfig`; ``rng`` neither a generator nor a seed.
    """

    def __init__(
        self,
        evaluate: Evaluate,
        initial_labels: ArrayLike,
        max_size: int,
        config: GAConfig | None = None,
        rng: np.random.Generator | int | None = None,
    ) -> None:
        if not callable(evaluate):
            raise ArgumentTypeError(
                f"evaluate must be a callable (B, n) labels -> (B,) costs, got {describe(evaluate)}"
            )
        if config is not None and not isinstance(config, GAConfig):
            raise ArgumentTypeError(f"config must be a GAConfig or None, got {describe(config)}")
        self.config = GAConfig() if config is None else config
        self.max_size = check_int(max_size, "max_size", 1)
        self._evaluate = evaluate
        self._rng = as_generator(rng)
        x = as_labels(initial_labels, "initial_labels")
        self.n = x.size
        self.n_labels = self.n if self.config.n_labels is None else self.config.n_labels
        self.n_generations = 0
        self.n_evaluations = 0
        O = self.config.operators  # noqa: E741  (the paper's symbol)
        self._crossovers = [k for k in range(2) if O[k]]  # 0: O1C, 1: O2C
        self._mutations = [k for k in range(3) if O[2 + k]]  # 0: O1M, 1: O2M, 2: O3M
        self.population: IntArray
        self.costs: FloatArray
        self._initialize(x, "initial_labels")

    @property
    def best(self) -> IntArray:
        """``(n,)`` canonical labels of the best member."""
        return self.population[0].copy()

    @property
    def best_cost(self) -> float:
        """Cost of :attr:`best` at its last evaluation."""
        return float(self.costs[0])

    def reset_population(self, labels: ArrayLike) -> None:
        """Restart from ``labels`` ``(n,)`` as in ``__init__``; counters keep accumulating."""
        self._initialize(as_labels(labels, "labels"), "labels")

    def generation(self) -> tuple[IntArray, float]:
        """Run one generation of Alg. 2 (steps 4-15); return ``(best (n,), best cost)``."""
        cfg, rng = self.config, self._rng
        r = draw_rank(rng, cfg.alpha, cfg.population_size)  # steps 4-5
        new = [self.population[0].copy()]  # step 6: elitism
        while len(new) < cfg.population_size / 2:  # steps 7-10
            if cfg.redraw_partner:
                r = draw_rank(rng, cfg.alpha, cfg.population_size)
            new.append(self._crossover(r) if self._crossovers else self._mutate(new))
        while len(new) < cfg.population_size:  # steps 11-14
            new.append(self._mutate(new) if self._mutations else self._crossover(r))
        self._accept(np.stack(new))  # step 15
        self.n_generations += 1
        return self.best, self.best_cost

    def _crossover(self, r: int) -> IntArray:
        ops = (o1c_literal, o2c_literal) if self.config.variant == "literal" else (o1c, o2c)
        op = ops[self._crossovers[int(self._rng.integers(len(self._crossovers)))]]
        a, b = self.population[0], self.population[r]
        return op(a, b, self._rng, self.max_size, self.config.max_tries)

    def _mutate(self, members: list[IntArray]) -> IntArray:
        k = self._mutations[int(self._rng.integers(len(self._mutations)))]
        a = members[int(self._rng.integers(len(members)))]
        rng, s, t = self._rng, self.max_size, self.config.max_tries
        if self.config.variant == "literal":
            return (o1m_literal, o2m_literal, o3m)[k](a, rng, s, t)
        return o1m(a, self.n_labels, rng, s, t) if k == 0 else (o2m, o3m)[k - 1](a, rng, s, t)

    def _initialize(self, x: IntArray, name: str) -> None:
        if x.size != self.n:
            raise ValueError(f"{name} must have n={self.n} entries, got {x.size}")
        canon = canonical_labels(x)  # compacted first: labels like 10**12 allocate nothing
        sizes = np.bincount(canon)
        if np.any(over := sizes > self.max_size):
            k = int(np.argmax(over))
            c = int(x[np.argmax(canon == k)])  # named by the label as given
            msg = f"cluster {c} has {int(sizes[k])} members, max_size={self.max_size}"
            raise ValueError(f"{name} is infeasible: {msg}")
        x = canon
        N_S, rng = self.config.population_size, self._rng
        if self._mutations:
            others = [self._mutate([x]) for _ in range(N_S - 1)]
        else:
            others = [
                random_feasible_clustering(self.n, self.max_size, rng) for _ in range(N_S - 1)
            ]
        self._accept(np.stack([x, *others]))

    def _accept(self, candidates: IntArray) -> None:
        """Evaluate ``candidates`` ``(B, n)`` in one batch and store them sorted by cost."""
        candidates = np.stack([canonical_labels(c) for c in candidates])
        B = candidates.shape[0]
        raw = self._evaluate(candidates)
        try:
            J = np.asarray(raw)
        except ValueError as exc:  # ragged
            raise ValueError(f"evaluate must return (B,) real costs, got {describe(raw)}") from exc
        if J.dtype.kind not in "iuf":
            raise ValueError(f"evaluate must return (B,) real costs, got {describe(raw)}")
        J = J.astype(np.float64)
        if J.shape != (B,):
            raise ValueError(f"evaluate must return shape ({B},), got {J.shape}")
        if np.any(np.isnan(J)):
            raise ValueError("evaluate returned NaN costs")
        order = np.argsort(J, kind="stable")  # ties keep the elite (index 0) first
        self.population, self.costs = candidates[order], J[order]
        self.n_evaluations += B


# -- the plain label helpers and the bank's evaluate ----------------------------------------
def canonical_labels(labels: ArrayLike) -> IntArray:
    """Relabel by first appearance (the ``np.unique`` version of that time)."""
    x = as_labels(labels, "labels")
    _, first, inverse = np.unique(x, return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[inverse.reshape(-1)]


def cluster_keys(canon: np.ndarray) -> list[tuple[int, ...]]:
    """Member tuples of the clusters of a canonical labelling (stable argsort version)."""
    order = np.argsort(canon, kind="stable")
    bounds = np.flatnonzero(np.diff(canon[order])) + 1
    return [tuple(int(i) for i in part) for part in np.split(order, bounds)]


def check_clustering(problem: Any, labels: Any, name: str) -> np.ndarray:
    """``ClusteringProblem.check_clustering`` of that time (two relabellings per call)."""
    arr = problem.check_labels(labels, name)
    canon = canonical_labels(arr)
    if np.bincount(canon).max() > problem.max_cluster_size:
        raise ValueError(f"{name}: {problem.violation(arr)}")
    return canonical_labels(arr)


def old_evaluate(bank: ClusterFilterBank, candidates: Any) -> FloatArray:
    """``ClusterFilterBank.evaluate`` as it was: validate and key every row, no caches."""
    arr = np.asarray(candidates)
    single = arr.ndim == 1
    arr = arr[None] if single else arr
    keysets = [
        cluster_keys(check_clustering(bank.problem, row, f"candidates[{b}]"))
        for b, row in enumerate(arr)
    ]
    old_ensure(bank, {key for keys in keysets for key in keys})
    out = np.array([bank._cost_from_stats(keys) for keys in keysets])
    bank.n_cost_evaluations += len(keysets)
    return out[0:1] if single else out


def old_ensure(bank: ClusterFilterBank, keys: set[tuple[int, ...]]) -> None:
    """``ClusterFilterBank._ensure`` as it was (validating ``riccati_pass`` per group)."""
    missing = [key for key in keys if key not in bank._window]
    if missing:
        steps = next(iter(bank._hist.values())).shape[0] - 1  # k - l
        by_size: dict[int, list[tuple[int, ...]]] = defaultdict(list)
        for key in missing:
            by_size[len(key)].append(key)
        for group in by_size.values():
            F, Q, H = bank.problem.axis_model(group[0])
            P0 = bank._composed_priors(group)
            R = bank._noise(group, bank.k - steps + 1, bank.k + 1)  # R_{l+1} .. R_k
            hist = riccati_pass(P0, F, Q, H, R, steps)
            bank._store(group, hist)
        bank.n_cluster_passes += len(missing)
    for key in keys:
        if key not in bank._stats:
            bank._store([key], bank._window[key][None])
