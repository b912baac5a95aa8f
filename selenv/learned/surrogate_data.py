"""Datasets for the learned fusion surrogates LDMV and LPECMV (Chen & Kia 2022, Sec. III-IV).

A sample is one relative-range update of the cooperative-localisation simulator
(:class:`~selenv.families.cooperative.scenario.CLSimulation`, ``model="ins"``: n = 9, m = 1): the
two
agents' beliefs after a single-step propagation, the Jacobians and the noise,
``(P_i, P_j, H_i, H_j, R)``, labelled by the exact batched solvers of ``selenv.core``:

* ``omega`` -- ``w*`` of DMV (eq. 6), :func:`~selenv.core.fusion.batch.dmv_omega_batch`;
* ``C`` and ``C_diag`` -- ``C* = L_i^-1 X* L_j^-T`` of PECMV (eqs. 8, 12) and its diagonal
  (the label of LPECMV method 3), :func:`~selenv.core.fusion.batch.pecmv_batch`;
* ``log_det_pecmv`` -- the optimal value of eq. (8a).

Generation. Task ``t`` draws a scenario from its own seed (``SeedSequence(seed).spawn``), runs
the simulator with a random fusion rule (dmv / pecmv / naive) for a random number of steps and
records the beliefs after every ``predict()`` for every relative pair; it then keeps a random
subset and perturbs it so the dataset covers far more than one trajectory's beliefs: each of
``P_i``, ``P_j`` is scaled by a log-uniform factor in ``[1/scale_range, scale_range]`` and its
position block rotated by a random rotation ``Q`` (``P -> T P T^T``, ``T = blkdiag(Q, I)``);
a fraction ``keep_raw`` of the rows is left unperturbed. ``R`` is the simulator's (fixed): the
features of eq. (13) do not contain ``R``, so a surrogate is valid for the ``R`` it was trained
on (kept in the header). Tasks run on a :mod:`selenv.parallel` executor (this process, a pool
of spawned single-threaded processes, or Ray tasks) behind a tqdm bar; each task's seed is
spawned from the master seed, so the result depends on neither the executor nor ``workers``.

File format (``.npz``, no pickles): ``P_i``, ``P_j`` (N, n, n), ``H_i``, ``H_j`` (N, m, n),
``R`` (m, m), ``omega`` (N,), ``C`` (N, n, n), ``C_diag`` (N, n), ``log_det_pecmv`` (N,), and
``header``: a JSON string ``{"format", "n", "m", "count", "seed", "R", "generation",
"label_stats", "selenv_version"}``.

Features (eq. 13), :func:`features`: the upper triangles of ``P_i`` and ``P_j`` and the entries
of ``H_i``, ``H_j`` -- ``n(n+1) + 2 m n`` numbers (108 for n = 9, m = 1), made scale-sane:
diagonal entries as ``log P_kk``, off-diagonal ones as correlations ``P_kl / sqrt(P_kk P_ll)``
(in [-1, 1]), Jacobian entries through ``symlog(x) = sign(x) log(1 + |x|)``. The standardisation
(mean, std over the training split) lives in the model (:mod:`selenv.learned.surrogates`).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

import selenv
from selenv.atomic import atomic_path
from selenv.core.fusion.batch import dmv_omega_batch, pecmv_batch
from selenv.core.linalg import FloatArray
from selenv.families.cooperative.scenario import CLConfig, CLSimulation, make_cl_problem
from selenv.parallel import Executor, LocalExecutor, ProcessExecutor

__all__ = [
    "ARRAYS",
    "FORMAT",
    "MAX_BYTES_PER_ROW",
    "MAX_ROWS",
    "DatasetTooLargeError",
    "GenerationConfig",
    "SurrogateDataset",
    "features",
    "generate_dataset",
    "label",
    "load_dataset",
    "n_features",
    "save_dataset",
]

FORMAT = "selenv-surrogate-data-v1"
#: arrays of a dataset file besides ``header``
ARRAYS = ("P_i", "P_j", "H_i", "H_j", "R", "omega", "C", "C_diag", "log_det_pecmv")
#: default ceiling on a dataset's rows (``load_dataset(max_rows=...)``, ``--max-samples``)
MAX_ROWS = 200_000
#: bytes one row may take in one array (4 KiB: a float64 (n, n) block up to n = 22)
MAX_BYTES_PER_ROW = 4096
_MAX_SMALL_BYTES = 1 << 20  # ``R`` and ``header``: at most 1 MiB each
_TINY = 1e-300  # floor of a variance inside the log (features stay finite for any finite input)


def n_features(n: int, m: int) -> int:
    """Length of a feature vector: two upper triangles and two Jacobians, ``n(n+1) + 2mn``."""
    return n * (n + 1) + 2 * m * n


@lru_cache(maxsize=8)
def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Row-major upper triangle of an n x n matrix as flat indices, and where its diagonal is."""
    iu, ju = np.triu_indices(n)
    return iu * n + ju, np.flatnonzero(iu == ju)


def _triangle(P: FloatArray) -> FloatArray:
    """(..., n(n+1)/2): ``log P_kk`` on the diagonal, correlations above it (row-major)."""
    n = P.shape[-1]
    flat, diag = _triu(n)
    d = np.maximum(np.diagonal(P, axis1=-2, axis2=-1), _TINY)
    s = np.sqrt(d)  # divide by s_k and s_l in turn: s_k s_l could overflow or underflow
    with np.errstate(over="ignore"):
        full = P / s[..., :, None] / s[..., None, :]  # finite off the diagonal: s >= 1e-150
    out = full.reshape(*P.shape[:-2], n * n)[..., flat]
    np.clip(out, -1.0, 1.0, out=out)
    out[..., diag] = np.log(d)
    return out


def _symlog(x: FloatArray) -> FloatArray:
    return np.sign(x) * np.log1p(np.abs(x))


def features(P_i: Any, P_j: Any, H_i: Any, H_j: Any) -> FloatArray:
    """Input vector of eq. (13) for a batch of fusion problems.

    Args:
        P_i: (B, n, n) covariance of agent i (symmetric; only the upper triangle is read).
        P_j: (B, n, n) covariance of agent j.
        H_i: (B, m, n) Jacobian w.r.t. agent i.
        H_j: (B, m, n) Jacobian w.r.t. agent j.

    Returns:
        (B, n(n+1) + 2mn) float64, laid out as ``[tri(P_i), tri(P_j), H_i.ravel(), H_j.ravel()]``
        with ``tri(P)`` the row-major upper triangle holding ``log P_kk`` on the diagonal and
        ``P_kl / sqrt(P_kk P_ll)`` (clipped to [-1, 1]) off it, and Jacobian entries as
        ``sign(x) log(1 + |x|)``. Finite for every finite input (variances are floored at
        1e-300 inside the log), so a surrogate's output constraint holds everywhere.

    Raises:
        ValueError: wrong shapes or non-finite entries (names the argument).
    """
    values = (P_i, P_j, H_i, H_j)
    arrs = {k: np.asarray(v, dtype=np.float64) for k, v in zip(_NAMES, values, strict=True)}
    Pi = arrs["P_i"]
    if Pi.ndim != 3 or Pi.shape[1] != Pi.shape[2] or Pi.shape[1] == 0:
        raise ValueError(f"P_i must be a (B, n, n) stack, got shape {Pi.shape}")
    Bn, n = Pi.shape[0], Pi.shape[1]
    Hi = arrs["H_i"]
    if Hi.ndim != 3 or Hi.shape[0] != Bn or Hi.shape[2] != n or Hi.shape[1] == 0:
        raise ValueError(f"H_i must be (B, m, n) = ({Bn}, m, {n}), got shape {Hi.shape}")
    m = Hi.shape[1]
    for name, shape in (("P_j", (Bn, n, n)), ("H_j", (Bn, m, n))):
        if arrs[name].shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {arrs[name].shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # one test first: finite sums are common
        total = sum(float(a.sum()) for a in arrs.values())
    if not np.isfinite(total):  # a NaN / inf entry, or finite entries whose sum overflows
        for name, a in arrs.items():
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite (no NaN/inf)")
    tri = _triangle(np.stack((Pi, arrs["P_j"]), axis=1)).reshape(Bn, -1)  # both in one pass
    H = np.concatenate((Hi.reshape(Bn, -1), arrs["H_j"].reshape(Bn, -1)), axis=1)
    return np.concatenate((tri, _symlog(H)), axis=1)


_NAMES = ("P_i", "P_j", "H_i", "H_j")


@dataclass(frozen=True, kw_only=True)
class GenerationConfig:
    """How samples are drawn (see the module docstring).

    Attributes:
        per_task: rows kept from one simulated scenario.
        min_steps, max_steps: range of the scenario length (steps of 0.1 s).
        scale_range: ``P_i``, ``P_j`` are scaled by log-uniform factors in [1/s, s].
        keep_raw: fraction of rows left unperturbed (the simulator's own beliefs).
        fusions: fusion rules the scenarios are run with (drawn uniformly per task).
        bearing_sigma_deg: ``None`` (default): relative range only (m = 1, ``R = [[0.1^2]]``);
            a value (deg): range + bearing (m = 2,
            ``R = diag(0.1^2, (bearing_sigma_deg pi / 180)^2)``), i.e. the scenarios are
            ``CLConfig(model="ins", bearing_sigma_deg=...)``.
    """

    per_task: int = 256
    min_steps: int = 5
    max_steps: int = 400
    scale_range: float = 100.0
    keep_raw: float = 0.2
    fusions: tuple[str, ...] = ("dmv", "pecmv", "naive")
    bearing_sigma_deg: float | None = None


@dataclass(frozen=True, kw_only=True, eq=False)
class SurrogateDataset:
    """Arrays of :data:`ARRAYS` plus the JSON-able ``header``."""

    P_i: FloatArray
    P_j: FloatArray
    H_i: FloatArray
    H_j: FloatArray
    R: FloatArray
    omega: FloatArray
    C: FloatArray
    C_diag: FloatArray
    log_det_pecmv: FloatArray
    header: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.P_i.shape[0])

    def features(self) -> FloatArray:
        """:func:`features` of every row."""
        return features(self.P_i, self.P_j, self.H_i, self.H_j)

    def subset(self, idx: Any) -> SurrogateDataset:
        """Rows ``idx`` (``R`` and the header are shared)."""
        rows = {k: getattr(self, k)[idx] for k in ARRAYS if k != "R"}
        header = {**self.header, "count": int(rows["omega"].shape[0])}
        return SurrogateDataset(R=self.R, header=header, **rows)


def label(
    P_i: FloatArray, P_j: FloatArray, H_i: FloatArray, H_j: FloatArray, R: FloatArray
) -> dict[str, FloatArray]:
    """Exact labels ``omega``, ``C``, ``C_diag``, ``log_det_pecmv`` of a batch (batched solvers)."""
    omega = dmv_omega_batch(P_i, P_j, H_i, H_j, R)
    pec = pecmv_batch(P_i, P_j, H_i, H_j, R)
    C_diag = np.diagonal(pec.C, axis1=1, axis2=2).copy()
    return {"omega": omega, "C": pec.C, "C_diag": C_diag, "log_det_pecmv": pec.log_det}


def _rotation(rng: np.random.Generator, d: int) -> FloatArray:
    """Uniform random rotation (Haar QR with sign fix, det +1)."""
    Q, Rq = np.linalg.qr(rng.standard_normal((d, d)))
    Q = Q * np.sign(np.diagonal(Rq))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def _perturb(P: FloatArray, rng: np.random.Generator, gen: GenerationConfig) -> FloatArray:
    """Scale each covariance log-uniformly and rotate its position block (rows 0..2)."""
    Bn, n = P.shape[0], P.shape[1]
    s = np.exp(rng.uniform(-1.0, 1.0, Bn) * np.log(gen.scale_range))
    T = np.repeat(np.eye(n)[None], Bn, axis=0)
    T[:, :3, :3] = np.stack([_rotation(rng, 3) for _ in range(Bn)])
    out = s[:, None, None] * np.einsum("bij,bjk,blk->bil", T, P, T)  # s T P T^T
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _task(seed: np.random.SeedSequence, n_rows: int, gen: GenerationConfig) -> dict[str, Any]:
    """One scenario: simulate, record the beliefs after every predict, subsample, perturb, label."""
    rng = np.random.default_rng(seed)
    steps = int(rng.integers(gen.min_steps, gen.max_steps + 1))
    cfg = CLConfig(horizon=steps + 1, bearing_sigma_deg=gen.bearing_sigma_deg)
    sim = CLSimulation(make_cl_problem(cfg, rng), fusion=str(rng.choice(gen.fusions)))
    rec: dict[str, list[FloatArray]] = {k: [] for k in _NAMES}
    for _ in range(steps):
        sim.predict()  # single-step propagation: the beliefs a relative update would see
        for p, (i, j) in enumerate(cfg.relative_pairs):
            H_i, H_j, _ = sim.relative_terms(p)
            for k, v in zip(_NAMES, (sim.P[i], sim.P[j], H_i, H_j), strict=True):
                rec[k].append(v.copy())
        sim.zupt_updates()
        sim.beacon_updates()
        for p in sim.available():
            sim.relative_update(p)
    total = len(rec["P_i"])
    idx = rng.choice(total, size=n_rows, replace=n_rows > total)
    arr = {k: np.stack(v)[idx] for k, v in rec.items()}
    raw = rng.random(n_rows) < gen.keep_raw
    for k in ("P_i", "P_j"):
        arr[k] = np.where(raw[:, None, None], arr[k], _perturb(arr[k], rng, gen))
    arr.update(label(arr["P_i"], arr["P_j"], arr["H_i"], arr["H_j"], sim.R_rel))
    arr["R"] = sim.R_rel
    return arr


def _run_task(task: tuple[np.random.SeedSequence, int, GenerationConfig]) -> dict[str, Any]:
    """:func:`_task` of one ``(seed, rows, gen)`` tuple (the executors map one argument)."""
    return _task(*task)


def generate_dataset(
    n_samples: int,
    *,
    seed: int = 0,
    workers: int = 0,
    gen: GenerationConfig | None = None,
    progress: bool = True,
    executor: Executor | None = None,
) -> SurrogateDataset:
    """Simulate, perturb and label ``n_samples`` rows (module docstring for the recipe).

    Task ``i`` draws from ``SeedSequence(seed).spawn(n_tasks)[i]``, so the dataset depends on
    ``seed`` and ``gen`` only, never on how the tasks are executed.

    Args:
        n_samples: rows.
        seed: master seed (task seeds are spawned from it).
        workers: processes when no ``executor`` is given (0: ``os.cpu_count()``; 1: in this
            process, no pool). The pool's workers die with this process and leave SIGINT
            to it (:class:`selenv.parallel.ProcessExecutor`).
        gen: sampling knobs (default :class:`GenerationConfig`).
        progress: show a tqdm bar over the samples.
        executor: where the tasks run (:mod:`selenv.parallel`: local, a process pool, Ray);
            overrides ``workers``.

    Raises:
        ValueError: ``n_samples < 1`` or ``workers < 0``.
    """
    gen = GenerationConfig() if gen is None else gen
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    n_tasks = -(-n_samples // gen.per_task)
    sizes = [gen.per_task] * (n_tasks - 1) + [n_samples - gen.per_task * (n_tasks - 1)]
    seeds = np.random.SeedSequence(seed).spawn(n_tasks)
    tasks = list(zip(seeds, sizes, [gen] * n_tasks, strict=True))
    if executor is None:
        workers = min(workers or os.cpu_count() or 1, n_tasks)
        executor = LocalExecutor() if workers == 1 else ProcessExecutor(workers)
        with executor:
            parts = executor.map(
                _run_task,
                tasks,
                desc="surrogate data",
                unit="sample",
                weights=sizes,
                progress=progress,
            )
    else:
        parts = executor.map(
            _run_task,
            tasks,
            desc="surrogate data",
            unit="sample",
            weights=sizes,
            progress=progress,
        )
    arrays = {k: np.concatenate([p[k] for p in parts]) for k in ARRAYS if k != "R"}
    R = parts[0]["R"]
    n, m = arrays["P_i"].shape[1], arrays["H_i"].shape[1]
    om = arrays["omega"]
    header = {
        "format": FORMAT,
        "n": int(n),
        "m": int(m),
        "count": int(n_samples),
        "seed": int(seed),
        "R": R.tolist(),
        "generation": {"scenario": _scenario_doc(gen), **_gen_dict(gen)},
        "label_stats": {
            "omega_mean": float(om.mean()),
            "omega_eq_1": float(np.mean(om >= 1.0)),
            "omega_min": float(om.min()),
            "C_diag_abs_mean": float(np.abs(arrays["C_diag"]).mean()),
        },
        "selenv_version": selenv.__version__,
    }
    return SurrogateDataset(R=R, header=header, **arrays)


def _scenario_doc(gen: GenerationConfig) -> str:
    """The header's ``generation.scenario``: unchanged for m = 1, the bearing noise for m = 2."""
    if gen.bearing_sigma_deg is None:
        return "CLConfig(model='ins') defaults"
    return f"CLConfig(model='ins', bearing_sigma_deg={gen.bearing_sigma_deg!r}), else defaults"


def _gen_dict(gen: GenerationConfig) -> dict[str, Any]:
    """The header's ``generation`` fields.

    ``bearing_sigma_deg`` only when set: m = 1 headers are those from before the option.
    """
    out: dict[str, Any] = {
        "per_task": gen.per_task,
        "min_steps": gen.min_steps,
        "max_steps": gen.max_steps,
        "scale_range": gen.scale_range,
        "keep_raw": gen.keep_raw,
        "fusions": list(gen.fusions),
    }
    if gen.bearing_sigma_deg is not None:
        out["bearing_sigma_deg"] = gen.bearing_sigma_deg
    return out


def save_dataset(ds: SurrogateDataset, path: str | Path) -> Path:
    """Write ``ds`` as a compressed ``.npz`` (see the module docstring); return the path.

    ``.npz`` is appended to a path without it (numpy's rule). The file is written atomically
    (:func:`selenv.atomic.atomic_path`): an interrupted or failed write leaves a previous file
    byte-identical and no partial file.

    Raises:
        OSError: the write failed (full disk, file-size limit, ...); its ``filename`` is the
            target (not the temporary file).
    """
    path = Path(path)
    if path.suffix != ".npz":
        path = Path(f"{path}.npz")
    arrays = {k: getattr(ds, k) for k in ARRAYS}
    header = np.array(json.dumps(ds.header))
    try:
        with atomic_path(path) as temp:
            np.savez_compressed(temp, header=header, **arrays)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
    return path


class DatasetTooLargeError(ValueError):
    """A dataset file declares arrays beyond the ceilings of :func:`load_dataset`."""


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype from a member's ``.npy`` header (only the header is inflated)."""
    from numpy.lib import format as npy_format

    with zf.open(info) as fh:
        version = npy_format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = npy_format.read_array_header_2_0(fh)
        else:  # pragma: no cover - numpy's read_magic refuses others already
            raise ValueError(f"unsupported .npy version {version}")
    return tuple(int(d) for d in shape), np.dtype(dtype)


def _check_sizes(path: Path, max_rows: int) -> None:
    """Refuse, from the zip directory and the ``.npy`` headers alone, arrays over the ceilings.

    Raises:
        DatasetTooLargeError: names the array, what it declares and the limit.
        ValueError: not a zip of ``.npy`` members, or an array missing.
    """
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ValueError(f"cannot read surrogate dataset {path}: {exc}") from None
    with zf:
        members = {info.filename: info for info in zf.infolist()}
        missing = [k for k in (*ARRAYS, "header") if f"{k}.npy" not in members]
        if missing:
            raise ValueError(f"surrogate dataset {path} lacks arrays {missing}")
        shapes: dict[str, tuple[int, ...]] = {}
        for name in (*ARRAYS, "header"):
            info = members[f"{name}.npy"]
            try:
                shape, dtype = _npy_header(zf, info)
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
                msg = " ".join(str(exc).split())
                raise ValueError(
                    f"surrogate dataset {path}: array {name!r} has no valid .npy header: {msg}"
                ) from None
            if dtype.hasobject:
                raise ValueError(f"surrogate dataset {path}: array {name!r} holds Python objects")
            nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            small = name in ("R", "header")
            if small:
                limit, what = _MAX_SMALL_BYTES, "1 MiB"
            else:
                rows = shape[0] if shape else 0
                if rows > max_rows:
                    raise DatasetTooLargeError(
                        f"surrogate dataset {path}: array {name!r} declares {rows:,} rows "
                        f"(shape {shape}, {nbytes / 2**20:,.0f} MiB), over the limit of "
                        f"{max_rows:,} rows"
                    )
                limit = max(rows, 1) * MAX_BYTES_PER_ROW
                what = f"{MAX_BYTES_PER_ROW} bytes per row"
            declared = max(nbytes, info.file_size - 4096)  # the zip's own size claim, too
            if declared > limit:
                raise DatasetTooLargeError(
                    f"surrogate dataset {path}: array {name!r} declares shape {shape} "
                    f"({declared / 2**20:,.1f} MiB inflated), over the limit of {what}"
                )
            shapes[name] = shape
        counts = {k: shapes[k][0] if shapes[k] else None for k in ARRAYS if k != "R"}
        if len(set(counts.values())) != 1:
            raise ValueError(f"surrogate dataset {path}: arrays disagree on the row count {counts}")


def load_dataset(path: str | Path, *, max_rows: int = MAX_ROWS) -> SurrogateDataset:
    """Read a file written by :func:`save_dataset`.

    Before any array is inflated, the zip directory and each member's ``.npy`` header
    (shape, dtype) are read: more than ``max_rows`` rows, more than
    :data:`MAX_BYTES_PER_ROW` bytes per row in an array, an ``R`` or ``header`` over 1 MiB, or
    an array of Python objects is refused, so a small file that would inflate to gigabytes is
    refused within milliseconds. Members other than the dataset's arrays are not read.

    Raises:
        DatasetTooLargeError: an array over a ceiling (names the array and the limit).
        ValueError: missing or unreadable file, missing arrays or a header that is not this
            format (names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cannot read surrogate dataset {path}: no such file")
    _check_sizes(path, max_rows)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in (*ARRAYS, "header")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        msg = " ".join(str(exc).split())
        raise ValueError(f"cannot read surrogate dataset {path}: {msg}") from None
    try:
        header = json.loads(str(data.pop("header")))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"surrogate dataset {path} has an invalid JSON header: {exc}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ValueError(f"surrogate dataset {path}: header format is not {FORMAT!r}")
    return SurrogateDataset(header=header, **{k: data[k] for k in ARRAYS})
