"""The published studies (``docs/studies/<study>/``): aggregating the committed database
again gives the committed AUC table, byte for byte, as the README promises anyone who
clones it, and prints that table's figures in the terminal. A change to the statistics
that moves a published figure fails here; the study's report is then written again with
the change (its README says how)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from sweeper.cli import main

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = sorted(
    p.parent.parent for p in (ROOT / "docs" / "studies").glob("*/aggregate/auc_table.csv")
)


def test_the_thesis_study_is_published():
    assert "fetch_reach_cpu" in [p.name for p in PUBLISHED]


@pytest.mark.parametrize("folder", PUBLISHED, ids=lambda p: p.name)
def test_aggregating_a_published_study_again_gives_its_auc_table(
    folder: Path, tmp_path: Path, capsys
):
    spec = ROOT / "studies" / f"{folder.name}.yaml"
    database = tmp_path / "study.db"
    shutil.copy(folder / "study.db", database)  # the committed file stays untouched
    out = tmp_path / "aggregate"
    storage = ["--storage", f"sqlite:///{database}", "--no-dashboard", "--out", str(out)]
    assert main(["aggregate", str(spec), *storage]) == 0
    committed = (folder / "aggregate" / "auc_table.csv").read_text()
    assert (out / "auc_table.csv").read_text() == committed

    # the terminal's table: every method, its IQM AUC and interval as in the CSV
    printed = capsys.readouterr().out.splitlines()
    table = pd.read_csv(folder / "aggregate" / "auc_table.csv")
    for row in table.itertuples():
        (line,) = [line for line in printed if line.split(" ", 1)[0] == row.method]
        if row.done:  # a method with nothing done yet (a running study's snapshot) shows "–"
            assert f"{row.iqm:.3f} [{row.iqm_low:.3f}, {row.iqm_high:.3f}]" in line
        else:
            assert "–" in line and "nan" not in line
        assert line.endswith(f"{row.done}/{row.planned}")
    assert any(line.startswith("Highest IQM AUC: ") for line in printed)
    assert f"  report:    {out / 'report.md'}" in printed
    assert f"  dashboard: sweeper dashboard {spec} --storage sqlite:///{database}" in printed


@pytest.mark.parametrize("folder", PUBLISHED, ids=lambda p: p.name)
def test_a_published_study_is_complete_and_in_today_s_format(folder: Path, tmp_path: Path):
    """Every finished trial's video is in ``artifacts/``, and its record is today's: a
    ``method`` param, no constant as a param, and no machine-readable value (the curve, the
    worker, machines, videos) as a user attr, which the dashboard shows as raw JSON."""
    import optuna
    from optuna.distributions import CategoricalDistribution
    from optuna.trial import TrialState

    from sweeper.storage import artifacts_in
    from sweeper.storage._attrs import SYSTEM_ATTRS
    from sweeper.storage._params import is_fixed

    shutil.copy(folder / "study.db", tmp_path / "study.db")
    (name,) = optuna.get_all_study_names(f"sqlite:///{tmp_path / 'study.db'}")
    study = optuna.load_study(study_name=name, storage=f"sqlite:///{tmp_path / 'study.db'}")
    finished = study.get_trials(states=(TrialState.COMPLETE, TrialState.PRUNED))
    assert finished
    for trial in finished:
        key = trial.user_attrs["key"]
        assert trial.params["method"] == trial.user_attrs["method"], key
        constants = [name for name, d in trial.distributions.items()
                     if isinstance(d, CategoricalDistribution) and is_fixed(d.choices)]  # fmt: skip
        assert not constants, f"{key}: constants as params {constants}"
        raw = [k for k in SYSTEM_ATTRS & trial.user_attrs.keys()
               if not isinstance(trial.user_attrs[k], str)]  # fmt: skip
        assert not raw, f"{key}: raw JSON user attrs {raw}"
        for meta in artifacts_in(trial.system_attrs):
            assert (folder / "artifacts" / meta["artifact_id"]).is_file(), f"{key}: {meta}"


#: the budget ladder's joined report (``docs/budget/``): these published studies, joined
BUDGET_STUDIES = ("fetch_reach_cpu", "fetch_reach_budget", "fetch_reach_budget_seeds")


def test_the_published_budget_report_is_the_published_studies_joined(tmp_path: Path):
    """``docs/budget/budget_table.csv`` is what ``sweeper aggregate`` makes of the three
    committed databases today, byte for byte: a new snapshot of any of them fails here
    until the joined report is written again (``docs/budget/README.md`` says how)."""
    specs, storages = [], []
    for study in BUDGET_STUDIES:
        shutil.copy(ROOT / "docs" / "studies" / study / "study.db", tmp_path / f"{study}.db")
        specs.append(str(ROOT / "studies" / f"{study}.yaml"))
        storages += ["--storage", f"sqlite:///{tmp_path / f'{study}.db'}"]
    out = tmp_path / "budget"
    assert main(["aggregate", *specs, *storages, "--no-dashboard", "--out", str(out)]) == 0
    for table in ("budget_table.csv", "budget_controls.csv"):
        committed = (ROOT / "docs" / "budget" / table).read_text()
        assert (out / table).read_text() == committed, f"docs/budget/{table} is out of date"
