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
