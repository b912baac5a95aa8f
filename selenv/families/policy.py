"""The record of a shipped learned policy, and its measured standing.

Learned policies are records, as families are (:class:`~selenv.families.spec.FamilySpec`): a
:class:`PolicySpec` declared in the family's ``policies`` module names the agent, the env ids or
PettingZoo modules it plays, its loader (a ``"module:attr"`` factory above this layer, imported
only when the agent is built), the checkpoint it loads, the command that trained it, the
configurations it is valid on and the deprecated names it replaces. Its **standing** is not
written in code: it is measured by ``selenv bench`` on held-out seeds and stored in the
checkpoint's JSON (``"standings"``, written by ``scripts/record_standings.py``), so the numbers
``selenv list`` and the docs show are the ones a run produced.

:mod:`selenv.agents.learned` registers every record as an agent, the deprecated names, and
``learned``: per env (and per PettingZoo mode), the record with the best held-out standing.

A standing entry (JSON)::

    {"agent": "ppo", "env_id": "selenv/FIMSelection-v1", "env_kwargs": {},
     "baseline": "greedy", "seed": 30000, "episodes": 30,
     "mean_difference": 0.035, "ci95": [0.025, 0.045], "wins": 28, "ties": 0, "losses": 2,
     "decision_time_ratio": 8.1, "command": "selenv bench ...", "measured": "2026-12-07"}

``mean_difference`` is the mean per-seed paired difference of the return against
``baseline`` (``ci95``: the bench's percentile-bootstrap interval), ``decision_time_ratio`` the
agent's mean decision time over the baseline's in the same run.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from types import MappingProxyType
from typing import Any

from selenv.shipped import checkpoint_dir
from selenv.untrusted import read_text

__all__ = ["METHODS", "PolicySpec", "Standing", "read_standings"]

#: how a record's policy was produced (``PolicySpec.method``)
METHODS = {
    "rl": "reinforcement learning (PPO on the env's reward)",
    "distillation": "imitation of a lookahead expert (DAgger / expert iteration)",
    "learned_search": "a short lookahead guided by a learned policy",
    "cem": "the cross-entropy method on episode returns",
    "rllib": "multi-agent RL with RLlib",
}

#: ceiling on a checkpoint JSON read for its standings (shipped ones: 3-20 KB)
_MAX_JSON_BYTES = 1 << 20


@dataclass(frozen=True)
class Standing:
    """One measured result of a record on held-out seeds (module docstring)."""

    agent: str
    env_id: str
    env_kwargs: Mapping[str, Any]
    baseline: str
    seed: int
    episodes: int
    mean_difference: float
    ci95: tuple[float, float]
    wins: int
    ties: int
    losses: int
    decision_time_ratio: float
    command: str
    measured: str = ""
    #: the run's non-myopic reference (``rollout``) where it ran: its ``mean_difference``,
    #: ``ci95``, ``decision_time_ratio``, and this agent's ``share_of_edge`` (mean difference
    #: over the reference's) with its bootstrap ``share_ci95``
    reference: Mapping[str, Any] | None = None

    @property
    def beats_baseline(self) -> bool:
        """Whether the 95 % CI of the paired difference lies above 0."""
        return self.ci95[0] > 0

    def summary(self) -> str:
        """``+0.035 [+0.025, +0.045] vs greedy (28/0/2, 30 seeds), 8.1x its decision time``."""
        return (
            f"{self.difference_text()} vs "
            f"{self.baseline} ({self.wins}/{self.ties}/{self.losses}, {self.episodes} seeds"
            f"{_kwargs_text(self.env_kwargs)}), {self.decision_time_ratio:.1f}x its decision time"
            + self.reference_text()
        )

    def difference_text(self) -> str:
        """``+0.035 [+0.025, +0.045]``: the mean difference and its CI, 3 decimals below 1."""
        size = abs(self.mean_difference)
        digits = 3 if size < 1 else 2 if size < 100 else 1
        lo, hi = self.ci95
        return f"{self.mean_difference:+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"

    def reference_text(self) -> str:
        """``; 88 % [56, 137] of rollout's edge at 1/5 of its decision time`` (or empty)."""
        ref = self.reference
        if ref is None:
            return ""
        lo, hi = ref["share_ci95"]
        ratio = self.decision_time_ratio / ref["decision_time_ratio"]
        when = f"1/{1 / ratio:.0f}" if ratio < 1 else f"{ratio:.1f}x"
        return (
            f"; {100 * ref['share_of_edge']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}] of "
            f"{ref['agent']}'s edge at {when} of its decision time"
        )


def _kwargs_text(kwargs: Mapping[str, Any]) -> str:
    return "".join(f", {k}={v}" for k, v in sorted(kwargs.items()))


@dataclass(frozen=True, kw_only=True)
class PolicySpec:
    """Everything the package needs to know of one shipped learned agent.

    Args:
        name: the agent name (``selenv bench --agents NAME``).
        plays: the env ids (current version) or PettingZoo modules it plays.
        factory: ``"module:attr"`` of the agent factory (above the families; imported on build).
        checkpoint: file name in ``checkpoints/`` whose JSON holds the record's standings (the
            weights the agent loads, or the policy its search uses).
        method: how it was produced, a key of :data:`METHODS`.
        description: one line for ``selenv list``.
        trainer: the command that produced the checkpoint (``python -m selenv.train....``).
        kwargs: keywords the factory always gets.
        baseline: the heuristic it is measured against (``greedy``; ``brute_force`` where the
            per-step optimum is the heuristic to beat).
        budget: its decision budget in words (``"8 cost evaluations per decision"``).
        max_decision_ratio: the same budget as a ceiling on its decision time over its
            baseline's (``2.0``: at most twice brute force's); a standing measured above it
            is reported but does not make the record ``learned``. ``None``: no ceiling.
        valid: env parameters it was trained and verified on, ``{parameter: allowed values}``;
            on another value the agent warns once per episode configuration
            (:class:`selenv.agents.learned.OutsideValidityWarning`). Empty: no limit known.
        aliases: deprecated agent names it replaces, ``{old name: options}``; they keep
            working for one release with a ``DeprecationWarning`` naming the new spelling.
        retired: why the shipped policy is retired (it did not beat its baseline), naming
            what to use instead; empty for a current record. A retired record keeps its name
            for one release: played from its shipped checkpoint it warns
            (``DeprecationWarning``), with the user's own ``checkpoint=`` it loads that file
            silently; it is never in ``selenv bench``'s defaults nor a candidate of ``learned``.
    """

    name: str
    plays: tuple[str, ...]
    factory: str
    checkpoint: str
    method: str
    description: str
    trainer: str = ""
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    baseline: str = "greedy"
    budget: str = ""
    max_decision_ratio: float | None = None
    valid: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    aliases: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    retired: str = ""

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ValueError(f"PolicySpec name must be an identifier, got {self.name!r}")
        if self.name == "learned":
            raise ValueError("'learned' is resolved from the records, not declared by one")
        if self.method not in METHODS:
            raise ValueError(f"PolicySpec {self.name}: method must be one of {sorted(METHODS)}")
        if ":" not in self.factory:
            raise ValueError(f"PolicySpec {self.name}: factory must be 'module:attr'")
        if not self.plays:
            raise ValueError(f"PolicySpec {self.name}: plays names no env")
        object.__setattr__(self, "kwargs", MappingProxyType(dict(self.kwargs)))
        valid = {k: tuple(v) for k, v in self.valid.items()}
        object.__setattr__(self, "valid", MappingProxyType(valid))
        aliases = {k: MappingProxyType(dict(v)) for k, v in self.aliases.items()}
        object.__setattr__(self, "aliases", MappingProxyType(aliases))

    def standings(self) -> tuple[Standing, ...]:
        """This record's entries in its checkpoint's JSON (empty when none was recorded)."""
        return tuple(
            s
            for s in read_standings(self.checkpoint)
            if s.agent == self.name and s.env_id in self.plays
        )

    def within_budget(self, standing: Standing) -> bool:
        """Whether ``standing``'s decision time is within :attr:`max_decision_ratio`."""
        ceiling = self.max_decision_ratio
        return ceiling is None or standing.decision_time_ratio <= ceiling

    def outside(self, parameters: Mapping[str, Any]) -> dict[str, Any]:
        """The env parameters (of :attr:`valid`) whose value it was not verified on."""
        return {
            k: parameters[k]
            for k, allowed in self.valid.items()
            if k in parameters and parameters[k] not in allowed
        }


def _standing(entry: Any, source: str) -> Standing:
    """One JSON entry as a :class:`Standing` (a malformed one is a ``ValueError``)."""
    try:
        ci = entry["ci95"]
        out = Standing(
            agent=str(entry["agent"]),
            env_id=str(entry["env_id"]),
            env_kwargs=MappingProxyType(dict(entry.get("env_kwargs") or {})),
            baseline=str(entry["baseline"]),
            seed=int(entry["seed"]),
            episodes=int(entry["episodes"]),
            mean_difference=float(entry["mean_difference"]),
            ci95=(float(ci[0]), float(ci[1])),
            wins=int(entry["wins"]),
            ties=int(entry["ties"]),
            losses=int(entry["losses"]),
            decision_time_ratio=float(entry["decision_time_ratio"]),
            command=str(entry["command"]),
            measured=str(entry.get("measured", "")),
            reference=_reference(entry.get("reference")),
        )
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"{source}: malformed standing entry ({exc!r})") from None
    numbers = (out.mean_difference, *out.ci95, out.decision_time_ratio)
    if not all(math.isfinite(x) for x in numbers):
        raise ValueError(f"{source}: standing entry of {out.agent!r} has a non-finite number")
    return out


def _reference(block: Any) -> Mapping[str, Any] | None:
    """The optional ``reference`` block, its numbers as floats (``None`` when absent)."""
    if block is None:
        return None
    return MappingProxyType(
        {
            "agent": str(block["agent"]),
            "mean_difference": float(block["mean_difference"]),
            "decision_time_ratio": float(block["decision_time_ratio"]),
            "share_of_edge": float(block["share_of_edge"]),
            "share_ci95": (float(block["share_ci95"][0]), float(block["share_ci95"][1])),
        }
    )


@cache
def read_standings(checkpoint: str) -> tuple[Standing, ...]:
    """The ``"standings"`` of shipped checkpoint ``checkpoint``'s JSON (cached per file).

    A checkpoint without a JSON, or a JSON without standings, has none.

    Raises:
        ValueError: the JSON is not valid, or an entry is malformed (the message names the file).
    """
    stem = checkpoint.rsplit(".", 1)[0]
    path = checkpoint_dir() / f"{stem}.json"
    if not path.is_file():
        return ()
    text = read_text(path, "checkpoint metadata", max_bytes=_MAX_JSON_BYTES)
    try:
        meta = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"checkpoint metadata {path} is not valid JSON: {exc}") from None
    entries = meta.get("standings", []) if isinstance(meta, dict) else []
    if not isinstance(entries, list):
        raise ValueError(f"checkpoint metadata {path}: 'standings' must be a list")
    return tuple(_standing(e, str(path)) for e in entries)
