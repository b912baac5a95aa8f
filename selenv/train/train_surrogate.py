"""Train an LDMV or LPECMV fusion surrogate (Chen & Kia 2022, Sec. III-IV) on simulator data.

Readable top to bottom (CleanRL style): the :class:`Config` dataclass is the command line, then
data (generated with :func:`selenv.learned.surrogate_data.generate_dataset` or loaded with
``--data``),
a seeded train / validation / test split (paper: 40000 / 5000 / 5000), training with Table II's
hyper-parameters by default (but Adam for LDMV, see :data:`DEFAULT_OPTIMIZER`) behind a tqdm
bar, TensorBoard under ``runs/``, early stopping on the validation loss (best weights kept),
then test metrics and the checkpoint ``<out>.pt`` with its metadata ``<out>.json``:

* LDMV: MSE, ``R`` of the fit (Pearson correlation of ``omega_hat`` and ``omega*``, Fig. 6a),
  ``R^2`` and the DMV cost gap ``log det Pbar(omega_hat) - log det Pbar(omega*) >= 0``.
* LPECMV: MSE and the objective gap of Fig. 2, ``log det P(C_hat) - log det P(C*) <= 0``
  (``C*`` maximises eq. 8a, so a learned ``C`` is less conservative by that many nats).

    python -m selenv.train.train_surrogate --kind ldmv       # -> runs/surrogates/ldmv.pt + .json
    python -m selenv.train.train_surrogate --kind lpecmv --method 1   # -> lpecmv_method1.pt there
    python -m selenv.train.train_surrogate --kind lpecmv --bearing-sigma-deg 2  # lpecmv_m2.pt
                              # range + bearing (m = 2), R = diag(0.1^2, (2 deg)^2)
    python -m selenv.train.train_surrogate --config configs/ldmv.toml \
        --out checkpoints/ldmv.pt --force                      # the shipped checkpoint, again
    tensorboard --logdir runs

An existing output (``<out>.pt``, ``<out>.json``, ``<out>.resume.pt``, ``--save-data``) is
refused before any data is generated, unless ``--force`` (or ``--resume``); the shipped
surrogates' runs are ``configs/ldmv.toml``, ``configs/lpecmv*.toml``; with range + bearing
(m = 2) ``configs/ldmv_m2.toml``, ``configs/lpecmv_m2.toml``.

Nothing a run produces is lost or half-written:

* every file (weights and metadata as a pair, the dataset, the resume state) is written
  atomically (:mod:`selenv.atomic`): a killed or failed write leaves the previous file
  byte-identical; the metadata records the weights' SHA-256, so a mismatched pair is refused
  by :meth:`~selenv.learned.surrogates.Surrogate.load`;
* SIGINT / SIGTERM while training: the current epoch finishes, then the best weights so far
  are saved (metadata ``"complete": false``, ``"interrupted": "SIGINT"``, the epochs done) with
  the resume state ``<out>.resume.pt``, and the command exits 130 / 143 with one line; a
  second signal abandons at once (outputs untouched). ``--checkpoint-every K`` writes the
  resume state every K epochs; ``--resume <out>.resume.pt`` (same options) continues with the
  weights, optimiser, schedule, batch order (RNG), epoch count and best-so-far, and ends with
  the same weights as an uninterrupted run; ``--max-minutes M`` stops the same way after the
  first epoch that ends past ``M`` minutes (``"interrupted": "max-minutes"``, exit 75);
* a failed write (full disk, file-size limit) is one line and exit code 1; usage errors
  (bad options, an unreadable or oversized ``--data``, a bad ``--resume``) are one line and
  exit code 2, found before any work; another run writing the same ``--out`` is exit 2;
* work is bounded before it starts: ``--samples`` <= ``--max-samples`` (200,000), ``--epochs``
  <= ``--max-epochs`` (10,000), hidden widths <= ``--max-width`` (4,096, at most 64 layers and
  50 million parameters), ``--batch-size`` <= ``--max-batch-size`` (65,536), ``--workers`` <=
  256; a ``--data`` file is checked against ``--max-samples`` from its zip directory and array
  headers before it is inflated;
* the generation pool's workers die with this process, even after ``kill -9``
  (:class:`selenv.parallel.ProcessExecutor`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import shlex
import sys
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm.auto import tqdm

from selenv.atomic import OutputLock, describe_os_error, probe_writable, write_bytes
from selenv.core.fusion import dmv_update, pecmv_update
from selenv.exits import DeferredSignals, UsageError, guarded_main
from selenv.learned.config import arg, check_outputs, parse_config
from selenv.learned.surrogate_data import (
    MAX_ROWS,
    DatasetTooLargeError,
    GenerationConfig,
    SurrogateDataset,
    generate_dataset,
    load_dataset,
    n_features,
    save_dataset,
)
from selenv.learned.surrogates import (
    C_SCALE,
    KINDS,
    MAX_HIDDEN_LAYERS,
    MAX_PARAMETERS,
    METHODS,
    TABLE_II,
    Surrogate,
    barrier_loss,
    n_parameters,
)
from selenv.learned.tensor_load import load_tensors
from selenv.learned.trainer import (
    BUDGET,
    RunStop,
    TrainingBudgetReached,
    check_max_minutes,
    run_arg,
)
from selenv.parallel import make_executor
from selenv.parallel.errors import ExecutorError, WorkerDiedError
from selenv.untrusted import NotParsedError, loads_json

#: Table II's optimisers except LDMV: its SGD (lr 0.05, batch 256) stays at the mean on our data
#: (test R 0.16; 0.24 with momentum 0.9) while Adam at the same lr reaches R 0.92 (50k samples,
#: seed 0). ``--optimizer sgd`` restores Table II.
DEFAULT_OPTIMIZER = {"ldmv": "adam", "lpecmv": str(TABLE_II["lpecmv"]["optimizer"])}
SCRIPT = "selenv.train.train_surrogate"
PROG = f"python -m {SCRIPT}"
#: format tag of the resume state ``<out>.resume.pt``
RESUME_FORMAT = "selenv-surrogate-resume-v1"
#: fixed ceiling of --workers (processes or Ray tasks in flight)
MAX_WORKERS = 256
#: rough memory per dataset row (arrays, features, float32 copies) for the --samples estimate
_BYTES_PER_ROW = 4096
#: options that may differ between a run and its --resume (they do not change the result)
RESUME_FREE = frozenset({
    "out", "force", "progress", "tensorboard_dir", "torch_threads", "checkpoint_every",
    "resume", "max_samples", "max_epochs", "max_width", "max_batch_size", "workers",
    "executor", "address", "save_data", "max_minutes",
})  # fmt: skip
#: test hook: called with the number of epochs done after each epoch (None: nothing)
_after_epoch: Callable[[int], None] | None = None
#: where a run writes without --out: runs/surrogates/<name>.pt (never checkpoints/)
DEFAULT_OUT_DIR = "runs/surrogates"


@dataclass
class Config:
    """Every knob of a run; each field is a ``--kebab-case`` command-line option."""

    kind: str = arg("ldmv", "surrogate: ldmv (omega of DMV) or lpecmv (C of PECMV)")
    method: int = arg(3, "LPECMV output method of Table I (1, 2, 3); ldmv ignores it")
    # data
    samples: int = arg(50_000, "dataset rows to generate (ignored with --data)")
    bearing_sigma_deg: float | None = arg(
        None,
        "relative bearing noise (deg) of the generated scenarios: range + bearing, m = 2 "
        "(unset: range only, m = 1; ignored with --data)",
    )
    data: str = arg("", "load this .npz dataset instead of generating one")
    save_data: str = arg("", "also write the generated dataset to this .npz")
    workers: int = arg(0, "generation processes / Ray tasks in flight (0: all cores)")
    executor: str = arg("", "local | process | ray (empty: a local pool of --workers processes)")
    address: str = arg(
        "", "Ray cluster to join with --executor ray (empty: start a local instance)"
    )
    val_fraction: float = arg(0.1, "validation share of the rows (early stopping)")
    test_fraction: float = arg(0.1, "test share of the rows (the metrics in the JSON)")
    # model and training (0 / "": Table II)
    hidden: str = arg("", "comma-separated hidden widths, e.g. 256,256,256 (empty: Table II)")
    activation: str = arg("", "sigmoid | tanh | relu (empty: Table II)")
    epochs: int = arg(200, "maximum training epochs")
    batch_size: int = arg(0, "minibatch size (0: Table II)")
    lr: float = arg(0.0, "learning rate; the peak one with --lr-schedule onecycle (0: Table II)")
    optimizer: str = arg("", "sgd | adam (empty: adam for ldmv, Table II's for lpecmv)")
    momentum: float = arg(0.0, "SGD momentum (--optimizer sgd only)")
    lr_schedule: str = arg("constant", "constant | onecycle (cosine one-cycle peaking at --lr)")
    barrier_lambda: float = arg(1e-3, "weight of the barrier term of eq. 14 (method 1 only)")
    objective_loss: bool = arg(
        False,
        "lpecmv method 3 only: train on the PECMV objective eq. 8a itself (mean gap "
        "log det P_i+(C*) - log det P_i+(C_hat)) instead of the MSE to diag(C*)",
    )
    patience: int = arg(20, "epochs without a better validation loss before stopping")
    seed: int = arg(0, "seed of the data generation, the split, the initialisation and batches")
    # outputs
    out: str = arg(
        "",
        f"checkpoint path (.pt; its metadata goes next to it as .json); empty: "
        f"{DEFAULT_OUT_DIR}/<name>.pt with name ldmv, lpecmv (method 3) or lpecmv_method<m>",
    )
    force: bool = arg(False, "overwrite existing outputs (--out .pt / .json, --save-data)")
    tensorboard_dir: str = arg("runs", "TensorBoard log folder (empty: no TensorBoard logs)")
    progress: bool = run_arg("progress", True)
    torch_threads: int = arg(1, "torch CPU threads of this process")
    # interruptions and resuming
    checkpoint_every: int = arg(
        0,
        "write the resume state <out>.resume.pt every K epochs (0: only when SIGINT/SIGTERM "
        "stops the run)",
    )
    resume: str = arg(
        "",
        "continue the run whose resume state is this file (<out>.resume.pt; same options; "
        "the outputs may exist)",
    )
    max_minutes: float | None = run_arg("max_minutes", None, unit="an epoch")
    # ceilings (bounded work, checked before anything runs)
    max_samples: int = arg(MAX_ROWS, "ceiling of --samples and of the rows of a --data file")
    max_epochs: int = arg(10_000, "ceiling of --epochs")
    max_width: int = arg(4_096, "ceiling of each --hidden width")
    max_batch_size: int = arg(65_536, "ceiling of --batch-size")


def parse_args(argv: list[str] | None = None) -> Config:
    """Build a :class:`Config` from the command line (one option per field, ``--config``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def checkpoint_name(cfg: Config) -> str:
    """``ldmv``, ``lpecmv`` (method 3) or ``lpecmv_method<m>``; ``_m2`` appended with bearings."""
    method = cfg.method if cfg.kind == "lpecmv" else 3
    name = cfg.kind if cfg.kind == "ldmv" or method == 3 else f"lpecmv_method{method}"
    return name if cfg.bearing_sigma_deg is None or cfg.data else f"{name}_m2"


def output_path(cfg: Config) -> Path:
    """The checkpoint's ``.pt`` path: ``--out`` or ``runs/surrogates/<name>.pt``."""
    return Path(cfg.out or f"{DEFAULT_OUT_DIR}/{checkpoint_name(cfg)}.pt").with_suffix(".pt")


def resume_path(cfg: Config) -> Path:
    """Where the run keeps its resume state: ``<out>.resume.pt`` next to the checkpoint."""
    pt = output_path(cfg)
    return pt.with_name(f"{pt.stem}.resume.pt")


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: ``.pt`` and ``.json`` (and ``--save-data``'s ``.npz``).

    The resume state :func:`resume_path` is checked with them before the run.
    """
    pt = output_path(cfg)
    files = [pt, pt.with_suffix(".json")]
    if cfg.save_data and not cfg.data:
        data = Path(cfg.save_data)
        files.append(data if data.suffix == ".npz" else Path(f"{data}.npz"))  # numpy's rule
    return files


def targets(ds: SurrogateDataset, kind: str, method: int) -> np.ndarray:
    """Labels: ``omega`` (B,), ``diag C*`` (B, n) for method 3, ``vec C*`` (B, n^2) else."""
    if kind == "ldmv":
        return ds.omega
    return ds.C_diag if method == 3 else ds.C.reshape(len(ds), -1)


def objective_terms(ds: SurrogateDataset) -> dict[str, torch.Tensor]:
    """float64 tensors of every row for :func:`pecmv_log_det` (and the optimum ``opt``)."""
    P_i, P_j = torch.from_numpy(ds.P_i), torch.from_numpy(ds.P_j)
    return {
        "P_i": P_i,
        "P_j": P_j,
        "L_i": torch.linalg.cholesky(P_i),
        "L_j": torch.linalg.cholesky(P_j),
        "H_i": torch.from_numpy(ds.H_i),
        "H_j": torch.from_numpy(ds.H_j),
        "R": torch.from_numpy(np.asarray(ds.R, dtype=np.float64)),
        "opt": torch.from_numpy(ds.log_det_pecmv),
    }


def pecmv_log_det(c: torch.Tensor, t: dict[str, torch.Tensor], rows: torch.Tensor) -> torch.Tensor:
    """Eq. (8a) per row, differentiable in the diagonal ``c`` (B, n) of ``C``.

    ``X = L_i diag(c) L_j^T`` (eq. 11), ``U = P_i H_i^T + X H_j^T``,
    ``S = H_i U + H_j (X^T H_i^T + P_j H_j^T) + R``, ``P_i+ = P_i - U S^-1 U^T`` (eq. 9): the
    update of :func:`selenv.core.fusion.pecmv_update` with a given ``C``; returns
    ``log det P_i+`` (B,) in float64.
    """
    P_i, P_j, L_i, L_j = (t[k][rows] for k in ("P_i", "P_j", "L_i", "L_j"))
    H_i, H_j = t["H_i"][rows], t["H_j"][rows]
    X = (L_i * c.to(torch.float64)[:, None, :]) @ L_j.transpose(1, 2)
    U = P_i @ H_i.transpose(1, 2) + X @ H_j.transpose(1, 2)
    V = X.transpose(1, 2) @ H_i.transpose(1, 2) + P_j @ H_j.transpose(1, 2)
    S = H_i @ U + H_j @ V + t["R"]
    P = P_i - U @ torch.linalg.solve(0.5 * (S + S.transpose(1, 2)), U.transpose(1, 2))
    return torch.linalg.slogdet(0.5 * (P + P.transpose(1, 2)))[1]


def evaluate(sur: Surrogate, ds: SurrogateDataset) -> dict[str, float]:
    """Test metrics of ``sur`` on ``ds`` (see the module docstring)."""
    args = (ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    if sur.kind == "ldmv":
        w_hat, w = sur.predict_omega(*args), ds.omega

        def dmv_cost(k: int, omega: float) -> float:
            return dmv_update(
                ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k], ds.R, omega=omega, validate=False
            ).log_det

        best = np.array([dmv_cost(k, float(w[k])) for k in range(len(ds))])
        gap = np.array([dmv_cost(k, float(w_hat[k])) for k in range(len(ds))]) - best
        gap_one = np.array([dmv_cost(k, 1.0) for k in range(len(ds))]) - best  # no update
        r = float(np.corrcoef(w_hat, w)[0, 1]) if np.std(w_hat) > 0 and np.std(w) > 0 else 0.0
        ss_res, ss_tot = float(np.sum((w_hat - w) ** 2)), float(np.sum((w - w.mean()) ** 2))
        return {
            "mse": float(np.mean((w_hat - w) ** 2)),
            "R": r,
            "R2": 1.0 - ss_res / ss_tot if ss_tot > 0 else 0.0,
            "dmv_cost_gap_mean": float(np.mean(gap)),
            "dmv_cost_gap_max": float(np.max(gap)),
            "dmv_cost_gap_omega1_mean": float(np.mean(gap_one)),  # baseline: never update
        }
    C_hat = sur.predict_C(*args)
    y = targets(ds, "lpecmv", sur.method)
    y_hat = np.diagonal(C_hat, axis1=1, axis2=2) if sur.method == 3 else C_hat.reshape(len(ds), -1)

    def pecmv_value(k: int, C: np.ndarray) -> float:
        return pecmv_update(
            ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k], ds.R, C=C, validate=False
        ).log_det

    gap = np.array([pecmv_value(k, C_hat[k]) for k in range(len(ds))]) - ds.log_det_pecmv
    zero = np.zeros((sur.n, sur.n))
    gap_zero = np.array([pecmv_value(k, zero) for k in range(len(ds))]) - ds.log_det_pecmv
    diag = [np.diag(np.diag(ds.C[k])) * C_SCALE for k in range(len(ds))]  # method 3's target
    gap_diag = np.array([pecmv_value(k, diag[k]) for k in range(len(ds))]) - ds.log_det_pecmv
    return {
        "mse": float(np.mean((y_hat - y) ** 2)),
        "objective_gap_mean": float(np.mean(gap)),
        "objective_gap_median": float(np.median(gap)),
        "objective_gap_min": float(np.min(gap)),
        "objective_gap_zero_C_mean": float(np.mean(gap_zero)),  # baseline: X = 0 (naive)
        "objective_gap_diag_C_star_mean": float(np.mean(gap_diag)),  # baseline: exact diag(C*)
        "max_norm_C": float(np.max(np.linalg.norm(C_hat, 2, axis=(1, 2)))),
    }


def parse_hidden(cfg: Config) -> tuple[int, ...] | None:
    """``--hidden`` as widths (``None``: Table II's), checked against the ceilings.

    Raises:
        UsageError: not comma-separated positive integers, more than 64 layers, a width over
            ``--max-width``, or more parameters than a surrogate may have.
    """
    if not cfg.hidden:
        return None
    try:
        hidden = tuple(int(h) for h in cfg.hidden.split(","))
    except ValueError:
        raise UsageError(f"--hidden must be comma-separated integers, got {cfg.hidden!r}") from None
    if min(hidden) < 1:
        raise UsageError(f"--hidden widths must be >= 1, got {cfg.hidden!r}")
    if len(hidden) > MAX_HIDDEN_LAYERS:
        raise UsageError(
            f"--hidden has {len(hidden)} layers, over the limit of {MAX_HIDDEN_LAYERS}"
        )
    if max(hidden) > cfg.max_width:
        raise UsageError(
            f"--hidden width {max(hidden):,} is over the ceiling of {cfg.max_width:,}; raise it "
            f"with --max-width {max(hidden)}"
        )
    n, m = 9, 2 if cfg.bearing_sigma_deg is not None else 1
    count = n_parameters(n_features(n, m), hidden, n * n)
    if count > MAX_PARAMETERS:
        raise UsageError(
            f"--hidden {cfg.hidden} gives about {count:,} parameters, over the limit of "
            f"{MAX_PARAMETERS:,} a surrogate checkpoint may have"
        )
    return hidden


def check_config(cfg: Config) -> None:
    """Refuse, before any work, option combinations and sizes the training cannot run.

    Every size that multiplies work or memory is checked against its ceiling (the message
    names the option, the ceiling and the ``--max-...`` option that raises it).

    Raises:
        UsageError: (a ``ValueError``) naming the option.
    """
    if cfg.kind not in KINDS:
        raise UsageError(f"--kind must be one of {KINDS}, got {cfg.kind!r}")
    check_max_minutes(cfg.max_minutes)
    if cfg.method not in METHODS:
        raise UsageError(f"--method must be one of {METHODS}, got {cfg.method}")
    if cfg.objective_loss and (cfg.kind, cfg.method) != ("lpecmv", 3):
        raise UsageError("--objective-loss needs --kind lpecmv --method 3")
    if cfg.bearing_sigma_deg is not None and not 1e-3 <= cfg.bearing_sigma_deg <= 90.0:
        raise UsageError(
            "--bearing-sigma-deg must be in [0.001, 90] deg (or unset), got "
            f"{cfg.bearing_sigma_deg}"
        )
    if not (
        0 < cfg.val_fraction and 0 < cfg.test_fraction and cfg.val_fraction + cfg.test_fraction < 1
    ):
        raise UsageError("--val-fraction and --test-fraction must be > 0 with a sum < 1")
    if cfg.optimizer not in ("", "sgd", "adam"):
        raise UsageError(f"--optimizer must be sgd or adam, got {cfg.optimizer!r}")
    if cfg.lr_schedule not in ("constant", "onecycle"):
        raise UsageError(f"--lr-schedule must be constant or onecycle, got {cfg.lr_schedule!r}")
    for name in ("max_samples", "max_epochs", "max_width", "max_batch_size"):
        if getattr(cfg, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(cfg, name)}")
    for name in ("epochs", "batch_size", "patience", "checkpoint_every", "workers"):
        if getattr(cfg, name) < 0:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 0, got {getattr(cfg, name)}")
    if not cfg.data and not 1 <= cfg.samples <= cfg.max_samples:
        if cfg.samples < 1:
            raise UsageError(f"--samples must be >= 1, got {cfg.samples}")
        gib = cfg.samples * _BYTES_PER_ROW / 2**30
        raise UsageError(
            f"--samples {cfg.samples:,} is over the ceiling of {cfg.max_samples:,} rows (about "
            f"{gib:,.1f} GiB of memory for the dataset); raise it with --max-samples "
            f"{cfg.samples}"
        )
    if cfg.epochs > cfg.max_epochs:
        raise UsageError(
            f"--epochs {cfg.epochs:,} is over the ceiling of {cfg.max_epochs:,}; raise it with "
            f"--max-epochs {cfg.epochs}"
        )
    if cfg.batch_size > cfg.max_batch_size:
        raise UsageError(
            f"--batch-size {cfg.batch_size:,} is over the ceiling of {cfg.max_batch_size:,}; "
            f"raise it with --max-batch-size {cfg.batch_size}"
        )
    if cfg.workers > MAX_WORKERS:
        raise UsageError(f"--workers {cfg.workers} is over the limit of {MAX_WORKERS}")
    parse_hidden(cfg)


def load_or_generate(cfg: Config) -> SurrogateDataset:
    """The dataset: ``--data`` loaded, or generated (on ``--executor`` if given) and saved.

    Raises:
        UsageError: an unreadable, malformed or oversized ``--data`` file (checked before it is
            inflated), or a bad ``--executor`` / ``--address``.
        OSError: ``--save-data`` could not be written (the message names that file).
    """
    if cfg.data:
        try:
            return load_dataset(cfg.data, max_rows=cfg.max_samples)
        except DatasetTooLargeError as exc:
            raise UsageError(f"--data: {exc}; raise it with --max-samples") from None
        except ValueError as exc:
            raise UsageError(f"--data: {' '.join(str(exc).split())}") from None
    executor = None
    if cfg.executor or cfg.address:
        try:
            executor = make_executor(
                cfg.executor or "process",
                num_workers=cfg.workers or None,
                address=cfg.address or None,
            )
        except ExecutorError as exc:  # unknown executor, Ray missing, bad address
            raise UsageError(" ".join(str(exc).split())) from None
    try:
        with executor or contextlib.nullcontext():
            ds = generate_dataset(
                cfg.samples,
                seed=cfg.seed,
                workers=cfg.workers,
                gen=GenerationConfig(bearing_sigma_deg=cfg.bearing_sigma_deg),
                progress=cfg.progress,
                executor=executor,
            )
    except ExecutorError as exc:  # an unreachable --address is found when Ray starts
        raise UsageError(" ".join(str(exc).split())) from None
    if cfg.save_data:
        save_dataset(ds, cfg.save_data)
    return ds


def split_rows(n_rows: int, cfg: Config) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(train, val, test)`` row indices: a permutation seeded by ``cfg.seed``, test first."""
    n_val = max(1, int(cfg.val_fraction * n_rows))
    n_test = max(1, int(cfg.test_fraction * n_rows))
    if n_rows - n_val - n_test < 1:
        raise ValueError(f"dataset of {n_rows} rows is too small to split")
    perm = np.random.default_rng(cfg.seed).permutation(n_rows)
    return perm[n_test + n_val :], perm[n_test : n_test + n_val], perm[:n_test]


def make_optimizer(
    cfg: Config, net: torch.nn.Module, opt_name: str, lr: float, total_steps: int
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler | None]:
    """The optimizer (Table II: SGD with momentum, or Adam) and the learning-rate schedule."""
    opt: torch.optim.Optimizer
    if opt_name == "sgd":
        opt = torch.optim.SGD(net.parameters(), lr=lr, momentum=cfg.momentum)
    else:
        opt = torch.optim.Adam(net.parameters(), lr=lr)
    if cfg.lr_schedule == "onecycle":
        return opt, torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=lr, total_steps=max(1, total_steps)
        )
    return opt, None


@dataclasses.dataclass
class FitResult:
    """What :func:`fit` reports: the epochs run, the best epoch and its validation loss.

    ``interrupted`` is ``"SIGINT"`` / ``"SIGTERM"`` when a signal stopped the run after an
    epoch (``None`` otherwise); ``resume_state`` is then the serialised resume state at that
    epoch (see :func:`resume_blob`), for the caller to write after the weights.
    """

    epochs_run: int
    best_epoch: int
    best_val_loss: float
    wall_seconds: float
    interrupted: str | None = None
    resume_state: bytes | None = None


def resume_blob(state: dict[str, Any]) -> bytes:
    """``state`` serialised with ``torch.save`` (tensors, numbers, strings: ``weights_only``)."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def read_resume(path: str | Path) -> dict[str, Any]:
    """The resume state written by an earlier run (``weights_only``: no code runs).

    Raises:
        UsageError: missing or unreadable file, or not a resume state.
    """
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"--resume {path}: no such file")
    try:  # truncated, junk or hostile files alike: one line, nothing run
        state = load_tensors(
            path, f"--resume {path}", kind="a readable resume state", junk="a readable resume state"
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not isinstance(state, dict) or state.get("format") != RESUME_FORMAT:
        raise UsageError(f"--resume {path}: not a resume state of {SCRIPT}")
    return state


def fit(
    cfg: Config,
    net: torch.nn.Module,
    data: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    optim: tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler | None],
    batch_size: int,
    name: str,
    writer: SummaryWriter | None,
    *,
    stop: DeferredSignals | None = None,
    resume: dict[str, Any] | None = None,
    checkpoint: Callable[[bytes], object] | None = None,
    stamp: dict[str, Any] | None = None,
) -> FitResult:
    """Mini-batch training with early stopping on the validation loss; best weights restored.

    ``data`` is ``(X_train, Y_train, X_val, Y_val)``; batches are drawn by a generator seeded
    with ``cfg.seed``; stops after ``cfg.patience`` epochs without a better validation loss.

    ``stop`` (a :class:`~selenv.exits.DeferredSignals`) is checked after every epoch: when
    set, training ends there (``FitResult.interrupted``) with the resume state of that epoch.
    ``resume`` (from :func:`read_resume`) restores the weights, optimiser, schedule, batch
    generator, epoch count and best-so-far, so the run continues exactly where it stopped.
    ``checkpoint`` receives the serialised resume state every ``cfg.checkpoint_every`` epochs;
    ``stamp`` is stored in it (the config and data fingerprint a resume must match).
    """
    Xt, Yt, Xv, Yv = data
    opt, sched = optim
    gen = torch.Generator().manual_seed(cfg.seed)
    best, best_state, best_epoch, first = float("inf"), None, -1, 0
    spent = 0.0
    if resume is not None:
        net.load_state_dict(resume["net"])
        opt.load_state_dict(resume["optimizer"])
        if sched is not None and resume.get("scheduler") is not None:
            sched.load_state_dict(resume["scheduler"])
        gen.set_state(resume["generator"])
        best, best_epoch = float(resume["best"]), int(resume["best_epoch"])
        best_state = resume["best_state"]
        first, spent = int(resume["epochs_done"]), float(resume.get("wall_seconds", 0.0))
    epoch = first - 1
    start = time.perf_counter()

    def state(done: int) -> bytes:
        return resume_blob({
            "format": RESUME_FORMAT, "epochs_done": done, "net": net.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict() if sched is not None else None,
            "generator": gen.get_state(), "best": best, "best_epoch": best_epoch,
            "best_state": best_state, "wall_seconds": spent + time.perf_counter() - start,
            **(stamp or {}),
        })  # fmt: skip

    interrupted, blob = None, None
    bar = tqdm(
        range(first, cfg.epochs),
        desc=f"train {name}",
        unit="epoch",
        disable=not cfg.progress,
        initial=first,
        total=cfg.epochs,
    )
    for epoch in bar:
        net.train()
        total = 0.0
        for idx in torch.randperm(len(Xt), generator=gen).split(batch_size):
            loss = loss_fn(net(Xt[idx]), Yt[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            if sched is not None:
                sched.step()
            total += float(loss.detach()) * len(idx)
        net.eval()
        with torch.no_grad():
            val_loss = float(loss_fn(net(Xv), Yv))
        train_loss = total / len(Xt)
        if writer is not None:
            writer.add_scalar("loss/train", train_loss, epoch)
            writer.add_scalar("loss/val", val_loss, epoch)
        bar.set_postfix(train=f"{train_loss:.3g}", val=f"{val_loss:.3g}")
        improved = val_loss < best
        if improved:
            best, best_epoch = val_loss, epoch
            best_state = {k: v.clone() for k, v in net.state_dict().items()}
        if _after_epoch is not None:
            _after_epoch(epoch + 1)
        if not improved and epoch - best_epoch >= cfg.patience:
            break  # early stopping: the run is complete
        if isinstance(stop, RunStop) and epoch + 1 < cfg.epochs:
            stop.check_budget()  # a spent --max-minutes stops here, as a signal does
        if stop is not None and stop.signal is not None:
            interrupted, blob = stop.signal, state(epoch + 1)
            break
        every = cfg.checkpoint_every
        if checkpoint is not None and every and (epoch + 1) % every == 0:
            checkpoint(state(epoch + 1))
    bar.close()
    if best_state is not None:
        net.load_state_dict(best_state)
    epochs_run = epoch + 1 if cfg.epochs else 0
    wall = spent + time.perf_counter() - start
    return FitResult(epochs_run, best_epoch, best, wall, interrupted, blob)


def loss_name(cfg: Config, method: int) -> str:
    """The loss :func:`main` trains with: eq. (8a), the barrier of eq. (14), or Table II's MSE."""
    if cfg.objective_loss:
        return "objective eq. 8a"
    return "barrier eq. 14" if method == 1 and cfg.kind == "lpecmv" else "mse"


def _stamp(cfg: Config, X: np.ndarray) -> dict[str, Any]:
    """What a resume must match: the result-changing options and the features' SHA-256."""
    options = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in RESUME_FREE}
    return {
        "config": json.dumps(options, sort_keys=True),
        "data_sha256": hashlib.sha256(np.ascontiguousarray(X).tobytes()).hexdigest(),
    }


def _check_resume(cfg: Config, state: dict[str, Any], stamp: dict[str, Any]) -> None:
    """Refuse a resume state of another run (names the first differing option, or the data)."""
    try:  # bounded: the state is a file of the user's
        saved = loads_json(str(state.get("config")), f"--resume {cfg.resume}: config")
    except NotParsedError:
        saved = None
    except ValueError as exc:  # too large or nested too deeply
        raise UsageError(str(exc)) from None
    if not isinstance(saved, dict):
        raise UsageError(f"--resume {cfg.resume}: the state records no options")
    now = json.loads(stamp["config"])
    for key in sorted(set(saved) | set(now)):
        if saved.get(key) != now.get(key):
            raise UsageError(
                f"--resume {cfg.resume}: it was run with --{key.replace('_', '-')} "
                f"{saved.get(key)!r}, this run has {now.get(key)!r}; resume with the same options"
            )
    if state.get("data_sha256") != stamp["data_sha256"]:
        raise UsageError(
            f"--resume {cfg.resume}: the dataset differs from the one the run was trained on "
            "(same --data file, or the same --samples / --seed / --bearing-sigma-deg)"
        )


def _stop_line(sig: str) -> str:
    if sig == BUDGET:
        return "stopped at its --max-minutes budget"
    return "interrupted (SIGINT)" if sig == "SIGINT" else f"terminated ({sig})"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Generate or load data, train, save the checkpoint and its metadata; return the metadata.

    Raises:
        UsageError: a usage error found before any work (a ``ValueError``; exit code 2 from
            the command line).
        OutputBusyError: another run is writing the same ``--out``.
        OSError: a write failed; its ``filename`` is the output (exit code 1).

    A SIGINT / SIGTERM while training saves the best weights so far (``"complete": false``)
    and the resume state, prints one line on stderr and returns the metadata, whose
    ``"interrupted"`` names the signal (:func:`cli` exits 130 / 143).
    """
    cfg = parse_args(argv)
    check_outputs(
        PROG,
        [*outputs(cfg), resume_path(cfg)],
        force=cfg.force or bool(cfg.resume),
        folders=[cfg.tensorboard_dir] if cfg.tensorboard_dir else [],
    )
    check_config(cfg)
    out = output_path(cfg)
    try:
        probe_writable(out)
    except OSError as exc:
        raise UsageError(describe_os_error(exc, out)) from None
    resume = read_resume(cfg.resume) if cfg.resume else None
    with OutputLock(out):
        return _run(cfg, argv, out, resume)


def _run(
    cfg: Config, argv: list[str] | None, out: Path, resume: dict[str, Any] | None
) -> dict[str, Any]:
    """The run behind :func:`main`, once the options and outputs were checked and locked."""
    t2 = TABLE_II[cfg.kind]
    batch_size = cfg.batch_size or int(t2["batch_size"])
    lr = cfg.lr or float(t2["lr"])
    opt_name = cfg.optimizer or DEFAULT_OPTIMIZER[cfg.kind]
    method = cfg.method if cfg.kind == "lpecmv" else 3
    name = checkpoint_name(cfg)
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)

    # 1. data
    start = time.perf_counter()
    ds = load_or_generate(cfg)
    gen_seconds = time.perf_counter() - start
    train, val, test = split_rows(len(ds), cfg)
    X = ds.features().astype(np.float32)
    Y = targets(ds, cfg.kind, method).astype(np.float32)
    Xt, Yt = torch.from_numpy(X[train]), torch.from_numpy(Y[train])
    Xv, Yv = torch.from_numpy(X[val]), torch.from_numpy(Y[val])
    terms = objective_terms(ds) if cfg.objective_loss else {}
    if cfg.objective_loss:  # the "labels" are row numbers into the problems of `terms`
        Yt, Yv = torch.from_numpy(train), torch.from_numpy(val)
    stamp = _stamp(cfg, X)
    if resume is not None:
        _check_resume(cfg, resume, stamp)

    # 2. model (input standardisation from the training split only)
    n, m = int(ds.header["n"]), int(ds.header["m"])
    sur = Surrogate.create(
        cfg.kind,
        method=method,
        n=n,
        m=m,
        hidden=parse_hidden(cfg),
        activation=cfg.activation or None,
    )
    sur.set_normalisation(X[train])
    steps_per_epoch = -(-len(train) // batch_size)
    optim = make_optimizer(cfg, sur.net, opt_name, lr, cfg.epochs * steps_per_epoch)

    def loss_fn(pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if cfg.objective_loss:  # mean gap to the optimum of eq. (8a), >= 0
            return torch.mean(terms["opt"][y] - pecmv_log_det(pred, terms, y))
        if method == 1 and cfg.kind == "lpecmv":
            return barrier_loss(pred, y, cfg.barrier_lambda)
        return torch.mean((pred - y) ** 2)  # MSE (Table II)

    # 3. train: early stopping on the validation loss, best weights restored; SIGINT/SIGTERM
    # stop after the current epoch and keep the best weights so far
    log_dir = Path(cfg.tensorboard_dir) / f"surrogate_{name}_{cfg.seed}_{int(time.time())}"
    writer = SummaryWriter(str(log_dir)) if cfg.tensorboard_dir else None
    state_path = resume_path(cfg)
    with RunStop(cfg.max_minutes) as stop:
        result = fit(
            cfg, sur.net, (Xt, Yt, Xv, Yv), loss_fn, optim, batch_size, name, writer,
            stop=stop, resume=resume, checkpoint=lambda blob: write_bytes(state_path, blob),
            stamp=stamp,
        )  # fmt: skip

        # 4. test metrics (skipped when interrupted), checkpoint and metadata
        complete = result.interrupted is None
        metrics = evaluate(sur, ds.subset(test)) if complete else None
        if writer is not None:
            for k, v in (metrics or {}).items():
                writer.add_scalar(f"test/{k}", v, result.best_epoch)
            writer.close()
        sur.meta.update(
            {
                "complete": complete,
                "R": ds.R.tolist(),
                "training_data": {
                    **{k: ds.header.get(k) for k in ("format", "count", "seed", "generation")},
                    "label_stats": ds.header.get("label_stats"),
                    "source": cfg.data or "generated",
                    "split": {"train": len(train), "val": len(val), "test": len(test)},
                    "generation_seconds": round(gen_seconds, 1),
                },
                "training": {
                    "command": f"{PROG} " + shlex.join(sys.argv[1:] if argv is None else argv),
                    "config": dataclasses.asdict(cfg),
                    "optimizer": opt_name,
                    "lr_schedule": cfg.lr_schedule,
                    "momentum": cfg.momentum if opt_name == "sgd" else None,
                    "lr": lr,
                    "batch_size": batch_size,
                    "loss": loss_name(cfg, method),
                    "barrier_lambda": cfg.barrier_lambda if method == 1 else None,
                    "epochs_max": cfg.epochs,
                    "epochs_run": result.epochs_run,
                    "best_epoch": result.best_epoch,
                    "best_val_loss": result.best_val_loss,
                    "patience": cfg.patience,
                    "seed": cfg.seed,
                    "wall_seconds": round(result.wall_seconds, 1),
                    "tensorboard": str(log_dir) if writer is not None else None,
                    "resumed_from": cfg.resume or None,
                },
                "metrics": {"test": metrics},
            }
        )
        if not complete:
            sur.meta["interrupted"] = result.interrupted
        bearing = (ds.header.get("generation") or {}).get("bearing_sigma_deg")
        if bearing is not None:  # m = 2: the bearing noise of R[1, 1], in the scenario's unit
            sur.meta["bearing_sigma_deg"] = bearing
        sur.save(out)
        if result.resume_state is not None:
            write_bytes(state_path, result.resume_state)
        elif state_path.exists():  # complete: the resume state of this output is obsolete
            state_path.unlink()
        meta = json.loads(out.with_suffix(".json").read_text())
        late = stop.signal  # a signal during the metrics or the save: kept, then reported
    if result.interrupted is not None:
        print(
            f"{PROG}: {_stop_line(result.interrupted)} after {result.epochs_run} of "
            f"{cfg.epochs} epochs; best weights so far (epoch {result.best_epoch + 1}) saved "
            f"to {out} (incomplete); continue with --resume {state_path}",
            file=sys.stderr,
        )
        return meta
    print(json.dumps({"checkpoint": str(out), "metrics": metrics}, indent=2))
    if late is not None:
        meta["interrupted"] = late  # the outputs are complete; only the exit code says so
        print(f"{PROG}: {_stop_line(late)} after the run completed; {out} saved", file=sys.stderr)
    return meta


def _exit_code(meta: dict[str, Any]) -> int:
    sig = meta.get("interrupted")
    codes = {"SIGINT": 130, "SIGTERM": 143, BUDGET: TrainingBudgetReached.exit_code}
    return codes.get(str(sig), 0) if sig else 0


def _cli_main(argv: list[str] | None = None) -> int:
    """:func:`main` as a command: its exit code, one line for a pool worker that died."""
    try:
        return _exit_code(main(argv))
    except (WorkerDiedError, BrokenProcessPool) as exc:
        print(f"{PROG}: data generation failed: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1


def cli(argv: list[str] | None = None) -> None:
    """Console-script entry point ``selenv-train-surrogate`` (same options as ``main``).

    Exit codes: 0 done; 2 a usage error or an output another run is writing (one line);
    1 a failed write or a worker that died (one line); 130 / 143 stopped by SIGINT / SIGTERM
    (the best weights so far and the resume state saved, one line); 75 stopped by
    ``--max-minutes`` (the same, resumable).
    """
    sys.exit(guarded_main(_cli_main, PROG, argv))


if __name__ == "__main__":
    cli()
