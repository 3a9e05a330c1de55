"""Paired successive halving in a launched study: equal budgets per method at every rung,
decisions stored once, stopped trials PRUNED, promoted ones going on in their own trial."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from pathlib import Path

import optuna
import pandas as pd
import pytest
import ray
from conftest import assert_uninterrupted_curve, write_ci_spec
from optuna.trial import TrialState

from agent.config import Outcome, TrialResult
from agent.metrics import normalized_auc
from sweeper.plan._halving import HALVING_ATTR, Ladder
from sweeper.run._launch import launch, prepare
from sweeper.storage import curve_of, open_storage, trial_attr

ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake train below

#: each (method, config)'s success rate per 100 steps: pixel's best config starts slowly
QUALITY = {
    "pixel": {0: 0.3, 1: 0.9, 2: 0.6},
    "linear": {0: 0.8, 1: 0.1, 2: 0.5},
}
BUDGET = {"env_steps": 400, "seed_steps": 100, "eval_every": 100, "eval_episodes": 1}


def staged_trial(config, report=None):
    """A trial that honours ``stop_at`` like agent.train: its curve so far from its
    'checkpoint' (a file of the step reached), paused at stop_at, each run's env steps
    appended to ``ran.txt`` beside it."""
    folder = Path(config.checkpoint_dir)
    folder.mkdir(parents=True, exist_ok=True)
    marker = folder / "checkpoint.pt"
    start = int(marker.read_text()) if marker.exists() else 0
    end = config.stop_at or config.total_steps
    rate = QUALITY[config.method][int(folder.parent.name)]  # .../<method>/<config_id>/<seed>
    steps = list(range(0, end + 1, config.eval_every))
    success = [min(1.0, rate * s / 300) for s in steps]
    for step, value in zip(steps, success, strict=True):
        report(step, {"success_rate": value, "final_distance": 1 - value})
    with (folder / "ran.txt").open("a") as log:
        log.write(f"{start} {end}\n")
    marker.write_text(str(end))
    return TrialResult(
        steps=tuple(steps),
        metrics={"success_rate": tuple(success), "final_distance": tuple(1 - v for v in success)},
        auc=normalized_auc(steps, success),
        outcome=Outcome.PAUSED if config.stop_at else Outcome.COMPLETED,
        resumed_from=start or None,
    )


def _spec(tmp_path, rule="per_method"):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    path = write_ci_spec(
        tmp_path / "ci.yaml",
        storage=url,
        checkpoints=str(tmp_path / "ck"),
        trials_per_method=3,
        seeds=[0, 1],
        budget=BUDGET,
        random_episodes=0,
        halving={"rungs": [200, 300], "keep": 0.5, "rule": rule},
        execution={"keep_checkpoints": True},
    )
    return prepare(str(path))


def _ran(tmp_path: Path) -> dict[str, int]:
    """Env steps each method's trials ran, from the trials' own logs."""
    spent: dict[str, int] = {}
    for log in (tmp_path / "ck").rglob("ran.txt"):
        method = log.parent.parent.parent.name
        for line in log.read_text().split("\n"):
            if line:
                start, end = map(int, line.split())
                spent[method] = spent.get(method, 0) + end - start
    return spent


def test_every_method_runs_the_same_trials_and_steps_at_every_rung(tmp_path):
    spec, plan = _spec(tmp_path)
    assert plan.schedule.stops == (200, 300, 400) and plan.schedule.sizes == (3, 2, 1)
    assert launch(spec, plan, train=staged_trial) == 0
    study = optuna.load_study(study_name="ci", storage=open_storage(spec.storage_url))
    # by the AUC so far at 200: pixel keeps 1, 2 (the slow start 0 is out), linear 0, 2
    assert study.user_attrs[HALVING_ATTR] == {
        "200": {"linear": [0, 2], "pixel": [1, 2]},
        "300": {"linear": [0], "pixel": [1]},
    }
    trials = {t.user_attrs["key"]: t for t in study.get_trials()}
    assert len(trials) == len(study.get_trials()) == 12  # one Optuna trial per key
    for method in ("pixel", "linear"):
        states = {}
        for key, trial in trials.items():
            if key.startswith(f"{method}/"):
                rung = trial.user_attrs.get("rung", "full")
                states.setdefault((trial.state, rung), []).append(key)
        assert {k: len(v) for k, v in states.items()} == {
            (TrialState.PRUNED, 200): 2,
            (TrialState.PRUNED, 300): 2,
            (TrialState.COMPLETE, "full"): 2,
        }
    # 3 configs x 2 seeds x 200, then 2 x 2 x 100, then 1 x 2 x 100: for each method
    assert _ran(tmp_path) == {"pixel": 1800, "linear": 1800}
    winner = trials["pixel/1/0"]
    assert winner.user_attrs["outcome"] == "completed"
    assert sorted(winner.intermediate_values) == [0, 100, 200, 300, 400]
    assert trials["pixel/0/1"].user_attrs["outcome"] == "pruned"
    assert trials["pixel/0/1"].user_attrs["auc_at_rung"] == pytest.approx(0.1)
    # the replay of the study's recorded curves takes the live run's decisions
    curves = {
        (t.user_attrs["method"], t.user_attrs["config_id"], t.user_attrs["seed"]): (
            curve_of(t)["step"],
            curve_of(t)["success_rate"],
        )
        for t in trials.values()
    }
    ladder = Ladder(plan.schedule, range(3), (0, 1), ("linear", "pixel"))
    ladder.decide(curves)
    assert ladder.as_attr() == study.user_attrs[HALVING_ATTR]
    # a relaunch has nothing left: pruned keys are done
    assert launch(spec, plan, train=staged_trial) == 0
    assert len(study.get_trials()) == 12

    # aggregate says what each comparison covers
    from sweeper.results.cli_aggregate import aggregate

    result = aggregate(spec.storage_url, "ci", tmp_path / "agg", dashboard=False)
    assert result.table.set_index("method")["n"].to_dict() == {"pixel": 2, "linear": 2}
    halving = pd.read_csv(tmp_path / "agg" / "halving.csv").set_index("method")
    # every configuration at the first rung: AUC until 200 is rate / 3, IQM of 6 trials
    assert halving.loc["pixel", "rung_iqm"] == pytest.approx((0.1 + 0.2 + 0.2 + 0.3) / 4)
    assert halving.loc["linear", "rung_iqm"] == pytest.approx((0.1 + 0.5 + 0.5 + 0.8) / 12)
    assert halving["n"].tolist() == [6, 6] and halving["survivors"].tolist() == [2, 2]
    assert halving["env_steps"].tolist() == [1800, 1800]
    assert halving["compute_fraction"].tolist() == [0.75, 0.75]
    report = (tmp_path / "agg" / "report.md").read_text()
    assert "full-budget comparison of each method's surviving configurations" in report


def test_mean_rank_keeps_the_same_configurations_for_every_method(tmp_path):
    spec, plan = _spec(tmp_path, rule="mean_rank")
    assert launch(spec, plan, train=staged_trial) == 0
    study = optuna.load_study(study_name="ci", storage=open_storage(spec.storage_url))
    # ranks at 200: pixel 1 > 2 > 0, linear 0 > 2 > 1: mean ranks 0: 2, 1: 2, 2: 2
    decisions = study.user_attrs[HALVING_ATTR]
    assert decisions["200"]["pixel"] == decisions["200"]["linear"] == [0, 1]
    assert decisions["300"]["pixel"] == decisions["300"]["linear"]
    assert _ran(tmp_path)["pixel"] == _ran(tmp_path)["linear"] == 1800


def test_a_promoted_trial_s_curve_is_the_uninterrupted_one(tmp_path):
    """Real trials (agent.train) on point_reach: the survivor paused at each rung and went
    on from its checkpoint; its curve equals the same key run straight through."""
    path, url = _real_halving_spec(tmp_path, "ci", methods={"linear": {"latent_dim": 16}})
    spec, plan = prepare(str(path))
    assert launch(spec, plan) == 0
    study = optuna.load_study(study_name="ci", storage=open_storage(url))
    survivor = next(t for t in study.get_trials() if t.state == TrialState.COMPLETE)
    assert survivor.user_attrs["resumed_from"] == 200  # it paused at the rung
    entry = next(e for e in plan.entries if e.key == survivor.user_attrs["key"])
    assert_uninterrupted_curve(survivor, entry.trial_config)
    assert [t.state for t in study.get_trials()].count(TrialState.PRUNED) == 1


def _real_halving_spec(tmp_path, study, **changes):
    """The CI study, 2 configurations of 300 steps halved at 200 (one goes on), real
    trials; ``changes`` on top."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    path = write_ci_spec(
        tmp_path / "spec.yaml",
        study=study,
        storage=url,
        checkpoints=str(tmp_path / "ck"),
        trials_per_method=2,
        budget={"env_steps": 300, "seed_steps": 100, "eval_every": 100, "eval_episodes": 1},
        random_episodes=0,
        halving={"rungs": [200], "keep": 0.5},
        execution={"retries": 1, "checkpoint_every": 100},
        **changes,
    )
    return path, url


def _trials(url: str, study: str) -> list[optuna.trial.FrozenTrial]:
    try:
        return optuna.load_study(study_name=study, storage=open_storage(url)).get_trials()
    except KeyError:  # not created yet
        return []


def check_exact_rungs(trials, plan) -> dict[str, optuna.trial.FrozenTrial]:
    """Every key done once: per method one configuration PRUNED at the rung and one
    COMPLETE, nothing left live; the survivors' curves are their uninterrupted runs'."""
    done = [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    by_key = {t.user_attrs["key"]: t for t in done}
    assert sorted(by_key) == sorted(plan.keys()) and len(done) == len(by_key)
    assert not [t for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    for method in ("linear", "pixel"):
        mine = [t for k, t in by_key.items() if k.startswith(f"{method}/")]
        assert sorted(t.state for t in mine) == [TrialState.COMPLETE, TrialState.PRUNED]
        pruned = next(t for t in mine if t.state == TrialState.PRUNED)
        assert pruned.user_attrs["rung"] == 200
        assert curve_of(pruned)["step"] == [0, 100, 200]
    entries = {e.key: e for e in plan.entries}
    for key, trial in by_key.items():
        if trial.state == TrialState.COMPLETE:
            assert_uninterrupted_curve(trial, entries[key].trial_config)
    return by_key


@pytest.mark.slow
def test_a_driver_killed_mid_rung_leaves_the_ledger_exact(tmp_path, local_ray):
    import subprocess

    from conftest import wait_until

    path, url = _real_halving_spec(tmp_path, "rungkill")
    plan = prepare(str(path))[1]
    log = tmp_path / "driver.log"

    def start():
        return subprocess.Popen(
            [sys.executable, "-m", "sweeper.cli", "launch", str(path), "--address", local_ray],
            stdout=log.open("a"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=tmp_path,
        )

    def paused():  # a trial waits at the rung, another has not decided its method yet
        trials = _trials(url, "rungkill")
        waiting = [
            t for t in trials if t.state == TrialState.RUNNING and "paused_at" in t.user_attrs
        ]
        return (
            waiting
            and HALVING_ATTR
            not in optuna.load_study(study_name="rungkill", storage=open_storage(url)).user_attrs
        )

    first = start()
    try:
        wait_until(paused, 240, "a trial paused at the rung before any decision")
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(first.pid, signal.SIGKILL)
    second = start()
    try:
        assert second.wait(timeout=300) == 0, log.read_text()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(second.pid, signal.SIGKILL)
    trials = _trials(url, "rungkill")
    by_key = check_exact_rungs(trials, plan)
    # the paused trials the dead driver left went on from their checkpoint at the rung
    reaped = [
        t
        for t in trials
        if t.user_attrs.get("error") == "interrupted: its driver stopped"
        and "paused_at" in t.user_attrs
    ]
    assert reaped
    for trial in reaped:
        assert by_key[trial.user_attrs["key"]].user_attrs["resumed_from"] == 200


@pytest.mark.slow
def test_a_worker_killed_at_the_rung_leaves_the_ledger_exact(tmp_path, local_ray):
    import threading

    from conftest import wait_until

    path, url = _real_halving_spec(tmp_path, "rungworker")
    spec, plan = prepare(str(path))
    codes = []
    driver = threading.Thread(target=lambda: codes.append(launch(spec, plan)))
    driver.start()
    try:

        def at_rung():  # a trial evaluated at the rung: its worker is writing the pause
            for trial in _trials(url, "rungworker"):
                if trial.state == TrialState.RUNNING and 200 in trial.intermediate_values:
                    return trial_attr(trial, "worker")
            return None

        worker = wait_until(at_rung, 240, "a trial at the rung")
        with contextlib.suppress(ProcessLookupError):
            os.kill(worker["pid"], signal.SIGKILL)
    finally:
        driver.join(timeout=300)
    assert codes == [0]
    check_exact_rungs(_trials(url, "rungworker"), plan)
