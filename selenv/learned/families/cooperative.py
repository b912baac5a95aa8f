"""Learning code that serves ``CLScheduling``: the ``cem`` scorer and the ``rollout`` labeller.

``cem``: greedy's score plus a learned correction, trained on returns. The agent scores stop
with 0 and an open pair ``p`` with

    score(p) = S_h(p) + theta . phi(p)

where ``phi`` are the pair's features (:mod:`selenv.families.cooperative.features`: what the
fusion does to agent ``i``'s velocity and attitude uncertainty, the two agents' relative
uncertainty, time left, steps since the last fusions) and ``S_h`` is the objective drop of a
short lookahead: ``h = 0``, the previewed one-step gain (greedy's score; every open pair is a
candidate); ``h >= 1``, ``fast_rollout``'s simulation of ``h`` more filter steps of greedy
(:mod:`selenv.families.cooperative.fast_rollout`; candidates: stop and the ``top_k`` pairs of
largest gain, stop scored by its own simulation, ``h`` capped at its ceiling). ``theta``
(12 numbers) is fitted by the cross-entropy method on whole-episode returns
(:mod:`selenv.learned.rl.cem`, ``python -m selenv.train.train_cl_cem``), not on labels:
the policies fitted to ``rollout``'s per-decision labels stayed level with greedy (the
learned-selectors page).

The checkpoint is a JSON file of numbers (no code, no pickle): read with
:func:`~selenv.learned.resources.read_metadata` (size and depth bounded) and every field
checked. It is tied to the env configuration it was trained on (team size, model, objective,
fusion, budget): another one is refused at ``reset``.

The ``rollout`` labeller (:func:`collect_cl_rollout_labels`) labels ``CLScheduling-v1``
decisions with the ``rollout`` reference's scores, for expert iteration
(:mod:`selenv.learned.rl.expert`, ``python -m selenv.train.train_cl_expert``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from selenv.agents.rollout import best_index, ceiling_option
from selenv.core.linalg import FloatArray
from selenv.families.cooperative.fast_rollout import CLFastRolloutAgent
from selenv.families.cooperative.features import FEATURE_NAMES, FusionMemory, pair_features
from selenv.families.cooperative.rollout import CL_ENV_ID, CLRolloutAgent
from selenv.learned.resources import checkpoint_path, read_metadata

if TYPE_CHECKING:  # the labeller's collection loop is torch code, imported when it runs
    from selenv.learned.rl.expert import Label, LabelFn
    from selenv.learned.rl.ranking import RankingData

__all__ = [
    "CHECKPOINT_FORMAT",
    "CL_ID",
    "DEFAULT_CEM_CHECKPOINT",
    "ENV_CONFIG_KEYS",
    "CLLearnedScorerAgent",
    "cl_rollout_labeller",
    "collect_cl_rollout_labels",
    "env_config",
    "make_cl_cem",
    "read_scorer",
]

#: the env the ``rollout`` labeller serves
CL_ID = CL_ENV_ID

CHECKPOINT_FORMAT = "selenv-cl-linear-scorer"
#: the shipped checkpoint (in ``checkpoints/``)
DEFAULT_CEM_CHECKPOINT = "cl_scheduling_cem.json"
#: env settings a checkpoint is tied to (refused at ``reset`` when the env differs)
ENV_CONFIG_KEYS = ("n_agents", "model", "objective", "fusion", "budget")


def env_config(env: Any) -> dict[str, Any]:
    """The settings of a ``CLSchedulingEnv`` that a scorer checkpoint is tied to."""
    return {
        "n_agents": int(env.config.n_agents),
        "model": str(env.config.model),
        "objective": str(env.objective),
        "fusion": str(env.fusion),
        "budget": int(env.budget),
    }


def read_scorer(path: str | Path) -> dict[str, Any]:
    """The checked contents of a scorer checkpoint (a JSON file; no code is executed).

    Returns the parsed JSON with ``theta`` as a float array.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a scorer checkpoint, features other than this version's
            :data:`~selenv.families.cooperative.features.FEATURE_NAMES`, a ``theta`` that is
            not that many finite numbers, a bad lookahead, or a bad ``env_config``; the
            message names the file and the field.
    """
    data = read_metadata(path, "scorer checkpoint")
    where = f"scorer checkpoint {path}"
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{where}: not a {CHECKPOINT_FORMAT!r} file (field 'format')")
    if data.get("features") != list(FEATURE_NAMES):
        raise ValueError(
            f"{where}: field 'features' is {data.get('features')!r:.200}; this version computes "
            f"{list(FEATURE_NAMES)}"
        )
    theta = data.get("theta")
    if (
        not isinstance(theta, list)
        or len(theta) != len(FEATURE_NAMES)
        or not all(isinstance(t, float | int) and not isinstance(t, bool) for t in theta)
        or not all(math.isfinite(t) for t in theta)
    ):
        raise ValueError(f"{where}: field 'theta' must hold {len(FEATURE_NAMES)} finite numbers")
    look = data.get("lookahead")
    if not isinstance(look, dict) or set(look) != {"horizon", "top_k"}:
        raise ValueError(f"{where}: field 'lookahead' must be {{'horizon': h, 'top_k': k}}")
    try:
        ceiling_option(look["horizon"], "horizon", 0, False)
        ceiling_option(look["top_k"], "top_k", 1, False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: field 'lookahead': {exc}") from None
    cfg = data.get("env_config")
    if not isinstance(cfg, dict) or set(cfg) != set(ENV_CONFIG_KEYS):
        raise ValueError(f"{where}: field 'env_config' must have the keys {list(ENV_CONFIG_KEYS)}")
    return {**data, "theta": np.asarray(theta, dtype=np.float64)}


class CLLearnedScorerAgent(CLFastRolloutAgent):
    """Greedy's score (or a short lookahead's) plus a learned linear correction (module doc).

    Args:
        theta: (F,) the correction's weights, in the order of ``FEATURE_NAMES``.
        horizon: lookahead filter steps ``h`` (0: the one-step gain, every open pair scored).
        top_k: pairs scored besides stop when ``h >= 1``.
        env_config: the env settings the weights were trained on (``None``: not checked).

    Attributes:
        last_scores: ``{action: score}`` of the last decision (stop is ``P``).
    """

    name = "cem"

    def __init__(
        self,
        theta: FloatArray,
        horizon: int = 0,
        top_k: int = 3,
        env_config: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(top_k=top_k, horizon=horizon)
        self.theta = np.asarray(theta, dtype=np.float64)
        if self.theta.shape != (len(FEATURE_NAMES),) or not np.all(np.isfinite(self.theta)):
            raise ValueError(f"theta must hold {len(FEATURE_NAMES)} finite numbers")
        self.env_config = env_config

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Bind to the env; ``ValueError`` when it is not the configuration trained on."""
        super().reset(env, seed)
        ours = env_config(self.cl)
        if ours["model"] != "ins":
            raise ValueError(f"agent 'cem' needs the ins model (9 states), got {ours['model']!r}")
        if self.env_config is not None:
            diff = [k for k in ENV_CONFIG_KEYS if self.env_config.get(k) != ours[k]]
            if diff:
                shown = ", ".join(
                    f"{k}={self.env_config.get(k)!r} (env: {ours[k]!r})" for k in diff
                )
                raise ValueError(f"agent 'cem': its weights were trained with {shown}")
        try:
            k = self.cl.sim.k
        except RuntimeError:  # bound before the env's reset: the episode starts at step 0
            k = 0
        self.memory = FusionMemory(self.cl.config.n_agents, k)

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        """The best-scored action; a chosen pair is recorded in the episode's fusion memory."""
        choice, self.last_scores = self.scores()
        if choice != self.cl.n_pairs:
            self.memory.record(int(self._pairs[choice, 0]), self.cl.sim.k)
        return choice

    def scores(self) -> tuple[int, dict[int, float]]:
        """The choice and the score of every candidate (stop is ``P``, scored 0 at ``h = 0``)."""
        env = self.cl
        decision = self.candidates()
        stop = env.n_pairs
        open_ = decision.open_pairs
        if open_.size == 0:
            return stop, {stop: 0.0}
        gains = decision.pair_gains[open_]
        phi = pair_features(
            decision.root.P,
            decision.posteriors,
            self._pairs[open_],
            gains,
            decision.root.k,
            env.horizon,
            self.memory,
        )
        correction = phi @ self.theta
        if self.horizon == 0:
            actions = [stop, *(int(p) for p in open_)]
            values = [0.0, *(float(v) for v in gains + correction)]
        else:
            actions = decision.actions
            stack = self.simulate(decision, self.horizon)
            if stack.k < env.horizon:
                self.advance(stack, decision.root.u_hold)
            drop = decision.root.objective_value() - self.objective(stack)
            index = {int(p): n for n, p in enumerate(open_)}
            values = [float(drop[0])]
            values += [
                float(drop[c]) + float(correction[index[a]]) for c, a in enumerate(actions) if c
            ]
        return actions[best_index(values)], dict(zip(actions, values, strict=True))


def make_cl_cem(checkpoint: str | Path | None = None) -> CLLearnedScorerAgent:
    """The ``cem`` agent from a scorer checkpoint (default: the shipped one).

    Raises:
        FileNotFoundError, ValueError: as :func:`read_scorer`.
    """
    path = Path(checkpoint) if checkpoint is not None else checkpoint_path(DEFAULT_CEM_CHECKPOINT)
    data = read_scorer(path)
    look = data["lookahead"]
    return CLLearnedScorerAgent(
        data["theta"], horizon=look["horizon"], top_k=look["top_k"], env_config=data["env_config"]
    )


# -- the rollout labeller (expert iteration) --------------------------------------------------


def _cl_label(labeller: Any, view: Any, obs: dict[str, Any], n: int) -> Label:
    """Rollout's scores of stop and its ``top_k`` pairs (exact ties are not labelled)."""
    mask = np.asarray(obs["action_mask"], dtype=bool)
    if not mask[:-1].any():
        return None, None, n - 1, True  # stop is the only allowed action
    choice, scores = labeller.scores()
    values = list(scores.values())
    if not max(values) > min(values):  # every pair a no-op (DMV w* = 1): no label
        return None, None, choice, False
    row = view(obs)
    allowed = np.asarray(row["action_mask"], dtype=bool)
    d = np.full(n, np.inf)
    for a, value in scores.items():
        if allowed[a]:  # a restricted view (top-k) may differ on exact gain ties
            d[a] = -value
    return (row, d, choice, False) if np.isfinite(d).sum() > 1 else (None, None, choice, False)


def cl_rollout_labeller(top_k: int, horizon: int) -> tuple[CLRolloutAgent, LabelFn]:
    """The ``rollout`` reference and how it labels a decision.

    The :data:`~selenv.learned.rl.expert.Labeller` of :func:`collect_cl_rollout_labels`.

    Raises:
        ValueError: ``top_k`` < 1 or ``horizon`` < 0 (the agent's own checks).
    """
    return CLRolloutAgent(top_k=top_k, horizon=horizon), _cl_label


def collect_cl_rollout_labels(
    env_kwargs: dict[str, Any],
    n_states: int,
    seed: int,
    *,
    view: str | None = "cl_pairs_fused_top3",
    top_k: int = 3,
    horizon: int = 5,
    **options: Any,
) -> RankingData:
    """Label ``n_states`` CL decisions with the ``rollout`` reference's scores.

    The ``rollout`` agent (:class:`~selenv.families.cooperative.rollout.CLRolloutAgent`)
    scores stop and the ``top_k`` open pairs of a decision by simulating ``horizon`` filter
    steps of greedy on the forecast covariance recursion (no truth, no future noise); each
    evaluated action gets ``dJ = -score``, the others ``+inf``. Only decisions whose evaluated
    actions differ are labelled: stop-only steps carry no choice, and early in an episode
    every pair's fused update is a no-op (DMV's ``w* = 1``), so stop and the pairs tie
    exactly (about the first ten steps of the benchmark preset).

    Args:
        env_kwargs: ``CLScheduling-v1`` keyword arguments (``{}``: the benchmark preset).
        n_states: labelled decisions to collect (each with actions of different scores).
        seed: training seed (episode seeds: :func:`~selenv.learned.rl.expert.train_seed`).
        view: candidate view of the policy; ``cl_pairs_fused_top3`` allows exactly the
            labeller's candidates (stop and the ``top_k`` pairs by previewed gain).
        top_k: pairs the labeller scores per decision (besides stop).
        horizon: filter steps the labeller simulates after the current one.
        **options: ``explore``, ``behaviour`` (DAgger), ``workers`` and ``progress`` of the
            shared collection loop, :func:`selenv.learned.rl.expert.collect_rollout_labels`.

    Raises:
        ValueError: ``n_states``, ``workers``, ``top_k`` < 1, ``horizon`` < 0, or ``explore``
            outside [0, 1].
        TypeError: an unknown option.
    """
    from selenv.learned.rl.expert import collect_rollout_labels

    return collect_rollout_labels(
        CL_ID,
        env_kwargs,
        n_states,
        seed,
        labeller=cl_rollout_labeller,
        view=view,
        top_k=top_k,
        horizon=horizon,
        **options,
    )
