"""Paired successive halving: the schedule, the rules and the offline replay (pure)."""

from __future__ import annotations

import pytest

from sweeper.plan import _halving as halving
from sweeper.spec import default_rungs


def test_rung_sizes_keep_a_fraction_rounded_up_and_at_least_one():
    assert halving.rung_sizes(20, 3, 1 / 3) == (20, 7, 3)
    assert halving.rung_sizes(3, 3, 1 / 3) == (3, 1, 1)
    assert halving.rung_sizes(3, 2, 0.34) == (3, 2)  # 1.02 rounds up
    assert halving.rung_sizes(9, 3, 1 / 3) == (9, 3, 1)  # 3 * (1/3) is 1, not 2
    assert halving.rung_sizes(4, 1, 0.5) == (4,)
    with pytest.raises(ValueError, match="keep"):
        halving.rung_sizes(4, 2, 0.0)


def test_env_steps_spent_by_hand():
    # 20 configs to 2000, 7 on to 6000, 3 on to 20000, 2 seeds
    spent = halving.env_steps_spent((2000, 6000, 20000), (20, 7, 3), seeds=2)
    assert spent == 2 * (20 * 2000 + 7 * 4000 + 3 * 14000)
    assert spent / (20 * 2 * 20000) == pytest.approx(0.275)


def test_default_rungs_are_on_the_grid_below_the_budget():
    assert default_rungs(20000, 1000) == (2000, 6000)
    assert default_rungs(15000, 1000) == (1000, 5000)
    # never inside the random-action seed phase (fetch_reach_cpu: 1,000 seed steps)
    assert default_rungs(15000, 1000, seed_steps=1000) == (2000, 5000)
    assert default_rungs(20000, 1000, seed_steps=1000) == (2000, 6000)
    assert default_rungs(9000, 1000, seed_steps=2500) == (3000,)
    assert default_rungs(900, 1000) == ()


def test_auc_until_cuts_the_curve_at_the_rung():
    steps, values = (0, 10, 20, 30), (0.0, 1.0, 1.0, 0.0)
    assert halving.auc_until(steps, values, 20) == pytest.approx(0.75)  # (0.5 + 1) * 10 / 20
    assert halving.auc_until(steps, values, 30) == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="not an evaluation step"):
        halving.auc_until(steps, values, 15)


def test_best_breaks_ties_to_the_lower_id():
    assert halving.best({0: 0.5, 1: 0.7, 2: 0.7, 3: 0.1}, 1) == [1]
    assert halving.best({0: 0.5, 1: 0.7, 2: 0.7, 3: 0.1}, 2) == [1, 2]
    assert halving.best({0: 0.5, 1: 0.5}, 1) == [0]
    assert halving.best({0: 2.0, 1: 1.0, 2: 1.0}, 1, low_is_good=True) == [1]


def test_mean_ranks_by_hand_with_ties():
    scores = {"a": {0: 0.9, 1: 0.5, 2: 0.1}, "b": {0: 0.2, 1: 0.2, 2: 0.8}}
    # a: ranks 1, 2, 3; b: ranks 2.5, 2.5, 1
    assert halving.mean_ranks(scores) == {0: 1.75, 1: 2.25, 2: 2.0}
    with pytest.raises(ValueError, match="not"):
        halving.mean_ranks({"a": {0: 1.0, 1: 0.0}, "b": {0: 1.0}})


def test_promote_per_method_and_mean_rank():
    scores = {"a": {0: 0.9, 1: 0.5, 2: 0.1}, "b": {0: 0.2, 1: 0.3, 2: 0.8}}
    assert halving.promote(scores, 1, "per_method") == {"a": [0], "b": [2]}
    # mean ranks: 0 -> 2, 1 -> 2, 2 -> 2: all tied, the lowest id goes on for both
    assert halving.promote(scores, 1, "mean_rank") == {"a": [0], "b": [0]}
    with pytest.raises(ValueError, match="per_method, mean_rank"):
        halving.promote(scores, 1, "median")  # type: ignore[arg-type]


def _curves(shapes: dict[tuple[str, int], list[float]], seeds=(0, 1)):
    steps = list(range(0, 100 * len(next(iter(shapes.values()))), 100))
    return {(m, c, s): (steps, values) for (m, c), values in shapes.items() for s in seeds}


def test_replay_a_late_starter_is_lost_and_reported():
    # method a: config 1 starts slowly but ends best; the first rung at 100 drops it
    shapes = {
        ("a", 0): [0.0, 0.3, 0.3, 0.3, 0.3],
        ("a", 1): [0.0, 0.0, 1.0, 1.0, 1.0],
        ("a", 2): [0.0, 0.1, 0.1, 0.1, 0.1],
        ("b", 0): [0.0, 0.2, 0.2, 0.2, 0.2],
        ("b", 1): [0.0, 0.1, 0.1, 0.1, 0.1],
        ("b", 2): [0.0, 0.6, 0.9, 0.9, 0.9],
    }
    result = halving.replay(_curves(shapes), rungs=[100], keep=1 / 3, rule="per_method")
    a, b = result["a"], result["b"]
    assert a.alive == ((0, 1, 2), (0,)) and b.alive == ((0, 1, 2), (2,))
    assert a.best_full == 1 and a.chosen == 0 and not a.survived
    assert a.auc_lost == pytest.approx(0.625 - 0.2625)  # full AUCs of configs 1 and 0
    assert b.survived and b.auc_lost == 0
    # 3 configs to 100, 1 on to 400: (3 * 100 + 300) / (3 * 400)
    assert a.compute_fraction == pytest.approx(0.5)
    # a later rung keeps the late starter
    late = halving.replay(_curves(shapes), rungs=[200], keep=1 / 3, rule="per_method")
    assert late["a"].survived and late["a"].auc_lost == 0


def test_replay_mean_rank_keeps_the_comparison_paired():
    shapes = {
        (m, c): [0.0, 0.1 * (c + 1) * (1 if m == "a" else 3 - c), 0.5]
        for m in "ab"
        for c in range(3)
    }
    result = halving.replay(_curves(shapes), rungs=[100], keep=0.5, rule="mean_rank")
    assert result["a"].alive == result["b"].alive


def test_replay_refuses_an_incomplete_study_and_bad_rungs():
    shapes = {("a", 0): [0.0, 1.0, 1.0], ("a", 1): [0.0, 0.0, 1.0]}
    curves = dict(_curves(shapes))
    with pytest.raises(ValueError, match="budget"):
        halving.replay(curves, rungs=[200], keep=0.5, rule="per_method")
    del curves[("a", 1, 1)]
    with pytest.raises(ValueError, match="not complete"):
        halving.replay(curves, rungs=[100], keep=0.5, rule="per_method")


def _halving_spec(**halving):
    return _plain_spec(halving=halving)


def test_a_spec_halving_section_enters_the_plan_and_its_hash_only_when_present():
    from sweeper.plan._entries import build_plan
    from sweeper.spec._models import SpecError

    plain = build_plan(_plain_spec())
    assert plain.schedule is None
    spec = _halving_spec(rungs=[200, 400], keep=0.34)
    plan = build_plan(spec)
    assert plan.schedule.stops == (200, 400, 900) and plan.schedule.sizes == (3, 2, 1)
    assert plan.schedule.rule == "per_method"
    assert plan.hash != plain.hash and plan.keys() == plain.keys()
    assert (
        build_plan(_halving_spec(rungs=[200, 400], keep=0.34, rule="mean_rank")).hash != plan.hash
    )
    # the default rungs: 1/9 and 1/3 of 900 on the grid, 100 and 300; the first is the end
    # of the 100 seed steps, so it moves to the first evaluation past them
    assert build_plan(_halving_spec()).schedule.stops == (200, 300, 900)
    with pytest.raises(SpecError, match=r"past budget\.seed_steps"):
        _halving_spec(rungs=[100])


def _plain_spec(**changes):
    """studies/ci.yaml with 3 configurations of 900 steps, and ``changes``."""
    import yaml
    from conftest import CI_SPEC

    from sweeper.spec._models import parse_spec

    data = yaml.safe_load(CI_SPEC.read_text())
    data["trials_per_method"] = 3
    data["budget"] = {"env_steps": 900, "seed_steps": 100, "eval_every": 100, "eval_episodes": 1}
    return parse_spec(data | changes)


@pytest.mark.parametrize(
    ("halving", "message"),
    [
        ({"rungs": [250]}, "250 is not a rung: rungs are multiples of budget.eval_every=100"),
        ({"rungs": [100]}, "past budget.seed_steps=100"),
        ({"rungs": [900]}, "below budget.env_steps=900"),
        ({"rungs": [400, 200]}, "must increase strictly"),
        ({"keep": 1.0}, "keep"),
        ({"rule": "median"}, "rule"),
    ],
)
def test_a_bad_halving_section_is_one_line(halving, message):
    from sweeper.spec._models import SpecError

    with pytest.raises(SpecError, match=message.replace(".", r"\.")):
        _halving_spec(**halving)
