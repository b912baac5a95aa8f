"""TorchRL's own entry points collect on every env: batched ``GymEnv``, ``GymWrapper`` over
``gym.make_vec``, ``ActionMask``, and ``Collector`` over ``PettingZooWrapper``.

* ``GymEnv(id, num_envs=2)``: TorchRL builds a Gymnasium ``AsyncVectorEnv`` of spawned workers
  itself and reads every ``info`` key into its specs (a ``str`` or a key on some steps only
  breaks it), on all eight ids, then a ``Collector`` runs over it. The workers resolve the id
  in a fresh interpreter: from a script (which imports selenv) the plain id works, tested in a
  fresh process; elsewhere (pytest, notebooks) Gymnasium's module-prefixed id
  ``"selenv:selenv/..."`` imports selenv first;
* ``GymWrapper(gym.make_vec(id, autoreset_mode=...))``: TorchRL accepts Gymnasium vector envs in
  the ``SameStep`` or ``Disabled`` autoreset modes only and says so for Gymnasium's own default
  ``SyncVectorEnv`` too; the native vector envs take the mode as a keyword;
* a ``Collector`` over ``PettingZooWrapper`` for both modules (both modes of
  fim_selection_v0), every float it stores finite.

Needs the ``torchrl`` extra.
"""

from __future__ import annotations

import pathlib
import sys
import warnings

import _proc
import gymnasium as gym
import pytest
from gymnasium.vector import AutoresetMode

pytest.importorskip("torchrl")
torch = pytest.importorskip("torch")

from torchrl.collectors import Collector  # noqa: E402
from torchrl.envs import GymEnv, GymWrapper, TransformedEnv  # noqa: E402
from torchrl.envs.libs.pettingzoo import PettingZooWrapper  # noqa: E402
from torchrl.envs.transforms import ActionMask  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

import selenv  # noqa: E402, F401  (registers the ids)
from selenv.families import FAMILIES  # noqa: E402
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1  # noqa: E402

ALL_IDS = sorted(i for i in gym.registry if i.startswith("selenv/"))
CURRENT_IDS = [f.current_id for f in FAMILIES]


def _finite(td: object) -> None:
    for key in td.keys(True, True):  # type: ignore[attr-defined]
        value = td[key]  # type: ignore[index]
        if value.is_floating_point():
            assert torch.isfinite(value).all(), key


def _collect(env: object, frames: int = 64) -> int:
    collector = Collector(env, policy=None, frames_per_batch=frames // 2, total_frames=frames)
    seen = 0
    try:
        for td in collector:
            _finite(td)
            seen += td.numel()
    finally:
        collector.shutdown()
    return seen


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_batched_gymenv_specs_and_collector(env_id: str) -> None:
    """The module-prefixed id: TorchRL's workers are spawned processes that import only what
    the id names (``__main__`` here is pytest, which never imports selenv)."""
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the -v0 ids say they are old
        env = GymEnv(f"selenv:{env_id}", num_envs=2)
    try:
        assert tuple(env.batch_size) == (2,)
        check_env_specs(env, seed=0)
        assert _collect(env) == 64
    finally:
        env.close()


SCRIPT = """
import selenv, torch
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

if __name__ == "__main__":  # TorchRL's workers are spawned: they re-import this module
    env = GymEnv("selenv/FIMSelection-v1", num_envs=2)
    check_env_specs(env, seed=0)
    td = env.rollout(12, break_when_any_done=False)
    print("rolled", tuple(td.batch_size))
    env.close()
"""


def test_batched_gymenv_on_the_plain_id_from_a_script(tmp_path: pathlib.Path) -> None:
    script = tmp_path / "train.py"
    script.write_text(SCRIPT)
    out = _proc.run(
        [sys.executable, str(script)], timeout=300, cwd=tmp_path, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "rolled (2, 12)" in out.stdout


@pytest.mark.parametrize("mode", [AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
@pytest.mark.parametrize("env_id", CURRENT_IDS)
def test_gymwrapper_over_make_vec_with_action_mask(env_id: str, mode: AutoresetMode) -> None:
    torch.set_num_threads(1)
    venv = gym.make_vec(env_id, num_envs=2, autoreset_mode=mode)
    assert type(venv).__module__.startswith("selenv.families.")  # the native one
    env = TransformedEnv(GymWrapper(venv), ActionMask())
    try:
        check_env_specs(env, seed=0)
        assert _collect(env) == 64
    finally:
        env.close()


def test_gymwrapper_names_the_autoreset_modes_it_accepts() -> None:
    """TorchRL's rule, the same for Gymnasium's default vector env and the native one."""
    for venv in (
        gym.make_vec("selenv/FIMSelection-v1", num_envs=2),
        gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync"),
    ):
        assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP  # the default
        with pytest.raises(RuntimeError, match="SAME_STEP or DISABLED"):
            GymWrapper(venv)
        venv.close()


@pytest.mark.parametrize(
    ("module", "kwargs"),
    [
        (fim_selection_v0, {"mode": "cooperative"}),
        (fim_selection_v0, {"mode": "independent"}),
        (receiver_clustering_v1, {}),
    ],
    ids=["fim-cooperative", "fim-independent", "clustering"],
)
@pytest.mark.parametrize("parallel", [True, False], ids=["parallel", "aec"])
def test_pettingzoo_wrapper_collector(module: object, kwargs: dict, parallel: bool) -> None:
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        raw = module.parallel_env(**kwargs) if parallel else module.env(**kwargs)  # type: ignore[attr-defined]
        env = PettingZooWrapper(raw, use_mask=True, seed=0)
        assert _collect(env, frames=100) == 100
