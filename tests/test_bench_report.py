"""What a reader of ``selenv bench`` sees: objective direction, number formats, the plot."""

from __future__ import annotations

import importlib
import re
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from selenv.agents import make
from selenv.bench import AgentResult, EnvBenchResult, format_table, multiagent_modules
from selenv.bench.report import (
    OBJECTIVE_HEADERS,
    column_decimals,
    decimals_for,
    format_fixed,
    format_ms,
    plot_figure,
)
from selenv.bench.results import OBJECTIVE_DIRECTIONS, objective_direction
from selenv.families import ALL_ENV_IDS, FAMILIES

#: what each family's env docstring says of ``info["objective"]`` / the return, and the
#: direction that follows from it (whitespace collapsed before matching)
DOCUMENTED = {
    "fim": ("so the undiscounted return is ``f(F)``", "higher"),
    "landmarks": ("the return is minus the paper's objective eq. (12)", "lower"),
    "cooperative": ('``info["objective"]`` is the objective now (lower is better)', "lower"),
    "clustering": ('``-J`` after each filter step; ``info["objective"]`` is ``J``', "lower"),
}
STEPS = 40  # steps of a random episode checked per env


def _env_class(spec_path: str) -> type:
    module, cls = spec_path.split(":")
    return getattr(importlib.import_module(module), cls)


@pytest.mark.parametrize("family", FAMILIES, ids=lambda f: f.name)
def test_every_family_documents_the_direction_the_bench_shows(family: Any) -> None:
    phrase, direction = DOCUMENTED[family.name]
    doc = " ".join((_env_class(family.env_class).__doc__ or "").split())
    assert phrase in doc, f"{family.env_class}'s docstring no longer says {phrase!r}"
    assert OBJECTIVE_DIRECTIONS[family.name] == direction
    for env_id in (*(v.env_id for v in family.versions), *family.multiagent_modules):
        assert objective_direction(env_id) == direction


def test_unknown_env_has_no_direction() -> None:
    assert objective_direction("CartPole-v1") is None
    assert objective_direction("selenv_test/Toy-v0") is None


def _explains(direction: str, reward: float, prev: float, now: float) -> bool:
    """Whether ``reward`` is the documented function of the objective for ``direction``.

    A gain (``"higher"``): the reward is its increase (the return telescopes to the final
    objective). A cost (``"lower"``): the reward is its decrease or minus the cost itself.
    """
    s = 1.0 if direction == "higher" else -1.0
    tol = 1e-6 * max(1.0, abs(prev), abs(now))
    if abs(reward - s * (now - prev)) <= tol:
        return True
    return direction == "lower" and abs(reward + now) <= tol


def _random_steps(env_id: str) -> list[tuple[float, float, float]]:
    """``(reward, objective before, objective after)`` of the first steps of a random episode."""
    out = []
    if env_id in ALL_ENV_IDS:
        env = gym.make(env_id)
        agent = make("random" if "random" in _agents(env_id) else "fixed_random", env_id)
        obs, info = env.reset(seed=3)
        agent.reset(env, seed=3)
        for _ in range(STEPS):
            prev = float(info["objective"])
            obs, reward, term, trunc, info = env.step(agent.act(obs, info))
            out.append((float(reward), prev, float(info["objective"])))
            if term or trunc:
                break
        env.close()
        return out
    penv = importlib.import_module(env_id).parallel_env()
    policy = make("random", env_id)
    observations, infos = penv.reset(seed=3)
    policy.reset(penv, seed=3)
    for _ in range(STEPS):
        if not penv.agents:
            break
        prev = float(next(iter(infos.values()))["objective"])
        observations, rewards, _, _, infos = penv.step(policy.act(observations, infos))
        team = float(np.mean([float(r) for r in rewards.values()]))
        out.append((team, prev, float(next(iter(infos.values()))["objective"])))
    penv.close()
    return out


def _agents(env_id: str) -> list[str]:
    from selenv.agents import agents_for

    return agents_for(env_id)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("env_id", [*ALL_ENV_IDS, *multiagent_modules()])
def test_direction_matches_how_the_reward_uses_the_objective(env_id: str) -> None:
    """The return is maximised; the objective must be better in the direction the bench shows.

    Each step's reward is checked against the documented relation (gain: its increase; cost:
    its decrease or minus the cost), and the opposite direction must fail on some step.
    """
    direction = objective_direction(env_id)
    assert direction in ("higher", "lower")
    other = "lower" if direction == "higher" else "higher"
    steps = _random_steps(env_id)
    assert steps
    for reward, prev, now in steps:
        assert _explains(direction, reward, prev, now), (env_id, reward, prev, now)
    assert not all(_explains(other, *s) for s in steps), f"{env_id}: both directions fit"


def _result(env_id: str, returns: dict[str, list[float]], scale: float = 1.0) -> EnvBenchResult:
    episodes = len(next(iter(returns.values())))
    res = EnvBenchResult(env_id, {}, 0, episodes)
    for name, r in returns.items():
        res.agents[name] = AgentResult(
            name,
            returns=[scale * x for x in r],
            final_objectives=[-scale * x / 100 for x in r],
            decision_seconds=2.81e-5 * episodes,
            decisions=episodes,
        )
    return res


def test_number_formats() -> None:
    assert decimals_for(14350.0, 4) == 0
    assert decimals_for(1.089, 4) == 3
    assert decimals_for(-61.12, 4) == 2
    assert decimals_for(0.0534, 3) == 4
    assert decimals_for(1e-12, 3) == 6  # capped
    assert decimals_for(0.0, 3) == 2 and decimals_for(float("nan"), 3) == 2
    assert format_fixed(14350.4, 0) == "14,350"
    assert format_fixed(-1234567.891, 2) == "-1,234,567.89"
    assert format_fixed(-0.0001, 2) == "0.00"  # no "-0.00"
    assert format_fixed(0.5, 1, sign=True) == "+0.5"
    assert format_fixed(-0.5, 1, sign=True) == "-0.5"
    assert format_fixed(None, 2) == "-" and format_fixed(float("nan"), 2) == "-"
    assert format_ms(0.0578) == "57.8"
    assert format_ms(0.00196) == "1.96"
    assert format_ms(2.81e-5) == "0.0281"
    assert format_ms(9.3e-7) == "0.000930"
    assert format_ms(1.2345) == "1,234"
    assert column_decimals([14350.2, 12740.0, float("nan")]) == 0
    assert column_decimals([1.089, 0.3869]) == 3


def test_table_has_no_exponent_and_names_the_direction() -> None:
    rng = np.random.default_rng(0)
    base = 14350 + 900 * rng.standard_normal(5)
    res = _result(
        "selenv/LandmarkSelection-v1",
        {
            "random": list(base - 1630 + 40 * rng.standard_normal(5)),
            "greedy": list(base - 16 + rng.standard_normal(5)),
            "rollout": list(base),
        },
    )
    table = format_table(res)
    rows = table.splitlines()[:6]  # title, header, rule, 3 agents; the legend follows
    assert table.splitlines()[6].startswith("final objective:")
    assert not re.search(r"\de[+-]?\d", "\n".join(rows)), table
    header = table.splitlines()[1]
    assert OBJECTIVE_HEADERS["lower"] in header and "(lower is better)" in header
    row = next(ln for ln in table.splitlines() if ln.startswith("random"))
    # thousands separators in the return and in the Δ with its CI as "[lo, hi]"
    assert re.search(r"\d{2},\d{3} ± \d{3}", row), row
    assert re.search(r"-1,6\d\d\.\d \[-1,\d{3}\.\d, -1,\d{3}\.\d\]\*", row), row
    assert " 0.0281 " in row  # decision ms, 3 significant digits
    greedy = next(ln for ln in table.splitlines() if ln.startswith("greedy"))
    assert re.search(r"-1\d\.\d \[-1\d\.\d, -1\d\.\d\]\*", greedy), greedy
    fim = format_table(_result("selenv/FIMSelection-v1", {"a": [1.0, 2.0], "b": [2.0, 2.5]}))
    assert "final objective (higher is better)" in fim.splitlines()[1]
    toy = format_table(_result("CartPole-v1", {"a": [1.0, 2.0], "b": [2.0, 2.5]}))
    assert "final objective " in toy.splitlines()[1] and "better)" not in toy.splitlines()[1]


def test_json_names_the_direction() -> None:
    doc = _result("selenv/ReceiverClustering-v1", {"a": [1.0, 2.0]}).to_json()
    assert doc["objective_direction"] == "lower"
    doc = _result("selenv.multiagent.fim_selection_v0", {"a": [1.0, 2.0]}).to_json()
    assert doc["objective_direction"] == "higher"
    assert _result("CartPole-v1", {"a": [1.0]}).to_json()["objective_direction"] is None


def test_plot_shows_one_point_per_seed_over_the_mean_and_ci() -> None:
    rng = np.random.default_rng(1)
    episodes = 7
    res = _result(
        "selenv/FIMSelection-v1",
        {
            "random": list(rng.normal(20, 3, episodes)),
            "greedy": list(rng.normal(29, 1, episodes)),
            "swap": list(rng.normal(30, 1, episodes)),
        },
    )
    res.agents["brute_force"] = AgentResult("brute_force", skipped="too many subsets")
    assert res.baseline_name == "swap"
    fig = plot_figure(res)
    (ax,) = fig.axes
    for name in ("random", "greedy"):
        paired = res.paired(name)
        assert paired is not None
        (strip,) = [c for c in ax.collections if c.get_gid() == f"seeds:{name}"]
        ys = np.asarray(strip.get_offsets())[:, 1]
        assert ys.size == episodes
        np.testing.assert_allclose(np.sort(ys), np.sort(paired.diffs))
        (mean,) = [ln for ln in ax.lines if ln.get_gid() == f"mean:{name}"]
        assert float(np.asarray(mean.get_ydata())[0]) == pytest.approx(paired.mean_diff)
    assert not [c for c in ax.collections if str(c.get_gid()).startswith("seeds:swap")]
    assert "> 0: better than swap" in ax.get_ylabel()
    assert "swap" in ax.get_ylabel().split("\n")[0]
    box = ax.get_legend()
    assert box is not None
    legend = [t.get_text() for t in box.get_texts()]
    assert any("baseline: swap" in t for t in legend)
    assert "skipped: brute_force" in ax.get_title()
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert labels == ["random", "greedy"]
