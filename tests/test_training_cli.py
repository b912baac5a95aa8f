"""Training entry points: outputs under ``runs/``, no overwrite without ``--force``, ``--help``
that documents every option and its default, and ``configs/*.toml`` (``--config``) that match
the shipped checkpoints' recorded hyper-parameters.

Nothing here trains: every script is parsed, resolved, or stopped before its work starts (the
work functions are replaced by ones that fail the test if called).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import re
import shlex
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from selenv.learned.config import arg, build_parser, field_help, option_name, parse_config
from selenv.learned.resources import checkpoint_path

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    tomllib = pytest.importorskip("tomli")

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.toml"))

#: script -> (its default output files, the work functions that must not run before the check)
SCRIPTS: dict[str, tuple[list[str], list[str]]] = {
    "train_fim_ppo": (["runs/train_fim_ppo/policy.zip", "runs/train_fim_ppo/policy.json"],
                      ["train", "gym"]),
    "train_landmark_ppo": (["runs/train_landmark_ppo/policy.zip",
                            "runs/train_landmark_ppo/policy.json"], ["train", "gym"]),
    "train_cl_ppo": (["runs/train_cl_ppo/policy.zip", "runs/train_cl_ppo/policy.json"],
                     ["train", "gym"]),
    "train_clustering_ppo": (["runs/train_clustering_ppo/policy.zip",
                              "runs/train_clustering_ppo/policy.json"],
                             ["train", "gym", "collect_clustering_ranking"]),
    "train_fim_marl": (["runs/train_fim_marl/policy.zip", "runs/train_fim_marl/policy.json"],
                       ["train", "load_policy"]),
    "train_clustering_dagger": (["runs/train_clustering_dagger/policy.zip",
                                 "runs/train_clustering_dagger/policy.json"],
                                ["load_metadata", "collect_clustering_ranking",
                                 "model_from_checkpoint"]),
    "train_cl_expert": (["runs/train_cl_expert/policy.zip", "runs/train_cl_expert/policy.json",
                         *(f"runs/train_cl_expert/policy_round{r}.{ext}"
                           for r in range(3) for ext in ("zip", "json")),
                         "runs/train_cl_expert/policy.bench.json"], ["run_expert_iteration"]),
    "train_landmark_expert": (["runs/train_landmark_expert/policy.zip",
                               "runs/train_landmark_expert/policy.json",
                               *(f"runs/train_landmark_expert/policy_round{r}.{ext}"
                                 for r in range(3) for ext in ("zip", "json")),
                               "runs/train_landmark_expert/policy.bench.json"],
                              ["run_expert_iteration"]),
    "train_surrogate": (["runs/surrogates/ldmv.pt", "runs/surrogates/ldmv.json"],
                        ["generate_dataset", "load_dataset", "make_executor"]),
    "train_cl_cem": (["runs/train_cl_cem/scorer.json", "runs/train_cl_cem/scorer.bench.json"],
                     ["_run"]),
    "train_rllib_marl": (["runs/rllib_fim_selection_v0/policy.json",
                          "runs/rllib_fim_selection_v0/policy.pth",
                          "runs/rllib_fim_selection_v0/policy.metrics.json"], ["build_config"]),
}  # fmt: skip
#: a shipped file each script must refuse to overwrite without --force
SHIPPED = {
    "train_fim_ppo": "fim_selection_ppo.zip",
    "train_landmark_ppo": "landmark_selection_ppo_v01.zip",
    "train_cl_ppo": "cl_scheduling_ppo.zip",
    "train_clustering_ppo": "receiver_clustering_ppo.zip",
    "train_fim_marl": "fim_marl_ppo.zip",
    "train_clustering_dagger": "receiver_clustering_ppo.zip",
    "train_cl_expert": "cl_scheduling_ppo.zip",
    "train_landmark_expert": "landmark_selection_ppo.zip",
    "train_surrogate": "ldmv.pt",
    "train_rllib_marl": "rllib_fim_selection_v0",
    "train_cl_cem": "cl_scheduling_cem.json",
}
#: config keys the checkpoint's JSON does not record (the TOML gives the script's default)
NOT_RECORDED = {
    "fim_selection_ppo": {"vec_env", "tensorboard_dir", "torch_threads"},
    "rllib_receiver_clustering_v1": {"advantage_norm"},  # trained before the option existed
}
#: recorded keys that differ on purpose, with the reason
DIFFERS = {
    "receiver_clustering_ppo": {
        "checkpoint": "the JSON holds the training machine's absolute path of stage 1's output"
    }
}
#: bookkeeping, not hyper-parameters: where the run wrote, whether it overwrote, its bars
NOT_COMPARED = {"out", "force", "progress"}


def _module(name: str) -> ModuleType:
    if name == "train_rllib_marl":
        pytest.importorskip("ray")
    return importlib.import_module(f"selenv.train.{name}")


def _parse(module: ModuleType, argv: list[str]) -> Any:
    out = module.parse_args(argv)
    return out[0] if isinstance(out, tuple) else out  # train_rllib_marl: (config, env kwargs)


class _Boom:
    """Stands for a work function (or module): any use of it fails the test."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError(f"{self.name} ran before the outputs were checked")

    def __getattr__(self, attr: str) -> Any:
        raise AssertionError(f"{self.name}.{attr} used before the outputs were checked")


def _no_work(monkeypatch: pytest.MonkeyPatch, module: ModuleType, names: list[str]) -> None:
    for name in names:
        assert hasattr(module, name), f"{module.__name__} has no {name}"
        monkeypatch.setattr(module, name, _Boom(name))
    if module.__name__.endswith("train_rllib_marl"):  # imported inside main(): never start Ray
        monkeypatch.setattr("selenv.parallel.ray_session", _Boom("ray_session"))


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


# -- (a) default outputs ------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(SCRIPTS))
def test_default_outputs_are_under_runs(name: str) -> None:
    module = _module(name)
    paths = [str(p) for p in module.outputs(_parse(module, []))]
    assert paths == SCRIPTS[name][0]
    shipped = checkpoint_path("x").parent.resolve()
    for p in paths:
        assert p.startswith("runs/") and not Path(p).resolve().is_relative_to(shipped)


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (
            ["--samples", "2000", "--epochs", "2"],
            "runs/surrogates/ldmv.pt",
        ),  # a reported reproduction
        (["--kind", "lpecmv"], "runs/surrogates/lpecmv.pt"),
        (["--kind", "lpecmv", "--method", "1"], "runs/surrogates/lpecmv_method1.pt"),
        (["--kind", "lpecmv", "--method", "2"], "runs/surrogates/lpecmv_method2.pt"),
        (["--kind", "ldmv", "--method", "1"], "runs/surrogates/ldmv.pt"),
        (["--out", "elsewhere/mine"], "elsewhere/mine.pt"),
        (["--save-data", "d/data"], "runs/surrogates/ldmv.pt"),
    ],
)
def test_surrogate_outputs(argv: list[str], expected: str) -> None:
    module = _module("train_surrogate")
    paths = [str(p) for p in module.outputs(module.parse_args(argv))]
    assert paths[:2] == [expected, expected[: -len(".pt")] + ".json"]
    if "--save-data" in argv:
        assert paths[2] == "d/data.npz"  # numpy adds the suffix


# -- (b) existing outputs are refused before any work ----------------------------------------------
@pytest.mark.parametrize("which", [0, 1])
@pytest.mark.parametrize("name", list(SCRIPTS))
def test_existing_default_output_is_refused_before_any_work(
    name: str, which: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    module = _module(name)
    defaults, work = SCRIPTS[name]
    monkeypatch.chdir(tmp_path)
    existing = tmp_path / defaults[which]
    existing.parent.mkdir(parents=True)
    existing.write_text("precious")
    _no_work(monkeypatch, module, work)
    with pytest.raises(SystemExit) as exc:
        module.main([])
    assert exc.value.code == 2
    err = _one_line_error(capsys)
    assert defaults[which] in err and "--force" in err and "--out" in err, err
    assert existing.read_text() == "precious"
    # --force lets the run start: the first work function is reached (the patch is live)
    with pytest.raises(AssertionError, match="before the outputs were checked"):
        module.main(["--force", "--no-progress"] if name != "train_rllib_marl" else ["--force"])


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_shipped_checkpoint_is_refused_without_force(
    name: str, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    module = _module(name)
    _no_work(monkeypatch, module, SCRIPTS[name][1])
    shipped = checkpoint_path(SHIPPED[name])
    first = shipped if shipped.suffix else shipped.with_suffix(".json")
    before = first.stat().st_mtime_ns
    with pytest.raises(SystemExit) as exc:
        module.main(["--out", str(shipped)])
    assert exc.value.code == 2 and str(first) in _one_line_error(capsys)
    assert first.stat().st_mtime_ns == before


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_unwritable_output_folder_exits_2_before_any_work(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    module = _module(name)
    _no_work(monkeypatch, module, SCRIPTS[name][1])
    (tmp_path / "a_file").write_text("")
    suffix = Path(SCRIPTS[name][0][0]).suffix if name != "train_rllib_marl" else ""
    with pytest.raises(SystemExit) as exc:
        module.main(["--out", str(tmp_path / "a_file" / "sub" / f"policy{suffix}")])
    assert exc.value.code == 2
    assert "a_file is not a folder" in _one_line_error(capsys)


def test_fim_marl_eval_only_rewrites_the_json_only_with_force(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    module = _module("train_fim_marl")
    monkeypatch.setattr(module, "_evaluate", _Boom("_evaluate"))
    out = tmp_path / "m.zip"
    with pytest.raises(SystemExit) as exc:
        module.main(["--eval-only", "--out", str(out)])
    assert exc.value.code == 2 and "no checkpoint" in _one_line_error(capsys)
    out.write_text("")
    out.with_suffix(".json").write_text('{"env_kwargs": {}}')
    with pytest.raises(SystemExit):
        module.main(["--eval-only", "--out", str(out)])
    assert "m.json exists" in _one_line_error(capsys)
    with pytest.raises(AssertionError, match="_evaluate ran"):
        module.main(["--eval-only", "--force", "--out", str(out)])


# -- (c) --help ---------------------------------------------------------------------------------
def _help_entries(text: str) -> dict[str, str]:
    """``--option`` -> its help text (joined lines) from argparse's ``--help`` output."""
    body = text.split("options:", 1)[1]
    entries: list[list[str]] = []
    for line in body.splitlines():
        if re.match(r"^  -", line):
            entries.append([line.strip()])
        elif entries and line.startswith("    "):
            entries[-1].append(line.strip())
    out = {}
    for lines in entries:
        invocation, *first = re.split(r"\s{2,}", lines[0], maxsplit=1)
        text_ = " ".join([*first, *lines[1:]]).strip()
        for flag in re.findall(r"--[a-z][a-z0-9-]*", invocation):
            if not flag.startswith("--no-"):
                out[flag] = text_
    return out


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_help_gives_every_option_a_meaning_and_its_default(
    name: str, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "100")
    module = _module(name)
    with pytest.raises(SystemExit) as exc:
        module.main(["--help"])
    assert exc.value.code == 0
    entries = _help_entries(capsys.readouterr().out)
    expected = {option_name(f.name) for f in dataclasses.fields(module.Config)} | {"--config"}
    assert set(entries) - {"--help"} == expected
    for flag in expected:
        text = entries[flag]
        meaning = text.split("(default:")[0].strip()
        assert len(meaning) >= 8, f"{name} {flag}: no description: {text!r}"
        assert re.search(r"\(default: [^)]*\)?", text), f"{name} {flag}: no default: {text!r}"
    helps = field_help(module.Config)  # every field declares its meaning (arg(default, help))
    assert all(helps.values())


def test_a_field_without_a_description_is_an_error() -> None:
    @dataclasses.dataclass
    class Documented:
        steps: int = arg(3, "number of steps")

    @dataclasses.dataclass
    class Child(Documented):
        steps: int = 5  # a plain override keeps the parent's meaning
        rate: float = 0.1  # no meaning: rejected

    with pytest.raises(TypeError, match=r"Child\.rate has no description"):
        build_parser(Child, "x")
    assert field_help(Documented) == {"steps": "number of steps"}
    parser = build_parser(Documented, "x")
    assert "number of steps (default: 3)" in " ".join(parser.format_help().split())


# -- (d) configs/*.toml reproduce the shipped checkpoints' recorded hyper-parameters -------------
def _command_values(module: ModuleType, command: str) -> dict[str, Any]:
    """The options a recorded command line gave explicitly, parsed by the script."""
    command = re.sub(r"\s+\(.*\)\s*$", "", command)  # "... (then copied to ...)"
    tokens = shlex.split(command)[3:]  # python -m selenv.train.X
    cfg = _parse(module, tokens)
    given = {f.name for f in dataclasses.fields(cfg)
             if {option_name(f.name), "--no-" + option_name(f.name)[2:]} & set(tokens)}  # fmt: skip
    return {k: getattr(cfg, k) for k in given}


def _recorded(module: ModuleType, meta: dict[str, Any]) -> dict[str, Any]:
    """The hyper-parameters a checkpoint's JSON records for the script that made it."""
    name = module.__name__.rsplit(".", 1)[1]
    command = None
    if name in ("train_cl_expert", "train_landmark_expert"):
        block = dict(meta["expert_iteration"])
        command = block.pop("command")
    elif name == "train_clustering_dagger":
        block = dict(meta["dagger"])
    elif name == "train_surrogate":
        t, data = meta["training"], meta["training_data"]
        block = {**t.get("config", {}), **{k: v for k, v in t.items() if v is not None}}
        block.update(epochs=t["epochs_max"], samples=data["count"])
        block.update(val_fraction=data["split"]["val"] / data["count"],
                     test_fraction=data["split"]["test"] / data["count"])  # fmt: skip
        command = t["command"]
    elif name == "train_rllib_marl":
        block = dict(meta["training"])
        command = meta["trained_with"]
    elif name == "train_cl_cem":  # every option that shapes the search, as given
        block = dict(meta["training"]["options"])
    else:  # the SB3 PPO scripts: the training block, then what older JSONs kept elsewhere
        block = dict(meta["training"])
        arch, metrics = meta["architecture"], meta.get("metrics") or {}
        derived = {
            "env_kwargs": json.dumps(meta["env_kwargs"]),
            "algo": {"MaskablePPO": "maskable_ppo", "PPO": "ppo"}[block["algorithm"]],
            "view": meta["view"],
            "hidden": ",".join(map(str, arch["hidden"])),
            "activation": arch["activation"],
            "gain_skip_init": arch["gain_skip_init"],
            # the edit scorer (train_clustering_ppo): the factorised class or the MLP
            "scorer": "factorised"
            if arch.get("features_extractor", "").endswith("FactorisedEditScorer")
            else "mlp",
        }
        if "episodes" in metrics:
            derived.update(eval_episodes=metrics["episodes"], eval_seed=metrics["eval_seeds"][0])
        # the agents evaluated next to the policy (the oldest format: "<agent>_mean_objective")
        agents = metrics.get("agents") or [k[: -len("_mean_objective")] for k in metrics
                                           if k.endswith("_mean_objective")]  # fmt: skip
        baselines = [a for a in agents if a != "ppo" and not a.startswith("ppo_")]
        if baselines:
            derived["baselines"] = ",".join(baselines)
        for key, value in derived.items():
            block.setdefault(key, value)
        if name == "train_fim_marl":  # train() ran with eval_episodes=0; the script evaluated
            block["eval_episodes"] = metrics["episodes"]
    if command is not None:
        block.update(_command_values(module, command))
    if name == "train_rllib_marl":
        block.update(_rllib_budget(meta["training"]))
    fields = {f.name for f in dataclasses.fields(module.Config)}
    return {k: v for k, v in block.items() if k in fields}


def _rllib_budget(training: dict[str, Any]) -> dict[str, Any]:
    """The iterations and budget of an RLlib run as the trainer base's options.

    RLlib exports written before the trainer base record ``max_minutes`` 0.0 for no budget
    and, for a budget that cut the run, the iterations asked for; that run exported the
    iterations done as its complete module, which is ``--iterations <done>`` without a budget
    now (a budget stops with a resumable state instead). Exports of the trainer base record
    ``None`` and always ``iterations_done == iterations``: unchanged.
    """
    done, budget = training["iterations_done"], training.get("max_minutes")
    if budget is None:
        return {}
    assert budget == 0.0 or done < training["iterations"], training  # the budget cut the run
    return {"iterations": done, "max_minutes": None}


def _same(key: str, a: Any, b: Any) -> bool:
    if key == "env_kwargs":
        return bool(json.loads(a) == json.loads(b))
    return bool(a == b) and isinstance(a, bool) == isinstance(b, bool)


def _no_constant(name: str) -> None:
    raise ValueError(f"non-standard JSON constant {name}")


def test_shipped_metadata_and_bench_results_are_strict_json() -> None:
    """No NaN / Infinity: other JSON readers (jq, browsers) refuse them."""
    files = [*(ROOT / "checkpoints").glob("*.json"), *(ROOT / "docs" / "bench").glob("*.json")]
    assert len(files) > 20
    for path in files:
        json.loads(path.read_text(), parse_constant=_no_constant)


def test_every_shipped_checkpoint_has_a_config() -> None:
    shipped = {p.stem for p in (ROOT / "checkpoints").glob("*.json")}
    described = {Path(tomllib.loads(p.read_text())["out"]).stem for p in CONFIGS}
    assert described == shipped


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_config_matches_the_checkpoints_recorded_hyperparameters(path: Path, capsys) -> None:
    data = tomllib.loads(path.read_text())
    script, out = data["script"], data["out"]
    module = _module(script.rsplit(".", 1)[1])
    assert script == module.SCRIPT
    cfg = _parse(module, ["--config", str(path)])
    for p in module.outputs(cfg):  # the file's `out` is not applied: the run writes under runs/
        assert str(p).startswith("runs/"), p
    assert "is not replaced" in capsys.readouterr().err
    meta = json.loads((ROOT / Path(out).with_suffix(".json")).read_text())
    recorded = _recorded(module, meta)
    differs = DIFFERS.get(path.stem, {})
    compared = []
    for key, value in recorded.items():
        if key in NOT_COMPARED or key in differs:
            continue
        assert _same(key, getattr(cfg, key), value), (
            f"{path.name}: {key} = {getattr(cfg, key)!r}, the checkpoint recorded {value!r}"
        )
        compared.append(key)
    assert len(compared) >= 12, compared
    file_keys = set(data) - {"script", "out"}
    assert file_keys - set(recorded) == NOT_RECORDED.get(path.stem, set())
    # the header documents the command that reproduces the checkpoint
    header = path.read_text().split("\nscript =")[0]
    stage = out if "ranking" not in path.stem else "runs/train_clustering_ppo/"
    assert f"python -m {script} --config configs/{path.name} --out {stage}" in header
    if "ranking" not in path.stem:
        assert f"--config configs/{path.name} --out {out} --force" in header


# -- (e) --config: precedence and bad files ------------------------------------------------------
@dataclasses.dataclass
class _Cfg:
    steps: int = arg(10, "number of steps")
    rate: float = arg(0.5, "a rate")
    name: str = arg("a", "a name")
    fast: bool = arg(False, "go fast")
    out: str = arg("runs/x.zip", "output")
    force: bool = arg(False, "overwrite")


def _toml(tmp_path: Path, text: str) -> str:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return str(path)


def test_config_file_values_are_defaults_and_flags_override(tmp_path: Path, capsys) -> None:
    path = _toml(tmp_path, 'steps = 3\nrate = 2\nname = "b"\nfast = true\nout = "ck/y.zip"\n')
    cfg = parse_config(_Cfg, ["--config", path], "x", script="selenv.train.demo")
    assert cfg == _Cfg(steps=3, rate=2.0, name="b", fast=True)  # `out` is not applied
    assert isinstance(cfg.rate, float) and "ck/y.zip" in capsys.readouterr().err
    for argv in (["--config", path, "--steps", "7", "--no-fast"],
                 ["--steps", "7", "--no-fast", "--config", path]):  # fmt: skip
        cfg = parse_config(_Cfg, argv, "x")
        assert (cfg.steps, cfg.fast, cfg.name) == (7, False, "b")


def test_help_shows_the_config_files_values_as_defaults(tmp_path: Path, capsys) -> None:
    path = _toml(tmp_path, "steps = 3\n")
    with pytest.raises(SystemExit):
        parse_config(_Cfg, ["--config", path, "--help"], "x")
    assert "number of steps (default: 3)" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("stepz = 3\n", "unknown key 'stepz'"),
        ('steps = "3"\n', "key 'steps' must be a TOML integer, got string '3'"),
        ("steps = 3.5\n", "key 'steps' must be a TOML integer, got float"),
        ("fast = 1\n", "key 'fast' must be a TOML boolean, got integer"),
        ("name = 3\n", "key 'name' must be a TOML string"),
        ("rate = true\n", "key 'rate' must be a TOML float"),
        ("[steps]\nx = 1\n", "key 'steps' must be a TOML integer, got table"),
        ("force = true\n", "key 'force' is not allowed in a config file"),
        ('script = "selenv.train.other"\n', "key 'script' is 'selenv.train.other'"),
        ("out = 3\n", "key 'out' must be a string"),
        ("steps = \n", "not a valid TOML file"),
    ],
)
def test_bad_config_file_exits_2_naming_key_and_file(
    text: str, reason: str, tmp_path: Path, capsys
) -> None:
    path = _toml(tmp_path, text)
    with pytest.raises(SystemExit) as exc:
        parse_config(_Cfg, ["--config", path], "x", script="selenv.train.demo")
    assert exc.value.code == 2
    err = _one_line_error(capsys)
    assert reason in err and path in err, err


def test_missing_config_file_exits_2(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        parse_config(_Cfg, ["--config", str(tmp_path / "nope.toml")], "x")
    assert exc.value.code == 2 and "nope.toml" in _one_line_error(capsys)


@pytest.mark.parametrize(
    ("name", "text", "reason"),
    [
        ("train_fim_ppo", "n_envs = '8'\n", "key 'n_envs' must be a TOML integer"),
        ("train_fim_ppo", "total_steps = 8\n", "unknown key 'total_steps'"),
        ("train_surrogate", "lr = 'fast'\n", "key 'lr' must be a TOML float"),
        ("train_rllib_marl", "env = 'cartpole'\n", "key 'env' must be one of"),
        ("train_rllib_marl", "gain_skip_init = 'x'\n", "key 'gain_skip_init' must be a TOML"),
        ("train_cl_expert", 'script = "selenv.train.train_fim_ppo"\n', "not selenv.train.train_cl"),
        ("train_landmark_expert", "rounds = 1.0\n", "key 'rounds' must be a TOML integer"),
    ],
)  # fmt: skip
def test_scripts_reject_bad_config_files_before_any_work(
    name: str, text: str, reason: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    module = _module(name)
    _no_work(monkeypatch, module, SCRIPTS[name][1])
    path = _toml(tmp_path, text)
    with pytest.raises(SystemExit) as exc:
        module.main(["--config", path, "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = _one_line_error(capsys)
    assert reason in err and path in err, err
