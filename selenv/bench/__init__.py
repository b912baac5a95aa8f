"""Run agents x envs on identical seeded episodes; report a table, JSON and plots.

``run_bench(env_id, ["greedy", "random"], episodes=10)`` returns an :class:`EnvBenchResult`;
:func:`format_table`, :func:`write_json` and :func:`plot_result` present it. The ``selenv
bench`` command (:mod:`selenv.cli`) is a thin shell over these.
"""

from __future__ import annotations

from selenv.bench.report import (
    format_table,
    plot_filename,
    plot_result,
    results_to_json,
    write_json,
)
from selenv.bench.runner import (
    AgentRefused,
    AgentResult,
    BenchError,
    EnvBenchResult,
    EnvKwargsError,
    run_bench,
    run_episode,
)

__all__ = [
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "EnvBenchResult",
    "EnvKwargsError",
    "format_table",
    "plot_filename",
    "plot_result",
    "results_to_json",
    "run_bench",
    "run_episode",
    "write_json",
]
