"""Run agents x envs on identical seeded episodes; report paired statistics, JSON and plots.

``run_bench(env_id, ["greedy", "random"], episodes=10)`` returns an :class:`EnvBenchResult`
(``env_id`` a Gymnasium id or a PettingZoo module such as
``selenv.multiagent.fim_selection_v0``); its :meth:`~EnvBenchResult.paired` compares an agent
with the baseline on the same seeds (:mod:`selenv.bench.stats`). :func:`format_table`,
:func:`write_json` and :func:`plot_result` present it. The ``selenv bench`` command
(:mod:`selenv.cli`) is a thin shell over these.
"""

from __future__ import annotations

from selenv.bench.multiagent import multiagent_modules
from selenv.bench.report import (
    format_table,
    plot_filename,
    plot_result,
    results_to_json,
    write_json,
)
from selenv.bench.results import (
    AgentRefused,
    AgentResult,
    BenchError,
    EnvBenchResult,
    EnvKwargsError,
)
from selenv.bench.runner import check_env_id, check_env_kwargs, run_bench, run_episode
from selenv.bench.stats import PairedComparison, compare_paired

__all__ = [
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "EnvBenchResult",
    "EnvKwargsError",
    "PairedComparison",
    "check_env_id",
    "check_env_kwargs",
    "compare_paired",
    "format_table",
    "multiagent_modules",
    "plot_filename",
    "plot_result",
    "results_to_json",
    "run_bench",
    "run_episode",
    "write_json",
]
