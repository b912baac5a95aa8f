"""Paired statistics of the bench (selenv.bench.stats) against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from selenv.bench import AgentResult, BenchError, EnvBenchResult
from selenv.bench.stats import (
    BOOTSTRAP_RESAMPLES,
    bootstrap_ci,
    compare_paired,
    normalized_score,
    t_interval,
    win_tie_loss,
)

AGENT = np.array([3.0, 5.0, 4.0, 6.0, 2.0, 5.0])
BASE = np.array([2.0, 4.0, 4.0, 3.0, 3.0, 4.0])
# d = AGENT - BASE = [1, 1, 0, 3, -1, 1]: mean 5/6, sum of squared deviations 318/36
MEAN = 5.0 / 6.0
S = math.sqrt(318.0 / 36.0 / 5.0)  # sample std (ddof=1) = 1.32916...
T_975_5 = 2.570581835636315  # Student t quantile 0.975 with 5 degrees of freedom (tables)


def _reference_bootstrap(d: np.ndarray, seed: int = 0, resamples: int = 10_000) -> np.ndarray:
    """Percentile bootstrap with plain numpy, as the module docstring describes it."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, d.size, size=(resamples, d.size))
    return np.percentile(d[idx].mean(axis=1), [2.5, 97.5])


def test_t_interval_by_hand() -> None:
    half = T_975_5 * S / math.sqrt(6)
    lo, hi = t_interval(AGENT - BASE)
    assert (lo, hi) == pytest.approx((MEAN - half, MEAN + half), rel=1e-12)
    assert (lo, hi) == pytest.approx((-0.5615, 2.2282), abs=1e-4)


def test_bootstrap_matches_a_plain_numpy_reference_and_is_deterministic() -> None:
    d = AGENT - BASE
    ci = bootstrap_ci(d)
    np.testing.assert_allclose(ci, _reference_bootstrap(d), rtol=0, atol=1e-15)
    assert bootstrap_ci(d) == ci  # fixed seed: same output every call
    assert min(d) <= ci[0] <= MEAN <= ci[1] <= max(d)
    other = bootstrap_ci(d, rng=np.random.default_rng(1))
    np.testing.assert_allclose(other, _reference_bootstrap(d, seed=1), rtol=0, atol=1e-15)
    # many episodes: the resamples are drawn in blocks of rows, the same stream as one call
    big = np.random.default_rng(3).normal(0.2, 1.0, 700)
    np.testing.assert_allclose(bootstrap_ci(big), _reference_bootstrap(big), atol=1e-15)


def test_bootstrap_agrees_roughly_with_the_t_interval() -> None:
    d = np.random.default_rng(5).normal(0.3, 2.0, 200)
    (blo, bhi), (tlo, thi) = bootstrap_ci(d), t_interval(d)
    half = (thi - tlo) / 2
    assert abs(blo - tlo) < 0.1 * half and abs(bhi - thi) < 0.1 * half
    # the small hand-made sample: the percentile bootstrap is narrower than t (n = 6)
    (blo, bhi), (tlo, thi) = bootstrap_ci(AGENT - BASE), t_interval(AGENT - BASE)
    assert tlo < blo < MEAN < bhi < thi


def test_intervals_are_undefined_below_two_episodes() -> None:
    assert all(math.isnan(x) for x in bootstrap_ci([0.5]))
    assert all(math.isnan(x) for x in t_interval([0.5]))
    p = compare_paired([1.0], [0.5], "b")
    assert p.mean_diff == 0.5 and not p.significant
    assert p.to_json()["ci95"] == [None, None] and p.to_json()["ci95_t"] == [None, None]


def test_win_tie_loss_with_a_relative_tolerance() -> None:
    assert win_tie_loss(AGENT, BASE) == (4, 1, 1)
    base = np.array([1e6, 1e6, 1e6, 0.5, 0.5, -2e6])
    agent = base + np.array([1e-4, 2e-3, -2e-3, 5e-10, 2e-9, -1.9e-3])
    # tol = 1e-9 * max(1, |b|): 1e-3 for |b| = 1e6, 1e-9 for b = 0.5, 2e-3 for |b| = 2e6
    assert win_tie_loss(agent, base) == (2, 3, 1)
    with pytest.raises(ValueError, match="same episodes"):
        win_tie_loss([1.0, 2.0], [1.0])


def test_compare_paired_fields_and_json() -> None:
    p = compare_paired(AGENT, BASE, "base")
    assert p.baseline == "base" and p.n == 6
    assert p.diffs == (1.0, 1.0, 0.0, 3.0, -1.0, 1.0)
    assert p.mean_diff == pytest.approx(MEAN)
    assert (p.wins, p.ties, p.losses) == (4, 1, 1)
    assert p.ci95 == bootstrap_ci(AGENT - BASE)
    assert p.ci95_t == t_interval(AGENT - BASE)
    assert not p.significant  # the CI contains 0
    doc = p.to_json()
    assert {"baseline", "mean_diff", "ci95", "wins", "ties", "losses"} <= set(doc)
    assert doc["ci95"] == list(p.ci95)
    assert compare_paired(AGENT + 10, BASE, "base").significant
    assert BOOTSTRAP_RESAMPLES >= 10_000


def test_normalized_score() -> None:
    assert normalized_score(5.0, 1.0, 9.0) == pytest.approx(0.5)
    assert normalized_score(1.0, 1.0, 9.0) == 0.0
    assert normalized_score(-3.0, 1.0, 9.0) == pytest.approx(-0.5)
    assert normalized_score(5.0, None, 9.0) is None
    assert normalized_score(5.0, 5.0, 5.0) is None  # the random agent is the best: undefined


def _result(returns: dict[str, list[float] | None], baseline: str | None = None):
    res = EnvBenchResult("toy", {}, 0, 3, baseline=baseline)
    for name, r in returns.items():
        res.agents[name] = (
            AgentResult(name, skipped="refuses")
            if r is None
            else AgentResult(name, returns=r, final_objectives=r)
        )
    return res


def test_env_result_baseline_and_references() -> None:
    res = _result(
        {"fixed_random": [0.0, 1.0, 2.0], "a": [2.0, 3.0, 4.0], "b": [3.0, 3.0, 6.0], "x": None}
    )
    assert res.baseline_name == "b" and res.best_agent == "b"
    assert res.random_reference == "fixed_random"
    pa = res.paired("a")
    assert pa is not None and pa.baseline == "b" and pa.mean_diff == pytest.approx(-1.0)
    assert res.paired("x") is None
    assert res.normalized_score("a") == pytest.approx((3.0 - 1.0) / (4.0 - 1.0))
    assert res.normalized_score("b") == 1.0 and res.normalized_score("fixed_random") == 0.0
    doc = res.to_json()
    assert doc["baseline"] == "b" and doc["baseline_rule"] == "best mean return"
    assert doc["agents"]["x"] == {"skipped": "refuses"}
    explicit = _result({"a": [2.0, 3.0, 4.0], "b": [3.0, 3.0, 6.0]}, baseline="a")
    assert explicit.baseline_name == "a" and explicit.random_reference is None
    assert explicit.normalized_score("b") is None
    pb = explicit.paired("b")
    assert pb is not None and pb.mean_diff == pytest.approx(1.0)
    assert (pb.wins, pb.ties, pb.losses) == (2, 1, 0)
    with pytest.raises(BenchError, match="not among"):
        _result({"a": [1.0]}, baseline="zz").check_baseline()
    with pytest.raises(BenchError, match="skipped"):
        _result({"a": [1.0], "x": None}, baseline="x").check_baseline()
