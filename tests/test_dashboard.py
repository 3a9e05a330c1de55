"""`sweeper dashboard`: optuna-dashboard served on the CI study, queried over HTTP."""

from __future__ import annotations

import json
import urllib.request

import optuna
import pytest
from conftest import running_dashboard

from sweeper import cli
from sweeper.results._dashboard_card import COMPARISON_ID, split_views

#: no proxy: the dashboard is on this machine
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def get_json(url: str) -> dict:
    with OPENER.open(url, timeout=30) as response:
        return json.loads(response.read())


def test_dashboard_shows_trials_curves_and_the_comparison(ci_study, ci_aggregate):
    with running_dashboard(ci_study) as page:
        assert page.startswith("http://127.0.0.1:")  # bound to localhost by default
        base = page.split("/dashboard/")[0]
        studies = get_json(f"{base}/api/studies")["study_summaries"]
        study_id = next(s["study_id"] for s in studies if s["study_name"] == "ci")
        assert page.endswith(f"/dashboard/studies/{study_id}")
        detail = get_json(f"{base}/api/studies/{study_id}")

    stored = optuna.load_study(study_name="ci", storage=ci_study.storage_url).get_trials()
    assert len(detail["trials"]) == len(stored) == 2
    for trial in stored:
        served = next(t for t in detail["trials"] if t["number"] == trial.number)
        assert served["state"].upper() == "COMPLETE"
        points = {p["step"]: p["value"] for p in served["intermediate_values"]}
        assert points == pytest.approx(trial.intermediate_values)
        assert len(points) == 4  # steps 0, 100, 200, 300
    # the sweep's one card (its place on the page needs no hash seed), its views behind buttons
    assert [g["id"] for g in detail["plotly_graph_objects"]] == [COMPARISON_ID]
    figures = split_views(json.loads(detail["plotly_graph_objects"][0]["graph_object"]))
    assert list(figures) == ["comparison", "curves-success_rate", "curves-final_distance", "auc",
                             "profiles", "trials"]  # fmt: skip
    names = {trace.get("name", "") for trace in figures["curves-success_rate"]["data"]}
    assert {"pixel (n = 1)", "linear (n = 1)"} <= names
    points, iqm = figures["auc"]["data"]  # every trial's AUC; IQM with its CI
    assert sorted(points["y"]) == pytest.approx(sorted(t.value for t in stored))
    assert iqm["x"] == ["pixel", "linear"] and len(iqm["y"]) == 2
    note = detail["note"]["body"]
    assert "Method comparison" in note and "| pixel | 1 | 1 |" in note

    # Each trial's method at a glance: its user attrs in the trial table, its curve named
    # by key in a panel of its method, and a note line linking to the method's trials.
    assert {s["key"] for s in detail["union_user_attrs"]} >= {"method", "key"}
    for trial in stored:
        served = next(t for t in detail["trials"] if t["number"] == trial.number)
        attrs = {a["key"]: a["value"] for a in served["user_attrs"]}
        assert attrs["method"] == trial.user_attrs["method"]
        assert attrs["key"] == trial.user_attrs["key"]
    panels = figures["trials"]
    titles = [a["text"] for a in panels["annotations"]]
    assert titles == ["pixel", "linear"]
    for trial in stored:
        method = trial.user_attrs["method"]
        panel = titles.index(method)
        trace = next(t for t in panels["data"] if t["name"] == method)
        assert trace["xaxis"] == panels["xaxes"][panel]
        name = f"{trial.user_attrs['key']} (trial {trial.number})"
        points = {
            x: y for x, y, text in zip(trace["x"], trace["y"], trace["text"], strict=True)
            if text == name and x is not None
        }  # fmt: skip
        assert points == pytest.approx(trial.intermediate_values)
        number = trial.number
        link = f"/dashboard/studies/{study_id}/trials?numbers={number}"
        shown = f"[show them side by side]({link})"
        assert f"- **{trial.user_attrs['method']}**: trials {number} ({shown})" in note


def test_dashboard_importance_and_params_show_what_varies_and_the_method(ci_study, ci_aggregate):
    """Constant hyperparameters are no trial params (they are in the study attr
    fixed_params), so the importance and the trial table show what varies, method among it."""
    with running_dashboard(ci_study) as page:
        base, study_id = page.split("/dashboard/")[0], page.rsplit("/", 1)[1]
        detail = get_json(f"{base}/api/studies/{study_id}")
        importances = get_json(f"{base}/api/studies/{study_id}/param_importances")
    assert {p["name"] for p in detail["union_search_space"]} == {"lr", "method"}
    method = next(p for p in detail["union_search_space"] if p["name"] == "method")
    assert sorted(c["value"] for c in method["distribution"]["choices"]) == ["linear", "pixel"]
    shown = {i["name"] for i in importances["param_importances"][0]}
    assert shown == {"lr", "method"}
    attrs = {a["key"]: json.loads(a["value"]) for a in detail["user_attrs"]
             if a["key"] == "fixed_params"}  # fmt: skip
    assert attrs["fixed_params"]["hidden_sizes"] == "64x64"
    assert attrs["fixed_params"]["linear.latent_dim"] == 16
    figures = split_views(json.loads(detail["plotly_graph_objects"][0]["graph_object"]))
    table = figures["comparison"]["data"][0]
    assert table["type"] == "table" and "<b>pixel</b>" in json.dumps(table["cells"])
    for name in ("curves-success_rate", "curves-final_distance"):
        for trace in figures[name]["data"]:  # every trace says how it is drawn
            assert "mode" in trace, name
            if trace.get("fill"):  # a band: its fill only, no markers
                assert trace["mode"] == "lines", name


def test_dashboard_bad_input_exits_2(ci_study, tmp_path, capsys):
    missing = f"sqlite:///{tmp_path / 'absent.db'}"
    assert cli.main(["dashboard", str(ci_study.spec), "--storage", missing]) == 2
    assert "no database file" in capsys.readouterr().err
    other = tmp_path / "other.yaml"
    other.write_text(ci_study.spec.read_text().replace("study: ci", "study: other"))
    assert cli.main(["dashboard", str(other), "--storage", ci_study.storage_url]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sweeper dashboard: study 'other' not found") and "\n" not in err
