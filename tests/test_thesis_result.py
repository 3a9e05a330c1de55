"""benchmarks/thesis_result.py: the verdict rule on the thesis' claims (the README's table)."""

from __future__ import annotations

import importlib.util
import math

import optuna
from conftest import ROOT
from synthetic_study import write_planned_study

from sweeper.results._frame import load_study_frame
from sweeper.spec._models import load_spec

_spec = importlib.util.spec_from_file_location(
    "thesis_result", ROOT / "benchmarks" / "thesis_result.py"
)
thesis_result = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(thesis_result)


def test_a_claim_holds_only_when_every_interval_lies_above_one_half():
    judge = thesis_result.judge
    assert judge([(0.6, 0.9), (0.51, 1.0)]) == "holds"
    assert judge([(0.6, 0.9), (0.5, 1.0)]) == "not settled"  # 0.5 itself: a tie is possible
    assert judge([(0.6, 0.9), (0.0, 0.49)]) == "contradicted"  # one clearly behind
    assert judge([(0.2, 0.8)]) == "not settled"
    assert judge([]) == "not settled"  # no pair of trials
    assert judge([(math.nan, math.nan)]) == "not settled"


def test_solves_needs_the_bar_and_an_interval_above_chance():
    solved_at = thesis_result.solved_at
    assert solved_at(0.85, 0.5, 0.18)
    assert not solved_at(0.85, 0.18, 0.18)  # the interval reaches what chance gives
    assert not solved_at(0.79, 0.7, 0.18)  # below the bar
    assert solved_at(0.8, 0.0, None)  # no random agent measured: the bar alone
    assert thesis_result.condition("1/16, critic_tau 0.01", 15000, 4) == (
        "1/16 of A.1's gradient samples, critic_tau 0.01, 15k steps, 4 trials"
    )


def test_the_solves_claims_at_each_gradient_budget(tmp_path):
    frame = load_study_frame(thesis_result.STORAGE, "fetch_reach_cpu")
    missing = f"sqlite:///{tmp_path / 'none.db'}"
    lines = thesis_result.budget_claims(frame, [("fetch_reach_budget", missing)])
    assert len(lines) == 1 and lines[0].startswith("No budget study: ")
    assert not (tmp_path / "none.db").exists()  # nothing created

    url = f"sqlite:///{tmp_path / 'budget.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    spec = load_spec(ROOT / "studies" / "fetch_reach_budget.yaml")
    write_planned_study(url, spec, final_success=lambda key: 0.9 if "b128x2" in key else 0.3)
    follow_up = ("fetch_reach_budget_seeds", missing)  # not published: said, not joined
    lines = thesis_result.budget_claims(frame, [("fetch_reach_budget", url), follow_up])
    assert lines[1] == (
        f"fetch_reach_budget_seeds is not joined: {tmp_path / 'none.db'} does not exist "
        "(studies/fetch_reach_budget_seeds.yaml, not published yet)."
    )
    assert "Rule: " in lines[0] and "random agent's success rate (0.18)" in lines[0]
    claims = [line for line in lines if line.startswith("- ")]
    assert len(claims) == 8  # pixel and conv at 1/16, 1/16 with critic_tau 0.01, 1/4, 1/2
    # 4 trials a setting: fewer than 5, whichever side of the bar
    few = "- PIXEL solves FetchReach: not settled at 1/16 of A.1's gradient samples, "
    assert claims[0].startswith(few + "15k steps, 4 trials (IQM final success 0.20")
    assert claims[0].endswith("; fewer than 5 trials)")
    assert claims[1].startswith(few + "critic_tau 0.01, 15k steps, 4 trials")
    assert claims[3].startswith(  # above the bar, but on 4 trials
        "- PIXEL solves FetchReach: not settled at 1/2 of A.1's gradient samples, 15k steps, "
        "4 trials (IQM final success 0.90 [0.90, 0.90]; fewer than 5 trials)"
    )
    assert claims[7].startswith("- CONV solves FetchReach: not settled at 1/2 ")

    # the follow-up on seeds 2 and 3, published: every setting it ran gains its 4 trials
    more = f"sqlite:///{tmp_path / 'seeds.db'}"
    spec = load_spec(ROOT / "studies" / "fetch_reach_budget_seeds.yaml")
    write_planned_study(more, spec, final_success=lambda key: 0.9 if "b128x2" in key else 0.3)
    follow_up = ("fetch_reach_budget_seeds", more)
    lines = thesis_result.budget_claims(frame, [("fetch_reach_budget", url), follow_up])
    assert "(fetch_reach_cpu + fetch_reach_budget + fetch_reach_budget_seeds)" in lines[0]
    claims = [line for line in lines if line.startswith("- ")]
    assert len(claims) == 8
    published = "- PIXEL solves FetchReach: does not hold at 1/16 of A.1's gradient samples, "
    assert claims[0].startswith(published + "15k steps, 8 trials")
    assert "fewer than" not in claims[0]
    assert claims[3].startswith("- PIXEL solves FetchReach: holds at 1/2 ")  # 8 trials
