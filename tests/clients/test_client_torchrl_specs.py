"""TorchRL interop, single envs: ``GymEnv`` specs and masked rollouts, ``PettingZooWrapper``.

What a TorchRL user writes first, on default keywords: ``check_env_specs`` (reset / step /
rand_step agree with the declared specs) and a masked rollout (the ``ActionMask`` transform
for the Gymnasium ids, the wrapper's own mask handling for the PettingZoo modules) in which
every action taken is allowed by the mask it was taken under. Needs the ``torchrl`` extra.
The batched and collector paths are in ``test_client_torchrl.py``.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

torchrl = pytest.importorskip("torchrl")
torch = pytest.importorskip("torch")

from torchrl.envs import GymEnv, TransformedEnv  # noqa: E402
from torchrl.envs.libs.pettingzoo import PettingZooWrapper  # noqa: E402
from torchrl.envs.transforms import ActionMask  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

import selenv  # noqa: E402, F401  (registers the ids)
from selenv.families import ENV_IDS  # noqa: E402
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1  # noqa: E402


def _masked_rollout_ok(td: object, steps: int) -> None:
    """Every action of the rollout was allowed by the mask observed before it."""
    action = td["action"]  # type: ignore[index]
    mask = td["action_mask"]  # type: ignore[index]
    assert action.shape[: len(td.batch_size)] == td.batch_size  # type: ignore[attr-defined]
    one_hot = action.shape == mask.shape
    idx = action.float().argmax(-1, keepdim=True) if one_hot else action.long().unsqueeze(-1)
    allowed = torch.gather(mask.bool(), -1, idx)
    assert bool(allowed.all()), "a masked action was taken"
    assert td.batch_size[-1] == steps  # type: ignore[attr-defined]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymenv_specs_and_masked_rollout(env_id: str) -> None:
    env = TransformedEnv(GymEnv(env_id), ActionMask())
    check_env_specs(env, seed=0)
    td = env.rollout(12, break_when_any_done=False)
    _masked_rollout_ok(td, 12)
    env.close()


def test_gymenv_frozen_assignment_mode_specs() -> None:
    """ReceiverClustering-v1's assignment mode (MultiDiscrete actions) passes and rolls out."""
    env = GymEnv("selenv/ReceiverClustering-v1")
    check_env_specs(env, seed=0)
    td = env.rollout(5, break_when_any_done=False)
    assert td["action"].shape[0] == 5 and td["action_mask"].shape[-1] == 30 * 30
    env.close()


@pytest.mark.parametrize("module", [fim_selection_v0, receiver_clustering_v1])
@pytest.mark.parametrize("parallel", [False, True], ids=["aec", "parallel"])
def test_pettingzoo_wrapper_specs_and_rollout(module: object, parallel: bool) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        raw = module.parallel_env() if parallel else module.env()  # type: ignore[attr-defined]
        env = PettingZooWrapper(raw, use_mask=True, seed=0)
        check_env_specs(env, seed=0)
        td = env.rollout(15, break_when_any_done=False)
    assert td.batch_size[0] == 15
    for group in env.group_map:
        mask = td[group, "action_mask"].bool()
        action = td[group, "action"].long().unsqueeze(-1)
        assert bool(torch.gather(mask, -1, action).all()), f"{group}: a masked action was taken"
    assert np.isfinite(td["next", next(iter(env.group_map)), "reward"].numpy()).all()
