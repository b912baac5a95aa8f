"""RLlib's PPO on selenv ids with RLlib's and Gymnasium's documented API only.

Each scenario runs in a fresh Python process with its own local Ray (RLlib's env runners are
separate processes that never import the test module), and trains one iteration:

* the plain ids of all four envs with ``ray.init(runtime_env={
  "worker_process_setup_hook": "selenv.register"})`` (selenv's ids registered in every worker);
* Gymnasium's module-prefixed id ``"selenv:selenv/ReceiverClustering-v1"`` (Gymnasium imports
  ``selenv`` before making the env), no hook: the frozen version's MultiDiscrete actions;
* the control: the plain id without the hook fails in the env runners with Gymnasium's
  ``NamespaceNotFound`` (logged by RLlib before its own build error; what the two ways above
  fix).

The Dict observations go through RLlib's ``FlattenObservations`` env-to-module connector.
"""

from __future__ import annotations

import json
import sys

import _proc
import pytest

pytest.importorskip("ray.rllib")

#: the current ids (selenv.families.FAMILIES), spelled out: importing selenv here would not
#: change what the fresh processes see, but keeps this module light
IDS = [
    "selenv/FIMSelection-v1",
    "selenv/LandmarkSelection-v1",
    "selenv/CLScheduling-v1",
    "selenv/ReceiverClustering-v2",
]

SCRIPT = r"""
import json, sys
import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.connectors.env_to_module import FlattenObservations

env_ids, hook = sys.argv[1].split(","), sys.argv[2] == "hook"
runtime_env = {"worker_process_setup_hook": "selenv.register"} if hook else None
ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
try:
    for env_id in env_ids:
        config = (
            PPOConfig()
            .environment(env_id)
            .env_runners(
                num_env_runners=1,
                env_to_module_connector=lambda env, spaces=None, device=None: FlattenObservations(),
            )
            .training(train_batch_size_per_learner=128, minibatch_size=64, num_epochs=1)
        )
        try:
            algo = config.build_algo()
        except Exception as exc:  # the control: report the runner's error
            print(json.dumps({"env": env_id, "built": False, "error": repr(exc)[:2000]}))
            continue
        result = algo.train()
        sampled = result["env_runners"]["num_env_steps_sampled_lifetime"]
        learner = result["learners"]["default_policy"]
        losses = [float(learner[k]) for k in ("policy_loss", "vf_loss")]
        print(json.dumps({"env": env_id, "built": True, "sampled": int(sampled), "losses": losses}))
        algo.stop()
finally:
    ray.shutdown()
"""


def _train(env_ids: list[str], hook: bool) -> tuple[list[dict], str]:
    done = _proc.run(
        [sys.executable, "-c", SCRIPT, ",".join(env_ids), "hook" if hook else "none"],
        capture_output=True,
        text=True,
        timeout=800,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [json.loads(ln) for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert [out["env"] for out in lines] == env_ids, done.stdout[-2000:] + done.stderr[-2000:]
    return lines, done.stderr


@pytest.mark.parametrize(
    ("env_ids", "hook"),
    [(IDS, True), (["selenv:selenv/ReceiverClustering-v1"], False)],
    ids=["plain-ids-with-the-hook", "module-prefixed-id"],
)
def test_rllib_trains_one_iteration(env_ids: list[str], hook: bool) -> None:
    results, _ = _train(env_ids, hook)
    for out in results:
        assert out["built"], out
        assert out["sampled"] >= 128
        assert all(loss == loss and abs(loss) < 1e6 for loss in out["losses"])  # finite


def test_the_plain_id_without_the_hook_fails_in_the_runners() -> None:
    (out,), stderr = _train(["selenv/FIMSelection-v1"], hook=False)
    assert not out["built"]
    # the runner's error, as RLlib logs it before its own build error
    assert "NamespaceNotFound: Namespace selenv not found" in stderr, stderr[-3000:]
