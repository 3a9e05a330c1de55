"""The dashboard's figures refreshed by the driver while a launch runs
(``sweeper.results._live``): when a refresh runs, that it bounds its own cost, and that a
launch leaves the figures and the note in the study without ``sweeper aggregate``."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import optuna
import pytest
from conftest import ROOT, write_ci_spec
from optuna_dashboard import get_note
from optuna_dashboard._custom_plot_data import get_plotly_graph_objects
from synthetic_study import write_synthetic_study

from sweeper.results import _live as live
from sweeper.results._dashboard_card import COMPARISON_ID, NOTE_BEGIN, split_views
from sweeper.storage import StudyStore, open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_refreshes_are_spaced_by_their_cost_and_the_last_one_always_runs(monkeypatch):
    clock, costs, done = Clock(), iter([2.0, 10.0, 1.0, 1.0]), []

    def fake_refresh(store):
        done.append(clock.now)
        clock.now += next(costs)

    monkeypatch.setattr(live, "refresh", fake_refresh)
    refresher = live.FigureRefresh(None, min_interval=60.0, max_share=0.05, clock=clock)
    assert refresher.after_trial()  # the first result: at once
    assert refresher.next_at == 2.0 + 60.0  # 2 s / 0.05 = 40 s < 60 s
    clock.now = 61.0
    assert not refresher.after_trial()
    clock.now = 62.0
    assert refresher.after_trial()  # took 10 s: the next waits 10 / 0.05 = 200 s
    assert refresher.next_at == 72.0 + 200.0
    clock.now = 100.0
    assert refresher.after_trial(final=True)  # the launch's last trial: always
    assert done == [0.0, 62.0, 100.0]


def test_a_failing_refresh_is_said_once_and_never_raises(monkeypatch):
    def broken(store):
        raise RuntimeError("database is locked")

    monkeypatch.setattr(live, "refresh", broken)
    said = []
    refresher = live.FigureRefresh(None, min_interval=0.0, clock=Clock())
    assert refresher.after_trial(say=said.append) and refresher.after_trial(say=said.append)
    assert said == ["dashboard figures not refreshed: RuntimeError: database is locked"]


def test_refresh_saves_what_aggregate_saves(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    write_synthetic_study(url, "syn", methods=("pixel", "vae"), configs=3, random_success=0.1)
    store = StudyStore.find(open_storage(url), "syn")
    live.refresh(store)
    figures = get_plotly_graph_objects(store.storage.get_study_system_attrs(store.study_id))
    assert list(figures) == [COMPARISON_ID]
    assert {"comparison", "curves-success_rate", "auc"} <= set(
        split_views(json.loads(figures[COMPARISON_ID]))
    )
    note = get_note(optuna.load_study(study_name="syn", storage=url))
    assert note.startswith(NOTE_BEGIN) and "Ranked by IQM AUC" in note


def test_a_launch_leaves_the_comparison_in_the_dashboard(tmp_path):
    """``sweeper launch`` of the CI study, no ``sweeper aggregate``: the study holds the
    comparison of both trials (the last trial's refresh always runs)."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    path = write_ci_spec(tmp_path / "ci.yaml", storage=url, random_episodes=0)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    command = [sys.executable, "-m", "sweeper.cli", "launch", str(path)]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    storage = open_storage(url)
    study_id = storage.get_study_id_from_name("ci")
    figures = get_plotly_graph_objects(storage.get_study_system_attrs(study_id))
    values = [t.value for t in optuna.load_study(study_name="ci", storage=url).trials]
    shown = split_views(json.loads(figures[COMPARISON_ID]))
    auc = shown["auc"]["data"][0]["y"]
    assert sorted(auc) == pytest.approx(sorted(values))
    table = shown["comparison"]["data"][0]["cells"]["values"]
    assert table[2] == ["1/1", "1/1"]  # both trials in it
    note = get_note(optuna.load_study(study_name="ci", storage=url))
    assert "Ranked by IQM AUC" in note
