"""`sweeper aggregate`: the tidy frame, the statistics and the written files, checked
against the storage (a synthetic study with every trial fate, and the CI study)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import optuna
import pandas as pd
import plotly.graph_objects as go
import pytest
from optuna.trial import TrialState
from optuna_dashboard import get_note, save_note
from synthetic_study import Special, write_synthetic_study

from agent.metrics import normalized_auc
from sweeper import cli
from sweeper.results import cli_aggregate as aggregate_command
from sweeper.results._stats import (
    SUMMARIES,
    Group,
    iqm,
    probability_of_improvement,
    several,
    stratified_bootstrap,
)
from sweeper.results.cli_aggregate import (
    NOTE_BEGIN,
    NOTE_END,
    aggregate,
    auc_table,
    improvement_table,
    iqm_curves,
    load_study_frame,
    method_curves,
    profile_table,
    replace_note_section,
    study_info,
)
from sweeper.spec._models import load_spec
from sweeper.storage import current_trials, curve_of, ledger

METHODS = ("pixel", "linear", "vae")
FIGURES = ("curves.png", "trials.png", "auc.png", "efficiency.png", "profiles.png")
CSVS = (
    "frame.csv",
    "curves.csv",
    "auc_table.csv",
    "improvement.csv",
    "efficiency.csv",
    "profiles.csv",
)


def write_spec(path: Path, study: str, extra: str = "") -> Path:
    """A valid spec named ``study`` (aggregate needs only its name, storage and seed)."""
    text = (Path(__file__).parent.parent / "studies" / "ci.yaml").read_text()
    path.write_text(text.replace("study: ci", f"study: {study}") + extra)
    return path


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A synthetic study (a note of the user's already in it), aggregated by the CLI."""
    root = tmp_path_factory.mktemp("aggregate")
    url = f"sqlite:///{root / 'study.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = write_synthetic_study(url, "syn", methods=METHODS, configs=4, seeds=(0, 1))
    save_note(study, "my own notes")
    spec = write_spec(root / "syn.yaml", "syn")
    out = root / "out"
    args = argparse.Namespace(spec=[str(spec)], storage=url, out=str(out), no_dashboard=False)
    assert aggregate_command.run([load_spec(spec).with_overrides(storage=url)], args) == 0
    return url, out


def trials_of(url: str, name: str):
    return optuna.load_study(study_name=name, storage=url).get_trials()


def test_frame_matches_the_storage(synthetic):
    url, _ = synthetic
    frame = load_study_frame(url, "syn")
    trials = trials_of(url, "syn")
    current = {t.number for t in current_trials(trials).values()}
    assert frame["trial"].nunique() == len(trials) == 2 * 4 * 3 + 1  # + the reaped attempt
    assert study_info(frame).metrics[0] == "success_rate" and len(study_info(frame).metrics) == 5
    for trial in trials:
        rows = frame[frame["trial"] == trial.number]
        first = rows.iloc[0]
        assert first["state"] == trial.state.name
        assert first["counted"] == (trial.number in current)
        for key in ("method", "key", "config_id", "seed", "outcome"):
            assert first[key] == trial.user_attrs.get(key) or pd.isna(first[key])
        if trial.value is None:
            assert math.isnan(first["auc"])
        else:
            assert first["auc"] == pytest.approx(trial.value)
        for name, value in trial.params.items():
            assert first[f"params_{name}"] == value
        curve = curve_of(trial)
        assert rows["step"].tolist() == curve["step"]
        for metric in study_info(frame).metrics:
            expected = np.array(curve[metric], dtype=float)
            np.testing.assert_allclose(rows[metric].to_numpy(), expected, equal_nan=True)
        assert dict(zip(rows["step"], rows["success_rate"], strict=True)) == pytest.approx(
            trial.intermediate_values
        )


def test_auc_table_matches_the_storage(synthetic):
    url, out = synthetic
    frame = load_study_frame(url, "syn")
    table = auc_table(frame, driver_alive=False).set_index("method")
    trials = trials_of(url, "syn")
    plan = study_info(frame).attrs["plan"]
    counts = ledger(plan, trials, driver_alive=False)  # sweeper status's ledger
    done = [t for t in current_trials(trials).values() if t.state == TrialState.COMPLETE]
    assert list(table.index) == list(METHODS)
    for method in METHODS:
        row = table.loc[method]
        for column in ("planned", "done", "diverged", "running", "failed", "left"):
            assert row[column] == getattr(counts[method], column), (method, column)
        aucs = np.array([t.value for t in done if t.user_attrs["method"] == method])
        assert row["n"] == aucs.size
        assert row["mean"] == pytest.approx(aucs.mean())
        assert row["std"] == pytest.approx(aucs.std(ddof=1))
        assert row["median"] == pytest.approx(np.median(aucs))
        assert row["iqm"] == pytest.approx(iqm(aucs))
        assert row["iqm_low"] <= row["iqm"] <= row["iqm_high"]
        assert row["best_auc"] == pytest.approx(aucs.max())
        best = next(t for t in done if t.number == row["best_trial"])
        assert best.value == pytest.approx(aucs.max())
        assert f"lr={best.params['lr']}" in row["best_params"]
    assert table.loc["vae", "diverged"] == 1 and table.loc["linear", "failed"] == 1
    assert table.loc["vae", "left"] == 1  # RUNNING without a live driver
    written = pd.read_csv(out / "auc_table.csv").set_index("method")
    pd.testing.assert_frame_equal(written, table, check_dtype=False)


def test_improvement_is_paired_by_config_and_seed(synthetic):
    url, out = synthetic
    frame = load_study_frame(url, "syn")
    done = [t for t in current_trials(trials_of(url, "syn")).values() if t.value is not None]
    auc = {
        (t.user_attrs["method"], t.user_attrs["config_id"], t.user_attrs["seed"]): t.value
        for t in done
    }
    table = improvement_table(frame)
    assert len(table) == 6
    for row in table.itertuples():
        pairs = [
            (auc[row.method, c, s], auc[row.versus, c, s])
            for (m, c, s) in auc
            if m == row.method and (row.versus, c, s) in auc
        ]
        wins = sum((x > y) + 0.5 * (x == y) for x, y in pairs)
        assert row.pairs == len(pairs) and row.probability == pytest.approx(wins / len(pairs))
    written = pd.read_csv(out / "improvement.csv")
    pd.testing.assert_frame_equal(written, table, check_dtype=False)


def test_curves_are_means_over_done_trials(synthetic):
    url, out = synthetic
    frame = load_study_frame(url, "syn")
    curves = method_curves(frame)
    done = [
        t for t in current_trials(trials_of(url, "syn")).values() if t.state == TrialState.COMPLETE
    ]
    for method in METHODS:
        mine = [curve_of(t) for t in done if t.user_attrs["method"] == method]
        values = np.array([c["final_hand_distance"] for c in mine], dtype=float)
        part = curves[(curves["method"] == method) & (curves["metric"] == "final_hand_distance")]
        np.testing.assert_allclose(part["mean"], np.nanmean(values, axis=0))
        np.testing.assert_allclose(part["std"], np.nanstd(values, axis=0, ddof=1))
        assert part["n"].tolist() == np.isfinite(values).sum(axis=0).tolist()
    written = pd.read_csv(out / "curves.csv")
    pd.testing.assert_frame_equal(written, curves, check_dtype=False)


def test_the_report_says_which_learned_encoder_fits_collapsed(synthetic):
    url, out = synthetic
    frame = pd.read_csv(out / "frame.csv")
    current = current_trials(trials_of(url, "syn")).values()
    done = {t.number: t for t in current if t.state == TrialState.COMPLETE}
    vae = [t for t in done.values() if t.user_attrs["method"] == "vae"]
    collapsed = sum(t.user_attrs["encoder_fit"]["active_dims"] == 0 for t in vae)
    assert 0 < collapsed < len(vae)  # the fixture has both kinds
    rows = frame.drop_duplicates("trial").set_index("trial")
    for number, trial in done.items():
        fit = trial.user_attrs.get("encoder_fit", {})
        assert rows.loc[number, "reward_scale"] == trial.user_attrs["reward_scale"]
        if fit:
            assert rows.loc[number, "fit_active_dims"] == fit["active_dims"]
        else:
            assert np.isnan(rows.loc[number, "fit_active_dims"])
    report = (out / "report.md").read_text()
    section = report.split("## Learned encoders' fits")[1]
    (row,) = [line for line in section.splitlines() if line.startswith("| vae |")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1] == str(len(vae)) and cells[3] == str(collapsed)
    assert sorted(cells[2].split(", ")) == sorted(
        f"{t.user_attrs['encoder_fit']['active_dims']}/8" for t in vae
    )
    assert "| pixel |" not in section.split("Data:")[0]  # learning-free: no fit


def test_written_files_and_dashboard_note(synthetic):
    url, out = synthetic
    frame = pd.read_csv(out / "frame.csv")
    loaded = load_study_frame(url, "syn")
    assert len(frame) == len(loaded)
    np.testing.assert_allclose(frame["success_rate"], loaded["success_rate"])
    np.testing.assert_allclose(frame["auc"], loaded["auc"], equal_nan=True)
    for name in FIGURES:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert sorted(p.name for p in out.iterdir()) == sorted([*CSVS, *FIGURES, "report.md"])
    report = (out / "report.md").read_text()
    assert "**Partial study**" in report and "| vae | 8 | 7 | 1 |" in report
    for link in [part.split(")")[0] for part in report.split("](")[1:]]:
        assert (out / link).is_file(), link
    note = get_note(optuna.load_study(study_name="syn", storage=url))
    assert note.startswith("my own notes") and note.count(NOTE_BEGIN) == 1
    assert "| pixel | 8 | 8 |" in note and NOTE_END in note


def test_note_section_is_replaced_not_repeated():
    section = f"{NOTE_BEGIN}\nnew\n{NOTE_END}"
    assert replace_note_section("", section) == section
    first = replace_note_section("mine", section)
    assert first == f"mine\n\n{section}"
    again = replace_note_section(first + "\nafter", f"{NOTE_BEGIN}\nnewer\n{NOTE_END}")
    assert again == f"mine\n\n{NOTE_BEGIN}\nnewer\n{NOTE_END}\nafter"
    # a section written with the HTML-comment markers of before is replaced too
    old = "mine\n\n<!-- sweeper aggregate: begin (rewritten by every run) -->\nold\n"
    old += "<!-- sweeper aggregate: end -->\nafter"
    assert replace_note_section(old, section) == f"mine\n\n{section}\nafter"


def test_unknown_empty_or_missing_study_is_a_clear_error(synthetic, tmp_path, capsys):
    url, _ = synthetic
    with pytest.raises(ValueError, match=r"study 'nope' not found .* it has: syn"):
        load_study_frame(url, "nope")
    with pytest.raises(ValueError, match="no database file"):
        load_study_frame(f"sqlite:///{tmp_path / 'absent.db'}", "syn")
    optuna.create_study(storage=url, study_name="empty")
    with pytest.raises(ValueError, match="'empty' has no trials yet"):
        load_study_frame(url, "empty")
    spec = load_spec(write_spec(tmp_path / "empty.yaml", "empty")).with_overrides(storage=url)
    args = argparse.Namespace(out=None, no_dashboard=True)
    assert aggregate_command.run([spec], args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sweeper aggregate: study 'empty' has no trials") and "\n" not in err
    bad = write_spec(tmp_path / "bad.yaml", "syn", extra="trials_per_methd: 3\n")
    assert cli.main(["aggregate", str(bad)]) == 2
    assert "trials_per_methd" in capsys.readouterr().err


def test_ci_study_aggregates_from_its_storage(ci_study, ci_aggregate):
    """After `sweeper launch studies/ci.yaml`, `sweeper aggregate studies/ci.yaml` (run from
    the study's working directory by the fixture) wrote what the storage holds."""
    out = ci_aggregate
    trials = trials_of(ci_study.storage_url, "ci")
    frame = pd.read_csv(out / "frame.csv")
    table = pd.read_csv(out / "auc_table.csv").set_index("method")
    assert table.index.tolist() == ["pixel", "linear"]  # the spec's order
    assert sorted(frame["key"].unique()) == sorted(t.user_attrs["key"] for t in trials)
    for trial in trials:
        rows = frame[frame["trial"] == trial.number]
        steps, success = rows["step"].tolist(), rows["success_rate"].tolist()
        assert dict(zip(steps, success, strict=True)) == pytest.approx(trial.intermediate_values)
        assert rows["final_distance"].tolist() == pytest.approx(curve_of(trial)["final_distance"])
        assert rows["auc"].iloc[0] == pytest.approx(trial.value)
        assert trial.value == pytest.approx(normalized_auc(steps, success))
        method = trial.user_attrs["method"]
        assert table.loc[method, "done"] == 1 and table.loc[method, "n"] == 1
        assert table.loc[method, "mean"] == pytest.approx(trial.value)
        assert table.loc[method, "best_trial"] == trial.number
    curves = pd.read_csv(out / "curves.csv")
    assert set(curves["metric"]) == {"success_rate", "final_distance"}
    for name in FIGURES:
        assert (out / name).stat().st_size > 10_000, name
    report = (out / "report.md").read_text()
    assert "# Study `ci`" in report and "![AUC per method](auc.png)" in report
    # one trial per method: the warning stands under the table and beside both figures
    small = "**Small samples:** pixel (1), linear (1) done trials, fewer than 5"
    assert report.count(small) == 3
    assert "(1*)" in report and "fewer than 5 pairs" in report


def test_small_samples_are_named_below_five_trials_or_pairs(synthetic):
    from sweeper.results._report import few_trials_warning

    table = pd.DataFrame({"method": ["a", "b", "c"], "n": [5, 4, 0]})
    assert few_trials_warning(table) == (
        "**Small samples:** b (4) done trials, fewer than 5: their intervals are not reliable "
        "(rliable's guidance: 5 or more runs per method, preferably 10)."
    )
    assert few_trials_warning(table.assign(n=[5, 10, 0])) == ""  # none done: no interval
    _, out = synthetic  # 8 trials and 8 pairs per method (vae: 7 done): no warning
    report = (out / "report.md").read_text()
    assert "Small samples" not in report and "fewer than 5 pairs" not in report
    assert "(7)" in report  # vae's pairs, unmarked


def test_a_study_with_nothing_done_yet_aggregates(tmp_path):
    """Early in a sweep: one trial running with two evaluations, one waiting, one method
    without any trial yet."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    special = Special(running="pixel/0/0", failed="pixel/1/0")
    study = write_synthetic_study(url, "early", methods=("pixel",), configs=2, special=special)
    study.set_user_attr("plan", ["pixel/0/0", "pixel/1/0", "pixel/2/0", "vae/0/0"])
    study.enqueue_trial({}, user_attrs={"key": "pixel/2/0", "method": "pixel"})
    result = aggregate(url, "early", tmp_path / "out", dashboard=False, progress=lambda m: None)
    table = result.table.set_index("method")
    assert table.loc["pixel", ["planned", "done", "failed", "left"]].tolist() == [3, 0, 1, 2]
    assert table.loc["vae", ["planned", "done", "left", "n"]].tolist() == [1, 0, 1, 0]
    assert result.curves.empty and result.improvement.empty
    assert "**Partial study**" in result.report.read_text()
    assert all(path.is_file() for path in result.files)


def done_trials(url: str, name: str) -> list:
    trials = current_trials(trials_of(url, name)).values()
    return [t for t in trials if t.state == TrialState.COMPLETE]


def test_every_statistic_has_its_interval(synthetic):
    url, _ = synthetic
    table = auc_table(load_study_frame(url, "syn"), driver_alive=False, seed=5)
    table = table.set_index("method")
    done = done_trials(url, "syn")
    for method in METHODS:
        aucs = np.array([t.value for t in done if t.user_attrs["method"] == method])
        expected = stratified_bootstrap(several(*SUMMARIES.values()), {method: aucs}, seed=5)
        for index, name in enumerate(SUMMARIES):
            row = table.loc[method]
            assert row[name] == pytest.approx(SUMMARIES[name](aucs))
            assert row[f"{name}_low"] == pytest.approx(expected[method].low[index])
            assert row[f"{name}_high"] == pytest.approx(expected[method].high[index])
            assert row[f"{name}_low"] <= row[name] <= row[f"{name}_high"]
        assert table.loc[method, "optimality_gap"] == pytest.approx(np.mean(1 - aucs))


def test_improvement_interval_resamples_the_pairs(synthetic):
    url, _ = synthetic
    table = improvement_table(load_study_frame(url, "syn"), seed=2)
    auc = {
        (t.user_attrs["method"], t.user_attrs["config_id"], t.user_attrs["seed"]): t.value
        for t in done_trials(url, "syn")
    }
    for row in table.itertuples():
        keys = sorted((c, s) for m, c, s in auc if m == row.method and (row.versus, c, s) in auc)
        x = np.array([auc[row.method, c, s] for c, s in keys])
        y = np.array([auc[row.versus, c, s] for c, s in keys])
        name = f"{row.method}>{row.versus}"
        expected = stratified_bootstrap(probability_of_improvement, {name: Group((x, y))}, seed=2)
        assert (row.probability, row.low, row.high) == pytest.approx(tuple(expected[name]))
        assert row.low <= row.probability <= row.high
    # vae beats pixel on every shared pair but its diverged one: 6 of 7
    row = table[(table["method"] == "vae") & (table["versus"] == "pixel")].iloc[0]
    assert row.probability == pytest.approx(6 / 7) and row.low < row.probability < row.high


def test_sample_efficiency_curves_are_iqms_over_done_trials(synthetic):
    url, out = synthetic
    frame = load_study_frame(url, "syn")
    curves = iqm_curves(frame)
    done = done_trials(url, "syn")
    for method in METHODS:
        success = np.array(
            [curve_of(t)["success_rate"] for t in done if t.user_attrs["method"] == method]
        )
        part = curves[curves["method"] == method]
        assert part["step"].tolist() == [0, 1000, 2000, 3000, 4000]
        np.testing.assert_allclose(part["iqm"], iqm(success, axis=0))
        assert (part["n"] == len(success)).all()
        assert (part["low"] <= part["iqm"] + 1e-12).all() and (
            part["iqm"] <= part["high"] + 1e-12
        ).all()
    assert (part["high"] - part["low"]).iloc[-1] > 0  # a real band where trials differ
    written = pd.read_csv(out / "efficiency.csv")
    pd.testing.assert_frame_equal(written, curves, check_dtype=False)


def test_performance_profiles_count_trials_above_tau(synthetic):
    url, out = synthetic
    profiles = profile_table(load_study_frame(url, "syn"))
    done = done_trials(url, "syn")
    for method in METHODS:
        mine = [t for t in done if t.user_attrs["method"] == method]
        scores = {
            "auc": np.array([t.value for t in mine]),
            "final_success": np.array([curve_of(t)["success_rate"][-1] for t in mine]),
        }
        for score, values in scores.items():
            part = profiles[(profiles["method"] == method) & (profiles["score"] == score)]
            assert len(part) == 101 and part["tau"].iloc[-1] == 1.0
            expected = [np.mean(values > tau) for tau in part["tau"]]
            np.testing.assert_allclose(part["fraction"], expected)
            assert (part["low"] <= part["fraction"]).all()
            assert (part["fraction"] <= part["high"]).all()
    written = pd.read_csv(out / "profiles.csv")
    pd.testing.assert_frame_equal(written, profiles, check_dtype=False)


def test_compute_per_method_sums_the_trials_seconds(synthetic):
    url, out = synthetic
    table = pd.read_csv(out / "auc_table.csv").set_index("method")
    done = done_trials(url, "syn")
    for method in METHODS:
        seconds = [t.user_attrs["seconds"] for t in done if t.user_attrs["method"] == method]
        assert table.loc[method, "wall_s"] == pytest.approx(sum(seconds))
        assert table.loc[method, "wall_s_per_trial"] == pytest.approx(np.mean(seconds))
        assert table.loc[method, "cpu_s"] == pytest.approx(sum(seconds))  # 1 CPU per trial
        assert table.loc[method, "gpu_s"] == 0.0
    report = (out / "report.md").read_text()
    hours = table.loc["pixel", "wall_s"] / 3600
    assert f"| {hours:.2f} ({table.loc['pixel', 'wall_s_per_trial']:.0f}) |" in report


def test_dashboard_names_the_objective_and_holds_the_new_figures(synthetic):
    from optuna_dashboard._custom_plot_data import get_plotly_graph_objects

    from sweeper.results._dashboard_card import COMPARISON_ID, split_views

    url, _ = synthetic
    study = optuna.load_study(study_name="syn", storage=url)
    assert study.metric_names == ["AUC"]
    storage = optuna.storages.get_storage(url)
    figures = get_plotly_graph_objects(storage.get_study_system_attrs(study._study_id))
    assert list(figures) == [COMPARISON_ID]
    views = split_views(json.loads(figures[COMPARISON_ID]))
    assert {"profiles", "auc", "curves-success_rate"} <= set(views)
    assert "IQM" in views["curves-success_rate"]["title"]


def test_the_dashboard_card_opens_on_the_comparison_names_the_controls_and_the_best(tmp_path):
    """One saved figure (optuna-dashboard orders several as a set of their ids iterates),
    the figures saved before under other ids removed; its buttons show one view at a time;
    the controls are named as controls in the comparison and the note, beside the best
    trial of a method that is not one."""
    from optuna_dashboard import save_plotly_graph_object
    from optuna_dashboard._custom_plot_data import get_plotly_graph_objects

    from sweeper.results._dashboard_card import (
        COMPARISON_ID,
        HIDDEN_DOMAIN,
        save_to_dashboard,
        split_views,
    )
    from sweeper.results._frame import by_auc, scored, trial_rows
    from sweeper.results._tables import study_tables

    url = f"sqlite:///{tmp_path / 'study.db'}"
    fates = Special(diverged="pixel/0/0", reaped="pixel/1/0", failed="vae/1/0", running="vae/0/1")
    study = write_synthetic_study(url, "ctl", methods=("pixel", "vae", "state"), configs=2,
                                  seeds=(0, 1), special=fates)  # fmt: skip
    old = ("sweeper-auc", "sweeper-trials", "sweeper-profiles", COMPARISON_ID)
    for name in old:  # the six cards written before this figure, four of them here
        save_plotly_graph_object(study, go.Figure(), graph_object_id=name)
    save_plotly_graph_object(study, go.Figure(), graph_object_id="the-users-own")
    frame = load_study_frame(url, "ctl")
    storage = optuna.storages.get_storage(url)
    save_to_dashboard(storage, frame, study_tables(frame, driver_alive=False))

    figures = get_plotly_graph_objects(storage.get_study_system_attrs(study._study_id))
    assert sorted(figures) == sorted([COMPARISON_ID, "the-users-own"])  # theirs is kept
    figure = json.loads(figures[COMPARISON_ID])
    views = split_views(figure)
    assert [v["label"] for v in views.values()] == [
        "Comparison", "Success rate", "Other metrics", "AUC", "Profiles", "Every trial"
    ]  # fmt: skip
    other = views["curves-other"]  # sawyer_door's four other metrics, a panel each
    assert [a["text"] for a in other["annotations"]][:2] == ["angle success rate",
                                                             "hand success rate"]  # fmt: skip
    table = figure["data"][0]
    assert table["type"] == "table" and table["visible"] is True
    assert all(t["visible"] is False for t in figure["data"][1:])  # opens on the table
    for index, (key, view) in enumerate(views.items()):
        restyle, relayout = figure["layout"]["updatemenus"][0]["buttons"][index]["args"]
        shown = [t["meta"] for t, v in zip(figure["data"], restyle["visible"], strict=True) if v]
        assert set(shown) - {"comparison"} == ({key} - {"comparison"})
        assert restyle["domain.x"][0] == ([0, 1] if key == "comparison" else HIDDEN_DOMAIN)
        visible = {k.split(".")[0] for k, v in relayout.items() if k.endswith(".visible") and v}
        assert {f"xaxis{a[1:]}" for a in view["xaxes"]} == {a for a in visible if a[0] == "x"}
        assert (key == "comparison") == (not view["xaxes"])

    best = by_auc(trial_rows(scored(frame)).query("method != 'state'")).iloc[0]
    methods = table["cells"]["values"][1]
    assert methods[0] == "<b>state</b> <i>(control)</i>"  # the best method, a control
    assert "<b>vae</b>" in methods and "<b>pixel</b>" in methods
    assert f"best non-control trial: #{best['trial']} {best['key']}" in views["comparison"]["title"]
    note = get_note(study)
    assert "Ranked by IQM AUC (95% CI): state (control) " in note
    assert "| state (control) | 4 |" in note
    assert f"**Best non-control trial:** #{best['trial']} {best['key']} (vae)" in note
    assert f"it shows #{study.best_trial.number}, a trial of the control `state`" in note


def test_the_dashboard_trial_panel_spreads_a_large_method_over_its_auc_ranks():
    from sweeper.results._dashboard_card import TRIALS_PER_PANEL, _panel_trials

    few = pd.DataFrame({"trial": range(5), "auc": [0.1, 0.5, np.nan, 0.3, 0.2]})
    assert _panel_trials(few) is few
    many = pd.DataFrame({"trial": range(101), "auc": np.r_[np.linspace(0, 1, 100), np.nan]})
    shown = _panel_trials(many)
    assert len(shown) == TRIALS_PER_PANEL == shown["trial"].nunique()
    assert shown["trial"].iloc[0] == 99 and shown["trial"].iloc[-1] == 100  # best; no AUC
    gaps = np.diff(shown["trial"].iloc[:-1].to_numpy())
    assert gaps.max() - gaps.min() <= 1  # evenly spread over the ranks


# ---- the report and the dashboard as a reader meets them (issue 22) ----------------------
def test_best_trial_ties_go_to_the_lower_trial_number_everywhere(synthetic):
    from sweeper.results._frame import scored, trial_rows
    from sweeper.results._pictures import best_and_median

    url, _ = synthetic
    frame = load_study_frame(url, "syn")
    done = trial_rows(scored(frame))
    pixel = done[done["method"] == "pixel"]
    tied = pixel["trial"].tolist()[:3]
    frame.loc[frame["trial"].isin(tied), "auc"] = 1.0  # three trials share the best AUC
    table = auc_table(frame, driver_alive=False).set_index("method")
    best, _ = best_and_median(trial_rows(scored(frame)).query("method == 'pixel'"))
    assert table.loc["pixel", "best_trial"] == min(tied) == best[1]["trial"]


def test_curve_bands_are_clipped_and_the_random_agent_is_drawn(tmp_path):
    from sweeper.results._dashboard_card import COMPARISON_ID, save_to_dashboard, split_views
    from sweeper.results._figures import clip_band
    from sweeper.results._tables import study_tables

    low, high = clip_band("success_rate", np.array([-0.2, 0.5]), np.array([0.7, 1.3]))
    assert low.tolist() == [0.0, 0.5] and high.tolist() == [0.7, 1.0]
    low, high = clip_band("final_hand_distance", np.array([-0.1]), np.array([0.4]))
    assert low.tolist() == [0.0] and high.tolist() == [0.4]

    url = f"sqlite:///{tmp_path / 'study.db'}"
    write_synthetic_study(url, "rnd", methods=METHODS, configs=4, seeds=(0, 1), random_success=0.2)
    frame = load_study_frame(url, "rnd")
    tables = study_tables(frame, driver_alive=False)
    out = tmp_path / "out"
    result = aggregate(url, "rnd", out, dashboard=False, progress=lambda m: None)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in result.files)
    storage = optuna.storages.get_storage(url)
    save_to_dashboard(storage, frame, tables)
    from optuna_dashboard._custom_plot_data import get_plotly_graph_objects

    study_id = storage.get_study_id_from_name("rnd")
    figures = split_views(json.loads(get_plotly_graph_objects(
        storage.get_study_system_attrs(study_id))[COMPARISON_ID]))  # fmt: skip
    success = figures["curves-success_rate"]["data"]
    random = [t for t in success if t["name"].startswith("random agent")]
    assert len(random) == 1 and random[0]["y"] == [0.2, 0.2]
    others = [m for m in study_info(frame).metrics if m != "success_rate"]
    for key, metrics in (("curves-success_rate", ["success_rate"]), ("curves-other", others)):
        view = figures[key]
        for trace in view["data"]:
            if trace.get("fill"):  # a band: no markers, inside its metric's range
                metric = metrics[view["xaxes"].index(trace["xaxis"])]  # its panel's
                assert trace["mode"] == "lines"
                values = np.array(trace["y"], dtype=float)
                assert values.min() >= 0.0
                if metric.endswith("_rate"):
                    assert values.max() <= 1.0
    report = (out / "report.md").read_text()
    assert "a random agent succeeds in 0.20 of episodes" in report


def test_the_report_explains_its_ranking_from_its_own_tables(synthetic):
    from sweeper.results._report import ranking_sentence

    url, out = synthetic
    table = pd.read_csv(out / "auc_table.csv")
    improvement = pd.read_csv(out / "improvement.csv")
    sentence = ranking_sentence(table, improvement)
    ranked = table.sort_values("iqm", ascending=False)
    listed = ", ".join(
        f"{r.method} {r.iqm:.2f} [{r.iqm_low:.2f}, {r.iqm_high:.2f}]" for r in ranked.itertuples()
    )
    assert sentence.startswith(f"Ranked by IQM AUC (95% CI): {listed}; ")
    first, second = ranked["method"].iloc[:2]
    p = improvement.set_index(["method", "versus"]).loc[(first, second)]
    clear = "clearly ahead" if p["low"] > 0.5 else "not clearly ahead"
    assert f"{first} is {clear} of {second} (wins {p['probability']:.2f} " in sentence
    assert sentence.count(".") >= 1 and sentence.endswith(".")
    report = (out / "report.md").read_text()
    assert sentence in report.split("## AUC per method")[0]  # before the tables
    note = get_note(optuna.load_study(study_name="syn", storage=url))
    assert sentence in note and "```text" in note and "P(improvement)" in note
    assert "<!--" not in note  # optuna-dashboard would show an HTML comment as text


def test_aggregate_says_how_many_files_it_wrote(ci_study, ci_aggregate, tmp_path, capsys):
    out = tmp_path / "out"
    command = ["aggregate", str(ci_study.spec), "--storage", ci_study.storage_url]
    assert cli.main([*command, "--out", str(out), "--no-dashboard"]) == 0
    printed = capsys.readouterr().out
    written = sorted(p.name for p in out.iterdir())
    assert {"final_frames.png", "env_views.png", "report.md"} <= set(written)
    assert f"\nwrote {len(written)} files to {out}\n" in printed


def test_the_verdict_says_whether_the_best_interval_separates_it_from_the_next():
    from sweeper.results._report import verdict

    def table(*rows):
        return pd.DataFrame(rows, columns=["method", "n", "iqm", "iqm_low", "iqm_high"])

    apart = table(("a", 5, 0.2, 0.1, 0.3), ("b", 5, 0.6, 0.5, 0.7), ("c", 0, None, None, None))
    assert verdict(apart) == (
        "Highest IQM AUC: b, 0.600 [0.500, 0.700]; its 95% interval lies above that of the "
        "next, a, 0.200 [0.100, 0.300]."
    )
    close = table(("a", 5, 0.5, 0.3, 0.6), ("b", 5, 0.6, 0.5, 0.7))
    assert verdict(close).endswith("overlaps that of the next, a, 0.500 [0.300, 0.600]: "
                                   "this study does not separate the two.")  # fmt: skip
    assert verdict(apart.iloc[1:]) == (
        "Highest IQM AUC: b, 0.600 [0.500, 0.700]; no other method has a done trial."
    )
    assert verdict(apart.iloc[2:]) == "No method has a done trial yet."
