"""Trials recorded in an older format, rewritten in today's (``sweeper.storage._migrate``,
``StudyStore.upgrade``): every param on every trial and no ``method`` param, the curve a
user attr, before; the params that vary and ``method``, the constants once in the study
attr ``fixed_params``, the curve a system attr, today. Readers get the same study after,
and ``sweeper publish`` upgrades its copy, never the live database, and names the videos
of finished trials it cannot publish."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import optuna
import pandas as pd
import pytest
from conftest import write_ci_spec

from sweeper import cli
from sweeper.plan._entries import build_plan
from sweeper.results.cli_aggregate import load_study_frame
from sweeper.results.cli_status import status_lines
from sweeper.spec._models import load_spec
from sweeper.storage import (
    CURVE_ATTR,
    StorageError,
    StudyBusy,
    StudyStore,
    curve_of,
    open_storage,
    trial_attr,
)
from sweeper.storage._artifacts import ArtifactStore, trial_artifacts, upload_once
from sweeper.storage._attrs import shown
from sweeper.storage._open import open_study
from sweeper.storage._params import FIXED_PARAMS_ATTR, METHOD_PARAM

optuna.logging.set_verbosity(optuna.logging.WARNING)
CURVE = {"step": [0, 100, 200, 300], "success_rate": [0.0, 0.5, 1.0, 1.0],
         "final_distance": [1.0, 0.5, 0.25, 0.0]}  # fmt: skip

MACHINE = {"from_step": 0, "cpu": "AuthenticAMD 26 2", "cpu_name": "AMD EPYC", "kernels": "AVX512",
           "torch": "2.13.0+cpu"}  # fmt: skip
OLD_ATTRS = {CURVE_ATTR: CURVE, "worker": {"node": "n1", "pid": 7}, "machines": [MACHINE],
             "videos": {"episode-step300.mp4": "0568e6a1"}}  # fmt: skip


def old_study(
    spec_path: Path, relaunched: bool = False, videos: ArtifactStore | None = None
) -> StudyStore:
    """The CI study as the writer recorded it before: every param registered, no ``method``
    param, each curve, worker, machines and video map a user attr, both keys done.
    ``relaunched``: linear/0/0 failed then, and a relaunch with today's writer re-ran it (a
    study of both formats, and ``fixed_params``). ``videos``: each trial's video stored there."""
    spec = load_spec(spec_path)
    plan = build_plan(spec)
    attrs = {"plan_hash": plan.hash, "plan": plan.keys()}
    store = StudyStore.open_or_create(open_storage(spec.storage_url), "ci", attrs)
    store.add_waiting_many([
        (e.params, e.choices, {"method": e.method, "config_id": e.config_id, "seed": e.seed,
                               "key": e.key, "stage": "search", "plan_hash": plan.hash,
                               "attempts": 1})
        for e in plan.entries
    ])  # fmt: skip
    for trial in store.trials():
        store.start(trial._trial_id)
        store.report(trial._trial_id, dict(zip(CURVE["step"], CURVE["success_rate"], strict=True)))
        for key, value in OLD_ATTRS.items():  # the old place: raw JSON on the trial's page
            store.storage.set_trial_user_attr(trial._trial_id, key, value)
        if videos is not None:
            upload_once(store.storage, trial._trial_id, "episode-step300.mp4", b"mp4", videos)
        if relaunched and trial.user_attrs["method"] == "linear":
            store.fail(trial._trial_id, {"outcome": "failed", "error": "it died"})
        else:
            store.complete(trial._trial_id, 0.6, {"outcome": "completed", "seconds": 5.0})
    if relaunched:
        ((_, fresh),) = store.sync(plan.entries, plan.hash)
        store.start(fresh._trial_id)
        store.complete(fresh._trial_id, 0.7, {"outcome": "completed", "curve": CURVE})
    return store


def readers_view(spec_path: Path):
    """What the readers get: the aggregation's frame, ``sweeper status``' lines, and every
    trial's state, value, intermediate values, curve and other attrs as ``trial_attr`` reads
    them."""
    spec = load_spec(spec_path)
    url = spec.storage_url
    with open_study(url, "ci", write=False) as store:
        trials = [(t.number, t.state, t.value, t.intermediate_values, curve_of(t),
                   {k: trial_attr(t, k) for k in t.user_attrs if k != CURVE_ATTR})
                  for t in store.trials()]  # fmt: skip
        status = status_lines(spec, store)
    return load_study_frame(url, "ci"), status, trials


@pytest.mark.parametrize("relaunched", [False, True], ids=["old", "old-and-new"])
def test_upgrade_rewrites_old_trials_and_readers_get_the_same_study(tmp_path, relaunched):
    spec = write_ci_spec(tmp_path / "ci.yaml", storage=f"sqlite:///{tmp_path / 'study.db'}")
    store = old_study(spec, relaunched)
    frame, status, trials = readers_view(spec)

    done = store.upgrade()
    assert (done.params, done.curves, done.values) == (2, 2, 2)  # the failed linear trial's too
    after_frame, after_status, after_trials = readers_view(spec)
    pd.testing.assert_frame_equal(after_frame, frame)
    assert after_frame.to_csv() == frame.to_csv()
    assert after_status == status and after_trials == trials

    assert store.attrs[FIXED_PARAMS_ATTR] == done.fixed
    assert done.fixed["batch_size"] == 32 and done.fixed["linear.latent_dim"] == 16
    for trial in store.trials():  # today's format, every one
        assert trial.params["method"] == trial.user_attrs["method"]
        assert set(trial.params) == {"lr", METHOD_PARAM}  # the CI spec varies lr alone
        assert CURVE_ATTR not in trial.user_attrs and trial.system_attrs[CURVE_ATTR] == CURVE
        if trial.number < 2:  # an old trial's values: system attrs, the page's in words
            for key in ("worker", "machines", "videos"):
                assert trial.system_attrs[key] == OLD_ATTRS[key]
                assert trial.user_attrs[key] == shown(key, OLD_ATTRS[key])
            assert trial.user_attrs["machines"].startswith("from step 0: AMD EPYC (Auth")
    assert len({str(t.distributions[METHOD_PARAM]) for t in store.trials()}) == 1
    again = store.upgrade()
    assert (again.params, again.curves, again.values) == (0, 0, 0)  # nothing left to rewrite
    assert readers_view(spec)[2] == trials


def test_upgrade_refuses_a_driven_study_and_a_constant_it_cannot_keep_once(tmp_path):
    database = tmp_path / "study.db"
    store = old_study(write_ci_spec(tmp_path / "ci.yaml", storage=f"sqlite:///{database}"))
    before = trial_tables(database)
    store.claim_driver()  # a live driver (this process) writes it: not rewritten under it
    with pytest.raises(StudyBusy):
        store.upgrade()
    store.release_driver()
    store.set_study_attr(FIXED_PARAMS_ATTR, {"batch_size": 64})  # not the trials' 32
    with pytest.raises(StorageError, match="batch_size=32 is not the study's batch_size=64"):
        store.upgrade()
    assert trial_tables(database) == before  # nothing written


def trial_tables(database: Path) -> list[str]:
    """The database's trial tables, as SQL (the study attrs left out)."""
    dump = sqlite3.connect(database).iterdump()
    return [line for line in dump if "study_user_attributes" not in line]


def test_publish_upgrades_its_copy_and_names_each_missing_video(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    live = tmp_path / "live"
    spec = write_ci_spec(tmp_path / "ci.yaml", storage=f"sqlite:///{live / 'study.db'}")
    live.mkdir()
    store = old_study(spec, videos=ArtifactStore(str(live / "artifacts")))  # the spec's place
    ids = {t.user_attrs["key"]: trial_artifacts(store.storage, t._trial_id)[0]["artifact_id"]
           for t in store.trials()}  # fmt: skip
    (live / "artifacts" / ids["linear/0/0"]).unlink()  # lost, as runs/ once was
    before = list(sqlite3.connect(live / "study.db").iterdump())

    assert cli.main(["publish", str(spec), "--out", "pub"]) == 2
    out, err = capsys.readouterr()
    number = next(t.number for t in store.trials() if t.user_attrs["key"] == "linear/0/0")
    line = (f"trial {number} (linear/0/0): its video episode-step300.mp4 is missing "
            f"(artifacts/{ids['linear/0/0']})")  # fmt: skip
    assert f"sweeper publish: {line}\n" in err and err.count("sweeper publish: ") == 1
    assert ("today's format: the params of 2 trials, 2 curves, the worker, machines and videos "
            "of 2 trials") in out  # fmt: skip
    assert line in (tmp_path / "pub" / "status.txt").read_text()
    assert (tmp_path / "pub" / "aggregate" / "auc_table.csv").is_file()  # published anyway
    published = optuna.load_study(study_name="ci", storage="sqlite:///pub/study.db")
    assert all(METHOD_PARAM in t.params for t in published.trials)
    assert list(sqlite3.connect(live / "study.db").iterdump()) == before  # the live one: as it was
