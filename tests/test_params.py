"""Which params a trial is registered with (``sweeper.storage._params``): what varies and
``method``; the constants kept once in the study attr ``fixed_params`` and read back by the
aggregation; a study written before (every param on every trial) still syncs and reads."""

from __future__ import annotations

import optuna
import pytest
from conftest import CI_SPEC
from optuna.trial import TrialState

from sweeper.plan._entries import build_plan
from sweeper.results.cli_aggregate import load_study_frame, study_info
from sweeper.spec._models import load_spec
from sweeper.storage import StudyStore, open_storage
from sweeper.storage._params import FIXED_PARAMS_ATTR, applies_to, fixed_params, registered

optuna.logging.set_verbosity(optuna.logging.WARNING)


@pytest.fixture
def plan():
    return build_plan(load_spec(CI_SPEC))


def test_only_what_varies_and_the_method_are_registered(plan):
    entry = next(e for e in plan.entries if e.method == "linear")
    params, choices = registered(entry.params, entry.choices, entry.method, ("linear", "pixel"))
    assert set(params) == {"lr", "method"}  # the CI spec searches lr only
    assert params["method"] == "linear" and choices["method"] == ("linear", "pixel")
    assert choices["lr"] == entry.choices["lr"]
    constants = fixed_params((e.params, e.choices) for e in plan.entries)
    assert constants["hidden_sizes"] == "64x64" and constants["linear.latent_dim"] == 16
    assert "lr" not in constants and "method" not in constants
    assert set(constants) | {"lr"} == {k for e in plan.entries for k in e.params}
    assert applies_to("batch_size", "pixel") and applies_to("linear.latent_dim", "linear")
    assert not applies_to("linear.latent_dim", "pixel")


def _old_style_sync(store: StudyStore, entries, plan_hash: str) -> None:
    """What the writer did before: every param of every entry registered."""
    fresh = [
        (e.params, e.choices, {"method": e.method, "config_id": e.config_id, "seed": e.seed,
                               "key": e.key, "stage": "search", "plan_hash": plan_hash,
                               "attempts": 0})
        for e in entries
    ]  # fmt: skip
    store.add_waiting_many(fresh)


def test_a_study_registered_before_syncs_and_reads_with_its_constants(plan, tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    attrs = {"plan_hash": plan.hash, "plan": plan.keys()}
    store = StudyStore.open_or_create(open_storage(url), "ci", attrs)
    _old_style_sync(store, plan.entries, plan.hash)  # a study running before this change
    old = {t.user_attrs["key"]: t for t in store.trials()}
    store.start(old["pixel/0/0"]._trial_id)
    store.complete(old["pixel/0/0"]._trial_id, 0.25, {"outcome": "completed"})
    store.start(old["linear/0/0"]._trial_id)
    store.fail(old["linear/0/0"]._trial_id, {"outcome": "failed"})

    todo = store.sync(plan.entries, plan.hash)  # the relaunch, with this code
    assert [entry.key for entry, _ in todo] == ["linear/0/0"]
    fresh = todo[0][1]
    assert fresh.params == {"lr": 1e-3, "method": "linear"}
    assert store.attrs[FIXED_PARAMS_ATTR]["linear.latent_dim"] == 16
    assert store.sync(plan.entries, plan.hash)[0][1].number == fresh.number  # idempotent
    store.start(fresh._trial_id)
    store.complete(fresh._trial_id, 0.5, {"outcome": "completed"})

    study = optuna.load_study(study_name="ci", storage=url)  # Optuna reads the mix
    states = [t.state for t in study.trials]  # linear/0/0, pixel/0/0, linear/0/0 again
    assert states == [TrialState.FAIL, TrialState.COMPLETE, TrialState.COMPLETE]
    frame = load_study_frame(url, "ci")
    rows = frame.drop_duplicates("trial").set_index("key")
    everything = {k for e in plan.entries for k in e.params}
    expected = {e.key: e.params for e in plan.entries}
    for key in ("pixel/0/0", "linear/0/0"):  # old trial and new one: every param, same values
        row = rows[rows["counted"]].loc[key]
        mine = {c[len("params_") :]: v for c, v in row.items() if c.startswith("params_")}
        assert {k: v for k, v in mine.items() if v == v and v is not None} == expected[key]
    assert {c[len("params_") :] for c in frame.columns if c.startswith("params_")} == everything
    assert "params_method" not in frame.columns
    assert study_info(frame).searched == ("lr",)
