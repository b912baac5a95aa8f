"""Generate the benchmark tables of the README and of the ``make bench`` page from its JSON.

The committed ``make bench`` result, ``docs/bench/make_bench.json`` (the ``bench_results.json``
of a full run), is the one source of the numbers shown in:

* ``README.md``, between ``<!-- bench-table:start -->`` and ``<!-- bench-table:end -->``: per
  env, the best agent (mean return, decision time), ``greedy``, the best learned agent (agents
  registered with ``learned=True``, :class:`selenv.agents.AgentSpec`), the reference
  (``rollout``) and the random one, each as its mean per-seed return difference to the best
  agent, then the run's date and commit;
* ``docs/benchmarks/make_bench.md``, between ``<!-- bench-table:start NAME -->`` and
  ``<!-- bench-table:end NAME -->``: ``NAME`` ``run`` is the run's provenance, and ``NAME`` an
  env id is that env's table exactly as ``selenv bench`` prints it
  (:func:`selenv.bench.format_table` of the results rebuilt from the JSON).

Everything outside the markers is prose, left as it is. After a new ``make bench``::

    cp bench_results.json docs/bench/make_bench.json
    .venv/bin/python scripts/bench_tables.py --write   # rewrite the generated parts
    .venv/bin/python scripts/bench_tables.py --check   # exit 1 if they disagree with the JSON

``--write`` replaces both files together, atomically (:func:`selenv.atomic.atomic_paths`).
``--check`` prints one line per file that disagrees and exits 1; a missing or malformed JSON,
or a file without its markers, is one line and exit 2. ``tests/test_bench_tables.py`` runs the
check, so the tables cannot drift from the JSON.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from selenv.agents import AGENTS, parse_spec
from selenv.agents.learned import learned_target
from selenv.atomic import atomic_paths
from selenv.bench import AgentResult, EnvBenchResult, format_table
from selenv.bench.report import column_decimals, decimals_for, format_fixed, format_ms
from selenv.learned.resources import read_metadata

ROOT = Path(__file__).resolve().parents[1]
JSON_PATH = ROOT / "docs" / "bench" / "make_bench.json"
README = ROOT / "README.md"
PAGE = ROOT / "docs" / "benchmarks" / "make_bench.md"
COMMAND = ".venv/bin/python scripts/bench_tables.py --write"

#: the non-myopic reference agent shown in the README table where it ran
REFERENCE = "rollout"
#: the README's single block (no name)
README_BLOCK = ""
#: the page's provenance block
RUN_BLOCK = "run"


def _marker(tag: str) -> re.Pattern[str]:
    """The markers ``<!-- TAG:start [NAME] -->`` / ``<!-- TAG:end [NAME] -->``."""
    return re.compile(rf"<!-- {re.escape(tag)}:(start|end)(?: (\S+))? -->")


class BenchTablesError(ValueError):
    """The JSON or a target file cannot be used (one line, naming the file and the problem)."""


# ---------------------------------------------------------------- reading the JSON


def _get(obj: Any, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise BenchTablesError(f"{where}: no {key!r} entry")
    value = obj[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and bool not in _kinds(kind)):
        raise BenchTablesError(f"{where}: {key!r} is {type(value).__name__}, not {_name(kind)}")
    return value


def _kinds(kind: type | tuple[type, ...]) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)


def _name(kind: type | tuple[type, ...]) -> str:
    return " or ".join(k.__name__ for k in _kinds(kind))


def _numbers(obj: dict[str, Any], key: str, where: str) -> list[float]:
    values = _get(obj, key, list, where)
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise BenchTablesError(f"{where}: {key!r} holds a value that is not a number")
    return [float(v) for v in values]


def load_bench(path: str | Path = JSON_PATH) -> dict[str, Any]:
    """The ``make bench`` JSON at ``path``, read size- and depth-bounded, its shape checked.

    Raises:
        BenchTablesError: missing, unreadable, not the bench JSON's shape, or an incomplete
            (stopped) run, which is not one to publish.
    """
    try:
        doc = read_metadata(path, what="bench JSON")
    except (FileNotFoundError, ValueError) as exc:
        raise BenchTablesError(str(exc)) from None
    where = str(path)
    _get(doc, "provenance", dict, where)
    results = _get(doc, "results", list, where)
    if not results:
        raise BenchTablesError(f"{where}: 'results' is empty")
    for i, env in enumerate(results):
        env_id = _get(env, "env_id", str, f"{where} results[{i}]")
        if not _get(env, "complete", bool, f"{where} {env_id}"):
            raise BenchTablesError(
                f"{where}: the run on {env_id} was stopped early; publish a complete run"
            )
    return doc


def env_result(env: dict[str, Any]) -> EnvBenchResult:
    """The :class:`~selenv.bench.EnvBenchResult` of one element of the JSON's ``results``.

    Returns, objectives, decision times and cost evaluations come back as the run measured
    them, so every statistic (paired CIs, scores) is recomputed identically.
    """
    env_id = _get(env, "env_id", str, "results")
    where = f"bench JSON {env_id}"
    agents: dict[str, AgentResult] = {}
    for name, rec in _get(env, "agents", dict, where).items():
        at = f"{where} agent {name}"
        if isinstance(rec, dict) and "skipped" in rec:
            agents[name] = AgentResult(name, skipped=str(rec["skipped"]))
            continue
        decisions = _get(rec, "decisions", int, at)
        per_decision = None
        if rec.get("cost_evaluations_per_decision") is not None:
            per_decision = _get(rec, "cost_evaluations_per_decision", (int, float), at)
        agents[name] = AgentResult(
            name,
            returns=_numbers(rec, "returns", at),
            final_objectives=_numbers(rec, "final_objectives", at),
            decision_seconds=float(_get(rec, "decision_seconds_mean", (int, float), at))
            * decisions,
            decisions=decisions,
            cost_evaluations=None if per_decision is None else round(per_decision * decisions),
        )
    given = env.get("baseline_rule") == "given"
    bound = env.get("return_bound")
    bounds: dict[int, float] = {}
    if bound is not None:
        seeds = _get(bound, "seeds", list, f"{where} return_bound")
        values = _numbers(bound, "values", f"{where} return_bound")
        if len(seeds) != len(values) or not all(type(x) is int for x in seeds):
            raise BenchTablesError(f"{where}: return_bound needs as many int seeds as values")
        bounds = dict(zip(seeds, values, strict=True))
    result = EnvBenchResult(
        env_id=env_id,
        env_kwargs=_get(env, "env_kwargs", dict, where),
        seed=_get(env, "seed", int, where),
        episodes=_get(env, "episodes", int, where),
        agents=agents,
        baseline=_get(env, "baseline", str, where) if given else None,
        kind=str(env.get("kind", "gymnasium")),
        timestamp=str(env.get("timestamp", "")),
        env_config=env.get("env_config"),
        bounds=bounds,
        bound_kind=None if bound is None else str(bound.get("kind")),
        bound_method=None if bound is None else str(bound.get("method")),
    )
    if result.best_agent != env.get("best_agent"):
        raise BenchTablesError(
            f"{where}: 'best_agent' is {env.get('best_agent')!r} but the returns make "
            f"{result.best_agent!r} the best"
        )
    return result


# ---------------------------------------------------------------- the README table


def is_learned(spec: str, env_id: str) -> bool:
    """Whether agent ``spec`` is a learned policy on ``env_id`` (its registry entry says so)."""
    name, _ = parse_spec(spec)
    entry = AGENTS.get(name, {}).get(env_id)
    return entry is not None and entry.learned


@dataclass(frozen=True)
class Picks:
    """The agents of one README row (``None`` where the env has none that ran)."""

    best: str
    greedy: str | None
    learned: str | None
    reference: str | None
    random: str | None


def picks(result: EnvBenchResult) -> Picks:
    """The best agent by mean return, ``greedy``, the learned agent and the reference.

    The learned agent is ``learned`` (the recommended one) where it ran, else the learned one
    (:func:`is_learned`) of largest mean return, the first on a tie, as
    :attr:`EnvBenchResult.best_agent` breaks ties.
    """
    ran = {n: r for n, r in result.agents.items() if r.skipped is None}
    best = result.best_agent
    if best is None:
        raise BenchTablesError(f"bench JSON {result.env_id}: no agent ran")
    learned = [n for n in ran if is_learned(n, result.env_id)]
    if "learned" in ran:  # the recommended learned agent, whatever the others did
        learned = ["learned"]
    return Picks(
        best=best,
        greedy="greedy" if "greedy" in ran else None,
        learned=max(learned, key=lambda n: ran[n].mean_return) if learned else None,
        reference=REFERENCE if REFERENCE in ran else None,
        random=result.random_reference,
    )


def difference(result: EnvBenchResult, name: str, best: str) -> str:
    """Agent ``name``'s mean per-seed return difference to ``best`` (3 significant digits).

    ``*`` when its paired 95 % CI excludes 0; ``0`` for the best agent itself.
    """
    if name == best:
        return "0"
    p = EnvBenchResult(
        result.env_id, result.env_kwargs, result.seed, result.episodes, result.agents, best
    ).paired(name)
    if p is None:
        raise BenchTablesError(f"bench JSON {result.env_id}: {name!r} or {best!r} did not run")
    d = p.mean_diff
    size = float(f"{abs(d):.12g}")  # -0.1 summed from floats reads -0.100, not -0.1000
    text = "0" if d == 0.0 else format_fixed(d, decimals_for(size, 3), sign=True)
    return text + ("*" if p.significant else "")


def _gap(result: EnvBenchResult, name: str) -> str:
    """``"gap 0.157 %, "`` to the env's certified bound on the return; ``""`` without one."""
    gap = result.gap_to_bound(name)
    return "" if gap is None else f"gap {format_fixed(100.0 * gap[0], 3)} %, "


def _cell(result: EnvBenchResult, name: str | None, best: str, *, named: bool) -> str:
    if name is None:
        return ""
    ms = format_ms(result.agents[name].decision_seconds_mean)
    text = f"{difference(result, name, best)} ({_gap(result, name)}{ms} ms)"
    if name == "learned" and (target := learned_target(result.env_id)):
        return f"`learned` (`{target}`): {text}"
    return f"`{name}`: {text}" if named else text


def readme_row(result: EnvBenchResult) -> str:
    """One env's row of the README table."""
    p = picks(result)
    ran = [r.mean_return for r in result.agents.values() if r.skipped is None]
    best = result.agents[p.best]
    mean = format_fixed(best.mean_return, column_decimals(ran))
    random = ""
    if p.random is not None:
        random = difference(result, p.random, p.best).rstrip("*")
        if p.random != "random":
            random += f" (`{p.random}`)"
    cells = [
        f"`{result.env_id.split('/')[-1]}`",
        f"`{p.best}`: {mean} ({_gap(result, p.best)}{format_ms(best.decision_seconds_mean)} ms)",
        _cell(result, p.greedy, p.best, named=False),
        _cell(result, p.learned, p.best, named=True),
        _cell(result, p.reference, p.best, named=False),
        random,
    ]
    return "| " + " | ".join(cells) + " |"


def _date_commit(doc: dict[str, Any]) -> tuple[str, str]:
    prov = doc["provenance"]
    date = str(prov.get("timestamp") or "")[:10] or "an unknown date"
    commit = str(prov.get("git_commit") or "")[:7] or "an unknown commit"
    if prov.get("git_dirty"):
        commit += " with uncommitted changes"
    return date, commit


def readme_block(doc: dict[str, Any]) -> str:
    """The README's generated block: the table and the run it comes from."""
    date, commit = _date_commit(doc)
    results = [env_result(env) for env in doc["results"]]
    rows = [readme_row(r) for r in results]
    bounded = [r for r in results if r.bounds]
    note = ""
    if bounded:
        which = "; ".join(f"{r.env_id.split('/')[-1]}: {r.bound_method}" for r in bounded)
        note = (
            " gap: mean `(bound - return) / |bound|` to a certified upper bound on each "
            f"episode's return ({which}); the gap to the optimum is at most this."
        )
    return "\n".join(
        [
            "| env | best agent: mean return (decision) | `greedy` | `learned` "
            f"| `{REFERENCE}` (reference) | random |",
            "|---|---|---|---|---|---|",
            *rows,
            "",
            f"*`make bench` of {date}, commit {commit}.{note}*",
        ]
    )


# ---------------------------------------------------------------- the make bench page


def page_blocks(doc: dict[str, Any]) -> dict[str, str]:
    """The page's generated blocks: ``run`` (provenance) and one table per env id."""
    prov = doc["provenance"]
    date, commit = _date_commit(doc)
    packages = ", ".join(f"{k} {v}" for k, v in prov.get("packages", {}).items() if v)
    args = [str(a) for a in prov.get("argv", [])]
    argv = " ".join([Path(args[0]).name, *args[1:]] if args else [])  # no machine's paths
    run = (
        f"Run of {date} at commit {commit} (selenv {prov.get('selenv_version')}, Python "
        f"{prov.get('python')} on {prov.get('platform')}; {packages}); command: `{argv}`."
    )
    blocks = {RUN_BLOCK: run}
    for env in doc["results"]:
        result = env_result(env)
        blocks[result.env_id] = f"```text\n{format_table(result)}\n```"
    return blocks


# ---------------------------------------------------------------- markers


def fill(text: str, blocks: dict[str, str], where: str, tag: str = "bench-table") -> str:
    """``text`` with the content between each pair of markers replaced by ``blocks[name]``.

    Raises:
        BenchTablesError: a marker without its pair, a block name that is not generated, or a
            generated block with no markers in ``text``.
    """
    out: list[str] = []
    pos = 0
    seen: set[str] = set()
    open_name: str | None = None
    for m in _marker(tag).finditer(text):
        kind, name = m.group(1), m.group(2) or ""
        label = f"'<!-- {tag}:{kind}{' ' + name if name else ''} -->'"
        if kind == "start":
            if open_name is not None:
                raise BenchTablesError(f"{where}: {label} inside an open block")
            if name not in blocks:
                raise BenchTablesError(f"{where}: {label} names no generated block")
            if name in seen:
                raise BenchTablesError(f"{where}: {label} appears twice")
            out.append(text[pos : m.end()])
            out.append("\n" + blocks[name] + "\n")
            open_name = name
        else:
            if open_name != name:
                raise BenchTablesError(f"{where}: {label} closes no open block")
            seen.add(name)
            open_name = None
        pos = m.start() if kind == "end" else m.end()
    if open_name is not None:
        raise BenchTablesError(f"{where}: block {open_name!r} is never closed")
    missing = [n or "(the table)" for n in blocks if n not in seen]
    if missing:
        raise BenchTablesError(f"{where}: no markers for {', '.join(missing)}")
    out.append(text[pos:])
    return "".join(out)


def expected(
    json_path: str | Path = JSON_PATH, readme: str | Path = README, page: str | Path = PAGE
) -> dict[Path, tuple[str, str]]:
    """Each target file -> (its current text, the text the JSON gives it)."""
    doc = load_bench(json_path)
    targets = {Path(readme): {README_BLOCK: readme_block(doc)}, Path(page): page_blocks(doc)}
    out: dict[Path, tuple[str, str]] = {}
    for path, blocks in targets.items():
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise BenchTablesError(f"{path}: cannot be read: {exc.strerror}") from None
        out[path] = (text, fill(text, blocks, str(path)))
    return out


def _first_difference(old: str, new: str) -> str:
    a, b = old.splitlines(), new.splitlines()
    for i, (x, y) in enumerate(zip(a, b, strict=False)):
        if x != y:
            return f"line {i + 1} is {x[:60]!r}, the JSON gives {y[:60]!r}"
    return f"{len(a)} lines, the JSON gives {len(b)}"


def _show(path: str | Path) -> str:
    """``path`` relative to the repository when inside it (how messages name files)."""
    resolved = Path(path).resolve()
    return str(resolved.relative_to(ROOT)) if resolved.is_relative_to(ROOT) else str(path)


def check(
    json_path: str | Path = JSON_PATH, readme: str | Path = README, page: str | Path = PAGE
) -> list[str]:
    """One line per file whose generated parts disagree with the JSON (empty: all agree)."""
    return [
        f"{_show(path)}: generated part differs from {_show(json_path)} "
        f"({_first_difference(old, new)}); run {COMMAND}"
        for path, (old, new) in expected(json_path, readme, page).items()
        if old != new
    ]


def write(
    json_path: str | Path = JSON_PATH, readme: str | Path = README, page: str | Path = PAGE
) -> list[Path]:
    """Rewrite the generated parts of the files that disagree, together and atomically."""
    changed = {p: new for p, (old, new) in expected(json_path, readme, page).items() if old != new}
    if not changed:
        return []
    with atomic_paths(list(changed)) as temps:
        for temp, new in zip(temps, changed.values(), strict=True):
            temp.write_text(new, encoding="utf-8")
    return list(changed)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``--write`` or ``--check`` (exit 0 agree / written, 1 differ, 2 error)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite the generated parts")
    mode.add_argument("--check", action="store_true", help="exit 1 if they disagree")
    parser.add_argument("--json", default=str(JSON_PATH), help="the make bench JSON")
    parser.add_argument("--readme", default=str(README), help="the README to fill")
    parser.add_argument("--page", default=str(PAGE), help="the make bench page to fill")
    args = parser.parse_args(argv)
    try:
        if args.check:
            problems = check(args.json, args.readme, args.page)
            for line in problems:
                print(line, file=sys.stderr)
            return 1 if problems else 0
        for path in write(args.json, args.readme, args.page):
            print(f"wrote {path}")
    except BenchTablesError as exc:
        print(f"bench_tables.py: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bench_tables.py: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
