"""Resolved env configurations in bench JSON and checkpoint metadata: every keyword's value."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import selenv
from selenv.cli import main
from selenv.envs.resolved import jsonable, resolved_env_config
from selenv.families import ALL_ENV_IDS

assert selenv


@pytest.mark.parametrize("env_id", ALL_ENV_IDS)
def test_every_constructor_keyword_is_resolved_and_json(env_id) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(env_id)
    cfg = resolved_env_config(env)
    assert json.loads(json.dumps(cfg, allow_nan=False)) == cfg
    assert cfg["env_id"] == env_id
    params = cfg["parameters"]
    assert {"invalid_action", "render_mode"} <= set(params)
    for name in ("horizon", "objective", "budget", "n_agents"):  # preset-resolved, never None
        if name in params and "Landmark" not in env_id:
            assert params[name] is not None, name


def test_presets_are_resolved_to_their_values() -> None:
    """env_kwargs {} says nothing; the resolved values tell -v0 and -v1 apart."""
    v1 = resolved_env_config(gym.make("selenv/CLScheduling-v1"))["parameters"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        v0 = resolved_env_config(gym.make("selenv/CLScheduling-v0"))
    assert v0["make_kwargs"] == {"preset": "dense"}
    p0 = v0["parameters"]
    assert (v1["preset"], v1["n_agents"], v1["budget"], v1["horizon"]) == ("benchmark", 6, 1, 60)
    assert (p0["preset"], p0["n_agents"], p0["budget"], p0["horizon"]) == ("dense", 4, 2, 200)
    over = resolved_env_config(gym.make("selenv/CLScheduling-v1", budget=3))["parameters"]
    assert over["budget"] == 3 and over["n_agents"] == 6


def test_jsonable_types() -> None:
    out = jsonable({"a": np.arange(3), "b": (np.float32(0.5), np.inf), 1: np.bool_(True)})
    assert out == {"a": [0, 1, 2], "b": [0.5, "inf"], "1": True}


def test_bench_json_records_the_resolved_config(tmp_path: Path) -> None:
    out = tmp_path / "res.json"
    argv = ["bench", "selenv/FIMSelection-v1", "--agents", "greedy", "--episodes", "1"]
    kwargs = '{"n_candidates": 12, "budget": 2}'
    assert main([*argv, "--env-kwargs", kwargs, "--json", str(out), "--no-progress"]) == 0
    doc = json.loads(out.read_text())["results"][0]
    cfg = doc["env_config"]
    assert cfg["env_id"] == "selenv/FIMSelection-v1"
    assert cfg["parameters"]["n_candidates"] == 12 and cfg["parameters"]["budget"] == 2
    assert cfg["parameters"]["preset"] == "example2_moving"
    assert cfg["parameters"]["invalid_action"] == "raise"  # the bench's strict mode
    assert cfg["config"]["sensors"] == ["camera", "doppler"]
