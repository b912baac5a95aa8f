"""Learned fusion surrogates (LDMV, LPECMV): features, output constraints, checkpoints, training."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from selenv import fusion
from selenv.core.fusion import dmv_update, pecmv_update
from selenv.learned.surrogate_data import (
    GenerationConfig,
    SurrogateDataset,
    features,
    generate_dataset,
    load_dataset,
    n_features,
    save_dataset,
)
from selenv.learned.surrogates import C_SCALE, Surrogate
from selenv.train import train_surrogate

N, M = 9, 1


@pytest.fixture(scope="module")
def data() -> SurrogateDataset:
    return generate_dataset(300, seed=3, workers=1, progress=False)


def _saturating(kind: str, method: int, data: SurrogateDataset) -> Surrogate:
    """A surrogate whose last layer is blown up, so outputs hit sigmoid/tanh saturation."""
    torch.manual_seed(0)
    sur = Surrogate.create(kind, method=method)
    sur.set_normalisation(data.features())
    with torch.no_grad():
        last = sur.net.body[-1]
        assert isinstance(last, torch.nn.Linear)
        last.weight.mul_(1e3)
        last.bias.mul_(1e3)
    return sur


@pytest.fixture(scope="module")
def nets(data: SurrogateDataset) -> dict[Any, Surrogate]:
    return {
        "ldmv": _saturating("ldmv", 3, data),
        2: _saturating("lpecmv", 2, data),
        3: _saturating("lpecmv", 3, data),
    }


def test_features_shape_and_layout(data: SurrogateDataset) -> None:
    f = features(data.P_i, data.P_j, data.H_i, data.H_j)
    assert f.shape == (300, 108) == (300, n_features(N, M))
    assert np.all(np.isfinite(f))
    # first entry: log of P_i[0, 0]; second: correlation of P_i[0, 1]
    assert np.allclose(f[:, 0], np.log(data.P_i[:, 0, 0]))
    corr = data.P_i[:, 0, 1] / np.sqrt(data.P_i[:, 0, 0] * data.P_i[:, 1, 1])
    assert np.allclose(f[:, 1], corr)
    assert np.all(np.abs(f[:, 1:9]) <= 1.0)
    with pytest.raises(ValueError, match="H_j"):
        features(data.P_i, data.P_j, data.H_i, data.H_j[:, :, :3])
    with pytest.raises(ValueError, match="P_j"):
        bad = data.P_j.copy()
        bad[0, 0, 0] = np.nan
        features(data.P_i, bad, data.H_i, data.H_j)


def test_dataset_round_trip_and_labels(data: SurrogateDataset, tmp_path: Path) -> None:
    assert data.header["n"] == N and data.header["m"] == M and data.header["count"] == 300
    path = save_dataset(data, tmp_path / "d.npz")
    back = load_dataset(path)
    assert back.header == data.header
    for k in ("P_i", "omega", "C", "C_diag"):
        assert np.array_equal(getattr(back, k), getattr(data, k))
    again = generate_dataset(300, seed=3, workers=1, progress=False)
    assert np.array_equal(again.omega, data.omega)
    for row in (0, 150, 299):  # labels are the exact solvers' optimisers
        args = (data.P_i[row], data.P_j[row], data.H_i[row], data.H_j[row], data.R)
        assert dmv_update(*args).omega == pytest.approx(data.omega[row], abs=1e-9)
        assert np.allclose(pecmv_update(*args).C, data.C[row], atol=1e-9)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz"):
        load_dataset(tmp_path / "bad.npz")


def test_parallel_generation_matches_serial() -> None:
    gen = GenerationConfig(per_task=20, min_steps=2, max_steps=10)
    serial = generate_dataset(40, seed=5, workers=1, gen=gen, progress=False)
    parallel = generate_dataset(40, seed=5, workers=2, gen=gen, progress=False)
    assert np.array_equal(serial.P_i, parallel.P_i) and np.array_equal(serial.C, parallel.C)
    assert len(parallel) == 40 and parallel.header["generation"]["per_task"] == 20


def _spd(rng: np.random.Generator, scale: float) -> np.ndarray:
    A = rng.normal(size=(N, N))
    return scale * (A @ A.T / N + 0.1 * np.eye(N))


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**32 - 1),
    log_si=st.floats(-6, 6),
    log_sj=st.floats(-6, 6),
    log_sh=st.floats(-6, 6),
)
def test_constraints_hold_far_outside_training_data(
    nets: dict[Any, Surrogate], seed: int, log_si: float, log_sj: float, log_sh: float
) -> None:
    rng = np.random.default_rng(seed)
    B = 4
    P_i = np.stack([_spd(rng, 10.0**log_si) for _ in range(B)])
    P_j = np.stack([_spd(rng, 10.0**log_sj) for _ in range(B)])
    H_i = rng.normal(size=(B, M, N)) * 10.0**log_sh
    H_j = rng.normal(size=(B, M, N)) * 10.0**log_sh
    w = nets["ldmv"].predict_omega(P_i, P_j, H_i, H_j)
    assert w.shape == (B,) and np.all((w >= 0.0) & (w <= 1.0))
    for method in (2, 3):
        C = nets[method].predict_C(P_i, P_j, H_i, H_j)
        assert C.shape == (B, N, N)
        assert np.all(np.linalg.norm(C, 2, axis=(1, 2)) < 1.0)
        for k in range(B):
            L_i, L_j = np.linalg.cholesky(P_i[k]), np.linalg.cholesky(P_j[k])
            X = L_i @ C[k] @ L_j.T  # eq. (11)
            W = np.block([[np.eye(N), C[k]], [C[k].T, np.eye(N)]])  # whitened joint
            assert np.linalg.eigvalsh(W).min() > 0.0
            J = np.block([[P_i[k], X], [X.T, P_j[k]]])
            D = np.diag(1.0 / np.sqrt(np.diag(J)))  # congruence: same inertia as J
            np.linalg.cholesky(D @ J @ D)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    mats=arrays(
        np.float64,
        (2, 2 * N * N + 2 * M * N),
        elements=st.floats(-1e300, 1e300, allow_nan=False, allow_infinity=False),
    )
)
def test_constraints_hold_for_arbitrary_finite_matrices(
    nets: dict[Any, Surrogate], mats: np.ndarray
) -> None:
    B = mats.shape[0]
    P_i = mats[:, : N * N].reshape(B, N, N)
    P_j = mats[:, N * N : 2 * N * N].reshape(B, N, N)
    H_i = mats[:, 2 * N * N : 2 * N * N + N].reshape(B, M, N)
    H_j = mats[:, 2 * N * N + N :].reshape(B, M, N)
    w = nets["ldmv"].predict_omega(P_i, P_j, H_i, H_j)
    assert np.all((w >= 0.0) & (w <= 1.0))
    for method in (2, 3):
        C = nets[method].predict_C(P_i, P_j, H_i, H_j)
        assert np.all(np.isfinite(C)) and np.all(np.linalg.norm(C, 2, axis=(1, 2)) < 1.0)


def test_saturation_is_reached_and_margin_is_kept(
    nets: dict[Any, Surrogate], data: SurrogateDataset
) -> None:
    """The saturating fixture does hit tanh = +-1 in float32: the margin is what keeps ||C|| < 1."""
    C = nets[3].predict_C(data.P_i * 1e6, data.P_j * 1e-6, data.H_i, data.H_j)
    assert np.max(np.abs(C)) == pytest.approx(C_SCALE, abs=1e-7)
    assert np.max(np.linalg.norm(C, 2, axis=(1, 2))) < 1.0


def test_predictions_feed_the_exact_updates(
    nets: dict[Any, Surrogate], data: SurrogateDataset
) -> None:
    k = 7
    args = (data.P_i[k], data.P_j[k], data.H_i[k], data.H_j[k])
    w = nets["ldmv"].predict_omega(*args)
    assert w.shape == ()
    dmv_update(*args, data.R, omega=float(w))
    C = nets[3].predict_C(*args)
    assert C.shape == (N, N)
    res = pecmv_update(*args, data.R, C=C)
    assert res.log_det <= data.log_det_pecmv[k] + 1e-9  # C* maximises eq. (8a)


def test_save_load_round_trip(
    nets: dict[Any, Surrogate], data: SurrogateDataset, tmp_path: Path
) -> None:
    for key, sur in nets.items():
        pt = sur.save(tmp_path / f"s_{key}")
        assert pt.suffix == ".pt" and pt.with_suffix(".json").exists()
        back = Surrogate.load(tmp_path / f"s_{key}.json")
        meta = json.loads(pt.with_suffix(".json").read_text())
        assert meta["kind"] == sur.kind and meta["method"] == sur.method
        assert meta["n"] == N and meta["m"] == M and len(meta["normalisation"]["mean"]) == 108
        args = (data.P_i, data.P_j, data.H_i, data.H_j)
        if sur.kind == "ldmv":
            assert np.array_equal(back.predict_omega(*args), sur.predict_omega(*args))
        else:
            assert np.array_equal(back.predict_C(*args), sur.predict_C(*args))


def test_mismatches_raise(
    nets: dict[Any, Surrogate], data: SurrogateDataset, tmp_path: Path
) -> None:
    sur = nets[3]
    with pytest.raises(ValueError, match=r"n=9, m=1.*n=3, m=1"):
        sur.predict_C(
            data.P_i[:, :3, :3], data.P_j[:, :3, :3], data.H_i[..., :3], data.H_j[..., :3]
        )
    with pytest.raises(ValueError, match="not 'ldmv'"):
        sur.predict_omega(data.P_i, data.P_j, data.H_i, data.H_j)
    pt = sur.save(tmp_path / "c")
    js = pt.with_suffix(".json")
    meta = json.loads(js.read_text())
    meta["architecture"]["hidden"] = [20, 20]  # weights have three hidden layers
    js.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"c\.pt.*c\.json"):
        Surrogate.load(pt)
    meta["architecture"]["hidden"] = [20, 20, 20]
    meta["normalisation"]["mean"][0] += 1.0
    js.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="normalisation"):
        Surrogate.load(pt)
    del meta["kind"]
    js.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"c\.json"):
        Surrogate.load(pt)
    meta["kind"] = sur.kind
    meta["normalisation"]["mean"][0] -= 1.0
    js.write_text(json.dumps(meta))
    good = pt.read_bytes()
    for bad in (b"", good[: len(good) // 2], b"not a tensor file"):  # empty, truncated, junk
        pt.write_bytes(bad)  # the JSON records the good file's SHA-256: not a pair
        with pytest.raises(ValueError, match=r"c\.pt and metadata .*c\.json are not a pair"):
            Surrogate.load(pt)
    del meta["weights_sha256"]  # a JSON from before the hash: the file itself is checked
    js.write_text(json.dumps(meta))
    for bad in (b"", good[: len(good) // 2], b"not a tensor file"):
        pt.write_bytes(bad)
        with pytest.raises(ValueError, match=r"c\.pt are not a readable tensor file"):
            Surrogate.load(pt)
    buf = io.BytesIO()
    torch.save([torch.zeros(2)], buf)
    pt.write_bytes(buf.getvalue())
    with pytest.raises(ValueError, match="map parameter names to tensors"):
        Surrogate.load(pt)
    pt.unlink()
    with pytest.raises(ValueError, match=r"c\.pt are missing"):
        Surrogate.load(pt)
    js.write_text("{not json")
    with pytest.raises(ValueError, match=r"c\.json.*not valid JSON"):
        Surrogate.load(pt)
    js.unlink()
    with pytest.raises(ValueError, match=r"c\.json is missing"):
        Surrogate.load(pt)


@pytest.mark.parametrize(("kind", "method"), [("ldmv", 3), ("lpecmv", 3), ("lpecmv", 1)])
def test_training_script_end_to_end(
    kind: str, method: int, data: SurrogateDataset, tmp_path: Path
) -> None:
    data_path = save_dataset(data, tmp_path / "d.npz")
    out = tmp_path / "ck" / "s.pt"
    argv = [
        "--kind", kind, "--method", str(method), "--data", str(data_path), "--epochs", "2",
        "--out", str(out), "--tensorboard-dir", str(tmp_path / "runs"), "--no-progress",
    ]  # fmt: skip
    meta = train_surrogate.main(argv)
    assert out.exists() and out.with_suffix(".json").exists()
    assert list(Path(tmp_path / "runs").rglob("events.out.tfevents.*"))
    assert meta["training"]["epochs_run"] == 2
    assert meta["training_data"]["split"] == {"train": 240, "val": 30, "test": 30}
    test = meta["metrics"]["test"]
    if kind == "ldmv":
        assert {"mse", "R", "dmv_cost_gap_mean"} <= set(test) and test["dmv_cost_gap_mean"] >= 0
    else:
        assert test["objective_gap_mean"] <= 1e-9 and test["max_norm_C"] < 1.0
    sur = Surrogate.load(out)
    assert sur.kind == kind and sur.meta["metrics"]["test"] == test


def test_training_script_generates_data(tmp_path: Path) -> None:
    out = tmp_path / "g.pt"
    argv = [
        "--samples", "200", "--epochs", "1", "--workers", "1", "--out", str(out),
        "--tensorboard-dir", "", "--no-progress", "--save-data", str(tmp_path / "g.npz"),
    ]  # fmt: skip
    meta = train_surrogate.main(argv)
    assert meta["training_data"]["count"] == 200 and (tmp_path / "g.npz").exists()
    with pytest.raises(ValueError, match="--kind"):
        train_surrogate.main(["--kind", "nope"])


def test_shipped_checkpoints_load_and_predict(data: SurrogateDataset) -> None:
    root = Path(__file__).resolve().parents[1] / "checkpoints"
    ldmv = Surrogate.load(root / "ldmv.pt")
    lpecmv = Surrogate.load(root / "lpecmv.pt")
    assert json.loads((root / "ldmv.json").read_text())["metrics"]["test"]["R"] > 0.85
    omega = ldmv.predict_omega(data.P_i[:64], data.P_j[:64], data.H_i[:64], data.H_j[:64])
    assert np.all((omega >= 0) & (omega <= 1))
    assert np.mean(np.abs(omega - data.omega[:64])) < 0.05
    C = lpecmv.predict_C(data.P_i[:64], data.P_j[:64], data.H_i[:64], data.H_j[:64])
    assert np.all(np.linalg.norm(C, 2, axis=(1, 2)) < 1)


@pytest.mark.parametrize("activation", ["sigmoid", "tanh", "relu"])
@pytest.mark.parametrize(
    ("kind", "method"), [("ldmv", 3), ("lpecmv", 1), ("lpecmv", 2), ("lpecmv", 3)]
)
def test_numpy_forward_equals_torch_forward(
    data: SurrogateDataset, kind: str, method: int, activation: str
) -> None:
    """predict_* run a numpy copy of the forward pass; it must be the torch module's."""
    torch.manual_seed(3)
    sur = Surrogate.create(kind, method=method, hidden=(16, 8), activation=activation)
    X = data.features()
    sur.set_normalisation(X)
    with torch.no_grad():
        ref = sur.net(torch.from_numpy(X.astype(np.float32))).numpy()
    out = sur.forward_features(X)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)
    # the cached numpy views follow in-place updates and replaced parameters
    with torch.no_grad():
        sur.net.body[0].weight.mul_(2.0)
        sur.net.body[2].bias = torch.nn.Parameter(sur.net.body[2].bias + 0.5)
        ref2 = sur.net(torch.from_numpy(X.astype(np.float32))).numpy()
    np.testing.assert_allclose(sur.forward_features(X), ref2, rtol=1e-5, atol=1e-6)


def test_fusion_level_ldmv_lpecmv(nets: dict[Any, Surrogate], data: SurrogateDataset) -> None:
    """selenv.fusion.ldmv_update / lpecmv_update = the exact updates with the prediction."""
    k = 11
    args = (data.P_i[k], data.P_j[k], data.H_i[k], data.H_j[k])
    ldmv, lpecmv = nets["ldmv"], nets[3]
    ldmv.meta["R"] = lpecmv.meta["R"] = data.R.tolist()
    x, r = np.arange(N, dtype=float), np.array([0.3])
    got = fusion.ldmv_update(*args, data.R, x_i=x, residual=r, surrogate=ldmv)
    ref = dmv_update(*args, data.R, x_i=x, residual=r, omega=float(ldmv.predict_omega(*args)))
    np.testing.assert_array_equal(got.P, ref.P)
    np.testing.assert_array_equal(got.x, ref.x)
    got_p = fusion.lpecmv_update(*args, data.R, surrogate=lpecmv)
    ref_p = pecmv_update(*args, data.R, C=lpecmv.predict_C(*args))
    np.testing.assert_array_equal(got_p.P, ref_p.P)
    with pytest.raises(ValueError, match="trained with R"):
        fusion.ldmv_update(*args, 4.0 * data.R, surrogate=ldmv)
    with pytest.raises(ValueError, match="'lpecmv' surrogate"):
        fusion.lpecmv_update(*args, data.R, surrogate=ldmv)
    with pytest.raises(ValueError, match="variant"):
        fusion.lpecmv_update(*args, data.R, variant="nope")
    with pytest.raises(ValueError, match="P_j"):
        fusion.ldmv_update(args[0], args[1][:3, :3], *args[2:], data.R, surrogate=ldmv)
    shipped = fusion.ldmv_update(*args, data.R)  # the shipped checkpoint via the lazy hook
    assert np.all(np.linalg.eigvalsh(shipped.P) > 0)
    full = fusion.lpecmv_update(*args, data.R, variant="lpecmv_full")  # method 1, full C
    assert full.log_det <= data.log_det_pecmv[k] + 1e-9  # C* maximises eq. (8a)
    assert np.linalg.norm(full.C, 2) < 1.0
