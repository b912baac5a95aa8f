"""The edit view's rows, built by one gather per edit end, equal the per-column concatenation.

The concatenation below is the view's former construction (what the shipped checkpoints were
trained on); the elementwise operations involve no BLAS call, so the rows must be bit-equal.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401
from selenv.learned.rl.views import view_for

ENV_ID = "selenv/ReceiverClustering-v1"


def _reference_whitened(view, obs) -> np.ndarray:
    labels = np.asarray(obs["assignment"], dtype=np.intp)
    ls = np.log(np.maximum(np.asarray(obs["sigma"], dtype=np.float32), 1e-6))
    sizes = np.bincount(labels, minlength=labels.max() + 1).astype(np.float32)
    sums = np.zeros((sizes.size, 2), np.float32)
    np.add.at(sums, labels, ls)
    cl_mean = (sums / sizes[:, None])[labels]
    size = sizes[labels] / view.max_size
    pv = np.maximum(np.asarray(obs["position_var"], dtype=np.float64), 1e-12)
    lpv = np.log(pv)
    cv = np.zeros(sizes.size)
    np.add.at(cv, labels, pv)
    lcv = np.log(cv / sizes)[labels]
    rel_pv, rel_cv = lpv - lpv.max(), lcv - lcv.max()
    t = float(np.asarray(obs["time"]).reshape(-1)[0])
    i, j = view.i, view.j
    w = np.concatenate(
        [ls[i], ls[j], cl_mean[i], cl_mean[j], size[i, None], size[j, None],
         lpv[i, None], lpv[j, None], np.full((view.count, 1), t),
         rel_pv[i, None], rel_pv[j, None], rel_cv[i, None], rel_cv[j, None]],
        axis=1,
    ).astype(np.float32)  # fmt: skip
    w[0] = 0.0
    return w


def test_gathered_rows_equal_the_concatenation_over_episodes() -> None:
    rng = np.random.default_rng(0)
    for kwargs in ({"action_mode": "edit", "horizon": 12}, {"n_agents": 9, "horizon": 12}):
        env = gym.make(ENV_ID, **kwargs)
        view = view_for(ENV_ID, env, "clustering_edits")
        obs, _ = env.reset(seed=4)
        checked = 0
        for _ in range(12):
            out = view(obs)
            np.testing.assert_array_equal(out["whitened"], _reference_whitened(view, obs))
            checked += 1
            mask = np.asarray(env.unwrapped.action_masks(), dtype=bool)
            if mask.ndim == 1 and mask.size == view.count:
                action = int(rng.choice(np.flatnonzero(mask)))
            else:  # assignment mode: a random allowed edit, as the view maps it
                action = view.env_action(obs, int(rng.choice(np.flatnonzero(out["action_mask"]))))
            obs, _, term, trunc, _ = env.step(action)
            if term or trunc:
                break
        assert checked >= 5
        env.close()
