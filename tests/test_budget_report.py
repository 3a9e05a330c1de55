"""The gradient budget as an axis (``sweeper.results._budget``): studies of one env joined
by encoder, configuration and seed; settings labelled from the trials' SAC values; a study
whose configurations differ refused; the paired probability, n and CPU-hours per setting."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import optuna
import pandas as pd
import pytest
from conftest import ROOT
from optuna.trial import TrialState
from synthetic_study import write_planned_study

from sweeper import cli
from sweeper.plan import build_plan
from sweeper.results._budget import (
    a1_departures,
    budget_markdown,
    budget_table,
    controls_table,
    join_studies,
    precision_markdown,
    precision_table,
    setting_label,
    study_trials,
)
from sweeper.results._frame import load_study_frame, stage_frame
from sweeper.results._stats import iqm
from sweeper.spec._models import load_spec, parse_spec
from sweeper.storage import current_trials, curve_of

#: each method's final success rate on config 0, seed 0 (less 0.05 a config, more 0.02 a
#: seed): pixel gains with samples, conv_b128 loses to conv at 1/16 on every pair
LEVELS = {
    "pixel": 0.2,
    "linear": 0.1,
    "conv": 0.3,
    "state": 1.0,
    "pixel_tau01": 0.25,
    "pixel_b128": 0.5,
    "pixel_b128x2": 0.9,
    "conv_b128": 0.1,
}


def final_success(key: str) -> float:
    method, config_id, seed = key.split("/")
    return LEVELS[method] - 0.05 * int(config_id) + 0.02 * int(seed)


def spec_like(path: str, **changes):
    """The spec at ``path`` with top-level fields replaced."""
    data = load_spec(ROOT / path).model_dump(mode="json") | changes
    return parse_spec(data)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """A small fetch_reach_cpu (3 configs: pixel, linear, conv, state; 1800 s a trial, one
    CPU), a budget study on its first 2 configs (3600 s a trial, two CPUs), and the same
    budget study sampled with another seed (its configurations are not the others')."""
    url = f"sqlite:///{tmp_path_factory.mktemp('budget') / 'studies.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    cpu = spec_like(
        "studies/fetch_reach_cpu.yaml",
        study="cpu",
        methods={"pixel": {}, "linear": {}, "conv": {}, "state": {}},
    )
    methods = {
        "pixel_tau01": {"encoder": "pixel", "sac": {"critic_tau": 0.01}},
        "pixel_b128": {"encoder": "pixel", "sac": {"batch_size": 128}},
        "pixel_b128x2": {"encoder": "pixel", "sac": {"batch_size": 128, "updates_per_step": 2}},
        "conv_b128": {"encoder": "conv", "sac": {"batch_size": 128}},
    }
    budget = spec_like("studies/fetch_reach_budget.yaml", study="budget", methods=methods)
    budget = parse_spec(
        budget.model_dump(mode="json")
        | {"execution": budget.execution.model_dump(mode="json") | {"cpus_per_trial": 2}}
    )
    shifted = parse_spec(budget.model_dump(mode="json") | {"study": "shifted", "seed": 1})
    more_seeds = spec_like(  # a follow-up on new seeds for two of pixel's settings
        "studies/fetch_reach_budget.yaml",
        study="more_seeds",
        methods={"pixel": {}, "pixel_b128": methods["pixel_b128"]},
        seeds=[2, 3],
    )
    bf16 = spec_like(
        "studies/fetch_reach_cpu.yaml",
        study="bf16",
        methods={"pixel": {}, "state": {}},
        trials_per_method=2,
        precision="bf16",
    )
    write_planned_study(url, cpu, final_success=final_success, seconds=1800.0)
    write_planned_study(
        url, bf16, final_success=lambda key: final_success(key) - 0.1, seconds=900.0
    )
    skip = frozenset({"pixel_b128/1/1"})  # not done yet: n counts done trials
    write_planned_study(url, budget, final_success=final_success, seconds=3600.0, skip=skip)
    write_planned_study(url, shifted, final_success=final_success)
    write_planned_study(url, more_seeds, final_success=final_success, seconds=3600.0)
    return {
        name: stage_frame(load_study_frame(url, name), "search")
        for name in ("cpu", "budget", "shifted", "bf16", "more_seeds")
    }


@pytest.fixture(scope="module")
def joined(frames):
    join = join_studies([study_trials(n, frames[n]) for n in ("cpu", "budget")])
    return join, budget_table(join).set_index(["encoder", "setting"])


def test_setting_labels():
    assert setting_label(32, {}) == "1/16"
    assert setting_label(128, {}) == "1/4"
    assert setting_label(256, {}) == "1/2"
    assert setting_label(512, {}) == "1"
    assert setting_label(1024, {"critic_tau": 0.01}) == "2, critic_tau 0.01"
    values = {"batch_size": 32, "updates_per_step": 1, "critic_tau": 0.01, "num_filters": 16}
    values |= {"lr": 0.001, "hidden_sizes": "1024x1024", "buffer_capacity": 1_000_000}
    assert a1_departures(values) == {"critic_tau": 0.01, "num_filters": 16}


def test_settings_come_from_the_trials_values(joined):
    join, table = joined
    # every trial has these: said once, not in every label
    assert join.shared == ("buffer_capacity 100000", "num_filters 16")
    assert list(table.loc["pixel"].index) == ["1/16", "1/16, critic_tau 0.01", "1/4", "1/2"]
    assert list(table.loc["conv"].index) == ["1/16", "1/4"]
    assert table.loc[("pixel", "1/2"), "samples_per_step"] == 256
    assert table.loc[("pixel", "1/16, critic_tau 0.01"), "departures"] == "critic_tau 0.01"
    assert table.loc[("pixel", "1/4"), "methods"] == "budget: pixel_b128"


def test_the_join_keeps_the_configurations_every_setting_of_the_encoder_planned(joined):
    join, _ = joined
    both = {(c, s) for c in (0, 1) for s in (0, 1)}
    assert join.pairs["pixel"] == join.pairs["conv"] == both
    assert join.pairs["linear"] == {(c, s) for c in (0, 1, 2) for s in (0, 1)}  # cpu alone
    assert join.pairs["state"] == both  # the controls: where every encoder is compared
    trials = join.trials
    assert set(trials.loc[trials["method"] == "pixel", "config_id"]) == {0, 1}
    assert set(trials.loc[trials["method"] == "linear", "config_id"]) == {0, 1, 2}
    controls = controls_table(join).set_index("method")
    assert controls.loc["state", "n"] == 4
    assert controls.loc["state", "final_success_iqm"] == pytest.approx(
        iqm([final_success(f"state/{c}/{s}") for c, s in sorted(both)])
    )


def test_a_study_on_new_seeds_adds_trials_to_the_settings_it_runs(frames):
    names = ("cpu", "budget", "more_seeds")
    join = join_studies([study_trials(n, frames[n]) for n in names])
    assert not join.left_out
    assert join.pairs["pixel"] == {(c, s) for c in (0, 1) for s in (0, 1, 2, 3)}
    assert join.pairs["conv"] == {(c, s) for c in (0, 1) for s in (0, 1)}  # no new seeds
    assert join.pairs["state"] == {(c, s) for c in (0, 1) for s in (0, 1)}  # cpu's own
    table = budget_table(join).set_index(["encoder", "setting"])
    # cpu's 4 and the follow-up's 4; budget's 3 done and 4; budget's 4 alone
    assert table.loc[("pixel", "1/16"), "n"] == 8
    assert table.loc[("pixel", "1/16"), "methods"] == "cpu: pixel, more_seeds: pixel"
    assert table.loc[("pixel", "1/4"), "n"] == 7
    assert table.loc[("pixel", "1/2"), "n"] == 4
    assert table.loc[("conv", "1/16"), "n"] == 4
    # paired on the (config, seed) both settings have done
    assert table.loc[("pixel", "1/4"), "pairs"] == 7
    assert table.loc[("pixel", "1/2"), "pairs"] == 3  # against 1/4, whose 1/1 is not done
    done = [(c, s) for c in (0, 1) for s in range(4) if (c, s) != (1, 1)]  # 1/1: skipped
    assert table.loc[("pixel", "1/4"), "final_success_iqm"] == pytest.approx(
        iqm([final_success(f"pixel_b128/{c}/{s}") for c, s in done])
    )


def test_a_study_whose_configurations_differ_is_left_out(frames):
    studies = [study_trials(n, frames[n]) for n in ("cpu", "shifted", "budget")]
    join = join_studies(studies)
    assert join.studies == ("cpu", "budget")
    assert list(join.left_out) == ["shifted"]
    assert any(p.startswith("config 0: SAC ") for p in join.left_out["shifted"])
    assert "shifted" not in set(join.trials["study"])
    assert "**`shifted` is left out of the join**" in budget_markdown(
        join, budget_table(join), controls_table(join)
    )


def test_encoder_options_or_env_steps_that_differ_refuse_the_study(frames):
    cpu, budget = study_trials("cpu", frames["cpu"]), study_trials("budget", frames["budget"])
    assert not join_studies([cpu, budget]).left_out
    trials = budget.trials.copy()
    trials["options"] = [
        {**o, "latent_dim": 64} if m == "conv_b128" else o
        for m, o in zip(trials["method"], trials["options"], strict=True)
    ]
    join = join_studies([cpu, dataclasses.replace(budget, trials=trials)])
    assert join.studies == ("cpu",)
    assert any("conv option latent_dim 64" in p for p in join.left_out["budget"])
    longer = {**budget.conditions, "budget.env_steps": 20000}
    join = join_studies([cpu, dataclasses.replace(budget, conditions=longer)])
    assert join.left_out["budget"] == ["budget.env_steps 20000 (reference: 15000)"]


def test_the_higher_setting_is_compared_with_the_lower_on_the_same_pairs(joined):
    _, table = joined
    assert pd.isna(table.loc[("pixel", "1/16"), "versus"])  # the lowest: nothing below
    assert np.isnan(table.loc[("pixel", "1/16"), "p_improvement"])
    row = table.loc[("pixel", "1/4")]
    assert (row["versus"], row["p_improvement"], row["pairs"]) == ("1/16", 1.0, 3)
    assert table.loc[("pixel", "1/2"), "versus"] == "1/4"  # the next lower on the line
    assert table.loc[("pixel", "1/2"), "p_improvement"] == 1.0
    # another departure is compared with the setting without it at the same samples
    assert table.loc[("pixel", "1/16, critic_tau 0.01"), "versus"] == "1/16"
    assert table.loc[("conv", "1/4"), "p_improvement"] == 0.0  # worse on every pair


def test_n_and_cpu_hours(joined):
    _, table = joined
    assert table.loc[("pixel", "1/16"), "n"] == 4  # cpu's configs 0 and 1 only
    assert table.loc[("pixel", "1/4"), "n"] == 3  # pixel_b128/1/1 not done
    assert table.loc[("linear", "1/16"), "n"] == 6
    assert table.loc[("pixel", "1/16"), "cpu_hours"] == pytest.approx(4 * 1800 / 3600)
    assert table.loc[("pixel", "1/4"), "cpu_hours"] == pytest.approx(3 * 3600 * 2 / 3600)
    assert table.loc[("pixel", "1/2"), "reached"] == 4  # 0.9 - 0.05 + 0.02 >= 0.8
    assert table.loc[("pixel", "1/4"), "reached"] == 0
    expected = iqm([final_success(f"pixel_b128x2/{c}/{s}") for c in (0, 1) for s in (0, 1)])
    row = table.loc[("pixel", "1/2")]
    assert row["final_success_iqm"] == pytest.approx(expected)
    assert row["final_success_iqm_low"] <= row["final_success_iqm"] <= row["final_success_iqm_high"]


def test_a_study_in_bf16_is_paired_with_the_same_trials_in_fp32(frames):
    """bf16 is a departure of its study's settings, and precision_table gives the paired
    differences bf16 minus fp32 per line, the controls too: here 0.1 lower on every pair
    in half the time."""
    join = join_studies([study_trials(n, frames[n]) for n in ("cpu", "bf16")])
    assert not join.left_out  # the same configurations in another precision
    table = budget_table(join).set_index(["encoder", "setting"])
    assert table.loc[("pixel", "1/16, precision bf16"), "versus"] == "1/16"
    assert table.loc[("pixel", "1/16, precision bf16"), "n"] == 4
    assert "1/16, precision bf16" not in set(table.loc["linear"].index)
    assert set(controls_table(join)["setting"]) == {"1/16", "1/16, precision bf16"}
    precision = precision_table(join).set_index("line")
    assert list(precision.index) == ["pixel", "state"]
    for line in ("pixel", "state"):
        row = precision.loc[line]
        assert (row["precision"], row["settings"], row["pairs"]) == ("bf16", "1/16", 4)
        for column in ("", "_low", "_high"):
            assert row[f"final_success_difference{column}"] == pytest.approx(-0.1)
            assert row[f"auc_difference{column}"] < 0
        assert row["seconds_ratio"] == pytest.approx(0.5)
    text = precision_markdown(precision_table(join))
    assert "## Precision: the same trials in bf16 and in fp32" in text
    assert "| pixel | bf16 | 1/16 | 4* | -0.10 [-0.10, -0.10] |" in text
    fp32_only = join_studies([study_trials(n, frames[n]) for n in ("cpu", "budget")])
    assert precision_table(fp32_only).empty


def test_the_command_joins_the_published_study_with_a_budget_study(tmp_path, capsys):
    """``sweeper aggregate`` on a copy of the published fetch_reach_cpu with a synthetic
    study of studies/fetch_reach_budget.yaml in the same storage."""
    shutil.copy(ROOT / "docs" / "studies" / "fetch_reach_cpu" / "study.db", tmp_path / "s.db")
    url = f"sqlite:///{tmp_path / 's.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    budget = load_spec(ROOT / "studies" / "fetch_reach_budget.yaml")
    write_planned_study(url, budget, final_success=lambda key: 0.9, seconds=600.0)
    specs = [str(ROOT / "studies" / f"{s}.yaml") for s in ("fetch_reach_cpu", "fetch_reach_budget")]
    out = tmp_path / "out"
    assert cli.main(["aggregate", *specs, "--storage", url, "--out", str(out)]) == 0
    assert "gradient budget: 12 encoder x setting rows" in capsys.readouterr().out
    table = pd.read_csv(out / "budget_table.csv", keep_default_na=False)
    rows = [(r.encoder, r.setting, r.n) for r in table.itertuples()]
    ladder = ["1/16", "1/16, critic_tau 0.01", "1/4", "1/2"]
    assert rows == [
        *(("pixel", s, 4) for s in ladder),
        ("linear", "1/16", 6),
        *(("conv", s, 4) for s in ladder),
        ("conv (init pytorch)", "1/16", 6),
        ("vae", "1/16", 6),
        ("cvae", "1/16", 6),
    ]
    # pixel at 1/16: the published trials of configs 0 and 1 (config 2 is not in the budget)
    trials = current_trials(
        optuna.load_study(study_name="fetch_reach_cpu", storage=url).get_trials()
    )
    finals = [
        curve_of(t)["success_rate"][-1]
        for t in trials.values()
        if t.state == TrialState.COMPLETE
        and t.user_attrs["method"] == "pixel"
        and t.user_attrs["config_id"] in (0, 1)
    ]
    pixel = table[(table["encoder"] == "pixel") & (table["setting"] == "1/16")].iloc[0]
    assert len(finals) == 4 and pixel["final_success_iqm"] == pytest.approx(iqm(finals))
    controls = pd.read_csv(out / "budget_controls.csv")
    assert sorted(zip(controls["method"], controls["n"], strict=True)) == [
        ("state", 4),
        ("true_reward", 4),
    ]
    report = (out / "report.md").read_text()
    assert "## Gradient budget" in report and "left out of the join" not in report
    assert (out / "budget.png").read_bytes()[:4] == b"\x89PNG"


def test_the_bf16_pairs_span_settings_that_differ_in_sampled_values(tmp_path):
    """A sampled value outside A.1 (lr 3e-4) splits a study's configurations into two
    settings; each bf16 trial still pairs with its own fp32 twin, and the line's row pools
    the pairs of both settings."""
    url = f"sqlite:///{tmp_path / 'studies.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    text = load_spec(ROOT / "studies" / "point_reach_precision.yaml").model_dump(mode="json")
    fp32 = parse_spec(text | {"study": "fp32", "methods": {"pixel": {}}})
    bf16 = parse_spec(text | {"study": "bf16", "methods": {"pixel": {}}, "precision": "bf16"})
    lrs = {e.config_id: e.trial_config.sac.lr for e in build_plan(fp32).entries}
    assert sorted(set(lrs.values())) == [3e-4, 1e-3]  # both settings are there

    def level(key: str) -> float:  # differs by configuration: a wrong pairing would show
        _, config_id, seed = key.split("/")
        return 0.3 + 0.2 * int(config_id) + 0.05 * int(seed)

    write_planned_study(url, fp32, final_success=level)
    write_planned_study(url, bf16, final_success=lambda key: level(key) + 0.1)
    frames = {n: stage_frame(load_study_frame(url, n), "search") for n in ("fp32", "bf16")}
    join = join_studies([study_trials(n, frames[n]) for n in ("fp32", "bf16")])
    (row,) = precision_table(join).to_dict("records")
    assert (row["line"], row["precision"], row["pairs"]) == ("pixel", "bf16", 6)
    assert set(row["settings"].split("; ")) == {"1/16", "1/16, lr 0.0003"}
    for column in ("", "_low", "_high"):
        assert row[f"final_success_difference{column}"] == pytest.approx(0.1)
