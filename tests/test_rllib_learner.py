"""RLlib's PPO learner with advantages standardised over the loss mask (``rllib_learner``)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ray")
th = pytest.importorskip("torch")

from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner  # noqa: E402
from ray.rllib.core.columns import Columns  # noqa: E402
from ray.rllib.evaluation.postprocessing import Postprocessing  # noqa: E402

from selenv.learned.rl.rllib_learner import (  # noqa: E402
    MaskedAdvantagePPOTorchLearner,
    masked_standardize,
)
from selenv.train import train_rllib_marl  # noqa: E402


def test_masked_standardize_uses_only_the_masked_rows() -> None:
    rng = np.random.default_rng(0)
    adv = rng.normal(3.0, 2.0, size=60)
    mask = rng.random(60) < 0.8
    adv[~mask] = rng.normal(-40.0, 30.0, size=(~mask).sum())  # junk rows: must not matter
    out = masked_standardize(th.tensor(adv), th.tensor(mask)).numpy()
    real = adv[mask]
    np.testing.assert_allclose(out[mask], (real - real.mean()) / (real.std(ddof=1) + 1e-8),
                               rtol=1e-12)  # fmt: skip
    assert np.all(out[~mask] == 0.0)
    # RLlib's batch-wide standardisation (junk rows included) shifts and shrinks the real rows
    wide = (adv - adv.mean()) / adv.std()
    assert abs(wide[mask].mean()) > 0.3 and wide[mask].std() < 0.5


def test_masked_standardize_edge_cases() -> None:
    adv = th.tensor([1.0, 2.0, 4.0])
    every = masked_standardize(adv, th.ones(3, dtype=th.bool))
    np.testing.assert_allclose(masked_standardize(adv, None).numpy(), every.numpy())
    assert masked_standardize(adv, th.tensor([False, True, False])).tolist() == [0.0, 0.0, 0.0]
    assert masked_standardize(adv, th.zeros(3, dtype=th.bool)).tolist() == [0.0, 0.0, 0.0]
    out = masked_standardize(adv, th.tensor([1, 0, 1]))  # an integer mask is a mask
    assert out[1] == 0.0 and out[0] == -out[2]


def test_learner_hands_rllib_the_restandardised_advantages(monkeypatch) -> None:
    seen = {}

    def fake_loss(self, *, module_id, config, batch, fwd_out):  # RLlib's loss, recorded
        seen.update(batch)
        return th.tensor(0.0)

    monkeypatch.setattr(PPOTorchLearner, "compute_loss_for_module", fake_loss)
    adv = th.tensor([5.0, 1.0, 3.0, -100.0])
    mask = th.tensor([True, True, True, False])
    batch = {Postprocessing.ADVANTAGES: adv, Columns.LOSS_MASK: mask}
    learner = object.__new__(MaskedAdvantagePPOTorchLearner)  # no module needed for the hook
    learner.compute_loss_for_module(module_id="shared", config=None, batch=batch, fwd_out={})
    np.testing.assert_allclose(seen[Postprocessing.ADVANTAGES].numpy(), [1.0, -1.0, 0.0, 0.0],
                               atol=1e-6)  # fmt: skip
    assert batch[Postprocessing.ADVANTAGES] is adv and adv[3] == -100.0  # caller's batch kept


@pytest.mark.parametrize(("norm", "learner"), [("masked", MaskedAdvantagePPOTorchLearner),
                                               ("rllib", PPOTorchLearner)])  # fmt: skip
def test_advantage_norm_option_selects_the_learner(norm: str, learner: type) -> None:
    cfg, env_kwargs = train_rllib_marl.parse_args(["--advantage-norm", norm])
    assert train_rllib_marl.build_config(cfg, env_kwargs).learner_class is learner


def test_advantage_norm_rejects_unknown_values(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        train_rllib_marl.parse_args(["--advantage-norm", "sb3"])
    assert exc.value.code == 2
    assert "advantage-norm" in capsys.readouterr().err


def test_plot_rllib_training_draws_the_recorded_runs_and_refuses_other_files(
    tmp_path, capsys
) -> None:
    from pathlib import Path

    from conftest import load_script

    from selenv.exits import guarded_main

    script = load_script("plot_rllib_training")
    root = Path(__file__).resolve().parents[1] / "docs" / "bench" / "rllib_training"
    fig = tmp_path / "rllib.png"
    runs = [f"{p.stem}={p}" for p in sorted(root.glob("*.metrics.json"))]
    assert len(runs) == 3
    assert guarded_main(script.main, script.PROG, [*runs, "--out", str(fig)]) == 0
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["rllib.png"]  # no temporary left
    capsys.readouterr()
    other = tmp_path / "other.json"
    other.write_text('{"iteration": 1}')
    for bad in (f"x={other}", str(other), f"x={tmp_path / 'missing.json'}"):
        assert guarded_main(script.main, script.PROG, [bad, "--out", str(fig)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and ("LABEL=PATH" in err or str(tmp_path) in err)
    # the moving average: trailing mean over the window, fewer points at the start
    np.testing.assert_allclose(script.smooth(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1, 2, 4, 6])
