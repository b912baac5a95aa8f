"""The reproduction scripts end like every selenv command: one line and exit 2 on a usage
error, never a traceback, found before any work.

Every size that multiplies work or memory has a ceiling (``--allow-large`` lifts it) and every
value the envs would refuse is reported as the option the user typed. The cases run in this
process (``guarded_main(main, ...)`` with the script's argv, as its ``__main__`` block does,
with the work entry point replaced by a tripwire so a missed check fails at once instead of
starting a run); one subprocess per script proves the same in a real process.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import _proc
import pytest
from conftest import load_script

from selenv.exits import UsageError, check_size, guarded_main

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((ROOT / "scripts").glob("reproduce_*.py"))
NAMES = [s.stem for s in SCRIPTS]
HUGE = "1000000000"


@pytest.fixture(scope="module")
def modules() -> dict[str, ModuleType]:
    """Each script imported once for the whole file."""
    return {name: load_script(name) for name in NAMES}


class WorkStarted(Exception):
    """Raised by the tripwire: the script went past its up-front checks."""


def _tripwire(*args: Any, **kwargs: Any) -> None:
    raise WorkStarted("the run started: a usage error was not found up front")


def run_in_process(module: ModuleType, argv: list[str]) -> int:
    """Exit code of the script's ``__main__`` block for ``argv`` (argparse exits included)."""
    try:
        return guarded_main(module.main, module.PROG, argv)
    except SystemExit as exc:  # argparse's errors, as in a real process
        return int(exc.code or 0)


@pytest.fixture
def no_work(modules: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The output probe, the first step of every run, raises :class:`WorkStarted`."""
    for module in modules.values():
        monkeypatch.setattr(module, "_check_out", _tripwire)
    yield


# script -> (argv, the option the one line must name)
BAD: list[tuple[str, list[str], str]] = [
    ("reproduce_kirchner", ["--trials", HUGE], "--trials"),
    ("reproduce_kirchner", ["--trials", "10001"], "--trials"),
    ("reproduce_kirchner", ["--trials", "1"], "--trials"),
    ("reproduce_kirchner", ["--trials", "many"], "--trials"),
    ("reproduce_kirchner", ["--seed", "-1"], "--seed"),
    ("reproduce_greiff", ["--runs", HUGE], "--runs"),
    ("reproduce_greiff", ["--runs", "0"], "--runs"),
    ("reproduce_greiff", ["--table-runs", HUGE], "--table-runs"),
    ("reproduce_greiff", ["--table-runs", "0"], "--table-runs"),
    ("reproduce_greiff", ["--steps", HUGE], "--steps"),
    ("reproduce_greiff", ["--steps", "10001"], "--steps"),
    ("reproduce_greiff", ["--steps", "0"], "--steps"),
    (
        "reproduce_greiff",
        ["--runs", "10000", "--table-runs", "10000", "--steps", "2000"],
        "--runs x --table-runs x --steps",
    ),
    ("reproduce_greiff", ["--seed", "-1"], "--seed"),
    ("reproduce_greiff", ["--store", str(ROOT / "README.md")], "--store"),
    ("reproduce_greiff", ["--num-workers", HUGE], "--num-workers"),
    ("reproduce_soubaras", ["--runs", HUGE], "--runs"),
    ("reproduce_soubaras", ["--runs", "1"], "--runs"),
    ("reproduce_soubaras", ["--horizon", HUGE], "--horizon"),
    ("reproduce_soubaras", ["--horizon", "10001"], "--horizon"),
    ("reproduce_soubaras", ["--n-landmarks", "100000"], "--n-landmarks"),
    ("reproduce_soubaras", ["--n-landmarks", "0"], "--n-landmarks"),
    ("reproduce_soubaras", ["--k", "31"], "--k"),
    ("reproduce_soubaras", ["--k", "0"], "--k"),
    ("reproduce_soubaras", ["--n-landmarks", "200", "--k", "3"], "--k 3"),
    ("reproduce_soubaras", ["--n-landmarks", "200", "--k", "4", "--allow-large"], "--k 4"),
    ("reproduce_soubaras", ["--runs", "5000", "--horizon", "5000"], "--runs x --horizon"),
    ("reproduce_soubaras", ["--seed", "-1"], "--seed"),
    ("reproduce_soubaras", ["--workers", HUGE], "--num-workers"),
    ("reproduce_chen_kia", ["--runs", HUGE], "--runs"),
    ("reproduce_chen_kia", ["--runs", "0"], "--runs"),
    ("reproduce_chen_kia", ["--steps", HUGE], "--steps"),
    ("reproduce_chen_kia", ["--steps", "10001"], "--steps"),
    ("reproduce_chen_kia", ["--runs", "10000", "--steps", "10000"], "--runs x --steps"),
    ("reproduce_chen_kia", ["--bearing-sigma-deg", "nan"], "--bearing-sigma-deg"),
    ("reproduce_chen_kia", ["--bearing-sigma-deg", "0"], "--bearing-sigma-deg"),
    ("reproduce_chen_kia", ["--methods", "dmv,foo"], "--methods"),
    ("reproduce_chen_kia", ["--workers", HUGE, "--methods", "dmv"], "--num-workers"),
    ("reproduce_chen_kia_surrogates", ["--samples", HUGE], "--samples"),
    ("reproduce_chen_kia_surrogates", ["--samples", "1"], "--samples"),
    ("reproduce_chen_kia_surrogates", ["--calls", HUGE], "--calls"),
    ("reproduce_chen_kia_surrogates", ["--calls", "0"], "--calls"),
    ("reproduce_chen_kia_surrogates", ["--filter-runs", HUGE], "--filter-runs"),
    ("reproduce_chen_kia_surrogates", ["--filter-runs", "-1"], "--filter-runs"),
    ("reproduce_chen_kia_surrogates", ["--filter-steps", HUGE], "--filter-steps"),
    ("reproduce_chen_kia_surrogates", ["--filter-steps", "10001"], "--filter-steps"),
    (
        "reproduce_chen_kia_surrogates",
        ["--filter-runs", "10000", "--filter-steps", "10000"],
        "--filter-runs x --filter-steps",
    ),
    ("reproduce_chen_kia_surrogates", ["--quick", "--best-diagonal", "301"], "--best-diagonal"),
    ("reproduce_chen_kia_surrogates", ["--seed", "-1"], "--seed"),
    ("reproduce_chen_kia_surrogates", ["--workers", HUGE], "--num-workers"),
]


@pytest.mark.parametrize(
    ("name", "argv", "option"),
    BAD,
    ids=[f"{n.removeprefix('reproduce_')}:{' '.join(a)}" for n, a, _ in BAD],
)
def test_bad_value_is_a_one_line_usage_error_before_any_work(
    name: str,
    argv: list[str],
    option: str,
    modules: dict[str, ModuleType],
    no_work: None,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Exit 2, one stderr line ``<script>.py: error: ...`` naming the option, nothing written."""
    out = tmp_path / "figs"
    rc = run_in_process(modules[name], [*argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1, err
    assert err.startswith(f"{name}.py: error: "), err
    assert option in err, err
    assert "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_ceiling_message_says_how_to_lift_it(
    name: str, modules: dict[str, ModuleType], no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """Above a ceiling the line gives the ceiling and the one opt-in, ``--allow-large``."""
    module = modules[name]
    option, ceiling = next(iter(module.CEILINGS.items()))
    rc = run_in_process(module, [option, str(ceiling + 1)])
    err = capsys.readouterr().err
    assert rc == 2
    assert f"{option}: {ceiling + 1:,} exceeds the ceiling of {ceiling:,}" in err
    assert "pass --allow-large to run it anyway" in err


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_help_documents_the_ceilings_and_the_opt_in(
    name: str, modules: dict[str, ModuleType], capsys: pytest.CaptureFixture[str]
) -> None:
    module = modules[name]
    with pytest.raises(SystemExit) as exc:
        module.parse_args(["--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--allow-large" in text
    for ceiling in module.CEILINGS.values():
        assert f"{ceiling:,}" in text


def _args(module: ModuleType, argv: list[str]) -> argparse.Namespace:
    args: argparse.Namespace = module.parse_args(argv)
    return args


def _ceiling_cases() -> list[tuple[str, str]]:
    cases = {
        "reproduce_kirchner": ["--trials"],
        "reproduce_greiff": ["--runs", "--table-runs", "--steps"],
        "reproduce_soubaras": ["--runs", "--horizon"],
        "reproduce_chen_kia": ["--runs", "--steps"],
        "reproduce_chen_kia_surrogates": [
            "--samples", "--calls", "--filter-runs", "--filter-steps", "--best-diagonal",
        ],
    }  # fmt: skip
    return [(name, option) for name, options in cases.items() for option in options]


@pytest.mark.parametrize(("name", "option"), _ceiling_cases())
def test_value_at_the_ceiling_is_accepted_and_one_above_needs_the_opt_in(
    name: str, option: str, modules: dict[str, ModuleType]
) -> None:
    """The check alone (no run): ceiling passes, ceiling + 1 refused, passes with the opt-in."""
    module = modules[name]
    ceiling = module.CEILINGS[option]
    extra = ["--samples", str(ceiling + 1)] if option == "--best-diagonal" else []
    module.check_args(_args(module, [*extra, option, str(ceiling)]))
    above = [*extra, option, str(ceiling + 1)]
    with pytest.raises(UsageError, match=f"^{option}: .* exceeds the ceiling .*--allow-large"):
        module.check_args(_args(module, above))
    module.check_args(_args(module, [*above, "--allow-large"]))


def test_soubaras_brute_force_subsets_ceiling(modules: dict[str, ModuleType]) -> None:
    """C(N, K) per step: 200 choose 2 fine, 200 choose 3 only with the opt-in, 4 never."""
    module = modules["reproduce_soubaras"]
    module.check_args(_args(module, ["--n-landmarks", "200", "--k", "2"]))
    with pytest.raises(UsageError, match="1,313,400 subsets exceeds the ceiling of 100,000"):
        module.check_args(_args(module, ["--n-landmarks", "200", "--k", "3"]))
    module.check_args(_args(module, ["--n-landmarks", "200", "--k", "3", "--allow-large"]))
    with pytest.raises(UsageError, match="must be <= 2,000,000 subsets"):
        module.check_args(_args(module, ["--n-landmarks", "200", "--k", "4", "--allow-large"]))


def test_memory_estimate_grows_with_the_sizes(modules: dict[str, ModuleType]) -> None:
    """The memory estimates are linear in runs and (steps + 1); the opt-in lifts the ceiling."""
    greiff = modules["reproduce_greiff"]
    a = greiff.result_mib(_args(greiff, ["--runs", "100", "--table-runs", "0", "--steps", "99"]))
    b = greiff.result_mib(_args(greiff, ["--runs", "200", "--table-runs", "0", "--steps", "99"]))
    assert b > a > 0
    big = ["--runs", "10000", "--table-runs", "10000", "--steps", "2000"]
    with pytest.raises(UsageError, match="MiB exceeds the ceiling of 4,096 MiB"):
        greiff.check_args(_args(greiff, big))
    greiff.check_args(_args(greiff, [*big, "--allow-large"]))
    ck = modules["reproduce_chen_kia"]
    assert ck.result_mib(20, 100, 3) == pytest.approx(2 * ck.result_mib(10, 100, 3))
    assert ck.result_mib(10, 100, 6) == pytest.approx(2 * ck.result_mib(10, 100, 3))


# every command the documentation, the Makefile and the tests run: never refused
DOCUMENTED: list[tuple[str, list[str]]] = [
    ("reproduce_kirchner", []),
    ("reproduce_kirchner", ["--quick"]),
    ("reproduce_kirchner", ["--trials", "100", "--seed", "2020"]),
    ("reproduce_greiff", []),
    ("reproduce_greiff", ["--quick"]),
    ("reproduce_greiff", ["--runs", "100", "--table-runs", "50", "--steps", "500"]),
    ("reproduce_greiff", ["--runs", "16", "--table-runs", "4", "--steps", "200"]),
    ("reproduce_greiff", ["--ga-variant", "both", "--runs", "20", "--table-runs", "100"]),
    ("reproduce_greiff", ["--runs", "1000", "--table-runs", "1000", "--ga-variant", "both"]),
    ("reproduce_soubaras", []),
    ("reproduce_soubaras", ["--quick"]),
    ("reproduce_soubaras", ["--runs", "100", "--horizon", "300", "--seed", "2023"]),
    ("reproduce_chen_kia", []),
    ("reproduce_chen_kia", ["--quick"]),
    ("reproduce_chen_kia", ["--runs", "200"]),
    ("reproduce_chen_kia", ["--methods", "dmv,pecmv", "--bearing-sigma-deg", "2"]),
    ("reproduce_chen_kia_surrogates", []),
    ("reproduce_chen_kia_surrogates", ["--quick"]),
    ("reproduce_chen_kia_surrogates", ["--filter-runs", "0"]),
    ("reproduce_chen_kia_surrogates", ["--m", "2", "--filter-runs", "30"]),
    ("reproduce_chen_kia_surrogates", ["--samples", "1000", "--calls", "300"]),
    ("reproduce_chen_kia_surrogates",
     ["--m", "2", "--samples", "150", "--calls", "50", "--filter-runs", "0",
      "--best-diagonal", "150"]),
]  # fmt: skip


@pytest.mark.parametrize(
    ("name", "argv"), DOCUMENTED, ids=[f"{n}:{' '.join(a)}" for n, a in DOCUMENTED]
)
def test_documented_commands_pass_the_checks(
    name: str, argv: list[str], modules: dict[str, ModuleType]
) -> None:
    modules[name].check_args(_args(modules[name], argv))


def test_learned_method_without_checkpoint_is_refused_up_front(
    modules: dict[str, ModuleType],
    no_work: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A learned method with no shipped surrogate for the noise: exit 2 naming it, no run.

    The scenario's own check is replaced by one that refuses every learned method (the real
    one loads torch and the checkpoints, seconds this file does not spend).
    """
    module = modules["reproduce_chen_kia"]
    from selenv.families.cooperative import scenario

    assert module.check_learned_fusion is scenario.check_learned_fusion
    seen: list[tuple[float | None, str]] = []

    def refuse_learned(config: Any, method: str) -> None:
        seen.append((config.bearing_sigma_deg, method))
        if method in scenario.LEARNED_FUSIONS:
            raise ValueError(f"fusion={method!r} needs a shipped surrogate")

    monkeypatch.setattr(module, "check_learned_fusion", refuse_learned)
    rc = run_in_process(module, ["--bearing-sigma-deg", "5", "--methods", "dmv,ldmv"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1
    assert err.startswith(
        "reproduce_chen_kia.py: error: --methods: ldmv has no shipped surrogate for "
        "--bearing-sigma-deg 5;"
    ), err
    assert seen == [(5.0, "dmv"), (5.0, "ldmv")]


def test_check_size_bounds() -> None:
    """Equal to a bound or the ceiling is accepted; NaN fails any bound; the opt-in lifts."""
    check_size("--n", 5, low=5, high=5, ceiling=5)
    check_size("--n", 6, ceiling=5, lifted=True)
    with pytest.raises(UsageError, match=r"^--n: must be in \[1, 3\], got 4$"):
        check_size("--n", 4, low=1, high=3)
    with pytest.raises(UsageError, match=r"^--x: must be >= 0.5, got nan$"):
        check_size("--x", float("nan"), low=0.5)
    with pytest.raises(UsageError, match=r"^--n: 1,001 exceeds the ceiling of 1,000; pass --big"):
        check_size("--n", 1001, ceiling=1000, lift="--big")


@pytest.mark.parametrize("name", NAMES, ids=NAMES)
def test_unwritable_out_is_a_one_line_usage_error(
    name: str, modules: dict[str, ModuleType], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--out`` under a regular file: exit 2, one line naming --out and the cause."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    argv = ["--out", str(blocker / "figs")]
    if name != "reproduce_kirchner":
        argv += ["--executor", "local"]  # no pool started for a refused run
    if name == "reproduce_chen_kia":
        argv += ["--methods", "dmv"]
    rc = run_in_process(modules[name], argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1, err
    assert err.startswith(f"{name}.py: error: --out: cannot write"), err
    assert blocker.read_text() == "not a folder"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


# one real process per script: the value that used to run forever or end in a traceback
REAL = {
    "reproduce_kirchner": ["--trials", HUGE],
    "reproduce_greiff": ["--runs", HUGE],
    "reproduce_soubaras": ["--horizon", HUGE],
    "reproduce_chen_kia": ["--runs", HUGE],
    "reproduce_chen_kia_surrogates": ["--filter-steps", HUGE],
}


def test_huge_sizes_in_real_processes(tmp_path: Path) -> None:
    """The real ``python scripts/<name>.py``, all five at once: exit 2 and one line each, no
    traceback, no hang (a timeout ends a run that started), nothing written."""
    procs: dict[Path, tuple[Path, subprocess.Popen[str]]] = {}
    try:
        for script in SCRIPTS:
            out = tmp_path / script.stem
            procs[script] = (out, _proc.popen(
                [sys.executable, str(script), *REAL[script.stem], "--out", str(out)],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
            ))  # fmt: skip
        for script, (out, proc) in procs.items():
            _, err = _proc.communicate(proc, 120)
            assert proc.returncode == 2, err
            assert err.count("\n") == 1, err
            assert err.startswith(f"{script.name}: error: {REAL[script.stem][0]}: "), err
            assert "Traceback" not in err
            assert not out.exists()
    finally:
        for _, proc in procs.values():
            _proc.stop(proc)
