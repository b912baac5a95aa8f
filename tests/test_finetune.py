"""Fine-tuning from a checkpoint: --init-from loads the weights exactly, --critic-warmup freezes
the actor, mismatches and bad values are usage errors before any training."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from selenv.exits import UsageError
from selenv.learned.rl.finetune import CRITIC_PREFIXES
from selenv.learned.rl.safe_load import read_weights
from selenv.train import train_fim_ppo

TINY = [
    "--env-kwargs", json.dumps({"n_candidates": 10, "budget": 3}),
    "--n-envs", "2", "--n-steps", "64", "--batch-size", "64", "--n-epochs", "2",
    "--eval-episodes", "0", "--tensorboard-dir", "", "--no-progress", "--checkpoint-every", "0",
]  # fmt: skip


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("base") / "a.zip"
    train_fim_ppo.main([*TINY, "--total-timesteps", "128", "--out", str(out)])
    return out


def _run(tmp_path: Path, name: str, *extra: str) -> tuple[Path, dict]:
    out = tmp_path / f"{name}.zip"
    meta = train_fim_ppo.main([*TINY, "--out", str(out), "--seed", "7", *extra])
    return out, meta


def _split(weights: dict[str, torch.Tensor]) -> tuple[dict, dict]:
    critic = {k: v for k, v in weights.items() if k.startswith(CRITIC_PREFIXES)}
    actor = {k: v for k, v in weights.items() if not k.startswith(CRITIC_PREFIXES)}
    assert critic and actor
    return actor, critic


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_init_from_loads_the_weights_exactly(base: Path, tmp_path: Path) -> None:
    out, meta = _run(tmp_path, "b", "--init-from", str(base), "--total-timesteps", "0")
    assert _same(read_weights(out), read_weights(base))
    base_meta = json.loads(base.with_suffix(".json").read_text())
    assert meta["init_from"]["checkpoint_sha256"] == base_meta["checkpoint_sha256"]
    assert meta["init_from"]["view"] == "identity"


def test_critic_warmup_trains_the_value_head_only(base: Path, tmp_path: Path) -> None:
    warm, _ = _run(
        tmp_path, "warm", "--init-from", str(base), "--total-timesteps", "128",
        "--critic-warmup", "128",
    )  # fmt: skip
    actor0, critic0 = _split(read_weights(base))
    actor, critic = _split(read_weights(warm))
    assert _same(actor, actor0)  # the one update of the run was the critic's
    assert not _same(critic, critic0)
    free, _ = _run(tmp_path, "free", "--init-from", str(base), "--total-timesteps", "128")
    assert not _same(_split(read_weights(free))[0], actor0)  # without warm-up the actor moves


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--hidden", "32,32"], "do not fit this run's policy"),
        (["--view", "invariant"], "was trained on"),
    ],
)
def test_init_from_refuses_another_architecture_or_view(
    base: Path, tmp_path: Path, extra: list[str], match: str
) -> None:
    with pytest.raises(UsageError, match=match):
        _run(tmp_path, "x", "--init-from", str(base), "--total-timesteps", "64", *extra)
    assert not (tmp_path / "x.zip").exists()


# the bounds of --critic-warmup, --target-kl and --init-from: tests/test_training_faults.py


def test_normalize_reward_changes_the_training_signal_only(base: Path, tmp_path: Path) -> None:
    plain, _ = _run(tmp_path, "plain", "--init-from", str(base), "--total-timesteps", "128")
    scaled, meta = _run(
        tmp_path, "scaled", "--init-from", str(base), "--total-timesteps", "128",
        "--normalize-reward",
    )  # fmt: skip
    assert meta["training"]["normalize_reward"] is True
    assert not _same(read_weights(scaled), read_weights(plain))  # the option is not ignored
    assert read_weights(scaled).keys() == read_weights(plain).keys()  # same policy, no wrapper
