"""Learning code that serves ``LandmarkSelection``: ``ppo_search`` and the ``rollout`` labeller.

``ppo_search``: the learned policy as the prior of a short lookahead. A policy alone recovers
about half of the landmark ``rollout``'s edge over brute force; the lookahead itself,
restricted to a shortlist, recovers nearly all of it at brute force's cost
(``fast_rollout``, :mod:`selenv.families.landmarks.fast_rollout`). This agent joins the two the
way a search with a learned prior does: the policy (a candidate-scoring checkpoint, by default
the shipped ``ppo``) ranks the open landmarks once per filter step -- one forward pass, in
numpy (:meth:`~selenv.learned.rl.agent.SB3PolicyAgent.logits`) -- and
its ``shortlist`` best-scored landmarks are the only ones the lookahead considers (its
candidates and its simulated brute-force base). Everything else is ``fast_rollout``'s: the
``top_k`` K-subsets of the shortlist by one-step gain, each scored by minus the env's cost
eq. (11) of Soubaras & Chahbazian (2023) summed over its update and ``horizon`` simulated
updates, on the forecast (never the true state or future noise).

``fast_rollout`` ranks the shortlist by the single-landmark gain now, which misses landmarks
whose value lies in the future; the policy was trained on ``rollout``'s labels (the best
lookahead score of a subset holding the landmark), so it ranks by an estimate of exactly that.

Those labels come from :func:`collect_landmark_rollout_labels`, the labeller of expert
iteration (:mod:`selenv.learned.rl.expert`, ``python -m selenv.train.train_landmark_expert``).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.landmarks.fast_rollout import LandmarkFastRolloutAgent
from selenv.families.landmarks.rollout import LANDMARK_ENV_ID, LandmarkRolloutAgent
from selenv.learned.rl.agent import SB3PolicyAgent
from selenv.learned.rl.expert import Label, LabelFn, collect_rollout_labels
from selenv.learned.rl.ranking import RankingData

__all__ = [
    "LANDMARK_ID",
    "LANDMARK_LABELLERS",
    "LandmarkPolicySearchAgent",
    "collect_landmark_rollout_labels",
    "landmark_rollout_labeller",
    "make_landmark_ppo_search",
]

#: the env the ``rollout`` labeller serves
LANDMARK_ID = LANDMARK_ENV_ID
#: the landmark labellers: the ``rollout`` reference and its shortlist version
LANDMARK_LABELLERS = ("rollout", "fast_rollout")


class LandmarkPolicySearchAgent(LandmarkFastRolloutAgent):
    """``fast_rollout`` on the shortlist a learned policy ranks first (module docstring).

    Args:
        checkpoint: candidate-scoring checkpoint trained on ``LandmarkSelection-v1``
            (default: the shipped ``ppo``).
        top_k: candidate K-subsets scored per filter step (>= 1).
        horizon: future filter steps simulated (>= 0).
        shortlist: landmarks ``M`` the policy passes to the lookahead (>= 1; at least the
            budget ``K``).
        allow_large: lift the ceilings on ``top_k``, ``horizon`` and ``shortlist``.

    Raises:
        ValueError: a bad option, or the checkpoint is missing, unreadable or was trained on
            another env.
    """

    name = "ppo_search"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        top_k: int = 4,
        horizon: int = 10,
        shortlist: int = 6,
        allow_large: bool = False,
    ) -> None:
        super().__init__(top_k, horizon, shortlist, allow_large)
        self.policy = SB3PolicyAgent(checkpoint, env_id=LANDMARK_ENV_ID)

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Bind the lookahead and the policy to ``env`` (``LandmarkSelection``, log det)."""
        super().reset(env, seed)
        self.policy.reset(env, seed)

    def select_shortlist(
        self, obs: Any, info: dict[str, Any] | None, gains: FloatArray, M: int
    ) -> np.ndarray:
        """The ``M`` open landmarks of largest policy logit (ties: the larger gain, then index).

        Raises:
            ValueError: no observation (``scores()`` called outside an episode step).
        """
        if obs is None:
            raise ValueError(
                "agent 'ppo_search' ranks the shortlist from the observation: pass obs"
            )
        logits = np.asarray(self.policy.logits(obs, info or {}, backend="numpy"), np.float64)
        open_ = np.isfinite(gains)
        # lexsort: last key first -> logit descending, then gain descending, then index
        order = np.lexsort((-np.where(open_, gains, 0.0), -np.where(open_, logits, -np.inf)))
        return order[:M]


def make_landmark_ppo_search(**kwargs: Any) -> LandmarkPolicySearchAgent:
    """Registry factory of ``ppo_search`` (the keyword arguments of the class)."""
    return LandmarkPolicySearchAgent(**kwargs)


# -- the rollout labeller (expert iteration) --------------------------------------------------


def _landmark_label(labeller: Any, view: Any, obs: dict[str, Any], n: int) -> Label:
    """A landmark's label: minus the best score of rollout's candidate subsets containing it."""
    best, scores = labeller.scores()
    d = np.full(n, np.inf)
    for subset, value in scores.items():
        for lm in subset:
            d[lm] = min(d[lm], -value)
    finite = np.isfinite(d)
    if finite.sum() > 1 and np.ptp(d[finite]) > 0:
        return view(obs), d, best[0], False
    return None, None, best[0], False


def landmark_rollout_labeller(
    top_k: int, horizon: int, kind: str = "rollout"
) -> tuple[LandmarkFastRolloutAgent | LandmarkRolloutAgent, LabelFn]:
    """The labeller ``kind`` (one of :data:`LANDMARK_LABELLERS`) and how it labels a pick.

    With ``kind`` bound (``functools.partial``), the
    :data:`~selenv.learned.rl.expert.Labeller` of :func:`collect_landmark_rollout_labels`.

    Raises:
        ValueError: ``kind`` not a landmark labeller; a bad ``top_k`` or ``horizon`` (the
            agent's own checks).
    """
    if kind not in LANDMARK_LABELLERS:
        raise ValueError(f"labeller must be one of {LANDMARK_LABELLERS}, got {kind!r}")
    if kind == "fast_rollout":
        return LandmarkFastRolloutAgent(top_k=top_k, horizon=horizon), _landmark_label
    return LandmarkRolloutAgent(top_k=top_k, horizon=horizon), _landmark_label


def collect_landmark_rollout_labels(
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    top_k: int = 4,
    horizon: int = 10,
    labeller: str = "rollout",
    **options: Any,
) -> RankingData:
    """Label ``LandmarkSelection-v1`` picks with the landmark ``rollout`` reference's scores.

    At every pick the labeller scores its candidate subsets of the picks left in the filter
    step (``top_k`` by one-step gain plus brute force's own); a landmark's ``dJ`` is minus the
    best score of a candidate subset containing it, ``+inf`` if none does. The behaviour
    plays the first landmark of rollout's best subset (or ``behaviour``'s pick: DAgger).
    Picks where all labelled landmarks tie are skipped. Same seeds and options as
    :func:`selenv.learned.families.cooperative.collect_cl_rollout_labels`, plus ``labeller``:
    ``"rollout"`` (:class:`~selenv.families.landmarks.rollout.LandmarkRolloutAgent`) or
    ``"fast_rollout"`` (:class:`~selenv.families.landmarks.fast_rollout.LandmarkFastRolloutAgent`:
    the same forecast on a shortlist of the 6 landmarks with the largest single gain, 11-15x
    cheaper per label).

    Raises:
        ValueError: as :func:`~selenv.learned.families.cooperative.collect_cl_rollout_labels`;
            ``labeller`` not one of the two.
        TypeError: an unknown option.
    """
    if labeller not in LANDMARK_LABELLERS:
        raise ValueError(f"labeller must be one of {LANDMARK_LABELLERS}, got {labeller!r}")
    return collect_rollout_labels(
        LANDMARK_ID,
        env_kwargs,
        n_states,
        seed,
        labeller=partial(landmark_rollout_labeller, kind=labeller),
        view=None,
        top_k=top_k,
        horizon=horizon,
        **options,
    )
