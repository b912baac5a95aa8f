"""A trained (Maskable)PPO checkpoint as a :class:`selenv.agents.Agent` (registry name ``ppo``).

The checkpoint is a zip saved by SB3 with a JSON of its metadata next to it (same stem), as
written by the ``train/*_ppo.py`` scripts: the env id it was trained on, the candidate view
(:mod:`selenv.learned.rl.views`) that turns the env's observation into the policy's input, and the
layout. The policy's weights do not depend on the number of candidates, so one checkpoint
plays any instance of its env with the same per-candidate width::

    agent = selenv.agents.make("ppo", "selenv/LandmarkSelection-v1")  # shipped checkpoint
    agent = SB3PolicyAgent("my_run.zip", env_id="selenv/LandmarkSelection-v1")
    obs, info = env.reset(seed=0)
    agent.reset(env, seed=0)
    action = agent.act(obs, info)

The policy is rebuilt from the JSON (never unpickled from the zip): the per-candidate
``CandidateScorer`` (:mod:`selenv.learned.rl.safe_load`) or, when
``architecture.features_extractor`` is exactly
:data:`selenv.learned.families.clustering_edits.EDIT_EXTRACTOR`, the factorised edit scorer of
``ReceiverClustering-v1``
(:func:`selenv.learned.families.clustering_edits.load_edit_policy`); either way only the zip's
weight tensors are read.

Every failure to load or to apply a checkpoint (missing file, another env, another width) is
a ``ValueError`` naming the file and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from selenv.agents.base import Agent
from selenv.families import FAMILIES
from selenv.learned.resources import checkpoint_dir, read_metadata, with_shipped
from selenv.learned.rl.candidate_policy import (
    MASKED_LOGIT,
    CandidateScoringPolicy,
    CandidateScoringPPOPolicy,
    obs_layout,
)
from selenv.learned.rl.lean import LeanScorer, TopMScorer
from selenv.learned.rl.safe_load import checked_layout, load_policy
from selenv.learned.rl.views import CandidateView, view_for

__all__ = [
    "CHECKPOINT_DIR",
    "DEFAULT_CHECKPOINTS",
    "SB3PolicyAgent",
    "load_metadata",
    "make_ppo_agent",
]

FIM_ENV_ID = "selenv/FIMSelection-v1"
CHECKPOINT_DIR = checkpoint_dir()
#: env id -> the shipped checkpoint the ``ppo`` agent loads by default
DEFAULT_CHECKPOINTS = {
    f.agents_id: CHECKPOINT_DIR / f.checkpoint for f in FAMILIES if f.checkpoint is not None
}


def load_metadata(checkpoint: str | Path) -> dict[str, Any]:
    """Read and check the JSON metadata next to ``checkpoint`` (``foo.zip`` -> ``foo.json``).

    The file is untrusted: its size and nesting depth are bounded before it is parsed
    (:func:`selenv.learned.resources.read_metadata`) and every ``obs_layout`` size before
    anything is built (:func:`selenv.learned.rl.safe_load.checked_layout`).

    Raises:
        ValueError: the JSON is missing, unreadable, too large, nested too deep, not an
            object, or its ``obs_layout`` lacks an integer ``whitened_dim``, has sizes beyond
            ``CHECKPOINT_LIMITS`` or ``whitened_dim != m d``; a ``view`` or ``env_id`` that is
            not a string; the message names the file.
    """
    path = Path(checkpoint).with_suffix(".json")
    if not path.is_file():
        raise ValueError(f"checkpoint metadata {path} not found (expected next to {checkpoint})")
    meta = read_metadata(path)
    if not isinstance(meta, dict):
        raise ValueError(f"checkpoint metadata {path} must be a JSON object")
    checked_layout(meta, f"metadata {path}")
    for key in ("view", "env_id"):
        if meta.get(key) is not None and not isinstance(meta[key], str):
            raise ValueError(
                f"checkpoint metadata {path}: {key!r} must be a string, got {meta[key]!r:.80}"
            )
    return cast(dict[str, Any], meta)


class SB3PolicyAgent(Agent):
    """Acts with a MaskablePPO or PPO candidate-scoring checkpoint (greedy in its logits).

    Args:
        checkpoint: path of the SB3 zip; default: the shipped one of ``env_id``
            (:data:`DEFAULT_CHECKPOINTS`).
        env_id: the env the agent will play; the checkpoint must have been trained on it.
        deterministic: take the most likely action (default) rather than sample one.
        verify_top_k: 0 (default) plays the policy's action. ``k > 0`` uses the policy as a
            proposal: its ``k`` highest-scoring allowed actions are costed exactly by the
            view's :meth:`~selenv.learned.rl.views.CandidateView.verify` (only
            ``ReceiverClustering-v1``: ``k`` Algorithm 1 evaluations per decision) and the
            best improving one is played.
        lean: with ``deterministic``, take the action through
            :class:`~selenv.learned.rl.lean.LeanScorer` (the scorer's forward under
            ``torch.inference_mode``, the same action as SB3's ``predict`` at a fraction of
            its cost); ``False`` calls ``predict``.
        top_m: ``m > 0`` scores only the ``m`` allowed candidates of largest gain, in numpy
            (:class:`~selenv.learned.rl.lean.TopMScorer`): an approximation of the policy for large
            pools (``ppo:top_m=32``); 0 (default) evaluates the whole pool.

    Raises:
        ValueError: the checkpoint or its JSON is missing or unreadable, they disagree, or
            the checkpoint was trained on another env.
    """

    name = "ppo"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        env_id: str = FIM_ENV_ID,
        deterministic: bool = True,
        verify_top_k: int = 0,
        lean: bool = True,
        top_m: int = 0,
    ) -> None:
        if isinstance(verify_top_k, bool) or not isinstance(verify_top_k, int) or verify_top_k < 0:
            raise ValueError(f"verify_top_k must be an int >= 0, got {verify_top_k!r}")
        self.verify_top_k = verify_top_k
        if not isinstance(lean, bool):
            raise TypeError(f"lean must be a bool, got {type(lean).__name__}")
        self.lean = lean
        if isinstance(top_m, bool) or not isinstance(top_m, int) or top_m < 0:
            raise ValueError(f"top_m must be an int >= 0, got {top_m!r}")
        if top_m and not deterministic:
            raise ValueError("top_m needs deterministic=True (it takes the top scorer's argmax)")
        self.top_m = top_m
        self._top: dict[int, TopMScorer] = {}
        self._numpy: dict[tuple[int, int], TopMScorer] = {}  # logits(backend="numpy")
        if checkpoint is None:
            if env_id not in DEFAULT_CHECKPOINTS:
                raise ValueError(f"no shipped checkpoint for {env_id!r}; pass checkpoint=")
            checkpoint = DEFAULT_CHECKPOINTS[env_id]
        self.checkpoint = Path(checkpoint)
        self.env_id = env_id
        self.deterministic = deterministic
        if not self.checkpoint.is_file():
            raise ValueError(f"checkpoint {self.checkpoint} not found")
        self.metadata = load_metadata(self.checkpoint)
        trained_on = self.metadata.get("env_id", FIM_ENV_ID)
        if trained_on != env_id:
            raise ValueError(
                f"checkpoint {self.checkpoint} was trained on {trained_on!r}, not {env_id!r}"
            )
        # never SB3's load(): it unpickles the zip's data (code execution); see safe_load.
        # The architecture is chosen from two fixed loaders by an exact string of the JSON.
        # (a family's own architecture is rebuilt by its builder: safe_load.builder_for)
        policy = load_policy(self.checkpoint, self.metadata)
        if top_m and getattr(policy.pi_features_extractor, "scores_every_candidate", False):
            raise ValueError(
                f"top_m={top_m}: checkpoint {self.checkpoint} has a factorised edit scorer, "
                "which scores every edit cheaply already (use top_m=0)"
            )
        self.masked = isinstance(policy, CandidateScoringPolicy)  # MaskablePPO's policy
        layout = obs_layout(policy.observation_space)
        meta_layout = self.metadata["obs_layout"]
        if layout["whitened_dim"] != meta_layout["whitened_dim"]:
            raise ValueError(
                f"checkpoint {self.checkpoint}: the model's per-candidate width is "
                f"{layout['whitened_dim']} but its metadata says {self._expected()}"
            )
        trained_n = meta_layout.get("n_candidates_trained", layout["n"])
        if trained_n != layout["n"]:
            raise ValueError(
                f"checkpoint {self.checkpoint}: the model has {layout['n']} candidates but its "
                f"metadata says obs_layout n_candidates_trained={trained_n!r}"
            )
        self.whitened_dim = layout["whitened_dim"]
        self._policies: dict[int, CandidateScoringPolicy | CandidateScoringPPOPolicy] = {
            layout["n"]: policy
        }
        self.view: CandidateView | None = None
        self._lean: dict[int, LeanScorer] = {}

    # -- shape checks and N-independent rebuilds ---------------------------------------------
    def _expected(self) -> str:
        lay = self.metadata["obs_layout"]
        md = f"m={lay['m']}, d={lay['d']}, " if "m" in lay and "d" in lay else ""
        return f"{md}whitened_dim={lay['whitened_dim']}, 4 features"

    def check_space(self, observation_space: spaces.Space, env: Any = None) -> int:
        """Check a candidate-view ``observation_space`` against the checkpoint; return ``N``.

        Raises:
            ValueError: another per-candidate width or layout, naming both.
        """
        try:
            layout = obs_layout(observation_space)
        except ValueError as exc:
            raise ValueError(
                f"checkpoint {self.checkpoint} expects candidate observations with "
                f"{self._expected()}: {exc}"
            ) from exc
        if layout["whitened_dim"] != self.whitened_dim:
            actual = f"whitened_dim={layout['whitened_dim']}"
            base = getattr(env, "unwrapped", None)
            m, d = getattr(base, "m", None), getattr(base, "d", None)
            if m is not None and d is not None:
                actual = f"m={m}, d={d} ({actual})"
            raise ValueError(
                f"checkpoint {self.checkpoint} was trained on observations with "
                f"{self._expected()}; this env has {actual}"
            )
        return layout["n"]

    def policy_for(
        self, observation_space: spaces.Dict
    ) -> CandidateScoringPolicy | CandidateScoringPPOPolicy:
        """The checkpoint's policy for this candidate space (rebuilt once per new ``N``)."""
        n = self.check_space(observation_space)
        if n not in self._policies:
            src = next(iter(self._policies.values()))
            params = src._get_constructor_parameters()
            params.update(observation_space=observation_space, action_space=spaces.Discrete(n))
            policy = type(src)(**params)
            policy.load_state_dict(src.state_dict())
            policy.set_training_mode(False)
            self._policies[n] = policy
        return self._policies[n]

    # -- Agent protocol ------------------------------------------------------------------------
    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Build the env's candidate view and check it against the checkpoint."""
        super().reset(env, seed)
        self.view = view_for(self.env_id, env, self.metadata.get("view"))
        if self.verify_top_k and type(self.view).verify is CandidateView.verify:
            raise ValueError(
                f"verify_top_k={self.verify_top_k}: the {self.view.name!r} view of "
                f"{self.env_id} has no exact verification (use verify_top_k=0)"
            )
        try:
            space = self.view.space(env.observation_space)
        except ValueError as exc:
            raise ValueError(f"checkpoint {self.checkpoint}: {exc}") from exc
        self.check_space(space, env)
        self._policy = self.policy_for(space)
        if id(self._policy) not in self._lean:
            self._lean[id(self._policy)] = LeanScorer(self._policy)

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> Any:
        """The policy's action on the candidate view, with the env's mask applied."""
        view, cand, mask = self._candidates(obs, info, "act")
        if self.verify_top_k:
            return view.env_action(obs, self._verified(obs, cand, mask))
        if self.top_m:
            key = id(self._policy)
            if key not in self._top:
                self._top[key] = TopMScorer(self._policy, self.top_m)
            return view.env_action(obs, self._top[key].action(cand, mask))
        if self.deterministic and self.lean:
            return view.env_action(obs, self._lean[id(self._policy)].action(cand, mask))
        if self.masked:
            action, _ = self._policy.predict(  # type: ignore[call-arg]
                cand, action_masks=mask, deterministic=self.deterministic
            )
        else:  # plain PPO: the policy masks its logits from the observation's mask
            cand = {**cand, "action_mask": mask.astype(cand["action_mask"].dtype)}
            action, _ = self._policy.predict(cand, deterministic=self.deterministic)
        return view.env_action(obs, int(action))

    def logits(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], backend: str = "torch"
    ) -> np.ndarray:
        """The policy's logits ``(N,)`` of the env's observation (float32).

        The candidates are the view's (the env's actions for the identity views); masked
        candidates (the view's and the env's mask) get the masked logit
        :data:`~selenv.learned.rl.candidate_policy.MASKED_LOGIT`, so ``argmax`` is the action
        :meth:`act` plays.

        Args:
            obs: the env's observation.
            info: its info dict (its ``action_mask``, if any, is applied).
            backend: ``"torch"``: the scorer's own forward (:class:`LeanScorer`);
                ``"numpy"``: the same network evaluated in numpy float32 on the allowed
                candidates (:class:`~selenv.learned.rl.lean.TopMScorer` with ``m = N``),
                several times cheaper on small pools; equal up to float32 rounding.

        Raises:
            ValueError: called before :meth:`reset`, an unknown ``backend``, or the
                observation does not fit the checkpoint.
        """
        if backend not in ("torch", "numpy"):
            raise ValueError(f"backend must be 'torch' or 'numpy', got {backend!r}")
        _, cand, mask = self._candidates(obs, info, "logits")
        if backend == "torch":
            return self._lean[id(self._policy)].scores(cand, mask)
        key = (id(self._policy), mask.shape[0])
        if key not in self._numpy:
            self._numpy[key] = TopMScorer(self._policy, mask.shape[0])
        allowed = np.flatnonzero(mask)
        out = np.full(mask.shape[0], MASKED_LOGIT, dtype=np.float32)
        if allowed.size:
            out[allowed] = self._numpy[key].scores(cand, allowed)
        return out

    def _candidates(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], caller: str
    ) -> tuple[CandidateView, dict[str, np.ndarray], np.ndarray]:
        """The bound view, its candidates of ``obs`` and their mask (the view's and the env's)."""
        view = self.view
        if view is None:
            raise ValueError(f"call reset(env) before {caller}()")
        cand = view(obs)
        width = np.shape(cand["whitened"])[1]
        if width != self.whitened_dim:
            raise ValueError(
                f"checkpoint {self.checkpoint} expects {self._expected()}; "
                f"got an observation with whitened width {width}"
            )
        mask = np.asarray(cand["action_mask"], dtype=bool)
        if "action_mask" in info and np.shape(info["action_mask"]) == mask.shape:  # env's own
            mask = mask & np.asarray(info["action_mask"], dtype=bool)  # a view may restrict
        return view, cand, mask

    def scores(self, cand: dict[str, np.ndarray]) -> np.ndarray:
        """The policy's per-candidate scores (action logits before masking), ``(N,)``."""
        import torch as th

        policy = self._policy
        obs_t, _ = policy.obs_to_tensor(cand)
        with th.no_grad():
            feats = cast(th.Tensor, policy.extract_features(obs_t, policy.pi_features_extractor))
        n = np.shape(cand["action_mask"])[0]
        return np.asarray(feats[0, :n].cpu().numpy(), dtype=np.float64)

    def _verified(self, obs: dict[str, np.ndarray], cand: dict[str, np.ndarray], mask: Any) -> int:
        """The best of the policy's ``verify_top_k`` highest-scoring allowed candidates."""
        allowed = np.flatnonzero(mask)
        if allowed.size == 0:
            raise ValueError("no allowed action to verify (empty action mask)")
        s = self.scores({**cand, "action_mask": np.asarray(mask, cand["action_mask"].dtype)})
        k = min(self.verify_top_k, allowed.size)
        top = allowed[np.argsort(-s[allowed], kind="stable")[:k]]
        return int(self.view.verify(self.env, obs, top))  # type: ignore[union-attr]


def make_ppo_agent(shipped: str | None = None, **kwargs: Any) -> SB3PolicyAgent:
    """Registry factory of the ``ppo`` agents (``env_id=``, ``checkpoint=``, ``deterministic=``).

    Args:
        shipped: file name of a shipped checkpoint in ``checkpoints/`` (the ``ppo_general``
            agent); ``checkpoint=`` then must not be given.
        **kwargs: keyword arguments of :class:`SB3PolicyAgent`.

    Raises:
        ValueError: ``shipped`` is not a plain file name, or both are given.
    """
    return SB3PolicyAgent(**with_shipped(shipped, kwargs))
