r"""The ``selenv`` command line: ``selenv list`` and ``selenv bench``.

Examples::

    selenv list
    selenv bench selenv/FIMSelection-v1 --agents greedy,random --episodes 5 \
        --env-kwargs '{"n_candidates": 20, "budget": 4}' --json out.json --plot figs/
    selenv bench selenv.multiagent.fim_selection_v0 --env-kwargs '{"mode": "independent"}' \
        --baseline greedy

``ENV_ID`` is a Gymnasium id or a PettingZoo module of :mod:`selenv.multiagent`. Every agent
is compared with a baseline (``--baseline``, default the best mean return) on the same seeds:
paired mean difference of the return, bootstrap 95 % CI, wins/ties/losses (see
:mod:`selenv.bench.stats`). Tables are printed as each env finishes; the JSON and the plots are
written only once every env has run without a usage error.

Exit codes (the message is one line on stderr, never a traceback):

* 0: success.
* 2: a usage error, found before any episode runs (bad arguments or agent specs, unknown env,
  module or agent, an agent that does not apply to the env, invalid ``--env-kwargs``, a
  ``--baseline`` that is not among the agents run or was skipped, ``--episodes`` above
  ``--max-episodes`` (default 100,000) or more results than half the machine's memory, an
  unwritable or busy output, a bad executor choice or an unreachable ``--address``); nothing is
  written.
* 1: a run-time failure: the ``--json`` or a ``--plot`` file could not be written (full disk,
  file-size limit, permissions, read-only file system; the previous file is left byte for
  byte, and the results go to ``<json>.partial`` if that can be written, else the line says
  they could not be kept), or a process-pool / Ray worker died (the finished episodes go to
  ``<json>.partial``, ``complete: false``; the ``--json`` itself is left as it was).
* 130 / 143: SIGINT (Ctrl-C) / SIGTERM: the current episode is abandoned, the finished ones
  are kept: the table and the ``--json`` are written with ``"complete": false``, the episodes
  each agent finished and statistics on the seeds every agent finished (also with
  ``--executor process``, whose workers hand back the episodes of their current blocks). A
  run stopped before any episode finished leaves the ``--json`` untouched.

One writer per output: the ``--json`` file and the ``--plot`` folder are locked for the whole
run (``.<name>.lock`` next to them, :class:`selenv.atomic.OutputLock`); a second bench aiming
at either exits 2. Every file is written atomically (:mod:`selenv.atomic`), so an interrupted
or failed write (even SIGKILL) never leaves a truncated file.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import gymnasium as gym

from selenv import __version__
from selenv.agents import AGENTS, agents_for, default_agents, parse_spec
from selenv.agents.base import unknown_agent_message
from selenv.agents.learned import list_note
from selenv.atomic import OutputBusyError, OutputLock, describe_os_error, probe_replaceable
from selenv.atomic import write_json as atomic_write_json
from selenv.exits import DeferredSignals, Terminated, end_startup, hold_signals, sigterm_raises
from selenv.families import ENV_IDS
from selenv.parallel import (
    ExecutorError,
    WorkerDiedError,
    add_executor_arguments,
    executor_from_args,
    max_pool_workers,
)
from selenv.parallel.executors import POOL_WORKERS_PER_CPU
from selenv.untrusted import UntrustedInputError, loads_json

if TYPE_CHECKING:
    from selenv.bench.runner import EnvBenchResult
    from selenv.parallel import Executor

__all__ = ["build_parser", "main"]


def _int_at_least(low: int) -> Callable[[str], int]:
    """An argparse ``type=`` that accepts integers ``>= low`` with a clear message otherwise."""

    def parse(text: str) -> int:
        expected = f"expected an integer >= {low}"
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{expected}, got {value}")
        return value

    return parse


_positive_int = _int_at_least(1)
_non_negative_int = _int_at_least(0)


def _env_kwargs(text: str) -> dict[str, Any]:
    """``--env-kwargs`` parsed by the bounded reader (size and nesting checked first)."""
    try:
        value = loads_json(text, "JSON")
    except UntrustedInputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("JSON: ")) from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r:.200}")
    return value


class _OneLineParser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line on stderr (``PROG: error: ...``), exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: MESSAGE`` on one line and exit with code 2."""
        print(f"{self.prog}: error: {' '.join(message.split())}", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``selenv`` (subcommands ``list`` and ``bench``)."""
    parser = _OneLineParser(
        prog="selenv",
        description="State-estimation selection problems as Gymnasium envs, with baselines.",
    )
    parser.add_argument("--version", action="version", version=f"selenv {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sub.add_parser(
        "list", help="list the envs and PettingZoo modules and the agents that apply to each"
    )
    bench = sub.add_parser(
        "bench",
        help="run agents on the same seeded episodes and compare them",
        description="Run every agent on the same seeded episodes (episode e uses seed + e) "
        "and print a table of mean returns, final objectives, decision times and, against a "
        "baseline agent, the paired mean difference of the return per seed with its "
        "percentile-bootstrap 95 % CI (10,000 resamples, fixed seed; * when it excludes 0), "
        "wins/ties/losses and the normalised score (mean - random) / (best - random).",
    )
    bench.add_argument(
        "env_ids",
        nargs="*",
        metavar="ENV_ID",
        help="Gymnasium env ids or PettingZoo modules such as "
        "selenv.multiagent.fim_selection_v0 (default: every selenv Gymnasium env)",
    )
    bench.add_argument(
        "--agents",
        help="comma-separated agent names (default: every agent that applies to the env)",
    )
    bench.add_argument(
        "--episodes", type=_positive_int, default=10, help="episodes per agent (default 10)"
    )
    bench.add_argument(
        "--max-episodes",
        type=_positive_int,
        default=None,
        metavar="N",
        help="ceiling on --episodes, checked before anything runs (default 100,000); raise "
        "it for a deliberately huge run",
    )
    bench.add_argument(
        "--seed", type=_non_negative_int, default=0, help="seed of episode 0 (default 0)"
    )
    bench.add_argument(
        "--env-kwargs",
        type=_env_kwargs,
        default={},
        metavar="JSON",
        help="JSON object of env constructor keywords, e.g. '{\"budget\": 4}'",
    )
    bench.add_argument(
        "--baseline",
        metavar="NAME",
        help="agent the others are compared with on the same seeds (default: the agent with "
        "the best mean return); must be among the agents run",
    )
    bench.add_argument(
        "--json",
        metavar="PATH",
        help="write the results as JSON to PATH: {provenance, results: [one object per env]}",
    )
    bench.add_argument(
        "--plot",
        metavar="DIR",
        help="write one PNG per env into DIR: paired differences vs the baseline with 95 %% CIs",
    )
    bench.add_argument(
        "--no-bounds",
        action="store_true",
        help="skip the certified bound on each episode's return and the agents' gap to it "
        "(computed where the env family has one, e.g. FIMSelection's relaxation)",
    )
    bench.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    bench.add_argument(
        "--blas-threads",
        type=_non_negative_int,
        default=1,
        metavar="N",
        help="BLAS threads while episodes play (default 1: the problems are small matrices, "
        "for which more threads only add start-up cost; 0 leaves BLAS's own setting)",
    )
    bench.add_argument(
        "--torch-threads",
        type=_non_negative_int,
        default=1,
        metavar="N",
        help="torch intra-op threads of the learned agents while episodes play (default 1: "
        "one small forward pass per decision; 0 leaves torch's own setting)",
    )
    add_executor_arguments(bench)
    scripts = training_scripts()
    train = sub.add_parser(
        "train",
        help="run a training entry point of selenv.train (same options as python -m ...)",
        description="Run one of selenv's training entry points; everything after SCRIPT is "
        "passed to it (`selenv train SCRIPT --help` shows its options).\n\nscripts:\n"
        + "\n".join(f"  {name:<24}{doc}" for name, doc in scripts.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    train.add_argument("script", choices=list(scripts), metavar="SCRIPT", help="which script")
    train.add_argument("script_args", nargs=argparse.REMAINDER, help="the script's options")
    return parser


def training_scripts() -> dict[str, str]:
    """Module name -> first docstring line of each entry point in :mod:`selenv.train`.

    Read from the sources (``ast``), so listing them imports neither torch nor Ray.
    """
    import ast
    import importlib.util

    spec = importlib.util.find_spec("selenv.train")
    folder = Path(next(iter(spec.submodule_search_locations or [])))  # type: ignore[union-attr]
    out = {}
    for path in sorted(folder.glob("*.py")):
        if path.stem.startswith("_") or path.stem == "tune_results":
            continue
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        out[path.stem] = doc.split("\n")[0].rstrip(".")
    return out


def cmd_train(args: argparse.Namespace) -> int:
    """Run the script's console entry point (``cli``, else ``main``) on ``script_args``.

    Through ``cli`` a stopped or failed run prints the script's own line (what was saved, how to
    resume) and its exit code (usage 2, I/O 1, SIGINT 130, SIGTERM 143) is the command's.
    """
    import importlib
    import inspect

    with hold_signals():  # torch / Ray imports: a signal waits until they are done
        module = importlib.import_module(f"selenv.train.{args.script}")
    argv = list(args.script_args)
    entry = getattr(module, "cli", None)
    try:
        if entry is None:
            result = module.main(argv)
        elif inspect.signature(entry).parameters:
            result = entry(argv)
        else:  # a console script reading sys.argv
            saved = sys.argv
            sys.argv = [f"selenv train {args.script}", *argv]
            try:
                result = entry()
            finally:
                sys.argv = saved
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    return result if isinstance(result, int) else 0


def _listed_env_ids() -> list[str]:
    """``ENV_IDS``, other registered envs some agent applies to, then the PettingZoo modules."""
    from selenv.bench.multiagent import multiagent_modules

    extra = {e for by_env in AGENTS.values() for e in by_env if e in gym.registry}
    return [*ENV_IDS, *sorted(extra - set(ENV_IDS)), *multiagent_modules()]


def cmd_list() -> int:
    """Print every env id and PettingZoo module with the agents that apply and their notes."""
    for env_id in _listed_env_ids():
        print(env_id)
        names = agents_for(env_id)
        if not names:
            print("  (no agents registered)")
        width = max((len(n) for n in names), default=0)
        for name in names:
            spec = AGENTS[name][env_id]
            desc = spec.description
            if spec.learned:
                note = list_note(name, env_id)
                desc = f"{desc}\n  {' ' * width}  -> {note}" if note else desc
            print(f"  {name.ljust(width)}  {desc}".rstrip())
    return 0


def _note(message: str) -> None:
    print(f"selenv: note: {message}", file=sys.stderr)


def _error(message: str) -> int:
    print(f"selenv: error: {message}", file=sys.stderr)
    return 2


def _check_baseline(baseline: str, env_ids: list[str], names: list[str] | None) -> str | None:
    """Why ``baseline`` cannot be the baseline of every env (``None`` if it can), before running."""
    if names is not None and baseline not in names:
        return f"--baseline {baseline!r} is not among the agents run: {', '.join(names)}"
    for env_id in env_ids:
        if env_id not in AGENTS.get(parse_spec(baseline)[0], {}):
            return (
                f"--baseline {baseline!r} does not apply to {env_id} "
                f"(agents for it: {', '.join(agents_for(env_id))})"
            )
    return None


def _workers_problem(args: argparse.Namespace) -> str | None:
    """Why ``--num-workers`` is refused (``None`` if it is not), from the numbers alone.

    The process pool's ceiling (:func:`selenv.parallel.max_pool_workers`) is checked here,
    before the agents are built and before any executor starts, so the refusal costs no
    torch or Ray import.
    """
    workers = getattr(args, "num_workers", None)
    ceiling = max_pool_workers()
    if args.executor == "process" and workers is not None and workers > ceiling:
        return (
            f"--num-workers {workers} exceeds the ceiling of {ceiling} processes for "
            f"--executor process ({POOL_WORKERS_PER_CPU} per CPU of this machine); use "
            "fewer, or --executor ray with a cluster"
        )
    return None


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the benchmark described by the parsed ``args``; print tables, write JSON/plots.

    Everything that can be checked is checked before the first episode (exit code 2, nothing
    written); the outputs are locked for the whole run and written atomically once every env
    has run or the run was stopped (module docstring for the exit codes).
    """
    from selenv.bench import BenchError, check_env_id
    from selenv.bench.runner import MAX_EPISODES, episodes_problem

    why = _workers_problem(args)  # before any agent (torch) or executor (Ray) is loaded
    if why is not None:
        return _error(why)
    env_ids = list(dict.fromkeys(args.env_ids)) or list(ENV_IDS)
    for env_id in env_ids:
        try:
            check_env_id(env_id)
        except BenchError as exc:
            return _error(str(exc))
    names = None
    if args.agents is not None:
        names = [n.strip() for n in args.agents.split(",") if n.strip()]
        if not names:
            return _error("--agents is empty")
        for n in names:
            try:
                parse_spec(n)
            except ValueError as exc:
                return _error(f"--agents: {exc}")
        bad = [n for n in names if parse_spec(n)[0] not in AGENTS]
        if bad:
            return _error(unknown_agent_message([parse_spec(n)[0] for n in bad], env_ids))
    if args.baseline is not None:
        try:
            parse_spec(args.baseline)
        except ValueError as exc:
            return _error(f"--baseline: {exc}")
    runs = sum(len(names) if names else len(default_agents(e)) for e in env_ids)
    args.max_episodes = args.max_episodes or MAX_EPISODES
    why = episodes_problem(args.episodes, args.max_episodes, runs=runs)
    if why is not None:
        return _error(why)
    several = len(env_ids) > 1
    if several and names is None:
        for env_id in [e for e in env_ids if not agents_for(e)]:
            _note(f"skipping {env_id}: no registered agent applies to it")
        env_ids = [e for e in env_ids if agents_for(e)]
    if args.baseline is not None:
        why = _check_baseline(args.baseline, env_ids, names)
        if why is not None:
            return _error(why)
    why = _precheck(args, env_ids, names, several)
    if why is not None:
        return _error(why)
    try:
        with contextlib.ExitStack() as locks:
            for output in [args.json, args.plot]:
                if output:
                    locks.enter_context(OutputLock(output))
            executor = executor_from_args(args)
            with executor, sigterm_raises():  # after the executor: Ray sets its own handler
                return _run_envs(args, env_ids, names, several, executor)
    except (ExecutorError, OutputBusyError) as exc:
        return _error(str(exc))
    except OSError as exc:  # the lock file could not be created
        return _error(describe_os_error(exc))


def _probe(folder: Path) -> str | None:
    """Why no file can be written in the existing ``folder`` (``None`` if one can).

    A real probe (a temporary file of 4 KiB, written, flushed to disk and removed), not
    ``os.access``: root passes every permission check yet cannot create files in, e.g.,
    ``/proc``, nor write onto a full disk.
    """
    try:
        with tempfile.TemporaryFile(dir=folder) as fh:
            fh.write(b"\0" * 4096)
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def _unwritable(path: Path, option: str, *, folder: bool) -> str | None:
    """Why ``path`` cannot be written (``None`` if it can), creating nothing that stays."""
    if path.exists():
        if folder != path.is_dir():
            kind = "not a folder" if folder else "a folder, expected a file path"
            return f"{option} {path}: exists and is {kind}"
        target = path if folder else path.parent
        if not folder:
            try:  # an immutable or append-only file passes the folder probe, not the rename
                probe_replaceable(path)
            except OSError as exc:
                return f"{option} {describe_os_error(exc).removeprefix('cannot write ')}"
    else:
        target = path.parent
        while not target.exists():
            target = target.parent
        if not target.is_dir():
            return f"{option} {path}: {target} is not a folder"
    why = _probe(target)
    return None if why is None else f"{option} {path}: cannot write into {target} ({why})"


def _precheck(
    args: argparse.Namespace, env_ids: list[str], names: list[str] | None, several: bool
) -> str | None:
    """Check every argument before any work: outputs, env kwargs, named agents (and files).

    Returns:
        The one-line reason of the first problem, or ``None``.
    """
    from selenv.agents import make
    from selenv.bench import BenchError, EnvKwargsError, check_env_kwargs

    if args.json and (why := _unwritable(Path(args.json), "--json", folder=False)):
        return why
    if args.plot and (why := _unwritable(Path(args.plot), "--plot", folder=True)):
        return why
    for env_id in env_ids:
        try:
            check_env_kwargs(env_id, args.env_kwargs)
        except EnvKwargsError as exc:
            return f"--env-kwargs: {exc}"
        except BenchError as exc:
            return str(exc)
    for env_id in env_ids:
        for name in names or []:
            if env_id not in AGENTS[parse_spec(name)[0]]:
                if several:
                    continue  # noted and skipped when that env runs
                return (
                    f"agent {name!r} does not apply to {env_id} "
                    f"(agents for it: {', '.join(agents_for(env_id))})"
                )
            try:
                agent = make(name, env_id)  # options parsed, checkpoint files found and loaded
            except (TypeError, ValueError) as exc:  # a bad option name or value
                return f"cannot build agent {name!r} for {env_id}: {exc}"
            close = getattr(agent, "close", None)
            if callable(close):
                close()
    return None


def _run_envs(
    args: argparse.Namespace,
    env_ids: list[str],
    names: list[str] | None,
    several: bool,
    executor: Executor,
) -> int:
    """Run the checked bench of :func:`cmd_bench` on ``executor``; print and write results."""
    from selenv.bench import BenchError, EnvKwargsError, format_table, run_bench

    results: list[EnvBenchResult] = []  # every env started, the last one maybe incomplete
    stop: tuple[str, int] | None = None  # (what stopped the run, exit code)
    try:
        for env_id in env_ids:
            if several and names is not None:
                skip = [n for n in names if env_id not in AGENTS[parse_spec(n)[0]]]
                if skip:
                    _note(f"skipping {', '.join(skip)} on {env_id}: does not apply to it")
            try:
                result = run_bench(
                    env_id,
                    names,
                    episodes=args.episodes,
                    seed=args.seed,
                    env_kwargs=args.env_kwargs,
                    progress=not args.no_progress,
                    skip_inapplicable=several,
                    baseline=args.baseline,
                    executor=executor,
                    threads=(args.blas_threads or None, args.torch_threads or None),
                    max_episodes=args.max_episodes,
                    collect=results,
                    bounds=not args.no_bounds,
                )
            except EnvKwargsError as exc:
                return _error(f"--env-kwargs: {exc}")
            except BenchError as exc:
                return _error(str(exc))
            if len(results) > 1:
                print()
            print(format_table(result), flush=True)
    except KeyboardInterrupt:
        stop = ("interrupted (SIGINT)", 130)
    except Terminated:
        stop = ("terminated (SIGTERM)", 143)
    except WorkerDiedError as exc:
        stop = (str(exc), 1)
    except Exception as exc:  # a signal raised inside a C extension comes back wrapped
        stop = _signal_behind(exc)
        if stop is None:
            raise
    with DeferredSignals(second_raises=False) as late:
        return _finish(args, results, stop, executor, late.received)


def _signal_behind(exc: BaseException) -> tuple[str, int] | None:
    """The stop of a SIGINT / SIGTERM exception in ``exc``'s chain, else ``None``.

    Ray's Cython wrappers turn an exception raised by a signal handler into ``SystemError``.
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, KeyboardInterrupt):
            return ("interrupted (SIGINT)", 130)
        if isinstance(cur, Terminated):
            return ("terminated (SIGTERM)", 143)
        cur = cur.__cause__ or cur.__context__
    return None


def _finish(
    args: argparse.Namespace,
    results: list[EnvBenchResult],
    stop: tuple[str, int] | None,
    executor: Executor,
    late: list[int],
) -> int:
    """Print what a stopped run kept, write the JSON and the plots; return the exit code."""
    from selenv.bench import format_table, plot_filename, plot_result, results_to_json

    args.finished = True
    code = 0 if stop is None else stop[1]
    if stop is not None and results and not results[-1].complete:
        if len(results) > 1:
            print()
        print(format_table(results[-1]), flush=True)
    done = sum(n for r in results for n in r.episodes_done().values())
    kept = ""
    if args.json and results and (stop is None or done):
        doc = results_to_json(
            results, argv=getattr(args, "argv", None), executor=executor.describe()
        )
        target = Path(args.json)
        if stop is not None and stop[1] == 1:  # a failure: leave the --json as it was
            target = target.with_name(target.name + ".partial")
        try:
            atomic_write_json(target, doc)
            if stop is None:
                print(f"json: {target}", file=sys.stderr)
            kept = f"kept {done} finished episodes in {target} (marked incomplete)"
        except OSError as exc:
            code = 1 if code in (0, 1) else code
            if target != Path(args.json):
                kept = f"{describe_os_error(exc, target)}; the results could not be kept"
            else:
                kept = _keep_partial(target, doc, exc)
            if stop is None:
                print(f"selenv: {kept}", file=sys.stderr)
    elif stop is not None:
        if not done:
            kept = "no episode had finished" + (
                f"; {args.json} left as it was" if args.json else ""
            )
        else:
            kept = f"{done} finished episodes shown above (no --json given)"
    for result in results if args.plot else []:
        try:
            path = plot_result(result, args.plot)
        except OSError as exc:
            code = 1 if code in (0, 1) else code
            path = Path(args.plot) / plot_filename(result.env_id)
            print(f"selenv: {describe_os_error(exc, path)}", file=sys.stderr)
            continue
        print(f"plot: {path}", file=sys.stderr)
    if stop is not None:
        print(f"selenv: {stop[0]}; {kept}", file=sys.stderr)
    elif late:
        name = "SIGINT" if late[0] == signal.SIGINT else "SIGTERM"
        print(f"selenv: {name} received while writing the results (written)", file=sys.stderr)
        code = code or (130 if late[0] == signal.SIGINT else 143)
    return code


def _keep_partial(path: Path, doc: dict[str, object], exc: OSError) -> str:
    """After a failed write of ``path``: try ``<path>.partial``; one line saying what happened."""
    why = describe_os_error(exc, path)
    partial = path.with_name(path.name + ".partial")
    try:
        atomic_write_json(partial, doc)
    except OSError as again:
        cause = (again.strerror or str(again)).lower()
        return f"{why}; the results could not be kept ({partial}: {cause} as well)"
    return f"{why}; the results were kept in {partial}"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``selenv`` console script; returns the exit code.

    SIGINT / SIGTERM end any command with one line and exit 130 / 143. In the ``selenv``
    process the handlers are installed when ``selenv`` is first imported and the signals are
    held through the imports (:mod:`selenv._signals`): one received since exec stops here.

    Args:
        argv: arguments without the program name (default: ``sys.argv[1:]``).
    """
    args: argparse.Namespace | None = None
    try:
        with sigterm_raises():
            end_startup()
            parser = build_parser()
            try:
                args = parser.parse_args(None if argv is None else list(argv))
            except SystemExit as exc:  # argparse exits on --help, --version and usage errors
                return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
            if args.command == "list":
                return cmd_list()
            if args.command == "train":
                return cmd_train(args)
            args.argv = ["selenv", *(sys.argv[1:] if argv is None else argv)]
            return cmd_bench(args)
    except KeyboardInterrupt:  # during the checks or start-up, or while shutting down
        print(f"selenv: interrupted (SIGINT){_when_stopped(args)}", file=sys.stderr)
        return 130
    except Terminated:
        print(f"selenv: terminated (SIGTERM){_when_stopped(args)}", file=sys.stderr)
        return 143


def _when_stopped(args: argparse.Namespace | None) -> str:
    """What an interruption outside a bench run left: nothing, or the outputs already written."""
    if args is not None and args.command != "bench":
        return ""
    if getattr(args, "finished", False):
        return " while shutting down (the results were already reported above)"
    return " before any episode ran; nothing written"


if __name__ == "__main__":
    sys.exit(main())
