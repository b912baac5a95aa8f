"""Learned fusion surrogates: LDMV (``omega*``) and LPECMV (``C*``) of Chen & Kia 2022, Sec. III.

Both are MLPs on the features of eq. (13) (:func:`selenv.learned.surrogate_data.features`) whose
output
layer enforces the constraint of the optimiser they replace, for ANY finite input::

    features ─► (x - mean) / std ─► clamp ±1e4 ─► MLP ─► output activation
    LDMV            omega = sigmoid(y)                 in [0, 1]               (eq. 6)
    LPECMV method 3 C = diag(tanh(y)) (1 - 1e-6)       ||C||_2 < 1  (default, Table I)
    LPECMV method 2 C = tanh(Y) (1 - 1e-6) / D, D = n  ||C||_2 <= ||C||_F < 1
    LPECMV method 1 C = tanh(Y), barrier loss eq. (14) no guarantee; predict_C rescales
                                                       ||C||_2 >= 1 - 1e-6 onto it

so ``X = L_i C L_j^T`` (eq. 11) always makes ``[[P_i, X], [X^T, P_j]]`` positive definite
(Lemma III.1) and ``dmv_update(..., omega=...)``, ``pecmv_update(..., C=...)`` accept the
prediction. Table II's architectures are the defaults: LDMV 4 x 9 sigmoid (SGD, lr 0.05,
batch 256), LPECMV 3 x 20 tanh (Adam, lr 0.025, batch 512), 200 epochs, MSE (the training
script swaps LDMV's SGD for Adam, see ``selenv.train.train_surrogate.DEFAULT_OPTIMIZER``).

The input standardisation is a pair of buffers inside the module, so the state dict carries it.
:class:`Surrogate` wraps a module with its metadata: ``save`` writes ``<path>.pt`` (state dict)
and ``<path>.json`` (kind, method, architecture, normalisation, n, m, R, training data summary,
metrics, versions and the SHA-256 of the ``.pt``), both written atomically as a pair
(:func:`selenv.atomic.atomic_paths`: an interrupted or failed save leaves the previous pair
byte-identical); ``load`` refuses a ``.pt`` whose SHA-256 is not the one its JSON records
(a pair from two different saves), and checks the two against each other: every field has its type
(``method``, ``n``, ``m`` ints, ``activation`` one of ``sigmoid``/``tanh``/``relu``), the
redundant fields agree with each other (``architecture.output`` is the one of ``kind`` and
``method``, a barrier ``training.loss`` means method 1, ``n_features`` is that of ``n, m``), and
whatever the state dict implies agrees with them: the input width is ``n_features(n, m)``, the
hidden widths are ``architecture.hidden``, the output width is ``1`` (LDMV), ``n`` (LPECMV
method 3) or ``n * n`` (methods 1 and 2), and the parameter count is
``architecture.n_parameters``. Methods 1 and 2 have the same weight shapes, so they are told
apart by ``architecture.output`` (and ``training.loss``); the activation has no parameters,
so only its name is checked. ``predict_omega`` and
``predict_C`` are batched numpy in, numpy out: float32 inference through a numpy copy of the
forward pass (:meth:`Surrogate.forward_features`), no per-sample loop.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from torch import nn

import selenv
from selenv.atomic import atomic_paths
from selenv.core.linalg import FloatArray, as_float_array, check_finite
from selenv.learned.resources import checkpoint_path, read_metadata
from selenv.learned.surrogate_data import features, n_features
from selenv.learned.tensor_load import load_tensors

__all__ = [
    "C_SCALE",
    "FORMAT",
    "KINDS",
    "MAX_HIDDEN_LAYERS",
    "MAX_HIDDEN_WIDTH",
    "MAX_PARAMETERS",
    "METHODS",
    "TABLE_II",
    "Surrogate",
    "SurrogateNet",
    "barrier_loss",
    "describe_shipped",
    "n_parameters",
    "shipped",
    "shipped_catalogue",
]

FORMAT = "selenv-surrogate-v1"
KINDS = ("ldmv", "lpecmv")
METHODS = (1, 2, 3)
#: contraction margin: tanh saturates to exactly 1 in float32, so outputs are scaled by this
C_SCALE = 1.0 - 1e-6
#: ceilings on a checkpoint's metadata, checked by :meth:`Surrogate.load` before anything is
#: allocated (the training script checks ``--hidden`` against its own ``--max-width``)
MAX_HIDDEN_WIDTH = 65_536
MAX_HIDDEN_LAYERS = 64
MAX_PARAMETERS = 50_000_000  # 200 MB of float32 weights
MAX_STATE_DIM = 64  # n and m
_CLAMP = 1e4  # standardised features are clamped to +-this (finite outputs for any input)
_ACTIVATIONS: dict[str, type[nn.Module]] = {"sigmoid": nn.Sigmoid, "tanh": nn.Tanh, "relu": nn.ReLU}
_NUMPY_ACTIVATIONS: dict[type[nn.Module], Any] = {
    nn.Sigmoid: lambda z: 1.0 / (1.0 + np.exp(-z)),
    nn.Tanh: np.tanh,
    nn.ReLU: lambda z: np.maximum(z, 0.0),
}

#: Table II of the paper (hidden layers, activation, optimiser, batch size, learning rate, epochs)
TABLE_II: dict[str, dict[str, Any]] = {
    "ldmv": {"hidden": (9, 9, 9, 9), "activation": "sigmoid", "optimizer": "sgd",
             "batch_size": 256, "lr": 0.05, "epochs": 200},
    "lpecmv": {"hidden": (20, 20, 20), "activation": "tanh", "optimizer": "adam",
               "batch_size": 512, "lr": 0.025, "epochs": 200},
}  # fmt: skip


def _need_int(value: object, what: str) -> int:
    """``value`` if it is an int (not a bool, float or str), else ``TypeError`` naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{what} must be an int, got {value!r}")
    return int(value)


def _out_dim(kind: str, method: int, n: int) -> int:
    if kind == "ldmv":
        return 1
    return n if method == 3 else n * n


class SurrogateNet(nn.Module):
    """Standardise, MLP, constrained output (see the module docstring).

    Args:
        kind: ``"ldmv"`` or ``"lpecmv"``.
        method: LPECMV output method 1, 2 or 3 (ignored for LDMV).
        n: state dimension of each agent; m: measurement dimension.
        hidden: hidden layer widths; activation: ``sigmoid``, ``tanh`` or ``relu``.

    Buffers ``mean`` and ``std`` (n(n+1) + 2mn,) hold the input standardisation.

    Raises:
        TypeError: ``method``, ``n``, ``m`` or a hidden width is not an int.
        ValueError: unknown ``kind`` / ``method`` / ``activation``, or sizes below 1.
    """

    mean: th.Tensor
    std: th.Tensor

    def __init__(
        self, *, kind: str, method: int, n: int, m: int, hidden: tuple[int, ...], activation: str
    ) -> None:
        super().__init__()
        for value, what in (
            (method, "method"),
            (n, "n"),
            (m, "m"),
            *((h, "hidden") for h in hidden),
        ):
            _need_int(value, what)
        if not isinstance(kind, str) or kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if not isinstance(activation, str) or activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be in {sorted(_ACTIVATIONS)}, got {activation!r}")
        if n < 1 or m < 1 or not hidden or min(hidden) < 1:
            raise ValueError(f"need n, m >= 1 and hidden widths >= 1, got {n}, {m}, {hidden}")
        self.kind, self.method, self.n, self.m = kind, method, n, m
        d = n_features(n, m)
        self.register_buffer("mean", th.zeros(d))
        self.register_buffer("std", th.ones(d))
        sizes = [d, *hidden]
        layers: list[nn.Module] = []
        for a, b in pairwise(sizes):
            layers += [nn.Linear(a, b), _ACTIVATIONS[activation]()]
        layers.append(nn.Linear(sizes[-1], _out_dim(kind, method, n)))
        self.body = nn.Sequential(*layers)

    def forward(self, x: th.Tensor) -> th.Tensor:
        """(B, d) features -> (B,) omega (LDMV), (B, n) diagonal (method 3) or (B, n*n) C."""
        z = (x - self.mean) / self.std
        z = th.nan_to_num(z, nan=0.0, posinf=_CLAMP, neginf=-_CLAMP).clamp(-_CLAMP, _CLAMP)
        y = self.body(z)
        if self.kind == "ldmv":
            return th.sigmoid(y).squeeze(-1)
        t = th.tanh(y)
        if self.method == 1:
            return t
        return t * (C_SCALE / self.n if self.method == 2 else C_SCALE)


def barrier_loss(pred: th.Tensor, target: th.Tensor, lam: float) -> th.Tensor:
    """Eq. (14): ``mean(||Y - Yhat||_2 - lam log(1 - ||Yhat||_2))`` (method 1).

    The paper prints ``+ lam log(1 - ||Yhat||)``, which rewards approaching the boundary; the
    barrier it describes (infinite as ``||Yhat|| -> 1``) is the negative log used here.
    ``||Yhat||`` is clamped just below 1 so the loss stays finite while training.
    """
    norm = th.linalg.vector_norm(pred, dim=-1).clamp(max=1.0 - 1e-6)
    return (th.linalg.vector_norm(target - pred, dim=-1) - lam * th.log1p(-norm)).mean()


@dataclass(eq=False)
class Surrogate:
    """A trained (or fresh) LDMV / LPECMV module with its metadata; numpy in, numpy out."""

    net: SurrogateNet
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def create(
        cls,
        kind: str,
        *,
        method: int = 3,
        n: int = 9,
        m: int = 1,
        hidden: tuple[int, ...] | None = None,
        activation: str | None = None,
    ) -> Surrogate:
        """A fresh surrogate with Table II's architecture unless ``hidden``/``activation`` given.

        Raises:
            TypeError, ValueError: as :class:`SurrogateNet`.
        """
        if not isinstance(kind, str) or kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        t2 = TABLE_II[kind]
        hidden = tuple(t2["hidden"] if hidden is None else hidden)
        activation = t2["activation"] if activation is None else activation
        method = 3 if kind == "ldmv" else method
        net = SurrogateNet(kind=kind, method=method, n=n, m=m, hidden=hidden, activation=activation)
        meta = {
            "format": FORMAT,
            "kind": kind,
            "method": method,
            "n": n,
            "m": m,
            "n_features": n_features(n, m),
            "architecture": {
                "hidden": list(hidden),
                "activation": activation,
                "output": _output_doc(kind, method),
                "n_parameters": int(sum(p.numel() for p in net.parameters())),
            },
        }
        return cls(net=net, meta=meta)

    @property
    def kind(self) -> str:  # noqa: D102
        return self.net.kind

    @property
    def method(self) -> int:  # noqa: D102
        return self.net.method

    @property
    def n(self) -> int:  # noqa: D102
        return self.net.n

    @property
    def m(self) -> int:  # noqa: D102
        return self.net.m

    def set_normalisation(self, X: np.ndarray) -> None:
        """Standardise with the mean and std of training features ``X`` (B, d); std floor 1.

        Raises:
            TypeError: ``X`` is not real numeric.
            ValueError: ``X`` is not ``(B, n_features)`` with ``B >= 1``, or not finite; the
                surrogate is left unchanged.
        """
        X = as_float_array(X, "X")
        d = int(self.net.mean.shape[0])
        if X.ndim != 2 or X.shape[1] != d or X.shape[0] == 0:
            raise ValueError(f"X must have shape (B, {d}) with B >= 1, got {X.shape}")
        check_finite(X, "X")
        mean = X.mean(axis=0)
        std = X.std(axis=0)
        std = np.where(std > 1e-8, std, 1.0)
        self.net.mean.copy_(th.as_tensor(mean, dtype=th.float32))
        self.net.std.copy_(th.as_tensor(std, dtype=th.float32))

    # -- numpy path ---------------------------------------------------------------------------

    def _forward(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> tuple[np.ndarray, bool]:
        P_i, P_j = as_float_array(P_i, "P_i"), as_float_array(P_j, "P_j")
        H_i, H_j = as_float_array(H_i, "H_i"), as_float_array(H_j, "H_j")
        single = P_i.ndim == 2
        if single:
            P_i, P_j, H_i, H_j = (a[None] for a in (P_i, P_j, H_i, H_j))
        n_call = P_i.shape[-1] if P_i.ndim >= 1 else 0
        m_call = H_i.shape[-2] if H_i.ndim >= 2 else 0
        if n_call != self.n or m_call != self.m or H_j.shape[-2:] != (self.m, self.n):
            raise ValueError(
                f"surrogate {self.meta.get('path', '(unsaved)')} is for n={self.n}, m={self.m}; "
                f"the call has n={n_call}, m={m_call} (P_i {P_i.shape}, H_i {H_i.shape}, "
                f"H_j {H_j.shape})"
            )
        return self.forward_features(features(P_i, P_j, H_i, H_j)), single

    def forward_features(self, x: np.ndarray) -> np.ndarray:
        """The module's forward pass in numpy: (B, d) features -> (B,) / (B, n) / (B, n*n).

        Same float32 arithmetic as :meth:`SurrogateNet.forward` (tested equal to 1e-6) without
        torch's per-call dispatch, so one unbatched prediction costs a few microseconds of
        matrix products instead of ~100 us of framework overhead. The weights are zero-copy views
        of the module's tensors (:meth:`_numpy_params`), so a model being trained is current.
        """
        net = self.net
        mean, std, layers = self._numpy_params()
        z = (np.asarray(x, dtype=np.float32) - mean) / std
        np.clip(z, -_CLAMP, _CLAMP, out=z)  # +-inf -> +-clamp (as nan_to_num + clamp in torch)
        if np.isnan(z.sum()):
            z[np.isnan(z)] = 0.0
        with np.errstate(over="ignore"):
            for W, b, act in layers:
                z = z @ W + b
                if act is not None:
                    z = act(z)
            if net.kind == "ldmv":
                return 1.0 / (1.0 + np.exp(-z[:, 0]))  # sigmoid; exp overflow -> exactly 0
            t = np.tanh(z)
        if net.method == 1:
            return t
        return t * np.float32(C_SCALE / net.n if net.method == 2 else C_SCALE)

    def _numpy_params(self) -> tuple[np.ndarray, np.ndarray, list[tuple[Any, Any, Any]]]:
        """Zero-copy numpy views of the buffers and (W^T, b, activation) per layer, cached.

        Views share memory with the tensors, so in-place updates (optimiser steps,
        ``load_state_dict``, ``set_normalisation``) are seen; the cache is rebuilt when a
        tensor object is replaced.
        """
        net = self.net
        cache = self.__dict__.get("_np_cache")
        if cache is not None:
            owner, tensors, arrays = cache
            # the modules' own dicts, not Module.__getattr__: ~10x cheaper per lookup
            buffers = net._buffers
            if (
                owner is net
                and buffers["mean"] is tensors[0]
                and buffers["std"] is tensors[1]
                and all(
                    m._parameters["weight"] is w and m._parameters["bias"] is b
                    for m, w, b in tensors[2:]
                )
            ):
                return arrays
        mods = list(net.body)
        layers = []
        linears = []
        for i, mod in enumerate(mods):
            if isinstance(mod, nn.Linear):
                nxt = mods[i + 1] if i + 1 < len(mods) else None
                act = _NUMPY_ACTIVATIONS[type(nxt)] if nxt is not None else None
                layers.append((mod.weight.detach().numpy().T, mod.bias.detach().numpy(), act))
                linears.append((mod, mod.weight, mod.bias))
        arrays = (net.mean.numpy(), net.std.numpy(), layers)
        self.__dict__["_np_cache"] = (net, (net.mean, net.std, *linears), arrays)
        return arrays

    def _need(self, kind: str) -> None:
        if self.kind != kind:
            raise ValueError(f"this surrogate is {self.kind!r}, not {kind!r}")

    def predict_omega(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> FloatArray:
        """LDMV: ``omega_hat`` in [0, 1] for a batch of fusion problems.

        (B,) for (B, n, n) / (B, m, n) inputs, a 0-d float64 for one unbatched problem
        ((n, n) / (m, n)). Feed to ``dmv_update(..., omega=...)``.

        Raises:
            TypeError: an input is not real numeric (complex, bool, str, object).
            ValueError: not an LDMV surrogate, (n, m) of the call differ from the checkpoint's,
                or non-finite input.
        """
        self._need("ldmv")
        y, single = self._forward(P_i, P_j, H_i, H_j)
        w = np.clip(y.astype(np.float64), 0.0, 1.0)
        return w[0] if single else w

    def predict_C(self, P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> FloatArray:
        """LPECMV: ``C_hat`` (B, n, n) with ``||C_hat||_2 < 1`` (or (n, n) unbatched).

        ``X_hat = L_i C_hat L_j^T`` (``P = L L^T``), i.e. ``pecmv_update(..., C=C_hat)``.
        Method 1 has no built-in guarantee: rows with ``||C||_2 >= 1 - 1e-6`` are rescaled to
        that norm (``meta["architecture"]["output"]`` says so).

        Raises:
            TypeError: an input is not real numeric (complex, bool, str, object).
            ValueError: not an LPECMV surrogate, (n, m) mismatch, or non-finite input.
        """
        self._need("lpecmv")
        y, single = self._forward(P_i, P_j, H_i, H_j)
        y64 = y.astype(np.float64)
        Bn, n = y64.shape[0], self.n
        if self.method == 3:
            flat = np.zeros((Bn, n * n))
            flat[:, :: n + 1] = y64  # the diagonal of each row-major n x n block
            C = flat.reshape(Bn, n, n)
        else:
            C = y64.reshape(Bn, n, n)
        if self.method == 1 and Bn:
            norm = np.linalg.norm(C, 2, axis=(1, 2))
            C *= np.where(norm >= C_SCALE, C_SCALE / np.maximum(norm, C_SCALE), 1.0)[:, None, None]
        return C[0] if single else C

    # -- files --------------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write ``<path>.pt`` (state dict) and ``<path>.json`` (metadata); return the .pt path.

        The weights are serialised in memory, then both files are written to temporaries next
        to the targets and renamed over them together (:func:`selenv.atomic.atomic_paths`):
        a failed or interrupted save (full disk, file-size limit, SIGINT, SIGKILL) leaves the
        previous pair byte-identical and no partial file. The JSON records the ``.pt``'s
        SHA-256 (``weights_sha256``), so a reader finding halves of two saves refuses them.

        Raises:
            OSError: a write failed; its ``filename`` is the target, not the temporary.
        """
        pt = Path(path).with_suffix(".pt")
        js = pt.with_suffix(".json")
        meta = dict(self.meta)
        meta.pop("path", None)
        meta["normalisation"] = {
            "features": "selenv.learned.surrogate_data.features",
            "mean": self.net.mean.tolist(),
            "std": self.net.std.tolist(),
        }
        meta["versions"] = {"selenv": selenv.__version__, "torch": th.__version__}
        buffer = io.BytesIO()
        th.save(self.net.state_dict(), buffer)  # in memory: disk errors come from plain writes
        weights = buffer.getvalue()
        meta["weights_sha256"] = hashlib.sha256(weights).hexdigest()
        text = json.dumps(meta, indent=2) + "\n"
        current = pt
        try:
            with atomic_paths([pt, js]) as (tmp_pt, tmp_js):
                tmp_pt.write_bytes(weights)
                current = js
                tmp_js.write_text(text, encoding="utf-8")
                current = pt
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(current)) from exc
        self.meta = {**meta, "path": str(pt)}
        return pt

    @classmethod
    def load(cls, path: str | Path) -> Surrogate:
        """Read a checkpoint written by :meth:`save` (``path`` with or without suffix).

        The metadata is checked field by field and against the weights (see the module
        docstring) before the weights are loaded, so a JSON that describes other weights (e.g.
        method-1 weights labelled method 2, which have the same shapes) is refused instead of
        predicting wrongly.

        Raises:
            ValueError: the JSON or weights are missing or unreadable, the metadata is
                incomplete, has a field of the wrong type or value, declares sizes over
                :data:`MAX_STATE_DIM`, :data:`MAX_HIDDEN_WIDTH`, :data:`MAX_HIDDEN_LAYERS` or
                :data:`MAX_PARAMETERS` (checked before anything is allocated), the ``.pt`` is
                not the one whose SHA-256 the JSON records (``weights_sha256``; JSONs written
                before that field existed are checked field by field only), or the two do not
                match (the message names the files and the field).
        """
        pt = Path(path).with_suffix(".pt")
        js = pt.with_suffix(".json")
        try:
            meta = read_metadata(js, "surrogate metadata")
        except FileNotFoundError:
            raise ValueError(f"surrogate metadata {js} is missing") from None
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"surrogate metadata {js} is not valid JSON: {exc}") from None
        try:
            if not isinstance(meta, dict):
                raise ValueError(f"it must hold a JSON object, got {type(meta).__name__}")
            if meta["format"] != FORMAT:
                raise ValueError(f"format {meta['format']!r} is not {FORMAT!r}")
            spec = _meta_spec(meta)
            sur = cls.create(
                spec["kind"],
                method=spec["method"],
                n=spec["n"],
                m=spec["m"],
                hidden=spec["hidden"],
                activation=spec["activation"],
            )
            norm = meta["normalisation"]
            mean = np.asarray(norm["mean"], dtype=np.float32)
            std = np.asarray(norm["std"], dtype=np.float32)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"surrogate metadata {js} is invalid: {exc!s}") from None
        if not pt.is_file():
            raise ValueError(f"surrogate weights {pt} are missing (metadata {js})")
        n_params = int(sum(p.numel() for p in sur.net.parameters()))
        max_bytes = 8 * n_params + (4 << 20)  # float32 weights and buffers, plus the zip's frame
        if pt.stat().st_size > max_bytes:
            raise ValueError(
                f"surrogate weights {pt} are {pt.stat().st_size:,} bytes, more than the "
                f"{max_bytes:,} that metadata {js} allows for {n_params:,} parameters"
            )
        blob = pt.read_bytes()
        recorded = meta.get("weights_sha256")
        if recorded is not None and recorded != hashlib.sha256(blob).hexdigest():
            raise ValueError(
                f"surrogate weights {pt} and metadata {js} are not a pair: the .pt's SHA-256 is "
                f"not the one the JSON records (they come from different saves; re-run the "
                f"training or restore both files)"
            )
        state = load_tensors(  # one line if refused, nothing run
            blob, f"surrogate weights {pt}", verb="are", kind="a readable tensor file"
        )
        if not isinstance(state, dict):
            raise ValueError(f"surrogate weights {pt} must map parameter names to tensors")
        problem = _weights_disagree(state, spec, meta)
        if problem:
            raise ValueError(f"surrogate weights {pt} do not match metadata {js}: {problem}")
        try:
            sur.net.load_state_dict(state)
        except (RuntimeError, TypeError, ValueError) as exc:
            msg = (str(exc).splitlines() or [type(exc).__name__])[0]
            raise ValueError(f"surrogate weights {pt} do not match metadata {js}: {msg}") from None
        if mean.shape != sur.net.mean.shape or not (
            np.allclose(mean, sur.net.mean.numpy()) and np.allclose(std, sur.net.std.numpy())
        ):
            raise ValueError(f"normalisation in {js} does not match the buffers in {pt}")
        sur.meta = {**meta, "path": str(pt)}
        return sur


def _meta_spec(meta: dict[str, Any]) -> dict[str, Any]:
    """The architecture fields of a checkpoint's metadata, type-checked and cross-checked.

    Raises:
        KeyError: a required field is missing.
        ValueError: a field of the wrong type or value, or fields that contradict each other
            (the message names the field).
    """

    def int_field(value: object, field: str, lo: int = 1) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ValueError(f"{field} must be an int >= {lo}, got {value!r}")
        return value

    kind = meta["kind"]
    if not isinstance(kind, str) or kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    method = int_field(meta["method"], "method")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if kind == "ldmv" and method != 3:
        raise ValueError(f"method of an 'ldmv' surrogate must be 3 (unused), got {method!r}")
    n, m = int_field(meta["n"], "n"), int_field(meta["m"], "m")
    arch = meta["architecture"]
    if not isinstance(arch, dict):
        raise ValueError(f"architecture must be a JSON object, got {type(arch).__name__}")
    hidden = arch["hidden"]
    if not isinstance(hidden, list) or not hidden:
        raise ValueError(f"architecture.hidden must be a non-empty list of ints, got {hidden!r}")
    if len(hidden) > MAX_HIDDEN_LAYERS:
        raise ValueError(
            f"architecture.hidden has {len(hidden)} layers, over the limit of {MAX_HIDDEN_LAYERS}"
        )
    hidden = tuple(int_field(h, "architecture.hidden[]") for h in hidden)
    if max(hidden) > MAX_HIDDEN_WIDTH:
        raise ValueError(
            f"architecture.hidden has a width of {max(hidden):,}, over the limit of "
            f"{MAX_HIDDEN_WIDTH:,}"
        )
    for value, name in ((n, "n"), (m, "m")):
        if value > MAX_STATE_DIM:
            raise ValueError(f"{name} is {value}, over the limit of {MAX_STATE_DIM}")
    count = n_parameters(n_features(n, m), hidden, _out_dim(kind, method, n))
    if count > MAX_PARAMETERS:
        raise ValueError(
            f"architecture.hidden {list(hidden)} gives {count:,} parameters, over the limit "
            f"of {MAX_PARAMETERS:,}"
        )
    activation = arch["activation"]
    if not isinstance(activation, str) or activation not in _ACTIVATIONS:
        raise ValueError(
            f"architecture.activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}"
        )
    output = arch["output"]
    if output != _output_doc(kind, method):
        implied = [
            (k, mt) for k, mt in (("ldmv", 3), ("lpecmv", 1), ("lpecmv", 2), ("lpecmv", 3))
            if _output_doc(k, mt) == output
        ]  # fmt: skip
        says = f" (the output of kind {implied[0][0]!r}, method {implied[0][1]})" if implied else ""
        raise ValueError(
            f"architecture.output {output!r}{says} contradicts kind {kind!r}, method {method}, "
            f"whose output is {_output_doc(kind, method)!r}"
        )
    if "n_features" in meta and meta["n_features"] != n_features(n, m):
        raise ValueError(
            f"n_features is {meta['n_features']!r}, but n = {n}, m = {m} give {n_features(n, m)}"
        )
    loss = (
        (meta.get("training") or {}).get("loss") if isinstance(meta.get("training"), dict) else None
    )
    if isinstance(loss, str) and "barrier" in loss and (kind, method) != ("lpecmv", 1):
        raise ValueError(
            f"training.loss {loss!r} is the barrier loss of LPECMV method 1, but the metadata "
            f"says kind {kind!r}, method {method}"
        )
    return {"kind": kind, "method": method, "n": n, "m": m, "hidden": hidden,
            "activation": activation}  # fmt: skip


def _weights_disagree(state: dict[str, Any], spec: dict[str, Any], meta: dict[str, Any]) -> str:
    """What the state dict implies that the metadata contradicts (``""``: nothing found).

    Reads the ``body.<i>.weight`` matrices of the linear layers: input width, hidden widths,
    output width (the kind / method), and the parameter count. Anything not in that layout is
    left to ``load_state_dict``, whose error is reported as is.
    """
    layers: list[tuple[int, Any]] = []
    for key, value in state.items():
        parts = str(key).split(".")
        if len(parts) == 3 and parts[0] == "body" and parts[1].isdigit() and parts[2] == "weight":
            if not isinstance(value, th.Tensor) or value.ndim != 2:
                return ""
            layers.append((int(parts[1]), value))
    if not layers:
        return ""
    layers.sort(key=lambda item: item[0])
    shapes = [tuple(int(s) for s in w.shape) for _, w in layers]  # (out, in) per layer
    n, m, kind, method = spec["n"], spec["m"], spec["kind"], spec["method"]
    if shapes[0][1] != n_features(n, m):
        return (
            f"n = {n}, m = {m} give {n_features(n, m)} input features, but the first layer of "
            f"the weights takes {shapes[0][1]}"
        )
    hidden = [out for out, _ in shapes[:-1]]
    if hidden != list(spec["hidden"]):
        return f"architecture.hidden is {list(spec['hidden'])}, but the weights have {hidden}"
    out = shapes[-1][0]
    if out != _out_dim(kind, method, n):
        options = [("ldmv", 3), ("lpecmv", 3), ("lpecmv", 1), ("lpecmv", 2)]
        implied = [(k, mt) for k, mt in options if _out_dim(k, mt, n) == out]
        what = (
            ", ".join(
                "kind 'ldmv'" if k == "ldmv" else f"kind 'lpecmv' method {mt}" for k, mt in implied
            )
            or f"no surrogate with n = {n}"
        )
        field = "method" if any(k == kind for k, _ in implied) else "kind"
        return (
            f"{field} is {spec[field]!r}, but the output layer of the weights has width {out}, "
            f"which means {what} (kind {kind!r}, method {method} would have width "
            f"{_out_dim(kind, method, n)})"
        )
    count = sum(
        int(v.numel())
        for k, v in state.items()
        if isinstance(v, th.Tensor) and str(k).startswith("body.")
    )
    declared = meta["architecture"].get("n_parameters")
    if declared is not None and declared != count:
        return f"architecture.n_parameters is {declared!r}, but the weights have {count}"
    return ""


def n_parameters(d_in: int, hidden: tuple[int, ...], d_out: int) -> int:
    """Weights and biases of the MLP ``d_in -> hidden... -> d_out`` (no allocation)."""
    sizes = [d_in, *hidden, d_out]
    return sum(a * b + b for a, b in pairwise(sizes))


def _output_doc(kind: str, method: int) -> str:
    if kind == "ldmv":
        return "omega = sigmoid(y)"
    return {
        1: "C = tanh(Y) (n x n), barrier loss eq. 14; predict_C rescales ||C||_2 >= 1-1e-6",
        2: "C = tanh(Y) * (1-1e-6) / n (n x n)",
        3: "C = diag(tanh(y)) * (1-1e-6)",
    }[method]


#: the shipped checkpoints of each fusion name, loaded on first use by :func:`shipped`, which
#: picks the one trained for the problem's ``n`` and ``R`` (the first is the default, ``R=None``)
SHIPPED: dict[str, tuple[Path, ...]] = {
    "ldmv": (checkpoint_path("ldmv.pt"), checkpoint_path("ldmv_m2.pt")),
    "lpecmv": (checkpoint_path("lpecmv.pt"), checkpoint_path("lpecmv_m2.pt")),
    "lpecmv_full": (checkpoint_path("lpecmv_method1.pt"),),
    "lpecmv_objective": (checkpoint_path("lpecmv_objective.pt"),),
}
_LOADED: dict[Path, Surrogate] = {}
_CATALOGUE: dict[Path, dict[str, Any]] = {}


def shipped_catalogue(kind: str) -> list[dict[str, Any]]:
    """What the shipped checkpoints of ``kind`` are trained for, from their JSONs (no torch).

    Returns:
        one dict per file of ``SHIPPED[kind]`` that exists: ``path``, ``n``, ``m``, ``R``
        ((m, m) list), ``bearing_sigma_deg`` (``None`` for range only) and ``range_sigma``
        (``sqrt(R[0][0])``, m).

    Raises:
        ValueError: unknown ``kind`` or an unreadable JSON (names the file).
    """
    if kind not in SHIPPED:
        raise ValueError(f"kind must be one of {sorted(SHIPPED)}, got {kind!r}")
    out = []
    for pt in SHIPPED[kind]:
        if pt not in _CATALOGUE:
            js = pt.with_suffix(".json")
            if not (pt.is_file() and js.is_file()):
                continue
            try:
                meta = read_metadata(js, "surrogate metadata")
                R = np.asarray(meta["R"], dtype=np.float64)
                entry = {"path": pt, "n": int(meta["n"]), "m": int(meta["m"]), "R": R.tolist(),
                         "bearing_sigma_deg": meta.get("bearing_sigma_deg"),
                         "range_sigma": float(np.sqrt(R[0, 0]))}  # fmt: skip
            except (OSError, KeyError, TypeError, ValueError, IndexError) as exc:
                raise ValueError(f"surrogate metadata {js} is invalid: {exc!s}") from None
            if R.shape != (entry["m"], entry["m"]):
                raise ValueError(f"surrogate metadata {js}: R is not {entry['m']} x {entry['m']}")
            _CATALOGUE[pt] = entry
        out.append(_CATALOGUE[pt])
    return out


def describe_shipped(kind: str) -> str:
    """One line per shipped checkpoint of ``kind``: file, n, m, noise (for error messages)."""
    parts = []
    for e in shipped_catalogue(kind):
        noise = f"range_sigma {e['range_sigma']:.4g} m"
        if e["m"] == 2 and e["bearing_sigma_deg"] is not None:
            noise += f", bearing_sigma_deg {e['bearing_sigma_deg']:.4g}"
        parts.append(f"{e['path'].name} (n = {e['n']}, m = {e['m']}, {noise}, R = {e['R']})")
    return "; ".join(parts) or "none"


def shipped(kind: str, *, R: Any = None, n: int | None = None) -> Surrogate:
    """A shipped surrogate (``checkpoints/``), loaded once per process.

    ``kind``: ``"ldmv"``, ``"lpecmv"`` (method 3), ``"lpecmv_full"`` (method 1) or
    ``"lpecmv_objective"`` (method 3 trained on the objective eq. 8a, the calibrated one).
    ``R`` (m, m): the measurement noise of the problem; the checkpoint of ``kind`` whose ``m``
    and training ``R`` match it (:func:`selenv.core.fusion.surrogate.same_R`) and, when ``n``
    is given, whose ``n`` matches, is returned. ``R=None``: the range-only (m = 1) checkpoint,
    as before the m = 2 ones existed.

    This is the hook ``selenv.families.cooperative.scenario`` calls for ``fusion="ldmv"`` /
    ``"lpecmv"`` (through a lazy ``"module:attr"`` reference, so ``selenv`` never imports
    ``learned`` at import time).

    Raises:
        ValueError: unknown ``kind``, a missing / invalid checkpoint (names the file), or no
            shipped checkpoint trained for ``(n, R)`` (lists the shipped ones).
    """
    from selenv.core.fusion.surrogate import same_R  # core has no torch: imports stay downward

    if kind not in SHIPPED:
        raise ValueError(f"kind must be one of {sorted(SHIPPED)}, got {kind!r}")
    if R is None and n is None:
        pt = SHIPPED[kind][0]
    else:
        R_arr = None if R is None else np.atleast_2d(as_float_array(R, "R"))
        match = [
            e["path"]
            for e in shipped_catalogue(kind)
            if (n is None or e["n"] == n) and (R_arr is None or same_R(e["R"], R_arr))
        ]
        if not match:
            got = "" if R_arr is None else f", m = {R_arr.shape[0]}, R = {R_arr.tolist()}"
            raise ValueError(
                f"no shipped {kind!r} surrogate is trained for n = {n}{got}; shipped: "
                f"{describe_shipped(kind)}"
            )
        pt = match[0]
    if pt not in _LOADED:
        if not pt.is_file():
            raise ValueError(f"shipped checkpoint {pt} not found")
        _LOADED[pt] = Surrogate.load(pt)
    return _LOADED[pt]
