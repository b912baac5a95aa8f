"""``torch.compile`` for the candidate scorers, with an eager fallback that gives the same outputs.

The candidate scorers run one small MLP on every candidate of a minibatch, so a PPO update is
dominated by memory-bound elementwise kernels (the mask multiplies, ``tanh`` and its backward,
the masked sums); TorchInductor fuses them. :func:`compile_scorer` registers a compiled
version of a scorer's :meth:`~selenv.learned.rl.candidate_policy.CandidateScorer.scores` for
that module object; its ``forward`` plays it from then on. Nothing else changes: the weights,
the ``state_dict``, saved checkpoints and copies of the module (a copy runs eagerly) are those
of the eager module, and ``tests/test_compiled_scorer.py`` checks that the compiled outputs
equal the eager ones to ``1e-6`` (the gradients to ``1e-5``: float32 sums reordered).

Where TorchInductor cannot run (no C compiler, an unsupported platform) the first call that
fails warns once (:class:`CompileFallbackWarning`, naming the error) and the scorer runs eagerly
from then on: a run never stops because compiling failed.
"""

from __future__ import annotations

import warnings
import weakref
from collections.abc import Callable
from typing import Any

import torch as th
from torch import nn

__all__ = [
    "CompileFallbackWarning",
    "CompiledForward",
    "compile_policy",
    "compile_scorer",
    "compiled_forward",
]


class CompileFallbackWarning(UserWarning):
    """``torch.compile`` failed on a scorer; it runs eagerly (the same outputs, slower)."""


class CompiledForward:
    """``eager`` compiled by ``torch.compile``; falls back to ``eager`` for good on a failure.

    Args:
        eager: the function to compile (a bound method of the module).
        name: what the warning calls it.
    """

    def __init__(self, eager: Callable[..., Any], name: str) -> None:
        self.eager = eager
        self.name = name
        self.compiled: Callable[..., Any] = th.compile(eager)
        #: why compiling failed (``None``: the compiled function is in use)
        self.error: str | None = None

    def __call__(self, *args: Any) -> Any:
        """The compiled function's result, or the eager one's once compiling has failed."""
        if self.error is None:
            try:
                return self.compiled(*args)
            except Exception as exc:  # inductor unavailable, an unsupported op: run eagerly
                self.error = (f"{type(exc).__name__}: {exc}".strip().splitlines() or ["?"])[0]
                warnings.warn(
                    f"torch.compile failed on {self.name} ({self.error[:300]}); running it "
                    "eagerly (the same outputs, slower)",
                    CompileFallbackWarning,
                    stacklevel=2,
                )
        return self.eager(*args)


#: module -> its compiled scores (weak keys: a discarded module drops its compiled function)
_COMPILED: weakref.WeakKeyDictionary[nn.Module, CompiledForward] = weakref.WeakKeyDictionary()


def compile_scorer(module: nn.Module) -> CompiledForward:
    """Compile ``module.scores`` (a candidate scorer) for this module object; return it.

    Compiling happens at the first call (TorchInductor's own warm-up: seconds to a minute).
    Calling it again on the same module returns the registered function.

    Raises:
        TypeError: ``module`` has no ``scores`` method (not a candidate scorer).
    """
    scores = getattr(module, "scores", None)
    if not callable(scores):
        raise TypeError(f"expected a candidate scorer with scores(), got {type(module).__name__}")
    if module not in _COMPILED:
        _COMPILED[module] = CompiledForward(scores, type(module).__name__)
    return _COMPILED[module]


def compiled_forward(module: nn.Module) -> CompiledForward | None:
    """The compiled function registered for ``module`` by :func:`compile_scorer`, if any."""
    return _COMPILED.get(module)


def compile_policy(policy: Any) -> list[CompiledForward]:
    """Compile the candidate scorer(s) of an SB3 actor-critic ``policy`` (``--compile``).

    The actor's and the critic's features extractors (one module when shared, SB3's default
    for PPO); returns their compiled functions.

    Raises:
        TypeError: an extractor is not a candidate scorer.
    """
    modules = {policy.pi_features_extractor, policy.vf_features_extractor}
    return [compile_scorer(m) for m in sorted(modules, key=id)]
