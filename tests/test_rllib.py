"""RLlib path: the shared RLModule, the MultiAgentEnv adapter, training, safe export, bench agent.

Ray is started once for the file (module fixture ``ray_local``, one CPU) and must be gone,
with no raylet / gcs_server child left, when the file ends.
"""

from __future__ import annotations

import copy
import itertools
import json
import os
import shutil
import time
from pathlib import Path

import _proc
import numpy as np
import pytest

ray = pytest.importorskip("ray")
# RLlib registers its gymnasium id again for every algorithm built in the process
pytestmark = pytest.mark.filterwarnings("ignore:.*rllib-multi-agent-env-v0 already in registry")
th = pytest.importorskip("torch")

from ray.rllib.core.columns import Columns  # noqa: E402
from ray.rllib.utils.pre_checks.env import check_multiagent_environments  # noqa: E402

from selenv.agents import make  # noqa: E402
from selenv.bench import BenchError, run_bench  # noqa: E402
from selenv.learned.rl import rllib_agent  # noqa: E402
from selenv.learned.rl.rllib_agent import (  # noqa: E402
    RLlibPolicy,
    export_module,
    export_paths,
    load_exported,
)
from selenv.learned.rl.rllib_env import (  # noqa: E402
    CLUSTERING_MODULE,
    FIM_MODULE,
    SelenvMultiAgentEnv,
    acting_agents,
)
from selenv.learned.rl.rllib_module import MASKED_LOGIT, build_module  # noqa: E402
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1  # noqa: E402
from selenv.train import train_rllib_marl  # noqa: E402

SMALL_CL = {"n_agents": 4, "n_max_states": 10, "horizon": 6}
TINY = ["--iterations", "1", "--train-batch-size", "32", "--minibatch-size", "16",
        "--num-epochs", "1", "--num-env-runners", "0", "--eval-episodes", "0",
        "--no-progress", "--hidden", "16,16", "--vf", "16"]  # fmt: skip


def _ray_children() -> list[tuple[int, str]]:
    """Live (non-zombie) raylet / gcs_server processes started by this process."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        name = text[text.index("(") + 1 : text.rindex(")")]
        state, ppid = text[text.rindex(")") + 2 :].split()[:2]
        if int(ppid) == os.getpid() and state != "Z" and name in ("raylet", "gcs_server"):
            out.append((int(stat.parent.name), name))
    return out


@pytest.fixture(scope="module")
def ray_local():
    """One local Ray instance for the file; afterwards no Ray process of ours may remain."""
    from selenv.parallel import ray_session

    if not Path("/proc").is_dir():
        pytest.skip("needs /proc to check for leftover Ray processes")
    started_here = not ray.is_initialized()
    with ray_session(num_cpus=1) as session:
        if started_here:
            assert _ray_children(), "the session should have started a raylet"
        yield session
    if started_here:
        assert not ray.is_initialized()
        deadline = time.monotonic() + 15.0
        while _ray_children() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _ray_children(), f"Ray processes left behind: {_ray_children()}"


def _random_obs(rng: np.random.Generator, B: int, N: int, W: int) -> dict[str, th.Tensor]:
    mask = rng.random((B, N)) < 0.6
    mask[:, 0] = True
    return {
        "gain": th.tensor(rng.exponential(size=(B, N)), dtype=th.float32),
        "whitened": th.tensor(rng.normal(size=(B, N, W)) * 3, dtype=th.float32),
        "features": th.tensor(rng.random((B, N, 4)), dtype=th.float32),
        "selected": th.tensor(~mask & (rng.random((B, N)) < 0.5), dtype=th.int8),
        "budget_left": th.tensor(rng.random((B, 1)), dtype=th.float32),
        "action_mask": th.tensor(mask, dtype=th.int8),
    }


def _module_out(module, obs):
    with th.no_grad():
        logits = module.forward_inference({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
        value = module.compute_values({Columns.OBS: obs})
    return logits, value


# -- (a) the RLModule --------------------------------------------------------------------------
def test_module_is_permutation_equivariant() -> None:
    rng = np.random.default_rng(0)
    module = build_module(9, 5, {"gain_skip_init": 0.7})
    obs = _random_obs(rng, 4, 9, 5)
    logits, value = _module_out(module, obs)
    perm = th.tensor(rng.permutation(9))
    permuted = {k: (v if k == "budget_left" else v[:, perm]) for k, v in obs.items()}
    logits_p, value_p = _module_out(module, permuted)
    assert logits.shape == (4, 9) and value.shape == (4,)
    assert th.allclose(logits_p, logits[:, perm], atol=1e-5)
    assert th.allclose(value_p, value, atol=1e-5)
    # not trivially constant: the scores differ between allowed candidates
    allowed = logits[obs["action_mask"].bool()]
    assert allowed.std() > 1e-4


def test_module_is_pool_size_independent() -> None:
    rng = np.random.default_rng(1)
    module = build_module(9, 5)
    for n in (3, 9, 40):  # one module, three pool sizes
        logits, value = _module_out(module, _random_obs(rng, 2, n, 5))
        assert logits.shape == (2, n) and value.shape == (2,)
        assert th.isfinite(value).all()
    # no weight depends on N: a module for another pool size takes the same state_dict
    build_module(40, 5).load_state_dict(module.state_dict(), strict=True)
    with pytest.raises(RuntimeError):  # but the per-candidate width is part of the weights
        build_module(9, 6).load_state_dict(module.state_dict(), strict=True)


def test_masked_actions_get_zero_probability() -> None:
    from ray.rllib.core.distribution.torch.torch_distribution import TorchCategorical

    rng = np.random.default_rng(2)
    module = build_module(12, 4, {"gain_skip_init": 2.0})
    obs = _random_obs(rng, 8, 12, 4)
    logits, _ = _module_out(module, obs)
    mask = obs["action_mask"].bool()
    assert th.all(logits[~mask] == MASKED_LOGIT)
    probs = th.softmax(logits, dim=-1)
    assert probs[~mask].max() < 1e-30
    assert th.allclose(probs.sum(-1), th.ones(8))
    dist = module.get_exploration_action_dist_cls().from_logits(logits)
    assert isinstance(dist, TorchCategorical)
    th.manual_seed(0)
    samples = th.stack([dist.sample() for _ in range(300)])  # (300, 8)
    assert mask.gather(1, samples.T).all()
    entropy = dist.entropy()
    assert th.isfinite(entropy).all() and (entropy <= th.log(mask.sum(-1).float()) + 1e-5).all()


def test_module_ignores_rllib_model_config_keys_but_checks_its_own() -> None:
    from selenv.learned.rl.rllib_module import CandidateScoringRLModule, check_model_config

    space = build_module(5, 2).observation_space
    import gymnasium as gym

    module = CandidateScoringRLModule(
        observation_space=space,
        action_space=gym.spaces.Discrete(5),
        model_config={"vf_share_layers": False, "hidden": [8]},  # PPO merges vf_share_layers
    )
    assert module.module_config["hidden"] == [8]
    for bad in ({"hidden": []}, {"hidden": [0]}, {"activation": "gelu"}, {"vf_share_layers": 1}):
        with pytest.raises(ValueError):
            check_model_config(bad)
    with pytest.raises(ValueError, match="Discrete"):
        CandidateScoringRLModule(observation_space=space, action_space=gym.spaces.Discrete(6))


# -- (b) the env adapter -----------------------------------------------------------------------
ADAPTER_CASES = [
    ("fim_selection_v0", {}),
    ("fim_selection_v0", {"mode": "independent", "n_candidates": 8, "budgets": [2, 3]}),
    ("receiver_clustering_v1", SMALL_CL),
]


@pytest.mark.parametrize(("env", "kwargs"), ADAPTER_CASES)
def test_adapter_passes_rllib_env_check(env: str, kwargs: dict) -> None:
    adapter = SelenvMultiAgentEnv({"env": env, "env_kwargs": kwargs})
    check_multiagent_environments(adapter)
    space = adapter.observation_spaces[adapter.possible_agents[0]]
    obs, infos = adapter.reset(seed=5)
    assert obs and set(obs) == set(infos)
    assert all(space.contains(o) for o in obs.values())
    with pytest.raises(ValueError, match="unknown env_config"):
        SelenvMultiAgentEnv({"env": env, "typo": 1})


@pytest.mark.parametrize(("env", "kwargs"), ADAPTER_CASES)
def test_adapter_reproduces_the_pettingzoo_team_return(env: str, kwargs: dict) -> None:
    adapter = SelenvMultiAgentEnv({"env": env, "env_kwargs": kwargs})
    space = adapter.observation_spaces[adapter.possible_agents[0]]
    rng = np.random.default_rng(3)
    obs, _ = adapter.reset(seed=11)
    joint_actions, team_rewards, shown = [], [], []
    while True:
        assert all(space.contains(o) for o in obs.values())
        actions = {a: int(rng.choice(np.flatnonzero(o["action_mask"]))) for a, o in obs.items()}
        joint_actions.append({a: actions.get(a, 0) for a in adapter.penv.agents})
        shown.append(sorted(obs))
        obs, rewards, terms, truncs, last_infos = adapter.step(actions)
        team_rewards.append(float(np.mean(list(rewards.values()))))
        if terms["__all__"] or truncs["__all__"]:
            break
    assert set(obs) == set(adapter.possible_agents)  # the last step shows every agent
    # replay the same joint actions on the PettingZoo env itself
    module = fim_selection_v0 if env.startswith("fim") else receiver_clustering_v1
    penv = module.parallel_env(**kwargs)
    _, infos = penv.reset(seed=11)
    replay = []
    for i, joint in enumerate(joint_actions):
        assert shown[i] == sorted(acting_agents(penv, infos))
        _, rewards, _, _, infos = penv.step(joint)
        replay.append(float(np.mean(list(rewards.values()))))
    assert not penv.agents
    assert replay == pytest.approx(team_rewards, rel=0, abs=1e-12)
    assert sum(replay) != 0.0
    objective = last_infos[adapter.possible_agents[0]]["objective"]
    assert objective == pytest.approx(next(iter(infos.values()))["objective"])
    if env.startswith("fim") and not kwargs:  # cooperative: one agent decides per step
        assert all(len(s) == 1 for s in shown) and shown[0] == ["agent_0"]
        assert shown[-1] == ["agent_1"]


def test_adapter_is_seeded_by_reset() -> None:
    a = SelenvMultiAgentEnv({"env": "receiver_clustering_v1", "env_kwargs": SMALL_CL})
    b = SelenvMultiAgentEnv({"env": "receiver_clustering_v1", "env_kwargs": SMALL_CL})
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    oc, _ = b.reset(seed=8)
    key = "receiver_1"
    assert all(np.array_equal(oa[key][k], ob[key][k]) for k in oa[key])
    assert not all(np.array_equal(oa[key][k], oc[key][k]) for k in oa[key])


def test_cluster_label_view_is_label_equivariant() -> None:
    from selenv.learned.rl.rllib_env import ClusterLabelView

    penv = receiver_clustering_v1.parallel_env(n_agents=6, n_max_states=14)
    obs, _ = penv.reset(seed=1)
    view = ClusterLabelView(penv.max_size)
    o = obs["receiver_2"]
    v = view(o)
    labels = o["assignment"]
    own = int(labels[2])
    assert v["action_mask"][own] == 1 and v["gain"][own] == 1.0 and v["gain"].sum() == 1.0
    m = int(labels.max()) + 1
    assert not v["action_mask"][m + 1 :].any()  # one row for "new cluster"
    assert view.space(penv.observation_space("receiver_2")).contains(v)
    # relabel the clusters (a permutation of the used labels): rows move with their labels
    perm = np.random.default_rng(0).permutation(m)
    relabelled = dict(o, assignment=perm[labels])
    w = view(relabelled)
    for t in range(m):
        assert np.allclose(w["whitened"][perm[t]], v["whitened"][t])
        assert np.array_equal(w["features"][perm[t]], v["features"][t])


# -- (d) safe export and import ----------------------------------------------------------------
@pytest.fixture
def export(tmp_path: Path) -> Path:
    module = build_module(100, 16, {"hidden": [16, 16], "vf": [8]})
    meta = {"env_id": FIM_MODULE, "env_kwargs": {}}
    json_path, _ = export_module(module, tmp_path / "exp" / "policy", meta)
    return json_path


def test_export_roundtrip_and_bench_agent(export: Path) -> None:
    module, meta = load_exported(export)
    assert meta["env_id"] == FIM_MODULE and meta["obs_layout"]["whitened_dim"] == 16
    for path in (export, export.with_suffix(".pth"), export.with_suffix("")):
        assert export_paths(path) == (export, export.with_suffix(".pth"))
    agent = make(f"rllib:path={export}", FIM_MODULE)  # the policy record's agent, around it
    assert isinstance(getattr(agent, "inner", agent), RLlibPolicy)
    res = run_bench(FIM_MODULE, [f"rllib:path={export}"], episodes=1, progress=False,
                    env_kwargs={"n_candidates": 6, "budgets": 2})  # fmt: skip
    assert res.agents[f"rllib:path={export}"].skipped is None


def _rewrite(path: Path, **changes) -> None:
    meta = json.loads(path.read_text())
    for key, value in changes.items():
        node = meta
        *parents, leaf = key.split("__")
        for p in parents:
            node = node[p]
        node[leaf] = value
    path.write_text(json.dumps(meta))


class _Boom:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (self.marker.touch, ())


def test_tampered_or_malformed_exports_are_refused(export: Path, tmp_path: Path) -> None:
    pth = export.with_suffix(".pth")
    good_json, good_pth = export.read_text(), pth.read_bytes()

    def restore() -> None:
        export.write_text(good_json)
        pth.write_bytes(good_pth)

    def refused(match: str, name: Path) -> None:
        with pytest.raises(ValueError, match=match) as err:
            load_exported(export)
        assert str(name) in str(err.value)
        restore()

    raw = bytearray(good_pth)
    raw[len(raw) // 2] ^= 0xFF  # a flipped byte, same size
    pth.write_bytes(bytes(raw))
    refused("sha256", pth)
    export.write_text("{not json")
    refused("not valid JSON", export)
    _rewrite(export, format="something_else")
    refused("not an RLlib module export", export)
    _rewrite(export, module__class="os.system")
    refused("module class", export)
    _rewrite(export, module__model_config={"hidden": [32]})
    refused("do not fit", export)
    _rewrite(export, weights__file="../../etc/passwd.pth")
    refused("weights file", export)
    _rewrite(export, env_id="selenv/FIMSelection-v1")
    refused("no RLlib support", export)
    pth.unlink()
    refused("not found", pth)
    # a pickle that would run code: refused by weights_only, never executed
    marker = tmp_path / "executed"
    th.save({"w": _Boom(marker)}, pth)
    data = pth.read_bytes()
    import hashlib

    _rewrite(export, weights__bytes=len(data), weights__sha256=hashlib.sha256(data).hexdigest())
    refused("not a plain tensor file", pth)
    assert not marker.exists()
    with pytest.raises(ValueError, match="trained on"):
        RLlibPolicy(CLUSTERING_MODULE, path=export)


def test_bench_agent_without_export_says_how_to_train(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(rllib_agent, "CHECKPOINT_DIR", tmp_path)
    with pytest.raises(ValueError, match=r"train\.train_rllib_marl --env fim_selection_v0"):
        make("rllib", FIM_MODULE)
    res = run_bench(FIM_MODULE, None, episodes=1, progress=False,
                    env_kwargs={"n_candidates": 5, "budgets": 1})  # fmt: skip
    # `learned` plays the rllib record in the cooperative mode: skipped with the hint, not a crash
    assert "rllib" not in res.agents
    assert "selenv.train.train_rllib_marl" in res.agents["learned"].skipped
    with pytest.raises(BenchError, match="rllib"):  # named explicitly: a usage error
        run_bench(FIM_MODULE, ["rllib:path=nowhere.json"], episodes=1, progress=False)


# -- the training entry point: usage errors ----------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        (["--iterations", "0"], "--iterations must be >= 1"),
        (["--env-kwargs", "{oops"], "not valid JSON"),
        (["--env-kwargs", '{"nope": 1}'], "rejected by fim_selection_v0"),
        (["--env", "cartpole"], "invalid choice"),
        (["--minibatch-size", "64", "--train-batch-size", "32"], "minibatch"),
        (["--hidden", "16,x"], "--hidden"),
        (["--env-kwargs", "[" * 100_000 + "]" * 100_000], "nested deeper than"),
        (["--vf", "64," * 20 + "64"], "--vf has 21 layers"),
        (["--iterations", "100001"], "--iterations 100,001 is above its ceiling 100,000"),
        (["--num-epochs", "1001"], "--num-epochs 1,001 is above its ceiling 1,000"),
        (["--train-batch-size", str(2**21), "--minibatch-size", "64"], "--train-batch-size"),
        (["--num-env-runners", "100000"], "--num-env-runners 100,000 exceeds the"),
        (["--iterations", "100001", "--allow-large", "--num-epochs", "0"], "--num-epochs must be"),
    ],
)
def test_train_usage_errors_exit_2_on_one_line(argv, reason, tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        train_rllib_marl.main([*argv, "--out", str(tmp_path / "p")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and len(err.splitlines()) == 1, err


def test_train_refuses_to_overwrite_and_unreachable_address(tmp_path, capsys) -> None:
    (tmp_path / "p.json").write_text("{}")
    with pytest.raises(SystemExit) as exc:
        train_rllib_marl.main(["--out", str(tmp_path / "p")])
    assert exc.value.code == 2 and "--force" in capsys.readouterr().err
    if ray.is_initialized():  # a running session is reused: --address is not checked then
        pytest.skip("Ray already initialised in this process")
    with pytest.raises(SystemExit) as exc:
        train_rllib_marl.main([*TINY, "--address", "127.0.0.1:1", "--out", str(tmp_path / "q")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "127.0.0.1:1" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "q.json").exists()


# -- (c) smoke training, export, reload, bench ---------------------------------------------------
SMOKE = [
    (FIM_MODULE, "fim_selection_v0", {"n_candidates": 10, "budgets": 2}, {}),
    (CLUSTERING_MODULE, "receiver_clustering_v1", SMALL_CL, {**SMALL_CL, "n_agents": 6}),
]


@pytest.mark.parametrize(("module", "env", "kwargs", "bench_kwargs"), SMOKE)
def test_smoke_training_exports_a_playable_module(
    ray_local, module, env, kwargs, bench_kwargs, tmp_path
) -> None:
    out = tmp_path / "run" / "policy"
    meta = train_rllib_marl.main(
        [*TINY, "--env", env, "--env-kwargs", json.dumps(kwargs), "--out", str(out), "--seed", "3"]
    )
    assert meta["env_id"] == module and meta["iterations"] == 1
    assert meta["ray_version"] == ray.__version__
    records = json.loads(out.with_suffix(".metrics.json").read_text())
    assert len(records) == 1 and records[0]["env_steps_lifetime"] >= 32
    assert np.isfinite(records[0]["vf_loss"])
    loaded, _ = load_exported(out.with_suffix(".json"))  # weights_only, sha256 checked
    state = th.load(out.with_suffix(".pth"), weights_only=True)
    assert all(th.equal(state[k], v) for k, v in loaded.state_dict().items())
    # the exported module plays the bench (clustering: on more receivers than it trained on)
    spec = f"rllib:path={out}.json"
    res = run_bench(module, [spec], episodes=1, seed=1000, env_kwargs=bench_kwargs,
                    progress=False)  # fmt: skip
    played = res.agents[spec]
    assert played.skipped is None and len(played.returns) == 1
    assert np.isfinite(played.returns[0]) and played.returns[0] != 0.0
    with pytest.raises(SystemExit):  # the outputs exist now
        train_rllib_marl.main([*TINY, "--env", env, "--env-kwargs", json.dumps(kwargs),
                               "--out", str(out)])  # fmt: skip
    shutil.rmtree(out.parent)


@pytest.mark.parametrize("env_id", [FIM_MODULE, CLUSTERING_MODULE])
def test_shipped_modules_load_and_beat_random(env_id: str) -> None:
    path = rllib_agent.default_path(env_id)
    module, meta = load_exported(path)
    assert meta["env_id"] == env_id and meta["weights"]["file"] == path.with_suffix(".pth").name
    # the shipped module plays (and better than random) on default kwargs; receiver clustering
    # on a fifth of its 500 steps (the module's whole-length episodes are ~20 s of CI)
    kwargs = {"horizon": 100} if env_id == CLUSTERING_MODULE else {}
    res = run_bench(env_id, ["random", "rllib"], episodes=3, seed=777, progress=False,
                    env_kwargs=kwargs)  # fmt: skip
    assert res.agents["rllib"].skipped is None
    assert res.agents["rllib"].mean_return > res.agents["random"].mean_return


def test_shipped_fim_module_reproduces_its_recorded_result_against_sb3() -> None:
    """The held-out comparison recorded in the shipped JSON replays on this machine: the same
    decisions (returns within rtol 1e-9), and the recomputed paired CI includes or exceeds 0."""
    from selenv.bench.stats import compare_paired

    meta = json.loads(rllib_agent.default_path(FIM_MODULE).read_text())
    held = meta["held_out_bench"]
    first, last = held["seeds"]
    res = run_bench(FIM_MODULE, ["ppo", "rllib"], episodes=last - first + 1, seed=first,
                    progress=False, env_kwargs=held["env_kwargs"])  # fmt: skip
    ppo, ours = res.agents["ppo"].returns, res.agents["rllib"].returns
    recorded = held["agents"]
    np.testing.assert_allclose(np.mean(ppo), recorded["ppo"]["mean_return"], rtol=1e-9)
    np.testing.assert_allclose(np.mean(ours), recorded["rllib"]["mean_return"], rtol=1e-9)
    paired = compare_paired(ours, ppo, "ppo")
    np.testing.assert_allclose(paired.mean_diff, recorded["rllib"]["paired_vs_ppo"]["mean_diff"],
                               rtol=1e-6, atol=1e-9)  # fmt: skip
    assert paired.ci95[1] >= 0.0  # level with (or ahead of) the SB3 shared policy


def test_sb3_shared_policy_weights_play_the_same_through_rllib(tmp_path: Path) -> None:
    """The two training routes face the same decision problem: the SB3 shared policy's
    weights, moved into the RLlib module, take the SB3 policy's decisions through the RLlib
    adapter's view (same returns on every seed)."""
    from selenv.learned.rl.safe_load import load_policy

    root = Path(__file__).resolve().parents[1] / "checkpoints"
    meta = json.loads((root / "fim_marl_ppo.json").read_text())
    sb3 = load_policy(root / "fim_marl_ppo.zip", meta).state_dict()
    arch = meta["architecture"]
    module = build_module(100, 16, {"hidden": arch["hidden"], "vf": arch["net_arch"]["vf"]})
    prefixes = {"scorer.": "features_extractor.", "heads.": "mlp_extractor.",
                "value_out.": "value_net."}  # fmt: skip
    state = {}
    for key in module.state_dict():
        ours = next(p for p in prefixes if key.startswith(p))
        state[key] = sb3[prefixes[ours] + key[len(ours) :]]
    module.load_state_dict(state, strict=True)
    json_path, _ = export_module(module, tmp_path / "sb3" / "policy",
                                 {"env_id": FIM_MODULE, "env_kwargs": {}})  # fmt: skip
    spec = f"rllib:path={json_path}"
    res = run_bench(FIM_MODULE, ["ppo", spec, "greedy"], episodes=4, seed=1000, progress=False)
    ppo, moved = res.agents["ppo"].returns, res.agents[spec].returns
    np.testing.assert_allclose(moved, ppo, rtol=1e-12)
    assert not np.allclose(ppo, res.agents["greedy"].returns)  # the check can tell agents apart


# -- (d) outputs that survive failures and interruptions ---------------------------------------
def test_export_on_a_full_disk_keeps_the_previous_pair(tmp_path: Path, tmpfs_of_size) -> None:
    """ENOSPC while exporting: an OSError naming the output, the old pair byte-identical."""
    import errno

    mnt = tmpfs_of_size("256k")
    try:
        module = build_module(5, 2, {"hidden": [48, 48], "vf": [48]})
        meta = {"env_id": FIM_MODULE, "env_kwargs": {}}
        json_path, pth_path = export_module(module, mnt / "policy", meta)
        old = {p: p.read_bytes() for p in (json_path, pth_path)}
        used = sum(len(b) for b in old.values())
        (mnt / "filler").write_bytes(b"\0" * (256 * 1024 - used - 40 * 1024))  # ~40 KB left
        bigger = build_module(5, 2, {"hidden": [48, 48], "vf": [48]})
        with pytest.raises(OSError) as err:
            export_module(bigger, mnt / "policy", meta)
        assert err.value.errno == errno.ENOSPC and err.value.filename in map(str, old)
        assert {p: p.read_bytes() for p in old} == old  # byte-identical
        assert sorted(p.name for p in mnt.iterdir()) == ["filler", "policy.json", "policy.pth"]
        load_exported(json_path)  # still a matching, loadable pair
    finally:
        _proc.run(["umount", str(mnt)], capture_output=True, timeout=60)


def _signal_after_recording(monkeypatch, signum: int, at: int, check=None, times=1) -> None:
    """Send ``signum`` ``times`` to this process right after iteration ``at`` was sampled and
    learned, before the run has kept it."""
    import signal

    record = train_rllib_marl._record

    def record_then_signal(it, result, seconds):
        out = record(it, result, seconds)
        if it == at:
            if check is not None:
                check()
            for _ in range(times):
                os.kill(os.getpid(), signal.Signals(signum))
        return out

    monkeypatch.setattr(train_rllib_marl, "_record", record_then_signal)


def _last(out: Path) -> list[Path]:
    cfg, _ = train_rllib_marl.parse_args(["--out", str(out)])
    return train_rllib_marl.last_paths(cfg)


def test_interrupted_training_keeps_the_last_completed_iteration(
    ray_local, tmp_path, capsys, monkeypatch
) -> None:
    """SIGINT twice inside iteration 2, before the run has kept it: the second abandons it.

    The run keeps iteration 1 as the checkpoint ``<out>.last.*`` (a loadable export marked
    incomplete, with its metrics), skips the evaluation, writes no final export, and ends
    with exit 130 and one line naming the ``--resume`` option.
    """
    _signal_after_recording(monkeypatch, 2, at=2, times=2)
    out = tmp_path / "run" / "policy"
    argv = [*TINY, "--iterations", "4", "--eval-episodes", "2", "--checkpoint-every", "0",
            "--out", str(out)]  # fmt: skip
    assert train_rllib_marl.cli(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    last_json, _, optimizer, metrics = _last(out)
    assert len(err) == 1 and "SIGINT" in err[0] and "saved iteration 1 of 4" in err[0], err
    assert err[0].endswith(f"--resume {last_json}")
    module, meta = load_exported(last_json)  # playable as rllib:path=<out>.last.json
    assert meta["training"]["complete"] is False and meta["training"]["interrupted"] == "SIGINT"
    assert meta["iterations"] == 1 and "eval" not in meta
    assert meta["resume_state"]["iterations_done"] == 1 and optimizer.is_file()
    assert [r["iteration"] for r in json.loads(metrics.read_text())] == [1]
    assert not out.with_suffix(".json").exists() and not out.with_suffix(".metrics.json").exists()
    leftovers = [p.name for p in out.parent.iterdir() if p.name.startswith(".")]
    assert leftovers == []  # no temporary and no lock file left


def test_terminated_training_resumes_to_the_same_iteration_count(
    ray_local, tmp_path, capsys, monkeypatch
) -> None:
    """SIGTERM inside iteration 2: the run finishes it, keeps it, stops; then --resume.

    As under a fresh Ray start, Ray's SIGTERM handler is installed when the session starts:
    the run must still stop through the trainer base's handler, at the end of the iteration.

    The checkpoint is checked before Ray starts: another training option, a tampered or
    pickled optimizer file are refused (exit 2, one line). The resumed run restores the
    saved optimizer state exactly (compared tensor by tensor) and the weights, reaches
    iteration 4 with the metrics of iterations 1..4, and removes the checkpoint.
    """
    import contextlib
    import hashlib
    import signal
    import sys

    import selenv.parallel

    out = tmp_path / "run" / "policy"
    last_json, last_pth, optimizer, metrics = _last(out)

    def periodic_checkpoint_exists() -> None:
        meta = json.loads(last_json.read_text())
        assert meta["resume_state"]["iterations_done"] == 1
        assert meta["training"]["complete"] is False and "interrupted" not in meta["training"]

    _signal_after_recording(monkeypatch, 15, at=2, check=periodic_checkpoint_exists)
    session = selenv.parallel.ray_session

    @contextlib.contextmanager
    def session_as_if_started_here(*args, **kwargs):
        """ray.init (skipped: Ray runs already) replaces the SIGTERM handler by an exit."""
        with session(*args, **kwargs) as value:
            previous = signal.signal(signal.SIGTERM, lambda *_: sys.exit(15))
            try:
                yield value
            finally:
                signal.signal(signal.SIGTERM, previous)

    monkeypatch.setattr(selenv.parallel, "ray_session", session_as_if_started_here)
    argv = [*TINY, "--iterations", "4", "--checkpoint-every", "1", "--out", str(out)]
    assert train_rllib_marl.cli(argv) == 143
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "SIGTERM" in err[0] and err[0].endswith(f"--resume {last_json}")
    assert "saved iteration 2 of 4" in err[0], err  # the iteration in progress was finished
    assert json.loads(last_json.read_text())["training"]["interrupted"] == "SIGTERM"
    monkeypatch.undo()  # no more signals
    saved = th.load(optimizer, weights_only=True)
    saved_weights = th.load(last_pth, weights_only=True)

    def refused(extra: list[str], *words: str) -> None:
        with pytest.raises(SystemExit) as exc:
            train_rllib_marl.main([*argv, *extra])
        line = capsys.readouterr().err.strip()
        assert exc.value.code == 2 and len(line.splitlines()) == 1, line
        assert all(w in line for w in words), line

    refused([], "--resume", str(last_json), "--force")  # the checkpoint is not ignored
    refused(["--resume", str(last_json), "--lr", "0.002"], "--lr", "0.001", "0.002")
    good = optimizer.read_bytes()
    optimizer.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    refused(["--resume", str(last_json)], "optimizer.pth", "sha256")
    good_json = last_json.read_text()

    def replace_optimizer(obj) -> None:  # a new file whose sha256 the JSON records
        th.save(obj, optimizer)
        data = optimizer.read_bytes()
        meta = json.loads(good_json)
        entry = meta["extra_files"]["optimizer.pth"]
        entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
        last_json.write_text(json.dumps(meta))

    marker = tmp_path / "executed"
    replace_optimizer({"x": _Boom(marker)})  # code on unpickling
    refused(["--resume", str(last_json)], "not plain tensors")
    assert not marker.exists()
    wrong = copy.deepcopy(saved)
    next(iter(wrong.values()))["state"]["state"][1]["exp_avg"] = th.zeros(3)
    replace_optimizer(wrong)
    refused(["--resume", str(last_json)], "exp_avg of parameter 1 has shape (3,)")
    optimizer.write_bytes(good)
    last_json.write_text(good_json)

    restore = train_rllib_marl._restore
    compared = []

    def restore_and_compare(algo, resumed) -> None:
        restore(algo, resumed)
        state = algo.learner_group.get_state(components="learner")["learner"]
        for name, entry in saved.items():
            slots = state["optimizer"][name]["state"]["state"]
            assert set(slots) == set(entry["state"]["state"])
            for index, tensors in entry["state"]["state"].items():
                for key, value in tensors.items():
                    assert np.array_equal(np.asarray(slots[index][key]), np.asarray(value))
                    compared.append(key)
        module = state["rl_module"]["shared"]
        assert all(np.array_equal(np.asarray(module[k]), v) for k, v in saved_weights.items())
        assert algo.iteration == 2  # the checkpoint kept iteration 2

    monkeypatch.setattr(train_rllib_marl, "_restore", restore_and_compare)
    meta = train_rllib_marl.main([*argv, "--resume", str(last_json)])
    assert {"exp_avg", "exp_avg_sq", "step"} <= set(compared)
    assert meta["training"]["complete"] is True and meta["iterations"] == 4
    records = json.loads(out.with_suffix(".metrics.json").read_text())
    assert [r["iteration"] for r in records] == [1, 2, 3, 4]
    steps = [r["env_steps_lifetime"] for r in records]
    assert all(b > a for a, b in itertools.pairwise(steps)), steps  # the counters continue
    assert not any(p.exists() for p in _last(out))  # superseded by the complete export
    load_exported(out.with_suffix(".json"))


def test_max_minutes_keeps_the_iteration_and_resume_completes(
    ray_local, tmp_path, capsys, monkeypatch
) -> None:
    """``--max-minutes``, as every trainer's: at the end of the first iteration past the
    budget the run keeps it as ``<out>.last.*`` (``"interrupted": "max-minutes"``), skips the
    evaluation and exits 75 with one line naming ``--resume``; the resumed run has its own
    budget, which is not checked after the last iteration.

    The trainer base's clock is replaced by a counter that advances one minute per read (the
    first read is the run's start), so the budget expires at a known iteration.
    """
    from selenv.learned import trainer

    reads: list[float] = []

    def minutes() -> float:
        reads.append(60.0 * len(reads))
        return reads[-1]

    monkeypatch.setattr(trainer, "clock", minutes)
    out = tmp_path / "run" / "policy"
    last_json, _, _, metrics = _last(out)
    argv = [*TINY, "--iterations", "3", "--eval-episodes", "2", "--checkpoint-every", "0",
            "--out", str(out)]  # fmt: skip
    assert train_rllib_marl.cli([*argv, "--max-minutes", "1"]) == 75
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--max-minutes" in err[0] and "iteration 1 of 3" in err[0], err
    assert err[0].endswith(f"--resume {last_json}")
    _, meta = load_exported(last_json)
    training = meta["training"]
    assert training["interrupted"] == "max-minutes" and training["complete"] is False
    assert training["max_minutes"] == 1 and meta["resume_state"]["iterations_done"] == 1
    assert [r["iteration"] for r in json.loads(metrics.read_text())] == [1]
    assert not out.with_suffix(".json").exists() and "eval" not in meta
    assert len(reads) == 2  # the start, then the end of iteration 1

    del reads[:]  # a resumed run has its own budget: 1 minute per iteration, 2 allowed
    meta = train_rllib_marl.main([*argv, "--eval-episodes", "0", "--resume", str(last_json),
                                  "--max-minutes", "2"])  # fmt: skip
    assert meta["training"]["complete"] is True and meta["iterations"] == 3
    assert len(reads) == 2  # the start, the end of iteration 2 (not after the last one)
    records = json.loads(out.with_suffix(".metrics.json").read_text())
    assert [r["iteration"] for r in records] == [1, 2, 3]
    assert not any(p.exists() for p in _last(out))


def test_a_second_training_on_the_same_out_is_refused(tmp_path, capsys) -> None:
    """Another live process holds the output's lock: exit 2, one line, nothing written."""
    import sys

    out = tmp_path / "p"
    other = _proc.popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".p.json.lock").write_text(f"{other.pid}\n")
        with pytest.raises(SystemExit) as exc:  # usage errors exit through argparse's way
            train_rllib_marl.cli([*TINY, "--out", str(out)])
        assert exc.value.code == 2
    finally:
        _proc.stop(other)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "p.json" in err[0] and str(other.pid) in err[0], err
    assert not out.with_suffix(".json").exists()
