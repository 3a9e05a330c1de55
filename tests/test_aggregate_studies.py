"""`sweeper aggregate A.yaml B.yaml ...`: scores normalised by each study's own anchors
(random agent, best control), pooled with each study a stratum, in one report; a study
without anchors is reported and skipped."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import optuna
import pandas as pd
import pytest
from optuna.trial import TrialState
from synthetic_study import write_synthetic_study

from sweeper import cli
from sweeper.results._normalize import study_anchors
from sweeper.results._stats import SUMMARIES, Group, iqm, several, stratified_bootstrap
from sweeper.results.cli_aggregate import load_study_frame
from sweeper.storage import current_trials, curve_of

#: name -> (env, methods, random agent's success rate)
STUDIES = {
    "reach": ("fetch_reach", ("pixel", "vae", "state"), 0.10),
    "point": ("point_reach", ("pixel", "true_reward", "vae", "state"), 0.05),
    "door": ("sawyer_door", ("pixel", "vae"), 0.02),  # no control: not normalised
}


def write_spec(path: Path, study: str) -> Path:
    text = (Path(__file__).parent.parent / "studies" / "ci.yaml").read_text()
    path.write_text(text.replace("study: ci", f"study: {study}"))
    return path


@pytest.fixture(scope="module")
def combined(tmp_path_factory):
    root = tmp_path_factory.mktemp("combined")
    url = f"sqlite:///{root / 'studies.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    for index, (name, (env, methods, random)) in enumerate(STUDIES.items()):
        write_synthetic_study(
            url, name, methods=methods, configs=4, seeds=(0, 1), env=env,
            random_success=random, seed=index,
        )  # fmt: skip
    specs = [str(write_spec(root / f"{name}.yaml", name)) for name in STUDIES]
    out = root / "out"
    assert cli.main(["aggregate", *specs, "--storage", url, "--out", str(out)]) == 0
    return url, out, specs


def done_by_method(url: str, name: str) -> dict[str, list]:
    trials = current_trials(optuna.load_study(study_name=name, storage=url).get_trials())
    done: dict[str, list] = {}
    for trial in trials.values():
        if trial.state == TrialState.COMPLETE:
            done.setdefault(trial.user_attrs["method"], []).append(trial)
    return done


def expected_scores(url: str, name: str) -> pd.DataFrame:
    """Each done trial's normalised AUC and final success, computed from the storage."""
    _, _, random = STUDIES[name]
    done = done_by_method(url, name)

    def final(trial) -> float:
        return curve_of(trial)["success_rate"][-1]

    controls = {m: done[m] for m in ("state", "true_reward") if m in done}
    best = max(controls, key=lambda m: iqm([t.value for t in controls[m]]))
    one_auc = iqm([t.value for t in controls[best]])
    one_final = iqm([final(t) for t in controls[best]])
    rows = [
        {
            "study": name,
            "method": method,
            "trial": t.number,
            "auc_norm": (t.value - random) / (one_auc - random),
            "final_success_norm": (final(t) - random) / (one_final - random),
        }
        for method, trials in done.items()
        for t in trials
    ]
    return pd.DataFrame(rows)


def test_scores_are_normalised_by_each_studys_own_anchors(combined):
    url, out, _ = combined
    written = pd.read_csv(out / "normalized_scores.csv")
    expected = pd.concat([expected_scores(url, n) for n in ("reach", "point")])
    merged = written.merge(expected, on=["study", "trial"], suffixes=("", "_expected"))
    assert len(merged) == len(expected) == len(written)  # the door study is left out
    for score in ("auc_norm", "final_success_norm"):
        np.testing.assert_allclose(merged[score], merged[f"{score}_expected"])
    anchors = pd.read_csv(out / "anchors.csv").set_index("study")
    assert anchors.loc["reach", "control"] == "state"
    assert anchors.loc["reach", "random_success"] == pytest.approx(0.10)
    assert anchors.loc["point", "control"] == "state"  # the better of the two controls
    assert not anchors.loc["door", "normalized"]
    assert "no control method" in anchors.loc["door", "problem"]
    # the best control scores 1 in IQM on its own study, by construction
    reach = written[(written["study"] == "reach") & (written["method"] == "state")]
    assert iqm(reach["auc_norm"]) == pytest.approx(1.0)


def test_pooled_statistics_resample_within_studies(combined):
    url, out, _ = combined
    table = pd.read_csv(out / "normalized_table.csv")
    scores = pd.concat([expected_scores(url, n) for n in ("reach", "point")])
    assert set(table["method"]) == {"pixel", "vae", "state", "true_reward"}
    for row in table.itertuples():
        part = scores[scores["method"] == row.method]
        values, strata = part[f"{row.score}_norm"].to_numpy(), part["study"].to_numpy()
        assert row.studies == len(set(strata)) and row.n == len(values)
        expected = stratified_bootstrap(
            several(*SUMMARIES.values()), {row.method: Group((values,), strata)}, seed=0
        )[row.method]
        for index, name in enumerate(SUMMARIES):
            assert getattr(row, name) == pytest.approx(float(expected.point[index]))
            assert getattr(row, f"{name}_low") == pytest.approx(float(expected.low[index]))
            assert getattr(row, f"{name}_high") == pytest.approx(float(expected.high[index]))
        assert row.iqm_low <= row.iqm <= row.iqm_high
    true_reward = table[table["method"] == "true_reward"]
    assert (true_reward["studies"] == 1).all()  # only the point study has it
    profiles = pd.read_csv(out / "normalized_profiles.csv")
    part = profiles[(profiles["method"] == "vae") & (profiles["score"] == "auc")]
    vae = scores[scores["method"] == "vae"]["auc_norm"].to_numpy()
    np.testing.assert_allclose(part["fraction"], [np.mean(vae > t) for t in part["tau"]])
    assert part["tau"].max() == 1.5


def test_combined_report_holds_every_study(combined):
    url, out, _ = combined
    report = (out / "report.md").read_text()
    assert report.startswith("# 3 studies: normalised comparison")
    assert "**1 of 3 studies are not normalised**" in report
    assert "| door | sawyer_door | 0.020 | – | – | – | **no**: no control method" in report
    for name in STUDIES:
        assert f"### `{name}`" in report
    assert "| vae | normalised AUC | 2 |" in report
    for link in [part.split(")")[0] for part in report.split("](")[1:]]:
        assert (out / link).read_bytes()[:4] == b"\x89PNG", link
    # studies of different envs: no gradient budget join
    assert "Gradient budget" not in report and not (out / "budget_table.csv").exists()
    tables = pd.read_csv(out / "study_tables.csv")
    assert sorted(set(tables["study"])) == sorted(STUDIES)
    door = tables[tables["study"] == "door"].set_index("method")
    done = done_by_method(url, "door")
    for method in ("pixel", "vae"):
        assert door.loc[method, "done"] == len(done[method])
        assert door.loc[method, "iqm"] == pytest.approx(iqm([t.value for t in done[method]]))


def test_default_output_folder_and_a_bad_spec(combined, tmp_path, capsys):
    url, _, specs = combined
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert cli.main(["aggregate", specs[0], specs[1], "--storage", url]) == 0
        assert (tmp_path / "runs" / "combined" / "reach+point" / "report.md").is_file()
        capsys.readouterr()
        assert cli.main(["aggregate", specs[0], "nope.yaml", "--storage", url]) == 2
        assert "nope.yaml" in capsys.readouterr().err
        # one --storage per spec, in their order; another count is one line, exit 2
        two = ["--storage", url, "--storage", url]
        assert cli.main(["aggregate", specs[0], specs[1], *two]) == 0
        capsys.readouterr()
        assert cli.main(["aggregate", specs[0], specs[1], *two, "--storage", url]) == 2
        err = capsys.readouterr().err
        assert "--storage: give one URL for all 2 specs or one per spec, got 3" in err
        assert len(err.strip().splitlines()) == 1
    finally:
        os.chdir(here)


def test_anchors_say_why_a_study_is_not_normalised(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    write_synthetic_study(url, "unmeasured", methods=("pixel", "state"), random_success=None)
    anchors = study_anchors(load_study_frame(url, "unmeasured"))
    assert anchors.control == "state" and "no random-agent success rate" in anchors.problem
    write_synthetic_study(url, "easy", methods=("pixel", "state"), random_success=0.9)
    anchors = study_anchors(load_study_frame(url, "easy"))
    assert "does no better than the random agent" in anchors.problem
    write_synthetic_study(url, "fine", methods=("pixel", "state"), random_success=0.01)
    assert study_anchors(load_study_frame(url, "fine")).problem is None
