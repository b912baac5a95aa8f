"""The README's benchmark table and the ``make bench`` page are generated from the committed JSON.

``scripts/bench_tables.py --check`` must pass on the repository as committed; a perturbed JSON,
README or page must make it fail; the README row's picks (best, ``greedy``, best learned,
reference, random) are checked on small synthetic results.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from conftest import load_script

from selenv.agents import AGENTS
from selenv.bench import AgentResult, EnvBenchResult, format_table, results_to_json

ROOT = Path(__file__).resolve().parents[1]
CL = "selenv/CLScheduling-v1"


bt = load_script("bench_tables")


def _agent(name: str, returns: list[float], ms: float = 1.0) -> AgentResult:
    n = len(returns)
    return AgentResult(
        name,
        returns=list(returns),
        final_objectives=[-r for r in returns],
        decision_seconds=ms * 1e-3 * 10 * n,
        decisions=10 * n,
    )


def _result(agents: dict[str, list[float]], env_id: str = CL) -> EnvBenchResult:
    return EnvBenchResult(
        env_id=env_id,
        env_kwargs={},
        seed=0,
        episodes=len(next(iter(agents.values()))),
        agents={n: _agent(n, r) for n, r in agents.items()},
    )


#: CL returns on 4 seeds: rollout best, then cem (learned), round_robin, ppo (learned), greedy
SYNTHETIC = {
    "greedy": [1.00, 1.10, 0.90, 1.08],
    "round_robin": [1.03, 1.12, 0.93, 1.07],
    "random": [0.80, 0.85, 0.70, 0.93],
    "rollout": [1.10, 1.20, 1.00, 1.18],
    "cem": [1.06, 1.15, 0.95, 1.10],
    "ppo": [1.01, 1.11, 0.91, 1.06],
}


def _files(tmp_path: Path, results: list[EnvBenchResult]) -> tuple[Path, Path, Path]:
    """A JSON of ``results``, and a README and page with markers (filled by ``--write``)."""
    doc = results_to_json(results, argv=["selenv", "bench"])
    json_path = tmp_path / "bench.json"
    json_path.write_text(json.dumps(doc), encoding="utf-8")
    readme = tmp_path / "README.md"
    readme.write_text(
        "# x\n\n## Benchmark\n\nprose\n\n<!-- bench-table:start -->\n<!-- bench-table:end -->\n"
        "\nafter\n",
        encoding="utf-8",
    )
    page = tmp_path / "make_bench.md"
    blocks = "".join(
        f"## {r.env_id}\n\n<!-- bench-table:start {r.env_id} -->\nold\n"
        f"<!-- bench-table:end {r.env_id} -->\n\nprose about {r.env_id}\n\n"
        for r in results
    )
    page.write_text(
        "# page\n\n<!-- bench-table:start run -->\n<!-- bench-table:end run -->\n\n" + blocks,
        encoding="utf-8",
    )
    return json_path, readme, page


def test_committed_readme_and_page_agree_with_the_committed_json() -> None:
    """The repository's README table and make_bench.md tables are the JSON's (regenerate else)."""
    assert bt.JSON_PATH.is_file()
    assert bt.check() == []
    readme = bt.README.read_text(encoding="utf-8")
    doc = json.loads(bt.JSON_PATH.read_text(encoding="utf-8"))
    for env in doc["results"]:
        assert f"`{env['env_id'].split('/')[-1]}`" in readme
        assert f"`{env['best_agent']}`" in readme


def test_the_command_line_check_passes_on_the_repository(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--check`` on the repository's files: exit 0, nothing printed."""
    assert bt.main(["--check"]) == 0
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_page_tables_are_what_selenv_bench_prints(tmp_path: Path) -> None:
    """A page block is ``format_table`` of the run, rebuilt identically from its JSON."""
    result = _result(SYNTHETIC)
    json_path, readme, page = _files(tmp_path, [result])
    assert bt.write(json_path, readme, page) == [readme, page]
    text = page.read_text(encoding="utf-8")
    assert f"```text\n{format_table(result)}\n```" in text
    assert f"prose about {CL}" in text and "\nold\n" not in text
    assert bt.check(json_path, readme, page) == []
    assert bt.write(json_path, readme, page) == []  # nothing left to change


def test_a_perturbed_json_readme_or_page_is_detected(tmp_path: Path) -> None:
    """Changing a return in the JSON, or a digit in either file, makes the check fail."""
    json_path, readme, page = _files(tmp_path, [_result(SYNTHETIC)])
    bt.write(json_path, readme, page)
    assert bt.check(json_path, readme, page) == []
    good = {p: p.read_text(encoding="utf-8") for p in (json_path, readme, page)}

    doc = json.loads(good[json_path])
    doc["results"][0]["agents"]["greedy"]["returns"][0] += 0.01
    json_path.write_text(json.dumps(doc), encoding="utf-8")
    problems = bt.check(json_path, readme, page)
    assert len(problems) == 2 and all("differs from" in p for p in problems)
    json_path.write_text(good[json_path], encoding="utf-8")

    for path, start in ((readme, "| `CLScheduling-v1`"), (page, "greedy ")):
        line = next(ln for ln in good[path].splitlines() if ln.startswith(start))
        digit = next(c for c in line if c.isdigit())
        edited = line.replace(digit, str((int(digit) + 1) % 10), 1)
        path.write_text(good[path].replace(line, edited), encoding="utf-8")
        problems = bt.check(json_path, readme, page)
        assert len(problems) == 1 and problems[0].startswith(str(path)), problems
        path.write_text(good[path], encoding="utf-8")
    assert bt.check(json_path, readme, page) == []


def test_command_line_exit_codes(tmp_path: Path) -> None:
    """``--check``: 1 with one line per disagreeing file; a missing JSON or marker: 2, one line."""
    json_path, readme, page = _files(tmp_path, [_result(SYNTHETIC)])
    paths = ["--json", str(json_path), "--readme", str(readme), "--page", str(page)]
    assert bt.main(["--check", *paths]) == 1  # the files still hold "old"
    assert bt.main(["--write", *paths]) == 0
    assert bt.main(["--check", *paths]) == 0
    assert bt.main(["--check", *paths[:1], str(tmp_path / "none.json"), *paths[2:]]) == 2
    page.write_text(page.read_text(encoding="utf-8").replace("bench-table:end run", "x"))
    assert bt.main(["--check", *paths]) == 2


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["results"].clear(), "'results' is empty"),
        (lambda d: d["results"][0].update(complete=False), "stopped early"),
        (lambda d: d["results"][0]["agents"]["cem"].update(returns="x"), "'returns' is str"),
        (lambda d: d["results"][0].update(best_agent="greedy"), "'best_agent' is 'greedy'"),
        (lambda d: d.pop("provenance"), "no 'provenance' entry"),
    ],
)
def test_malformed_json_is_one_error_naming_the_problem(
    tmp_path: Path, edit: Any, message: str
) -> None:
    """A JSON that is not a complete bench result is refused with the entry named."""
    json_path, readme, page = _files(tmp_path, [_result(SYNTHETIC)])
    doc = json.loads(json_path.read_text(encoding="utf-8"))
    edit(doc)
    json_path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(bt.BenchTablesError, match=message):
        bt.check(json_path, readme, page)


def test_markers_must_match_the_generated_blocks() -> None:
    """Unknown, unclosed, duplicated and missing blocks are refused, not skipped."""
    blocks = {"a": "A", "b": "B"}
    ok = "<!-- bench-table:start a -->x<!-- bench-table:end a -->"
    ok += "<!-- bench-table:start b --><!-- bench-table:end b -->"
    assert bt.fill(ok, blocks, "f") == (
        "<!-- bench-table:start a -->\nA\n<!-- bench-table:end a -->"
        "<!-- bench-table:start b -->\nB\n<!-- bench-table:end b -->"
    )
    bad = {
        "no markers for b": ok.split("<!-- bench-table:start b")[0],
        "names no generated block": ok + "<!-- bench-table:start c -->",
        "never closed": "<!-- bench-table:start a -->",
        "closes no open block": "<!-- bench-table:end a -->",
        "inside an open block": "<!-- bench-table:start a --><!-- bench-table:start b -->",
        "appears twice": ok + "<!-- bench-table:start a --><!-- bench-table:end a -->",
    }
    for message, text in bad.items():
        with pytest.raises(bt.BenchTablesError, match=message):
            bt.fill(text, blocks, "f")


def test_picks_on_synthetic_results() -> None:
    """Best by mean return; best learned among the registry's learned agents; reference; random."""
    p = bt.picks(_result(SYNTHETIC))
    assert (p.best, p.greedy, p.learned, p.reference, p.random) == (
        "rollout", "greedy", "cem", "rollout", "random",
    )  # fmt: skip
    # round_robin beats ppo but is no learned agent; with cem gone ppo is the best learned
    p = bt.picks(_result({k: v for k, v in SYNTHETIC.items() if k != "cem"}))
    assert p.learned == "ppo"
    # a learned agent ahead of everything is both the best and the best learned agent
    ahead = {**SYNTHETIC, "cem": [r + 0.2 for r in SYNTHETIC["rollout"]]}
    p = bt.picks(_result(ahead))
    assert (p.best, p.learned) == ("cem", "cem")
    # no greedy, no learned agent, no reference and no random agent: empty cells
    p = bt.picks(_result({"round_robin": SYNTHETIC["round_robin"], "all": [0.4] * 4}))
    assert (p.best, p.greedy, p.learned, p.reference, p.random) == (
        "round_robin", None, None, None, None,
    )  # fmt: skip


def test_readme_row_shows_each_difference_to_the_best_agent() -> None:
    """The row's cells are the mean per-seed differences to the best agent, with the times."""
    row = bt.readme_row(_result(SYNTHETIC)).split(" | ")
    assert row[0] == "| `CLScheduling-v1`"
    assert row[1] == "`rollout`: 1.120 (1.00 ms)"  # its mean return, 4 significant digits
    assert row[2] == "-0.100* (1.00 ms)"  # greedy is 0.1 behind on every seed: CI excludes 0
    assert row[3] == "`cem`: -0.0550* (1.00 ms)"  # -0.04, -0.05, -0.05, -0.08
    assert row[4] == "0 (1.00 ms)"  # the reference is the best agent
    assert row[5] == "-0.300 |"  # random: -0.30, -0.35, -0.30, -0.25; no CI marker
    # a difference whose CI includes 0 has no marker: +0.05, -0.10, +0.05, -0.04
    mixed = {**SYNTHETIC, "greedy": [1.15, 1.10, 1.05, 1.14]}
    assert bt.readme_row(_result(mixed)).split(" | ")[2] == "-0.0100 (1.00 ms)"


def test_learned_marker_follows_the_layering() -> None:
    """The learned agents are exactly the policy records, their old names and ``learned``.

    A checkpoint-backed agent registered anywhere else (without a record) would drop out of
    the README's learned column and of ``learned``; every record's loader lives in
    ``selenv.learned`` (above the families), and no other agent's factory does.
    """
    from selenv.agents.learned import all_policies

    records = all_policies()
    names = {r.name for r in records} | {a for r in records for a in r.aliases} | {"learned"}
    marked = {name for name, by_env in AGENTS.items() if any(s.learned for s in by_env.values())}
    assert marked <= names
    assert {r.name for r in records} <= marked
    assert all(r.factory.startswith("selenv.learned.") for r in records)
    for by_env in AGENTS.values():
        for spec in by_env.values():
            if isinstance(spec.factory, str) and spec.factory.startswith("selenv.learned."):
                assert spec.learned, spec.name
    assert {"ppo", "cem", "ppo_search", "ppo_distilled"} <= marked
    assert not {"greedy", "rollout", "fast_rollout", "swap"} & marked


def test_write_leaves_the_files_unchanged_on_an_error(tmp_path: Path) -> None:
    """A page without its markers stops ``--write`` before anything is replaced."""
    json_path, readme, page = _files(tmp_path, [_result(SYNTHETIC)])
    page.write_text("# page without markers\n", encoding="utf-8")
    before = readme.read_bytes()
    with pytest.raises(bt.BenchTablesError, match="no markers"):
        bt.write(json_path, readme, page)
    assert readme.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "README.md",
        "bench.json",
        "make_bench.md",
    ]


def test_bounds_round_trip_and_show_as_gaps() -> None:
    """A JSON with a return bound gives back the bounds; rows and tables show each gap."""
    fim = "selenv/FIMSelection-v1"
    res = _result({"greedy": [9.0, 18.0], "swap": [9.5, 19.0], "random": [5.0, 6.0]}, fim)
    for agent in res.agents.values():
        agent.seeds = [0, 1]
    res.bounds, res.bound_kind, res.bound_method = {0: 10.0, 1: 20.0}, "bound", "relaxation"
    doc = json.loads(json.dumps(results_to_json([res], argv=["selenv", "bench"])))
    back = bt.env_result(doc["results"][0])
    assert back.bounds == {0: 10.0, 1: 20.0} and back.bound_method == "relaxation"
    assert back.gap_to_bound("greedy")[0] == pytest.approx(0.1)
    row = bt.readme_row(back)
    assert "`swap`: 14.25 (gap 5.000 %" in row and "(gap 10.000 %" in row
    assert "gap to bound" in format_table(back)
    assert "FIMSelection-v1: relaxation" in bt.readme_block(doc)
    bad = json.loads(json.dumps(doc))
    bad["results"][0]["return_bound"]["seeds"] = [0]
    with pytest.raises(bt.BenchTablesError, match="return_bound"):
        bt.env_result(bad["results"][0])
