"""`sweeper confirm`: each method's top-K configurations by search AUC re-run on fresh seeds
in the same study, counted by the same ledger, reported apart from the search."""

from __future__ import annotations

import sys
import zlib

import numpy as np
import optuna
import pandas as pd
import pytest
import ray
from conftest import CI_SPEC, write_ci_spec
from optuna.trial import TrialState

from agent.config import TrialResult
from agent.metrics import normalized_auc
from sweeper import cli
from sweeper.plan._entries import build_plan, confirm_plan, fresh_seeds
from sweeper.results.cli_aggregate import aggregate
from sweeper.run._confirm import confirm
from sweeper.run._launch import launch, prepare
from sweeper.storage import open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake trains below


pytestmark = pytest.mark.usefixtures("local_ray")


def by_config(config, report=None):
    """A constant success rate fixed by the SAC config, method and seed: configs differ,
    and a config's AUC on another seed differs from its search AUC."""
    text = f"{config.sac}/{config.method}/{config.seed}"
    level = (zlib.crc32(text.encode()) % 100) / 100
    steps = list(range(0, config.total_steps + 1, config.eval_every))
    success = [level] * len(steps)
    for step in steps:
        report(step, {"success_rate": level, "final_distance": 1 - level})
    metrics = {"success_rate": tuple(success), "final_distance": tuple(1 - v for v in success)}
    return TrialResult(steps=tuple(steps), metrics=metrics, auc=normalized_auc(steps, success))


def trials_of(url: str) -> list[optuna.trial.FrozenTrial]:
    return optuna.load_study(study_name="ci", storage=open_storage(url)).get_trials()


def test_confirm_plan_keys_seeds_and_checkpoints():
    spec, _ = prepare(str(CI_SPEC))
    search = build_plan(spec, study_uid="abc")
    seeds = fresh_seeds(spec.seeds, 3)
    assert seeds == (1, 2, 3) and not set(seeds) & set(spec.seeds)
    plan = confirm_plan(search, {"pixel": [0], "linear": [0]}, seeds)
    assert plan.keys() == [f"confirm/{m}/0/{s}" for m in ("linear", "pixel") for s in seeds]
    first = {e.method: e for e in search.entries}
    for entry in plan.entries:
        assert entry.stage == "confirm" and entry.trial_config.seed == entry.seed
        assert entry.params == first[entry.method].params
        assert entry.trial_config.checkpoint_dir.endswith(
            f"-abc/confirm/{entry.method}/0/{entry.seed}"
        )
        assert entry.trial_config.sac == first[entry.method].trial_config.sac
    assert plan.hash == confirm_plan(search, {"pixel": [0], "linear": [0]}, seeds).hash
    assert plan.hash != confirm_plan(search, {"pixel": [0]}, seeds).hash


def test_confirm_reruns_the_top_k_on_fresh_seeds_and_is_reported_apart(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    path = write_ci_spec(tmp_path / "ci.yaml", storage=url, trials_per_method=3, seeds=[0, 1])
    spec_path = str(path)
    assert cli.main(["confirm", spec_path, "--top-k", "2", "--seeds", "2"]) == 2
    assert "launch the study first" in capsys.readouterr().err
    spec, plan = prepare(spec_path)
    assert launch(spec, plan, train=by_config) == 0
    search = {t.user_attrs["key"]: t for t in trials_of(url)}
    assert len(search) == 12 and {t.user_attrs["stage"] for t in search.values()} == {"search"}

    assert confirm(spec, plan, 2, 2, train=by_config) == 0
    trials = trials_of(url)
    confirmed = [t for t in trials if t.user_attrs["stage"] == "confirm"]
    chosen = optuna.load_study(study_name="ci", storage=url).user_attrs["confirm"]
    for method in ("pixel", "linear"):
        aucs = {c: np.mean([search[f"{method}/{c}/{s}"].value for s in (0, 1)]) for c in range(3)}
        top = sorted(aucs, key=lambda c: (-aucs[c], c))[:2]
        assert chosen["configs"][method] == top
        mine = [t for t in confirmed if t.user_attrs["method"] == method]
        assert sorted(t.user_attrs["key"] for t in mine) == sorted(
            f"confirm/{method}/{c}/{s}" for c in top for s in (2, 3)
        )
        for trial in mine:
            assert trial.state == TrialState.COMPLETE
            same = search[f"{method}/{trial.user_attrs['config_id']}/0"]
            assert trial.params == same.params  # the same configuration, a fresh seed
    for trial in trials[:12]:  # the search is left as it was
        assert trial.datetime_complete == search[trial.user_attrs["key"]].datetime_complete

    assert confirm(spec, plan, 2, 2, train=by_config) == 0  # resumes: nothing left to run
    assert len(trials_of(url)) == 20
    capsys.readouterr()
    assert cli.main(["confirm", spec_path, "--top-k", "1", "--seeds", "2"]) == 2
    assert "was confirmed with --top-k 2 --seeds 2" in capsys.readouterr().err
    assert len(trials_of(url)) == 20

    capsys.readouterr()
    assert cli.main(["status", spec_path]) == 0
    status = capsys.readouterr().out.splitlines()
    stage = status.index(
        "confirmation stage: top 2 configurations per method on 2 fresh seeds (2, 3)"
    )
    rows = {line.split()[0]: line.split()[1:] for line in status[stage + 1 :] if line}
    assert rows["pixel"] == rows["linear"] == ["4", "4", "0", "0", "0", "0"]
    assert rows["total"] == ["8", "8", "0", "0", "0", "0"]
    search_rows = {line.split()[0]: line.split()[1:] for line in status[1:stage]}
    assert search_rows["pixel"] == ["6", "6", "0", "0", "0", "0"]

    result = aggregate(url, "ci", tmp_path / "out", dashboard=False, progress=lambda m: None)
    table = result.table.set_index("method")
    assert table.loc["pixel", "n"] == 6  # search trials only
    written = pd.read_csv(tmp_path / "out" / "confirm_table.csv")
    assert len(written) == 4
    for row in written.itertuples():
        keys = [f"{row.method}/{row.config_id}/{s}" for s in (0, 1)]
        assert row.search_auc == pytest.approx(np.mean([search[k].value for k in keys]))
        fresh = [
            t.value
            for t in confirmed
            if (t.user_attrs["method"], t.user_attrs["config_id"]) == (row.method, row.config_id)
        ]
        assert row.confirm_auc == pytest.approx(np.mean(fresh)) and row.n == 2
        assert row.drop == pytest.approx(row.search_auc - row.confirm_auc)
        assert (row.planned, row.done, row.left) == (2, 2, 0)
    report = result.report.read_text()
    assert "| pixel | config" in report and "how good it is on new seeds" in report
    best = written[(written["method"] == "pixel") & (written["rank"] == 1)].iloc[0]
    assert f"| {best.search_auc:.3f} | {best.confirm_auc:.3f} [" in report


def fail_pixel(config, report=None):
    if config.method == "pixel":
        raise ValueError("no")
    return by_config(config, report)


def test_confirm_refuses_an_unfinished_search_and_writes_nothing(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec_path = str(write_ci_spec(tmp_path / "ci.yaml", storage=url))
    spec, plan = prepare(spec_path)
    assert launch(spec, plan, train=fail_pixel) == 1
    before = trials_of(url)
    capsys.readouterr()
    assert cli.main(["confirm", spec_path, "--top-k", "1", "--seeds", "1"]) == 2
    assert "the search is not finished: 1 of 2" in capsys.readouterr().err
    assert cli.main(["confirm", spec_path]) == 2
    assert "give --top-k K and --seeds N" in capsys.readouterr().err
    assert len(trials_of(url)) == len(before)
    assert "confirm" not in optuna.load_study(study_name="ci", storage=url).user_attrs
