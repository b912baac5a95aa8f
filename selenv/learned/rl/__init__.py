"""RL glue between the selenv envs and stable-baselines3 / sb3-contrib.

* :mod:`selenv.learned.rl.candidate_policy` -- the permutation-equivariant candidate-scoring policy
  (DeepSets features extractor + MaskablePPO heads): one policy for any pool size ``N``.
* :mod:`selenv.learned.rl.views` -- per-env *candidate views*: each env's observation rewritten as a
  set of candidates (one row per action) so that the same policy class serves every env;
  :class:`~selenv.learned.rl.views.CandidateViewWrapper` applies one for training.
* :mod:`selenv.learned.rl.marl` -- PettingZoo -> SB3: a multi-agent env played turn by turn by one
  shared policy (parameter sharing).
* :mod:`selenv.learned.rl.training` -- the training loop the ``train/`` scripts share (vectorised
  envs, TensorBoard, tqdm, checkpoint + JSON metadata, evaluation against heuristics).
* :mod:`selenv.learned.rl.agent` -- a checkpoint as a :class:`selenv.agents.Agent` (``ppo``).
"""
