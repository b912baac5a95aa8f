"""Loading a policy checkpoint never executes code from the file (selenv.learned.rl.safe_load)."""

from __future__ import annotations

import base64
import io
import json
import pickle
import shutil
import zipfile
from pathlib import Path

import pytest
import torch as th

from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent, load_metadata
from selenv.learned.rl.safe_load import load_policy, read_weights

FIM_ID = "selenv/FIMSelection-v1"
SHIPPED = DEFAULT_CHECKPOINTS[FIM_ID]


class _Payload:
    """Unpickling this creates ``marker``: stands in for an arbitrary shell command."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (Path.touch, (self.marker,))


def _copy_with(tmp_path: Path, name: str, replace: dict[str, bytes]) -> Path:
    """The shipped checkpoint (zip + JSON) copied to ``tmp_path/name`` with entries replaced."""
    out = tmp_path / f"{name}.zip"
    with zipfile.ZipFile(SHIPPED) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            if item.filename in replace:  # deflated, as a zip bomb would be
                dst.writestr(item.filename, replace[item.filename], zipfile.ZIP_DEFLATED)
            else:
                dst.writestr(item, src.read(item))
    shutil.copy(SHIPPED.with_suffix(".json"), out.with_suffix(".json"))
    return out


def _hostile_data(marker: Path) -> bytes:
    """The zip's ``data`` JSON with a ``:serialized:`` field that runs the payload if unpickled."""
    with zipfile.ZipFile(SHIPPED) as zf:
        data = json.loads(zf.read("data"))
    blob = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
    data["policy_class"] = {":type:": "<class 'type'>", ":serialized:": blob}
    return json.dumps(data).encode()


def test_hostile_data_field_is_never_unpickled(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    bad = _copy_with(tmp_path, "hostile", {"data": _hostile_data(marker)})
    agent = SB3PolicyAgent(checkpoint=bad, env_id=FIM_ID)  # loads: only the weights are read
    assert not marker.exists()
    ref = SB3PolicyAgent(env_id=FIM_ID)
    for (k, a), (k2, b) in zip(
        agent._policies[200].state_dict().items(),
        ref._policies[200].state_dict().items(),
        strict=True,
    ):
        assert k == k2 and th.equal(a, b)
    # the file is live: SB3's own loader runs the payload (why selenv never calls it)
    from sb3_contrib import MaskablePPO

    with pytest.raises(Exception):  # noqa: B017  (the payload returns None: load then fails)
        MaskablePPO.load(bad, device="cpu")
    assert marker.exists()


def test_hostile_weights_are_refused(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    bad = _copy_with(tmp_path, "hostile_pth", {"policy.pth": pickle.dumps(_Payload(marker))})
    with pytest.raises(ValueError, match=r"policy.pth is not a plain tensor file"):
        read_weights(bad)
    with pytest.raises(ValueError, match="not a plain tensor file"):
        SB3PolicyAgent(checkpoint=bad, env_id=FIM_ID)
    assert not marker.exists()


def test_corrupt_files_and_mismatched_metadata_are_clear_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty.zip"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="not a readable zip"):
        read_weights(empty)
    nopth = tmp_path / "nopth.zip"
    with zipfile.ZipFile(nopth, "w") as zf:
        zf.writestr("data", "{}")
    with pytest.raises(ValueError, match=r"no policy\.pth"):
        read_weights(nopth)
    buf = io.BytesIO()
    th.save([th.zeros(2)], buf)
    listy = _copy_with(tmp_path, "listy", {"policy.pth": buf.getvalue()})
    with pytest.raises(ValueError, match="map parameter names to tensors"):
        read_weights(listy)
    meta = load_metadata(SHIPPED)
    wider = {**meta, "architecture": {**meta["architecture"], "hidden": [32, 32]}}
    with pytest.raises(ValueError, match="weights do not fit its metadata"):
        load_policy(SHIPPED, wider)
    other = {**meta, "training": {**meta["training"], "algorithm": "DQN"}}
    with pytest.raises(ValueError, match=r"training\.algorithm='DQN'"):
        load_policy(SHIPPED, other)


def test_model_from_checkpoint_continues_from_the_weights() -> None:
    import gymnasium as gym

    from selenv.learned.rl.safe_load import model_from_checkpoint

    meta = load_metadata(SHIPPED)
    env = gym.make(FIM_ID, n_candidates=20, budget=3)
    model = model_from_checkpoint(SHIPPED, meta, env)
    shipped = load_policy(SHIPPED, meta).state_dict()
    assert all(th.equal(v, shipped[k]) for k, v in model.policy.state_dict().items())
    model.learn(64)  # trains on from there


def test_oversized_truncated_and_malformed_metadata(tmp_path: Path) -> None:
    from selenv.learned.rl import safe_load

    big = _copy_with(tmp_path, "big", {"policy.pth": b"\0" * (safe_load.MAX_WEIGHTS_BYTES + 1)})
    assert big.stat().st_size < 2**20  # compresses to almost nothing: a zip-bomb-like entry
    with pytest.raises(ValueError, match="more than MAX_WEIGHTS_BYTES"):
        read_weights(big)
    cut = tmp_path / "cut.zip"
    cut.write_bytes(SHIPPED.read_bytes()[: SHIPPED.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"cut\.zip (is not a readable zip|has no policy\.pth)"):
        read_weights(cut)
    meta = load_metadata(SHIPPED)
    with pytest.raises(ValueError, match="'training' must be an object"):
        load_policy(SHIPPED, {**meta, "training": "x"})
    with pytest.raises(ValueError, match="architecture"):
        load_policy(SHIPPED, {**meta, "architecture": {**meta["architecture"], "hidden": "wide"}})


def test_v01_class_names_still_load(tmp_path: Path) -> None:
    """Checkpoints written before the move under ``selenv`` name ``learned.rl...`` classes."""
    from selenv.agents import make
    from selenv.learned.resources import checkpoint_path

    src = checkpoint_path("fim_selection_ppo.zip")
    dst = tmp_path / "old.zip"
    shutil.copy(src, dst)
    meta = json.loads(src.with_suffix(".json").read_text())
    for key in ("policy", "features_extractor"):
        meta["architecture"][key] = meta["architecture"][key].removeprefix("selenv.")
        assert meta["architecture"][key].startswith("learned.rl.")
    dst.with_suffix(".json").write_text(json.dumps(meta))
    make("ppo:" + str(dst), "selenv/FIMSelection-v1")  # loads
    meta["architecture"]["policy"] = "elsewhere.Policy"
    dst.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"elsewhere\.Policy"):
        make("ppo:" + str(dst), "selenv/FIMSelection-v1")
