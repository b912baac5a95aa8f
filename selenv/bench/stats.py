"""Paired statistics of the benchmark: differences against a baseline on the same seeds.

Every agent plays the same seeded episodes (episode ``e`` uses ``seed + e``), so agent and
baseline returns form pairs and the per-seed difference ``d_e = R_agent,e - R_baseline,e``
removes the scenario-to-scenario variance that an unpaired mean ± std keeps. For the
``n`` differences this module computes

* the mean difference ``d_bar``;
* a **percentile bootstrap** 95 % CI of the mean (:func:`bootstrap_ci`): ``resamples``
  (default 10,000) resamples of the ``n`` differences with replacement, each resample's mean,
  and the 2.5 / 97.5 percentiles of those means (``np.percentile``, linear interpolation).
  The resample indices come from an explicit ``np.random.Generator`` seeded with
  ``BOOTSTRAP_SEED`` (0), drawn as ``rng.integers(0, n, size=(resamples, n))`` in blocks of
  rows (the same stream as one call), so the CI is deterministic;
* the Student t-interval ``d_bar ± t_{0.975, n-1} s / sqrt(n)`` (``s`` the sample standard
  deviation, ``ddof=1``), for comparison (:func:`t_interval`);
* **wins / ties / losses**: seeds with ``d_e > tol_e`` / ``|d_e| <= tol_e`` / ``d_e < -tol_e``
  where ``tol_e = TIE_REL_TOL * max(1, |R_baseline,e|)`` (``TIE_REL_TOL = 1e-9``): a tie is
  a difference at floating-point noise level, relative to the baseline's return.

With fewer than two episodes a CI is undefined: both intervals are ``(nan, nan)`` (``None``
in the JSON). "A beats B" (DESIGN.md) means the paired 95 % CI of ``A - B`` excludes 0.

:func:`normalized_score` maps a mean return to ``(R - R_random) / (R_best - R_random)``: 0 for
the random reference, 1 for the best agent that was run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "BOOTSTRAP_RESAMPLES",
    "BOOTSTRAP_SEED",
    "CONFIDENCE",
    "TIE_REL_TOL",
    "PairedComparison",
    "bootstrap_ci",
    "compare_paired",
    "normalized_score",
    "t_interval",
    "win_tie_loss",
]

#: resamples of :func:`bootstrap_ci`
BOOTSTRAP_RESAMPLES = 10_000
#: seed of the generator of :func:`bootstrap_ci` (deterministic output)
BOOTSTRAP_SEED = 0
#: confidence level of the intervals
CONFIDENCE = 0.95
#: a pair is a tie when ``|d| <= TIE_REL_TOL * max(1, |baseline return|)``
TIE_REL_TOL = 1e-9
#: upper bound on the resample indices held in memory at once (rows are drawn in blocks)
_BLOCK_ELEMENTS = 2_000_000


def _as_1d(values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def _check_confidence(confidence: float) -> float:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    return float(confidence)


def bootstrap_ci(
    diffs: Sequence[float] | np.ndarray,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    rng: np.random.Generator | None = None,
) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean of ``diffs`` (see the module docstring).

    Args:
        diffs: ``(n,)`` paired differences.
        confidence: coverage of the interval (0.95: the 2.5 and 97.5 percentiles).
        resamples: number of bootstrap resamples (``>= 1``).
        rng: generator of the resample indices; default ``default_rng(BOOTSTRAP_SEED)``.

    Returns:
        ``(lo, hi)``; ``(nan, nan)`` when ``n < 2``.
    """
    d = _as_1d(diffs, "diffs")
    alpha = 1.0 - _check_confidence(confidence)
    if isinstance(resamples, bool) or not isinstance(resamples, int) or resamples < 1:
        raise ValueError(f"resamples must be an int >= 1, got {resamples!r}")
    n = d.size
    if n < 2:
        return (math.nan, math.nan)
    gen = np.random.default_rng(BOOTSTRAP_SEED) if rng is None else rng
    block = max(1, _BLOCK_ELEMENTS // n)
    means = np.empty(resamples)
    for start in range(0, resamples, block):
        rows = min(block, resamples - start)
        idx = gen.integers(0, n, size=(rows, n))  # resample with replacement
        means[start : start + rows] = d[idx].mean(axis=1)
    lo, hi = np.percentile(means, [100.0 * alpha / 2.0, 100.0 * (1.0 - alpha / 2.0)])
    return (float(lo), float(hi))


def t_interval(
    diffs: Sequence[float] | np.ndarray, *, confidence: float = CONFIDENCE
) -> tuple[float, float]:
    """Student t CI ``d_bar ± t_{1-a/2, n-1} s / sqrt(n)`` of the mean; ``(nan, nan)`` if n < 2."""
    d = _as_1d(diffs, "diffs")
    alpha = 1.0 - _check_confidence(confidence)
    n = d.size
    if n < 2:
        return (math.nan, math.nan)
    from scipy import stats as sps  # deferred: scipy.stats imports slowly (selenv list)

    half = float(sps.t.ppf(1.0 - alpha / 2.0, n - 1)) * float(d.std(ddof=1)) / math.sqrt(n)
    mean = float(d.mean())
    return (mean - half, mean + half)


def win_tie_loss(
    returns: Sequence[float] | np.ndarray,
    baseline_returns: Sequence[float] | np.ndarray,
    *,
    rel_tol: float = TIE_REL_TOL,
) -> tuple[int, int, int]:
    """Seeds on which the agent's return is above / equal to / below the baseline's.

    Equal means ``|d_e| <= rel_tol * max(1, |baseline_e|)`` (module docstring).
    """
    a, b = _paired(returns, baseline_returns)
    d = a - b
    tol = rel_tol * np.maximum(1.0, np.abs(b))
    return int(np.sum(d > tol)), int(np.sum(np.abs(d) <= tol)), int(np.sum(d < -tol))


def _paired(
    returns: Sequence[float] | np.ndarray, baseline_returns: Sequence[float] | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    a = _as_1d(returns, "returns")
    b = _as_1d(baseline_returns, "baseline_returns")
    if a.shape != b.shape:
        raise ValueError(
            f"paired returns need the same episodes: got {a.size} and {b.size} episodes"
        )
    return a, b


def _json_float(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


@dataclass(frozen=True, kw_only=True)
class PairedComparison:
    """An agent against the baseline on the same seeds (module docstring).

    Attributes:
        baseline: name of the baseline agent.
        diffs: ``(n,)`` per-seed differences ``agent - baseline`` of the episode return.
        mean_diff: mean of ``diffs``.
        ci95: percentile bootstrap CI of ``mean_diff`` (``(nan, nan)`` if n < 2).
        ci95_t: Student t-interval of ``mean_diff``, for comparison.
        wins: seeds where the agent's return is higher (beyond the tie tolerance).
        ties: seeds within the tie tolerance.
        losses: seeds where it is lower.
    """

    baseline: str
    diffs: tuple[float, ...]
    mean_diff: float
    ci95: tuple[float, float]
    ci95_t: tuple[float, float]
    wins: int
    ties: int
    losses: int

    @property
    def n(self) -> int:
        """Number of pairs (episodes)."""
        return len(self.diffs)

    @property
    def significant(self) -> bool:
        """Whether the bootstrap CI excludes 0 (DESIGN.md's "A beats B" / "B beats A")."""
        lo, hi = self.ci95
        return not (math.isnan(lo) or lo <= 0.0 <= hi)

    def to_json(self) -> dict[str, Any]:
        """``{"baseline", "mean_diff", "ci95", "wins", "ties", "losses"}`` plus ``ci95_t``, ``n``.

        An undefined interval (``n < 2``) is ``[null, null]``.
        """
        return {
            "baseline": self.baseline,
            "mean_diff": self.mean_diff,
            "ci95": [_json_float(x) for x in self.ci95],
            "wins": self.wins,
            "ties": self.ties,
            "losses": self.losses,
            "ci95_t": [_json_float(x) for x in self.ci95_t],
            "n": self.n,
        }


def compare_paired(
    returns: Sequence[float] | np.ndarray,
    baseline_returns: Sequence[float] | np.ndarray,
    baseline: str,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    rel_tol: float = TIE_REL_TOL,
) -> PairedComparison:
    """Paired comparison of ``returns`` with ``baseline_returns`` (same seeds, same order).

    The bootstrap uses ``np.random.default_rng(seed)``, so equal inputs give equal output.
    """
    a, b = _paired(returns, baseline_returns)
    d = a - b
    w, t, lo = win_tie_loss(a, b, rel_tol=rel_tol)
    return PairedComparison(
        baseline=baseline,
        diffs=tuple(float(x) for x in d),
        mean_diff=float(d.mean()) if d.size else math.nan,
        ci95=bootstrap_ci(
            d, confidence=confidence, resamples=resamples, rng=np.random.default_rng(seed)
        ),
        ci95_t=t_interval(d, confidence=confidence),
        wins=w,
        ties=t,
        losses=lo,
    )


def normalized_score(
    mean_return: float, random_mean: float | None, best_mean: float
) -> float | None:
    """``(R - R_random) / (R_best - R_random)``; ``None`` without a random reference or if equal.

    0 is the random reference, 1 the best agent that was run; above 1 is impossible when
    ``best_mean`` is the best of the same run, below 0 means worse than random.
    """
    if random_mean is None or best_mean == random_mean:
        return None
    return float((mean_return - random_mean) / (best_mean - random_mean))
