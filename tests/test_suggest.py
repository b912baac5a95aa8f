"""'Did you mean' for mistyped env ids, agent names and keywords (selenv.suggest and its users)."""

from __future__ import annotations

import gymnasium as gym
import pytest

import selenv  # noqa: F401  (registers the Gymnasium ids)
from selenv.agents import AGENTS, agents_for, make
from selenv.bench import check_env_id
from selenv.bench.runner import BenchError
from selenv.cli import main
from selenv.suggest import close_matches, did_you_mean, did_you_mean_each, with_suggestion

FIM = "selenv/FIMSelection-v1"
CL = "selenv/CLScheduling-v1"
RC = "selenv/ReceiverClustering-v1"


# -- the helpers -------------------------------------------------------------------------------
def test_close_matches_finds_the_typo_and_nothing_for_a_stranger() -> None:
    names = ["greedy", "lazy_greedy", "random", "swap"]
    assert close_matches("gredy", names) == ["greedy"]  # lazy_greedy is much further
    assert close_matches("lazygreedy", names) == ["lazy_greedy"]
    assert close_matches("zzzz", names) == []
    assert close_matches("swap", ["swap"]) == []  # the word itself is no suggestion


def test_close_matches_ignores_case_and_keeps_the_spelling() -> None:
    ids = ["selenv/FIMSelection-v1", "selenv/CLScheduling-v1"]
    assert close_matches("selenv/fimselection-v1", ids) == ["selenv/FIMSelection-v1"]


def test_close_matches_refuses_a_non_string() -> None:
    with pytest.raises(TypeError, match="word must be a str"):
        close_matches(3, ["a"])  # type: ignore[arg-type]


def test_wording_of_one_two_and_no_suggestions() -> None:
    assert did_you_mean("budgt", ["budget", "horizon"]) == "did you mean 'budget'?"
    assert did_you_mean("ab", ["abc", "abd", "xyz"]) in {
        "did you mean 'abc' or 'abd'?",
        "did you mean 'abd' or 'abc'?",
    }
    assert did_you_mean("q", ["budget"]) == ""
    assert did_you_mean_each(["budgt", "q", "senors"], ["budget", "sensors"]) == (
        "did you mean 'budget' for 'budgt', 'sensors' for 'senors'?"
    )
    assert did_you_mean_each(["q", "w"], ["budget"]) == ""


def test_with_suggestion_joins_the_parts() -> None:
    known = ["budget"]
    assert with_suggestion("bad 'budgt'", "budgt", known, "known: budget") == (
        "bad 'budgt'; did you mean 'budget'? known: budget"
    )
    assert with_suggestion("bad 'q'", "q", known, "known: budget") == "bad 'q'; known: budget"
    assert with_suggestion("bad 'q'", "q", known) == "bad 'q'"


# -- agent names -------------------------------------------------------------------------------
def test_make_suggests_and_lists_only_the_agents_of_the_env() -> None:
    with pytest.raises(ValueError, match=r"did you mean 'greedy'\?") as exc:
        make("gredy", FIM)
    message = str(exc.value)
    assert message.startswith(f"unknown agent 'gredy' for {FIM}; ")
    listed = message.split("agents for this env: ")[1].split(", ")
    assert listed == agents_for(FIM)
    not_for_fim = [name for name, by_env in AGENTS.items() if FIM not in by_env]
    assert not_for_fim, "the check below needs an agent that does not apply to FIM"
    assert not set(not_for_fim) & set(listed)


def test_make_with_a_name_close_to_nothing_lists_without_a_question() -> None:
    with pytest.raises(ValueError, match="unknown agent") as exc:
        make("qqqqqq", FIM)
    assert "did you mean" not in str(exc.value)
    assert "agents for this env: " in str(exc.value)


def test_an_agent_option_typo_is_suggested() -> None:
    with pytest.raises(ValueError, match=r"no option.*'top_kk'.*did you mean 'top_k'\?"):
        make("rollout:top_kk=2", CL)


def test_bench_cli_unknown_agent_is_one_line_with_the_suggestion(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", FIM, "--agents", "gredy", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"unknown agent 'gredy' for {FIM}; did you mean 'greedy'? agents for this env: " in err
    assert err.rstrip().endswith(", ".join(agents_for(FIM)))


def test_bench_cli_several_unknown_agents_each_get_a_suggestion(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", FIM, "--agents", "gredy,swp", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'greedy' for 'gredy', 'swap' for 'swp'?" in err


# -- env ids -----------------------------------------------------------------------------------
def test_unknown_env_id_suggests_the_registered_one() -> None:
    with pytest.raises(BenchError, match=r"unknown env id .*did you mean 'selenv/FIMSelection-v1'"):
        check_env_id("selenv/FIMSelecton-v1")


def test_bench_cli_unknown_module_suggests_the_module(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "selenv.multiagent.fim_selecton_v0", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'selenv.multiagent.fim_selection_v0'?" in err and err.count("\n") == 1


# -- env constructor keywords ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("env_id", "typo", "meant"),
    [(FIM, "budgt", "budget"), (CL, "budgt", "budget"), (RC, "horizn", "horizon")],
)
def test_env_keyword_typo_is_a_type_error_with_a_suggestion(
    env_id: str, typo: str, meant: str
) -> None:
    with pytest.raises(TypeError, match=f"unexpected keyword argument '{typo}'") as exc:
        gym.make(env_id, **{typo: 3})
    assert f"did you mean '{meant}'?" in str(exc.value)
    assert f"'{meant}'" in str(exc.value).split("known: ")[1]


def test_env_keyword_stranger_is_listed_without_a_question() -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument 'colour'") as exc:
        gym.make(FIM, colour="red")
    assert "did you mean" not in str(exc.value) and "known: " in str(exc.value)


def test_vector_env_keyword_typo_is_a_type_error_with_a_suggestion() -> None:
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'budgt'.*'budget'\?"):
        gym.make_vec(FIM, num_envs=2, budgt=3)
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'horizn'.*'horizon'\?"):
        gym.make_vec(RC, num_envs=2, horizn=3)


def test_pettingzoo_keyword_typo_is_a_type_error_with_a_suggestion() -> None:
    from selenv.multiagent import fim_selection_v0, receiver_clustering_v1

    with pytest.raises(TypeError, match=r"unexpected keyword argument 'budgts'.*'budgets'\?"):
        fim_selection_v0.parallel_env(budgts=3)
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'horizn'.*'horizon'\?"):
        receiver_clustering_v1.parallel_env(horizn=3)
