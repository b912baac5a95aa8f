"""selenv: hard decision problems of state estimation as reinforcement-learning environments.

``import selenv`` registers the Gymnasium ids (``selenv/FIMSelection-v1``, ...) and the
baseline agents. See the README for the quick start.
"""

from __future__ import annotations

from selenv import agents, envs
from selenv.envs import ENV_IDS

__version__ = "0.1.0"
__all__ = ["ENV_IDS", "__version__", "agents", "envs"]
