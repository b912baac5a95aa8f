"""PettingZoo's ``max_cycles`` for the parallel envs: truncate every live agent after N steps.

PettingZoo's convention (its ``max_cycles_test``, the MPE and SISL envs): ``parallel_env(
max_cycles=N)`` ends an episode after ``N`` parallel steps with ``truncations`` true for every
agent still live, unless it ended earlier. ``None`` (the default) leaves the env's own end
(budgets, horizon) alone, so the default episodes are unchanged.
"""

from __future__ import annotations

from typing import Any

from selenv.scenarios.validation import check_integer

__all__ = ["MaxCycles"]

#: a ceiling on ``max_cycles`` (an episode that long would not fit in memory anyway)
MAX_CYCLES = 10**9


class MaxCycles:
    """Mixin for a ``ParallelEnv`` whose one-step logic is :meth:`_step_once`.

    The class calls :meth:`_set_max_cycles` from ``__init__`` and :meth:`_start_cycles` from
    ``reset``; :meth:`step` runs :meth:`_step_once` and applies the cap.
    """

    agents: list[str]
    max_cycles: int | None = None
    _cycles: int = 0

    def _set_max_cycles(self, max_cycles: int | None) -> None:
        """Validate and store ``max_cycles`` (``None`` or an int >= 1)."""
        if max_cycles is not None:
            max_cycles = check_integer(max_cycles, "max_cycles", 1, MAX_CYCLES)
        self.max_cycles = max_cycles

    def _start_cycles(self) -> None:
        self._cycles = 0

    def _step_once(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        raise NotImplementedError

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        """One parallel step; after ``max_cycles`` of them every live agent is truncated."""
        obs, rewards, terms, truncs, infos = self._step_once(actions)
        self._cycles += 1
        if self.max_cycles is not None and self._cycles >= self.max_cycles and self.agents:
            truncs = {a: truncs[a] or not terms[a] for a in truncs}
            self.agents = []
        return obs, rewards, terms, truncs, infos
