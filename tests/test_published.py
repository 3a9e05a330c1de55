"""The published studies (``docs/studies/<study>/``): aggregating the committed database
again gives the committed AUC table, byte for byte, as the README promises anyone who
clones it. A change to the statistics that moves a published figure fails here; the
study's report is then written again with the change (its README says how)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from sweeper.aggregate import aggregate
from sweeper.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = sorted(
    p.parent.parent for p in (ROOT / "docs" / "studies").glob("*/aggregate/auc_table.csv")
)


def test_the_thesis_study_is_published():
    assert "fetch_reach_cpu" in [p.name for p in PUBLISHED]


@pytest.mark.parametrize("folder", PUBLISHED, ids=lambda p: p.name)
def test_aggregating_a_published_study_again_gives_its_auc_table(folder: Path, tmp_path: Path):
    spec = load_spec(ROOT / "studies" / f"{folder.name}.yaml")
    database = tmp_path / "study.db"
    shutil.copy(folder / "study.db", database)  # the committed file stays untouched
    out = tmp_path / "aggregate"
    aggregate(f"sqlite:///{database}", spec.study, out, seed=spec.seed, dashboard=False,
              progress=lambda message: None)  # fmt: skip
    committed = (folder / "aggregate" / "auc_table.csv").read_text()
    assert (out / "auc_table.csv").read_text() == committed
