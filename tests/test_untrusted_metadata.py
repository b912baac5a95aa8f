"""Checkpoint metadata is untrusted: every size is bounded before anything is allocated.

The reported cases: ``hidden=[20000, 20000]`` in a ppo or rllib checkpoint's JSON ran for
more than 60 s and took 5 GB before any check; larger widths crashed with torch
``RuntimeError`` / numpy ``_ArrayMemoryError``; a JSON nested 10^5 deep raised an uncaught
``RecursionError`` in every loader. Each case here must be a ``ValueError`` naming the field,
the value and the ceiling, raised before any torch module is built or any weights file is
read; a metadata JSON recording another zip's ``checkpoint_sha256`` is refused naming both
files. (How long a refusal takes is measured by ``benchmarks/bench_refusals.py``.)
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import shutil
import zipfile
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

import pytest
import torch as th
from _work import no_work, torch_work

from selenv.learned.resources import CHECKPOINT_LIMITS, json_depth, read_metadata
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent, load_metadata

FIM_ID = "selenv/FIMSelection-v1"
SHIPPED = DEFAULT_CHECKPOINTS[FIM_ID]
SHIPPED_META: dict[str, Any] = json.loads(SHIPPED.with_suffix(".json").read_text())
DEEP = 100_000


def _deep_json() -> str:
    return '{"obs_layout": ' + "[" * DEEP + "]" * DEEP + "}"


def _before_any_work() -> AbstractContextManager[None]:
    """The block must end before any torch module is built or any weights file is read (the
    reported cases spent > 60 s and 5 GB building the network before any check)."""
    return no_work(torch_work())


def _edited(meta: dict[str, Any], **changes: Any) -> dict[str, Any]:
    """``meta`` deep-copied with ``a__b=value`` set (``a__b`` is ``meta["a"]["b"]``)."""
    out = copy.deepcopy(meta)
    for key, value in changes.items():
        node = out
        *parents, leaf = key.split("__")
        for p in parents:
            node = node[p]
        if value is _DROP:
            node.pop(leaf, None)
        else:
            node[leaf] = value
    return out


_DROP = object()


@pytest.fixture
def ppo_copy(tmp_path: Path) -> Path:
    """The shipped FIMSelection checkpoint copied to ``tmp_path/p.zip`` (+ ``p.json``)."""
    out = tmp_path / "p.zip"
    shutil.copy(SHIPPED, out)
    shutil.copy(SHIPPED.with_suffix(".json"), out.with_suffix(".json"))
    return out


def _write_meta(zip_path: Path, meta: dict[str, Any] | str) -> None:
    text = meta if isinstance(meta, str) else json.dumps(meta)
    zip_path.with_suffix(".json").write_text(text)


def _refused(load: Callable[[], Any], *fragments: str, before_work: bool = True) -> str:
    """``load()`` raises a ValueError whose message holds every fragment (with ``before_work``,
    before any torch module is built or weights file read)."""
    with _before_any_work() if before_work else nullcontext(), pytest.raises(ValueError) as err:
        load()
    message = str(err.value)
    for fragment in fragments:
        assert fragment in message, message
    assert "\n" not in message
    return message


# -- the reader ------------------------------------------------------------------------------
def test_json_depth_is_linear_and_ignores_strings() -> None:
    assert json_depth("[" * DEEP + "]" * DEEP) == DEEP  # no recursion
    assert json_depth('{"a": "[[[[{{{{\\"[[", "b": [[1]]}') == 3
    assert json_depth("17") == 0


def test_deep_or_large_metadata_is_refused_before_parsing(tmp_path: Path) -> None:
    deep = tmp_path / "deep.json"
    deep.write_text(_deep_json())
    limit = CHECKPOINT_LIMITS["max_metadata_depth"]
    _refused(lambda: read_metadata(deep), f"nested deeper than {limit}", str(deep))
    big = tmp_path / "big.json"
    big.write_text(json.dumps({"pad": "x" * (CHECKPOINT_LIMITS["max_metadata_bytes"] + 1)}))
    _refused(lambda: read_metadata(big), "more than the ceiling", "max_metadata_bytes")
    bad = tmp_path / "bad.json"
    bad.write_text('{"n": ' + "9" * 5000 + "}")  # beyond Python's int digit limit
    _refused(lambda: read_metadata(bad), "not valid JSON")
    with pytest.raises(FileNotFoundError, match=r"nope\.json"):
        read_metadata(tmp_path / "nope.json")


# -- SB3 ppo checkpoints ---------------------------------------------------------------------
@pytest.mark.parametrize(
    ("changes", "fragments"),
    [
        ({"architecture__hidden": [20000, 20000]}, ["architecture.hidden[0]=20,000", "4,096"]),
        ({"architecture__hidden": [10**12]}, ["architecture.hidden[0]", "max_width"]),
        ({"architecture__hidden": [64] * 100}, ["100 layers", "max_layers"]),
        ({"architecture__hidden": [4096, 4096]}, ["parameters", "max_parameters"]),
        ({"architecture__net_arch": {"pi": [], "vf": [10**6]}}, ["net_arch.vf[0]", "max_width"]),
        ({"architecture__hidden": [64.5]}, ["architecture.hidden[0]", "positive integer"]),
        ({"architecture__hidden": "64"}, ["architecture.hidden", "list of layer widths"]),
        ({"architecture__hidden": [0]}, ["architecture.hidden[0]", "positive integer"]),
        ({"architecture__gain_skip_init": "nan"}, ["gain_skip_init", "finite"]),
        ({"training__algorithm": ["PPO"]}, ["training.algorithm"]),
        ({"obs_layout__n_candidates_trained": 10**9}, ["n_candidates_trained=1,000,000,000"]),
        (
            {"obs_layout__whitened_dim": 10**5, "obs_layout__m": _DROP, "obs_layout__d": _DROP},
            ["whitened_dim=100,000", "max_candidate_width"],
        ),
        (
            {
                "obs_layout__n_candidates_trained": 99_000,
                "obs_layout__whitened_dim": 4000,
                "obs_layout__m": _DROP,
                "obs_layout__d": _DROP,
            },
            ["max_observation_entries"],
        ),
        ({"obs_layout__m": 3}, ["whitened_dim=14 != m*d = 3*7"]),
        ({"obs_layout__n_features": 10**7}, ["n_features", "max_candidate_width"]),
        ({"obs_layout__whitened_dim": True}, ["whitened_dim", "positive integer"]),
        ({"view": {"a": 1}}, ["'view' must be a string"]),
        ({"env_id": ["selenv/FIMSelection-v1"]}, ["'env_id' must be a string"]),
    ],
)
def test_ppo_metadata_sizes_are_bounded(
    ppo_copy: Path, changes: dict[str, Any], fragments: list[str]
) -> None:
    _write_meta(ppo_copy, _edited(SHIPPED_META, **changes))
    message = _refused(lambda: SB3PolicyAgent(ppo_copy, env_id=FIM_ID), *fragments)
    assert str(ppo_copy.stem) in message


def test_ppo_deep_metadata_is_a_value_error(ppo_copy: Path) -> None:
    _write_meta(ppo_copy, _deep_json())
    limit = CHECKPOINT_LIMITS["max_metadata_depth"]
    for load in (
        lambda: SB3PolicyAgent(ppo_copy, env_id=FIM_ID),
        lambda: load_metadata(ppo_copy),
    ):
        _refused(load, f"nested deeper than {limit}", "p.json")


def test_a_ceiling_can_be_raised_for_a_trusted_file(
    ppo_copy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The message names the ceiling's entry; raising it lets the next check decide."""
    _write_meta(ppo_copy, _edited(SHIPPED_META, architecture__hidden=[64, 64, 64]))
    monkeypatch.setitem(CHECKPOINT_LIMITS, "max_layers", 2)
    message = _refused(lambda: SB3PolicyAgent(ppo_copy, env_id=FIM_ID), "max_layers")
    assert "selenv.learned.resources.CHECKPOINT_LIMITS['max_layers']" in message
    monkeypatch.setitem(CHECKPOINT_LIMITS, "max_layers", 16)  # now the weights disagree
    with pytest.raises(ValueError, match="weights do not fit"):
        SB3PolicyAgent(ppo_copy, env_id=FIM_ID)


def test_shipped_checkpoints_are_far_below_the_ceilings() -> None:
    for env_id, checkpoint in DEFAULT_CHECKPOINTS.items():
        SB3PolicyAgent(checkpoint, env_id=env_id)


# -- checkpoint_sha256: a zip and a JSON from different saves ---------------------------------
def test_checkpoint_sha256_must_match_the_zip(ppo_copy: Path) -> None:
    digest = hashlib.sha256(ppo_copy.read_bytes()).hexdigest()
    _write_meta(ppo_copy, _edited(SHIPPED_META, checkpoint_sha256=digest))
    SB3PolicyAgent(ppo_copy, env_id=FIM_ID)  # the matching pair loads
    other = _edited(SHIPPED_META, checkpoint_sha256=hashlib.sha256(b"another save").hexdigest())
    _write_meta(ppo_copy, other)
    _refused(
        lambda: SB3PolicyAgent(ppo_copy, env_id=FIM_ID),
        str(ppo_copy),
        str(ppo_copy.with_suffix(".json")),
        "different saves",
        before_work=False,  # the pair's sizes pass the checks: the hash is compared at load
    )
    _write_meta(ppo_copy, _edited(SHIPPED_META, checkpoint_sha256="not-a-hash"))
    _refused(lambda: SB3PolicyAgent(ppo_copy, env_id=FIM_ID), "64 hex digits", before_work=False)


def test_model_from_checkpoint_checks_the_pair_too(ppo_copy: Path) -> None:
    """The path trainers use to continue from a file refuses a mismatched pair as well."""
    from selenv.learned.rl.safe_load import model_from_checkpoint

    meta = _edited(SHIPPED_META, checkpoint_sha256="0" * 64)
    _refused(lambda: model_from_checkpoint(ppo_copy, meta, env=None), "different saves")


# -- the factorised edit scorer -------------------------------------------------------------
def _edit_checkpoint(tmp_path: Path) -> tuple[Path, dict[str, Any]]:
    """A small factorised edit checkpoint (6 receivers) written as the trainers do."""
    from selenv.learned.families.clustering_edits import EDIT_EXTRACTOR, build_edit_policy
    from selenv.learned.rl.safe_load import POLICY_CLASSES

    n = 6
    cls = POLICY_CLASSES["MaskablePPO"]
    meta = {
        "env_id": "selenv/ReceiverClustering-v1",
        "training": {"algorithm": "MaskablePPO"},
        "architecture": {
            "policy": f"{cls.__module__}.{cls.__name__}",
            "features_extractor": EDIT_EXTRACTOR,
            "hidden": [16, 16],
            "activation": "tanh",
            "gain_skip_init": 1.0,
            "rank": 4,
            "net_arch": {"pi": [], "vf": [16]},
        },
        "obs_layout": {
            "whitened_dim": 17,
            "n_features": 4,
            "n_candidates_trained": 1 + n * n + n * (n - 1) // 2,
        },
    }
    policy = build_edit_policy(meta, "edit")
    buffer = io.BytesIO()
    th.save(policy.state_dict(), buffer)
    out = tmp_path / "edit.zip"
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("policy.pth", buffer.getvalue())
    return out, meta


def test_edit_policy_metadata_is_bounded(tmp_path: Path) -> None:
    from selenv.learned.families.clustering_edits import load_edit_policy

    checkpoint, meta = _edit_checkpoint(tmp_path)
    load_edit_policy(checkpoint, meta)  # the well-formed one loads
    cases: list[tuple[dict[str, Any], list[str]]] = [
        ({"architecture__rank": 10**6}, ["architecture.rank=1,000,000", "max_width"]),
        ({"architecture__rank": 4000, "architecture__hidden": [4000]}, ["max_parameters"]),
        ({"architecture__hidden": [20000, 20000]}, ["architecture.hidden[0]=20,000"]),
        ({"architecture__rank": "4"}, ["architecture.rank", "positive integer"]),
        ({"obs_layout__n_candidates_trained": 10**8}, ["n_candidates_trained", "100,000"]),
    ]
    for changes, fragments in cases:
        bad = _edited(meta, **changes)

        def load(bad: dict[str, Any] = bad) -> Any:
            return load_edit_policy(checkpoint, bad)

        _refused(load, *fragments)
    meta["checkpoint_sha256"] = "f" * 64
    # sizes within the ceilings: the recorded hash is compared when the pair loads
    _refused(
        lambda: load_edit_policy(checkpoint, meta),
        "edit.json",
        "different saves",
        before_work=False,
    )


# -- RLlib exports ---------------------------------------------------------------------------
@pytest.fixture
def rllib_copy(tmp_path: Path) -> Path:
    pytest.importorskip("ray.rllib")
    from selenv.learned.rl.rllib_agent import CHECKPOINT_DIR

    src = CHECKPOINT_DIR / "rllib_fim_selection_v0.json"
    shutil.copy(src, tmp_path / src.name)
    shutil.copy(src.with_suffix(".pth"), tmp_path / src.with_suffix(".pth").name)
    return tmp_path / src.name


def test_rllib_metadata_sizes_are_bounded(rllib_copy: Path) -> None:
    from selenv.learned.rl.rllib_agent import load_exported, make_rllib_policy

    good = json.loads(rllib_copy.read_text())
    load_exported(rllib_copy)
    cases: list[tuple[dict[str, Any], list[str]]] = [
        ({"module__model_config__hidden": [20000, 20000]}, ["hidden[0]=20,000", "4,096"]),
        ({"module__model_config__hidden": [4096, 4096]}, ["parameters", "max_parameters"]),
        ({"module__model_config__vf": [64] * 40}, ["40 layers", "max_layers"]),
        ({"obs_layout__n_candidates_trained": 10**9}, ["n_candidates_trained", "100,000"]),
        ({"obs_layout__whitened_dim": 10**6}, ["whitened_dim=1,000,000"]),
        ({"obs_layout__n_features": 5}, ["n_features=5"]),
        ({"module__model_config": [1]}, ["model_config must be a mapping"]),
    ]
    for changes, fragments in cases:
        rllib_copy.write_text(json.dumps(_edited(good, **changes)))
        _refused(lambda: load_exported(rllib_copy), str(rllib_copy), *fragments)
    rllib_copy.write_text(_deep_json())
    limit = CHECKPOINT_LIMITS["max_metadata_depth"]
    for load in (
        lambda: load_exported(rllib_copy),
        lambda: make_rllib_policy("selenv.multiagent.fim_selection_v0", path=str(rllib_copy)),
    ):
        _refused(load, f"nested deeper than {limit}", str(rllib_copy))


def test_rllib_training_refuses_widths_its_export_could_not_load(
    capsys: pytest.CaptureFixture[str],
) -> None:
    pytest.importorskip("ray.rllib")
    from selenv.train.train_rllib_marl import parse_args

    with _before_any_work(), pytest.raises(SystemExit) as exit_info:
        parse_args(["--hidden", "20000,20000", "--iterations", "1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--hidden[0]=20,000" in err[0] and "max_width" in err[0]


# -- the registry path selenv bench takes -----------------------------------------------------
def test_agent_registry_gives_a_value_error_for_a_hostile_checkpoint(ppo_copy: Path) -> None:
    """``selenv bench --agents ppo:checkpoint=FILE`` builds the agent through the registry."""
    import selenv.agents

    _write_meta(ppo_copy, _edited(SHIPPED_META, architecture__hidden=[20000, 20000]))
    _refused(lambda: selenv.agents.make("ppo", FIM_ID, checkpoint=str(ppo_copy)), "20,000")
    _write_meta(ppo_copy, _deep_json())
    _refused(lambda: selenv.agents.make("ppo", FIM_ID, checkpoint=str(ppo_copy)), "nested")
