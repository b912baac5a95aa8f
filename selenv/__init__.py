"""selenv: hard decision problems of state estimation as reinforcement-learning environments.

``import selenv`` registers the Gymnasium ids (``selenv/FIMSelection-v1``, ...; see
:mod:`selenv.families`) and the baseline agents. See docs/getting_started.md for the quick start.
"""

from __future__ import annotations

from selenv import _signals

_signals.start_cli()  # first: the `selenv` command handles SIGINT/SIGTERM before heavy imports

from selenv import _compat, agents, envs, families  # noqa: E402
from selenv.families import ENV_IDS  # noqa: E402

_compat.install()  # the module paths that moved into the family folders stay importable

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "agents", "envs", "families", "register"]


def register() -> tuple[str, ...]:
    """Make sure selenv's ids are registered in this process; return the current ids.

    Importing ``selenv`` registers them, so this is for hooks that take a function to run in
    processes selenv does not start, e.g. Ray's ``ray.init(runtime_env={
    "worker_process_setup_hook": "selenv.register"})``, after which RLlib's env runners resolve
    ``config.environment("selenv/FIMSelection-v1")``. (Anywhere ``gymnasium.make`` runs, the id
    ``"selenv:selenv/FIMSelection-v1"`` does the same: Gymnasium imports the module first.)
    """
    return ENV_IDS
