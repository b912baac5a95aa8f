"""Action validation shared by every env: what is outside a space, and what is merely invalid.

Gymnasium's rule is that every element of ``env.action_space`` is a legal input to ``step()``
(checkers, plain PPO, SuperSuit and TorchRL sample the space). selenv therefore separates:

* **outside the action space** (wrong type, shape or range): always ``TypeError`` /
  ``ValueError`` (:func:`check_discrete`);
* **inside the space but invalid now** (a masked candidate, an infeasible clustering): handled
  by the env's :class:`InvalidActionRule`, chosen with the constructor keywords
  ``invalid_action`` and ``invalid_action_penalty``:

  ========== ==========================================================================
  mode       effect of an invalid action
  ========== ==========================================================================
  noop       (default) no selection or clustering changes; the rest of the step
             happens (a budget slot or a time step is spent, so episodes stay bounded);
             ``info["invalid_action"] = True`` and ``info["invalid_code"]`` says why
             (:data:`INVALID_CODES`); the reward gets ``invalid_action_penalty``
             (default 0) added
  raise      ``ValueError`` naming the action and the reason in words (heuristics,
             ``selenv bench``, debugging: a buggy agent is caught)
  terminate  the episode ends (``terminated=True``) with reward
             ``invalid_action_penalty``, as PettingZoo's illegal-move wrappers do
  ========== ==========================================================================

Every step's ``info`` holds ``invalid_action`` (bool) and ``invalid_code`` (int, an index into
:data:`INVALID_CODES`, also ``env.metadata["invalid_codes"]``), valid steps and resets included,
so that learners that batch ``info`` (TorchRL, Tianshou) see the same keys and dtypes at every
step.

Masks are unaffected by the mode: ``action_masks()``, ``info["action_mask"]`` and
``obs["action_mask"]`` always say which actions are valid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.scenarios.validation import describe

__all__ = [
    "INFEASIBLE",
    "INVALID_ACTION_MODES",
    "INVALID_CODES",
    "MASKED",
    "MAX_PENALTY",
    "InvalidActionRule",
    "check_discrete",
    "invalid_code",
]

INVALID_ACTION_MODES = ("noop", "raise", "terminate")
#: largest ``|invalid_action_penalty|``
MAX_PENALTY = 1e6
PENALTY_RANGE = f"[{-MAX_PENALTY:g}, {MAX_PENALTY:g}]"
#: ``info["invalid_code"]`` -> meaning: ``0`` a valid action; ``1`` ``"masked"``: the action's
#: mask entry is False (a candidate already taken, a pair without a measurement, an edit the
#: state limit forbids); ``2`` ``"infeasible"``: an action the mask does not cover that breaks a
#: constraint (a ReceiverClustering assignment over the state limit)
INVALID_CODES = ("valid", "masked", "infeasible")
#: the codes of ``"masked"`` and ``"infeasible"``
MASKED, INFEASIBLE = 1, 2


def invalid_code(reason: str | None) -> int:
    """The ``info["invalid_code"]`` of an invalid-action reason (``None``: valid, code 0).

    A reason is written ``"<kind>: <details>"`` with ``<kind>`` one of :data:`INVALID_CODES`.

    Raises:
        ValueError: the reason does not start with a known kind (an env bug, not user input).
    """
    if reason is None:
        return 0
    kind = reason.split(":", 1)[0]
    if kind not in INVALID_CODES[1:]:
        raise ValueError(
            f"invalid-action reason {reason!r} must start with one of {INVALID_CODES[1:]}"
        )
    return INVALID_CODES.index(kind)


def check_discrete(action: Any, n: int, name: str = "action") -> int:
    """Validate an element of ``Discrete(n)`` and return it as ``int``.

    Accepts Python and numpy integers, and integer arrays of shape ``()`` or ``(1,)`` (what
    vectorised samplers hand out).

    Raises:
        TypeError: not an integer (bools and floats are rejected, never rounded).
        ValueError: outside ``[0, n)``.
    """
    a = np.asarray(action)
    if a.shape not in ((), (1,)) or a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
        raise TypeError(f"{name} must be an integer in [0, {n}), got {action!r}")
    k = int(a.reshape(()))
    if not 0 <= k < n:
        raise ValueError(f"{name} {k} is out of range: expected an integer in [0, {n})")
    return k


@dataclass(frozen=True)
class InvalidActionRule:
    """What an env does with an action that is in its space but invalid now.

    Attributes:
        mode: ``"noop"``, ``"raise"`` or ``"terminate"`` (module docstring).
        penalty: added to the reward of an invalid step (``noop``) or given as the reward of
            the terminating step (``terminate``); a float in ``[-1e6, 1e6]`` (rewards are
            stored as float32 by most learners), default 0.
    """

    mode: str = "noop"
    penalty: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.mode, str) or self.mode not in INVALID_ACTION_MODES:
            raise ValueError(
                f"invalid_action must be one of {INVALID_ACTION_MODES}, got {self.mode!r}"
            )
        p = self.penalty
        if isinstance(p, bool) or not isinstance(p, int | float | np.integer | np.floating):
            raise TypeError(
                f"invalid_action_penalty must be a float in {PENALTY_RANGE}, got {describe(p)}"
            )
        if not (math.isfinite(float(p)) and abs(float(p)) <= MAX_PENALTY):
            raise ValueError(
                f"invalid_action_penalty must be finite, in {PENALTY_RANGE}, got {p!r}"
            )
        object.__setattr__(self, "penalty", float(p))

    def check(self, what: str, reason: str | None) -> bool:
        """Return whether the action is invalid; in ``raise`` mode raise instead.

        Args:
            what: the action as the error message should name it (``"action 7"``).
            reason: ``None`` if the action is valid, else why it is not.

        Raises:
            ValueError: ``mode == "raise"`` and ``reason`` is not ``None``.
        """
        if reason is None:
            return False
        if self.mode == "raise":
            raise ValueError(f"{what} is invalid: {reason}")
        return True

    @property
    def terminates(self) -> bool:
        """Whether an invalid action ends the episode."""
        return self.mode == "terminate"

    @staticmethod
    def info(reason: str | None) -> dict[str, Any]:
        """The step's ``info`` entries: ``invalid_action`` (bool), ``invalid_code`` (int)."""
        return {"invalid_action": reason is not None, "invalid_code": invalid_code(reason)}

    @staticmethod
    def masked_info(invalid: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`info` batched, for sub-envs whose only invalid actions are masked ones.

        ``invalid`` ``(k,)`` bool -> ``invalid_action`` (it) and ``invalid_code`` ``(k,)``
        int64 (:data:`MASKED` where invalid, else 0).
        """
        invalid = np.asarray(invalid, dtype=np.bool_)
        return {
            "invalid_action": invalid,
            "invalid_code": np.where(invalid, MASKED, 0).astype(np.int64),
        }
