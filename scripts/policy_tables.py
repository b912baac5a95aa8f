"""Generate the learned-policy tables of the docs from the policy records and their standings.

The records (:class:`selenv.families.policy.PolicySpec`, one ``policies`` module per family) and
the standings in the checkpoint JSONs (``scripts/record_standings.py``) are the one source of
the tables in ``docs/guide/choosing_learned.md``, between ``<!-- policy-table:start policies -->``
and ``<!-- policy-table:end policies -->`` (the table of every shipped learned agent) and
``<!-- policy-table:start deprecated -->`` / ``end`` (the old names and what replaces them), and
of the README's ``learned`` block (what ``learned`` plays on each env, and its standing)::

    .venv/bin/python scripts/policy_tables.py --write   # rewrite the generated parts
    .venv/bin/python scripts/policy_tables.py --check   # exit 1 if they disagree

``tests/test_policy_tables.py`` runs the check, so the page cannot drift from the records.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from selenv.agents.learned import all_policies, resolve_learned
from selenv.atomic import write_text
from selenv.families.policy import METHODS, PolicySpec, Standing

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tables import BenchTablesError, fill

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "guide" / "choosing_learned.md"
README = ROOT / "README.md"
#: the marker tag: ``<!-- policy-table:start NAME -->`` ... ``<!-- policy-table:end NAME -->``
TAG = "policy-table"
COMMAND = ".venv/bin/python scripts/policy_tables.py --write"


def _at_defaults(record: PolicySpec, env_id: str) -> list[Standing]:
    mine = [s for s in record.standings() if s.env_id == env_id]
    return sorted(mine, key=lambda s: (bool(s.env_kwargs), sorted(s.env_kwargs.items())))


def _diff(s: Standing) -> str:
    mark = "" if s.beats_baseline else " (not a win)"
    where = "".join(f" at {k}={v}" for k, v in sorted(s.env_kwargs.items()))
    return f"{s.difference_text()}{mark}, {s.wins}/{s.ties}/{s.losses}{where}"


def _time(record: PolicySpec, s: Standing) -> str:
    text = f"{s.decision_time_ratio:.2f}x"
    if not record.within_budget(s):
        text += f" (over its {record.max_decision_ratio:g}x budget)"
    return text


def _share(s: Standing) -> str:
    ref = s.reference
    if ref is None:
        return "-"
    lo, hi = ref["share_ci95"]
    return f"{100 * ref['share_of_edge']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def _valid(record: PolicySpec) -> str:
    if not record.valid:
        return "any"
    return "; ".join(f"{k} in {', '.join(map(str, v))}" for k, v in record.valid.items())


def policies_block() -> str:
    """The table of every shipped learned agent, env by env, ``learned`` first."""
    rows = [
        "| env / module | agent | method | vs baseline on held-out seeds: mean [95 % CI], "
        "W/T/L | decision time / baseline's | share of `rollout`'s edge | verified on |",
        "|---|---|---|---|---|---|---|",
    ]
    envs = list(dict.fromkeys(e for r in all_policies() for e in r.plays))
    for env_id in envs:
        chosen = resolve_learned(env_id)
        first = f"`{env_id}`"
        if chosen is not None:
            rows.append(f"| {first} | **`learned`** | plays `{chosen[0].name}` | | | | |")
            first = ""
        for record in (r for r in all_policies() if env_id in r.plays):
            standings = _at_defaults(record, env_id)
            name = f"`{record.name}`" + (" (retired)" if record.retired else "")
            method = METHODS[record.method].split(" (")[0]
            if not standings:
                rows.append(
                    f"| {first} | {name} | {method} | not measured | | | {_valid(record)} |"
                )
                first = ""
                continue
            for s in standings:
                rows.append(
                    f"| {first} | {name} | {method} | {_diff(s)} vs `{s.baseline}` | "
                    f"{_time(record, s)} | {_share(s)} | {_valid(record)} |"
                )
                first = name = method = ""
    seeds = sorted({(s.seed, s.episodes) for r in all_policies() for s in r.standings()})
    where = ", ".join(f"seeds {a}-{a + n - 1}" for a, n in seeds)
    rows.append("")
    rows.append(
        f"Measured by `selenv bench` on {where} (never used in training or selection), at each "
        "env's default keywords unless a keyword is named; decision times are ratios to the "
        "baseline's, timed in interleaved rounds (`benchmarks/bench_decision_time.py`, one "
        "BLAS and one torch thread) for the Gymnasium envs and in the bench run for the "
        "PettingZoo modules."
    )
    return "\n".join(rows)


def deprecated_block() -> str:
    """The old names, what they now play, and the retired policies."""
    rows = ["| old name | on | use instead |", "|---|---|---|"]
    for record in all_policies():
        for alias, options in record.aliases.items():
            spelling = ":".join([record.name, *(f"{k}={v}" for k, v in options.items())])
            rows.append(f"| `{alias}` | {', '.join(record.plays)} | `{spelling}` |")
        if record.retired:
            rows.append(
                f"| `{record.name}` (shipped weights) | {', '.join(record.plays)} | "
                f"{record.retired} |"
            )
    return "\n".join(rows)


def readme_block() -> str:
    """The README's block: per env and module, what ``learned`` plays and how it stands."""
    rows = [
        "| env / module | `learned` plays | vs baseline on held-out seeds: mean [95 % CI], "
        "W/T/L (seeds) | decision time / baseline's |",
        "|---|---|---|---|",
    ]
    envs = list(dict.fromkeys(e for r in all_policies() for e in r.plays))
    for env_id in envs:
        for kwargs in _measured_settings(env_id):
            label = f"`{env_id}`" + "".join(f" ({k}={v})" for k, v in sorted(kwargs.items()))
            chosen = resolve_learned(env_id, kwargs if kwargs else None)
            if chosen is None:
                rows.append(f"| {label} | none yet | | |")
                continue
            record, standing = chosen
            rows.append(
                f"| {label} | `{record.name}` ({METHODS[record.method].split(' (')[0]}) | "
                f"{_diff(standing)} ({standing.episodes}) vs `{standing.baseline}` | "
                f"{standing.decision_time_ratio:.1f}x |"
            )
    return "\n".join(rows)


def _measured_settings(env_id: str) -> list[dict[str, object]]:
    """The defaults, then every keyword setting a standing of ``env_id`` was measured at."""
    settings: dict[str, dict[str, object]] = {"{}": {}}
    for record in all_policies():
        for s in record.standings():
            if s.env_id == env_id and s.env_kwargs:
                settings.setdefault(repr(sorted(s.env_kwargs.items())), dict(s.env_kwargs))
    return list(settings.values())


def expected(page: str | Path = PAGE, readme: str | Path = README) -> dict[Path, tuple[str, str]]:
    """Each target file -> (its current text, the text the records give it)."""
    targets = {
        Path(page): {"policies": policies_block(), "deprecated": deprecated_block()},
        Path(readme): {"learned": readme_block()},
    }
    out = {}
    for path, blocks in targets.items():
        text = path.read_text(encoding="utf-8")
        out[path] = (text, fill(text, blocks, str(path), tag=TAG))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``--write`` or ``--check`` (exit 0 agree / written, 1 differ, 2 error)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite the generated parts")
    mode.add_argument("--check", action="store_true", help="exit 1 if they disagree")
    parser.add_argument("--page", default=str(PAGE), help="the choosing page to fill")
    parser.add_argument("--readme", default=str(README), help="the README to fill")
    args = parser.parse_args(argv)
    try:
        texts = expected(args.page, args.readme)
    except (BenchTablesError, OSError, ValueError) as exc:
        print(f"policy_tables.py: {exc}", file=sys.stderr)
        return 2
    differ = {path: new for path, (old, new) in texts.items() if old != new}
    if args.check:
        for path in differ:
            print(
                f"{path}: generated part differs from the records; run {COMMAND}", file=sys.stderr
            )
        return 1 if differ else 0
    for path, new in differ.items():
        write_text(path, new)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
