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
__all__ = ["ENV_IDS", "__version__", "agents", "envs", "families"]
