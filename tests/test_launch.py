"""`sweeper launch` and `sweeper status` end to end, on one local Ray for the module."""

from __future__ import annotations

import json
import math
import os
import sqlite3
import sys
import time
import uuid
from pathlib import Path

import optuna
import pandas as pd
import psycopg
import pytest
import ray
import yaml
from conftest import CI_SPEC, PG_ADMIN, wait_until, write_ci_spec
from optuna.trial import TrialState

from agent.config import TrialResult
from agent.metrics import normalized_auc
from sweeper import cli
from sweeper.run import _launch as launcher
from sweeper.run._launch import launch, prepare
from sweeper.storage import CURVE_ATTR, StudyStore, artifacts_in, curve_of, open_storage, trial_attr
from sweeper.storage._writer import _this_driver

GRID = [0, 100, 200, 300]  # studies/ci.yaml: env_steps 300, eval_every 100

optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake trains below


pytestmark = pytest.mark.usefixtures("local_ray")


def load(url: str, name: str = "ci") -> optuna.Study:
    return optuna.load_study(study_name=name, storage=open_storage(url))


def check_ci_study(study: optuna.Study) -> None:
    """Exactly the two planned trials, complete, with curves, AUCs and attrs."""
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 2
    assert sorted(t.user_attrs["key"] for t in trials) == ["linear/0/0", "pixel/0/0"]
    for trial in trials:
        attrs = trial.user_attrs
        assert CURVE_ATTR not in attrs  # a system attr: the dashboard's trial table stays short
        curve = curve_of(trial)
        assert curve["step"] == GRID
        assert set(curve) == {"step", "success_rate", "final_distance"}
        assert trial.intermediate_values == dict(zip(GRID, curve["success_rate"], strict=True))
        assert trial.value == pytest.approx(normalized_auc(GRID, curve["success_rate"]))
        assert attrs["outcome"] == "completed"
        assert attrs["attempts"] == 1
        assert attrs["method"] == attrs["key"].split("/")[0]
        assert (attrs["config_id"], attrs["seed"]) == (0, 0)
        assert attrs["plan_hash"] == study.user_attrs["plan_hash"]
        worker = trial_attr(trial, "worker")
        assert worker["pid"] > 0
        # the machine it ran on, for anyone re-running it (agent.machine)
        machines = trial_attr(trial, "machines")
        assert [m["from_step"] for m in machines] == [0]
        assert machines[0]["kernels"] and machines[0]["cpu"]
        # the trial's page shows no JSON a person must parse: those values are system
        # attrs, with words under their keys (sweeper.storage._attrs)
        shown = {k: v for k, v in attrs.items() if isinstance(v, dict | list)}
        assert not shown, shown
        assert attrs["worker"] == f"pid {worker['pid']} on {worker['node']}"
        assert attrs["machines"].startswith("from step 0: ")
        # the params that vary are trial params, with the method; constants are study attrs
        assert set(trial.params) == {"lr", "method"}
        assert trial.params["method"] == attrs["method"]
    study_attrs = study.user_attrs
    fixed = study_attrs["fixed_params"]
    assert fixed["hidden_sizes"] == "64x64" and fixed["linear.latent_dim"] == 16
    assert study_attrs["plan"] == ["linear/0/0", "pixel/0/0"]
    assert study_attrs["spec"]["study"] == "ci"
    assert study_attrs["env"] == "point_reach"
    assert study_attrs["metric_names"] == ["success_rate", "final_distance"]
    assert study_attrs["versions"]["optuna"] == optuna.__version__
    assert study_attrs["revision"]
    assert study_attrs["driver"] is None  # released


def test_launch_ci_end_to_end_then_status_then_a_relaunch_reruns_nothing(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)  # the default storage and checkpoints go under runs/ci/
    assert cli.main(["launch", str(CI_SPEC)]) == 0
    url = "sqlite:///runs/ci/study.db"
    study = load(url)
    check_ci_study(study)
    assert (tmp_path / "runs" / "ci" / "checkpoints").is_dir()

    capsys.readouterr()
    assert cli.main(["status", str(CI_SPEC)]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line}
    # planned, done, diverged, running, failed, left
    assert rows["linear"] == ["1", "1", "0", "0", "0", "0"]
    assert rows["pixel"] == ["1", "1", "0", "0", "0", "0"]
    assert "driver: not running" in out

    before = [(t.number, t.datetime_complete) for t in study.get_trials()]

    def no_ray(*args, **kwargs):
        raise AssertionError("Ray was started")

    monkeypatch.setattr(launcher, "start_ray", no_ray)  # nothing left: no Ray (issue 22)
    assert cli.main(["launch", str(CI_SPEC)]) == 0  # nothing left: nothing re-run
    assert "2 of 2 trials done, 0 to run" in capsys.readouterr().err
    assert [(t.number, t.datetime_complete) for t in load(url).get_trials()] == before

    # anyone can re-run a recorded trial from its plan entry: here, the same curve exactly
    monkeypatch.undo()  # Ray's absence was the relaunch's check; rerun starts none anyway
    monkeypatch.chdir(tmp_path)
    layout = os.environ.get("GCRL_CONV_LAYOUT")
    assert cli.main(["rerun", str(CI_SPEC), "pixel/0/0"]) == 0
    assert os.environ.get("GCRL_CONV_LAYOUT") == layout  # the recorded layout only for the run
    out = capsys.readouterr().out
    assert "the same machine: the curve should be the recorded one" in out
    assert "the same curve: every metric at all 4 steps is the recorded float" in out
    # at other threads than the recorded ones it is another machine (sums split otherwise)
    assert cli.main(["rerun", str(CI_SPEC), "pixel/0/0", "--threads", "2"]) in (0, 1)
    out = capsys.readouterr().out
    assert ", 2 threads\nanother machine (or unknown)" in out
    with pytest.raises(SystemExit):
        cli.main(["rerun", str(CI_SPEC), "pixel/0/0", "--threads", "0"])
    assert "--threads: must be an integer >= 1, got 0" in capsys.readouterr().err
    assert [(t.number, t.datetime_complete) for t in load(url).get_trials()] == before

    # published while a driver holds it (this process poses as one): the copy is not driven
    optuna.load_study(study_name="ci", storage=url).set_user_attr("driver", _this_driver())
    assert cli.main(["publish", str(CI_SPEC), "--out", "pub"]) == 0
    pub = tmp_path / "pub"
    files = ["aggregate", "artifacts", "status.txt", "study.db"]  # one database file
    assert sorted(p.name for p in pub.iterdir()) == files
    assert len([p for p in (pub / "artifacts").rglob("*") if p.is_file()]) == 2  # 2 videos
    assert load(url).user_attrs["driver"]["pid"] == os.getpid()  # the live study: untouched
    assert load("sqlite:///pub/study.db").user_attrs["driver"] is None
    status_text = (pub / "status.txt").read_text()
    assert (
        "driver: not running" in status_text
        and "copied from sqlite:///runs/ci/study.db" in status_text
    )
    published = (pub / "aggregate" / "auc_table.csv").read_text()
    assert cli.main(["aggregate", str(CI_SPEC), "--storage", "sqlite:///pub/study.db",
                     "--out", "again", "--no-dashboard"]) == 0  # fmt: skip
    assert (tmp_path / "again" / "auc_table.csv").read_text() == published

    # a published video lost: a rerun with the recorded curve films it again, byte for byte
    (pixel,) = [t for t in load("sqlite:///pub/study.db").get_trials()
                if t.user_attrs["key"] == "pixel/0/0"]  # fmt: skip
    (meta,) = artifacts_in(pixel.system_attrs)
    lost = pub / "artifacts" / meta["artifact_id"]
    original = lost.read_bytes()
    lost.unlink()
    capsys.readouterr()
    pub_url = ["--storage", "sqlite:///pub/study.db"]
    assert cli.main(["publish", str(CI_SPEC), *pub_url, "--out", "pub2"]) == 2  # names it
    assert cli.main(["rerun", str(CI_SPEC), "pixel/0/0", *pub_url, "--restore-videos"]) == 0
    out = capsys.readouterr().out
    assert f"video {meta['filename']}: restored to pub/artifacts/{meta['artifact_id']}" in out
    assert lost.read_bytes() == original
    assert cli.main(["rerun", str(CI_SPEC), "pixel/0/0", *pub_url, "--restore-videos"]) == 0
    assert f"video {meta['filename']}: present" in capsys.readouterr().out
    # a record this run cannot repeat: it stops at the first evaluation that differs
    curve = curve_of(pixel)
    curve["final_distance"][0] += 1e-7
    with sqlite3.connect(pub / "study.db") as db:
        db.execute("UPDATE trial_system_attributes SET value_json = ? WHERE key = ? AND "
                   "trial_id = ?", (json.dumps(curve), CURVE_ATTR, pixel._trial_id))  # fmt: skip
    lost.unlink()
    assert cli.main(["rerun", str(CI_SPEC), "pixel/0/0", *pub_url, "--restore-videos"]) == 1
    out = capsys.readouterr().out
    assert out.count("  step ") == 1 and "another curve from here: step 0, final_distance" in out
    assert "stopped there" in out and not lost.exists()
    capsys.readouterr()
    assert cli.main(["publish", str(CI_SPEC), "--out", "runs/ci"]) == 2  # onto itself
    assert cli.main(["publish", str(CI_SPEC), "--storage", "postgresql://u@127.0.0.1/x"]) == 2
    errors = capsys.readouterr().err.splitlines()
    assert errors[0].startswith("sweeper publish: ") and "own database" in errors[0]
    assert "is not SQLite" in errors[1] and len(errors) == 2


def test_the_image_control_and_the_oracle_are_methods_like_any_other(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    vae = {"latent_dim": 8, "beta": 1.0, "lr": 1e-3, "epochs": 1, "num_images": 64}
    methods = {"true_reward": {}, "state": {}, "vae": vae}
    spec = write_ci_spec(tmp_path / "controls.yaml", methods=methods)
    assert cli.main(["launch", str(spec)]) == 0
    trials = load("sqlite:///runs/ci/study.db").get_trials()
    keys = ["state/0/0", "true_reward/0/0", "vae/0/0"]
    assert sorted(t.user_attrs["key"] for t in trials) == keys
    for trial in trials:
        assert trial.state == TrialState.COMPLETE and curve_of(trial)["step"] == GRID
        assert trial.user_attrs["reward_scale"] > 0  # the spec's default: "auto", measured
        fit = trial_attr(trial, "encoder_fit")  # a learned encoder's fit, as it went
        assert (fit is not None) == (trial.user_attrs["method"] == "vae")
        assert fit is None or (fit["latent_dim"] == 8 and 0 <= fit["active_dims"] <= 8)
    assert cli.main(["aggregate", str(spec)]) == 0
    table = (tmp_path / "runs" / "ci" / "aggregate" / "auc_table.csv").read_text()
    assert "true_reward" in table and "state" in table


def test_a_named_variant_runs_beside_its_encoder_to_aggregate_and_confirm(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    methods = {
        "conv": {"latent_dim": 16},
        "conv_pytorch_init": {"encoder": "conv", "init": "pytorch", "latent_dim": 16},
    }
    spec = write_ci_spec(tmp_path / "variant.yaml", methods=methods)
    assert cli.main(["launch", str(spec)]) == 0
    trials = {t.user_attrs["key"]: t for t in load("sqlite:///runs/ci/study.db").get_trials()}
    assert sorted(trials) == ["conv/0/0", "conv_pytorch_init/0/0"]
    base, variant = trials["conv/0/0"], trials["conv_pytorch_init/0/0"]
    assert variant.user_attrs["method"] == "conv_pytorch_init"
    fixed = load("sqlite:///runs/ci/study.db").user_attrs["fixed_params"]
    assert fixed["conv_pytorch_init.init"] == "pytorch" and fixed["conv.init"] == "drq"
    assert variant.params["method"] == "conv_pytorch_init" and base.params["method"] == "conv"
    for trial in (base, variant):
        assert trial.state == TrialState.COMPLETE and curve_of(trial)["step"] == GRID
    # the same SAC configuration and seed, another reward encoder: another reward scale
    assert base.user_attrs["reward_scale"] != variant.user_attrs["reward_scale"]

    capsys.readouterr()
    assert cli.main(["status", str(spec)]) == 0
    rows = {line.split()[0]: line.split()[1:] for line in capsys.readouterr().out.splitlines()}
    assert rows["conv_pytorch_init"] == rows["conv"] == ["1", "1", "0", "0", "0", "0"]
    assert cli.main(["aggregate", str(spec)]) == 0
    out = tmp_path / "runs" / "ci" / "aggregate"
    table = pd.read_csv(out / "auc_table.csv").set_index("method")
    assert set(table.index) == {"conv", "conv_pytorch_init"} and set(table["n"]) == {1}
    assert "conv_pytorch_init" in (out / "report.md").read_text()

    assert cli.main(["confirm", str(spec), "--top-k", "1", "--seeds", "1"]) == 0
    keys = {t.user_attrs["key"] for t in load("sqlite:///runs/ci/study.db").get_trials()}
    assert keys - set(trials) == {"confirm/conv/0/1", "confirm/conv_pytorch_init/0/1"}


def test_launch_on_postgresql(tmp_path):
    schema = f"sweeper_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as connection:
        connection.execute(f"CREATE SCHEMA {schema}")
    try:
        url = f"postgresql://postgres@127.0.0.1:5432/test?options=-csearch_path%3D{schema}"
        spec = write_ci_spec(
            tmp_path / "ci.yaml",
            storage=url,
            checkpoints=str(tmp_path / "checkpoints"),
            artifacts=str(tmp_path / "artifacts"),  # not the checkout's runs/
        )
        # one trial at a time with both of Ray's CPUs (the spec says 1 thread, 1 CPU a trial)
        args = ["--max-concurrent", "1", "--threads-per-trial", "2"]
        assert cli.main(["launch", str(spec), *args]) == 0
        check_ci_study(load(url))
        execution = load(url).user_attrs["spec"]["execution"]
        assert (execution["max_concurrent"], execution["threads_per_trial"]) == (1, 2)
        assert execution["cpus_per_trial"] == 2
    finally:
        with psycopg.connect(PG_ADMIN, autocommit=True) as connection:
            connection.execute(f"DROP SCHEMA {schema} CASCADE")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"trials_per_method": 0}, "trials_per_method"),
        ({"env": {"name": "point_reach", "options": {"nosuch": 1}}}, "env.options.nosuch"),
        ({"methods": {"pixel": {}, "linear": {"latent_dims": 8}}}, "methods.linear.latent_dims"),
        ({"storage": "postgresql://postgres@127.0.0.1:1/test"}, "storage"),
        ({"storage": "sqlite:///:memory:"}, "storage"),
        # each within what the filesystem, the database and the machine hold (issue 22)
        ({"study": "s" * 300}, "study"),
        ({"budget": {"env_steps": 10**12}}, "budget.env_steps"),
        ({"budget": {"env_steps": 10**8, "eval_every": 100}}, "budget.eval_every"),
        ({"trials_per_method": 2, "seeds": list(range(6000))}, "trials_per_method"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(tmp_path, monkeypatch, capsys, change, field):
    monkeypatch.chdir(tmp_path)
    spec = write_ci_spec(tmp_path / "bad.yaml", **change)
    assert cli.main(["launch", str(spec)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith("sweeper launch: ") and field in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]
    if "storage" not in change:  # a bad spec is one line for a reader too
        assert cli.main(["status", str(spec)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and field in err


def test_launch_refuses_another_plan(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    url = "sqlite:///runs/ci/study.db"
    StudyStore.open_or_create(open_storage(url), "ci", {"plan_hash": "0" * 64})
    assert cli.main(["launch", str(CI_SPEC)]) == 2
    assert "another plan" in capsys.readouterr().err
    assert load(url).get_trials() == []
    assert cli.main(["status", str(CI_SPEC)]) == 2


def test_help(capsys):
    for command, flags in [
        ("launch", ["--storage", "--address", "--max-concurrent", "--threads-per-trial"]),
        ("confirm", ["--max-concurrent", "--threads-per-trial"]),
        ("status", ["--storage"]),
    ]:
        with pytest.raises(SystemExit) as info:
            cli.main([command, "--help"])
        assert info.value.code == 0
        out = capsys.readouterr().out
        assert all(flag in out for flag in flags)


def fake_result(config, success: list[float], distance: list[float], **kw) -> TrialResult:
    steps = list(range(0, config.total_steps + 1, config.eval_every))
    return TrialResult(
        steps=tuple(steps),
        metrics={"success_rate": tuple(success), "final_distance": tuple(distance)},
        auc=normalized_auc(steps, success),
        **kw,
    )


def raise_or_diverge(config, report=None):
    """pixel raises; linear diverges after its second evaluation."""
    if config.method == "pixel":
        report(0, {"success_rate": 0.0, "final_distance": 1.0})
        raise ValueError("exploded on purpose")
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    report(100, {"success_rate": 0.5, "final_distance": 0.5})
    result = fake_result(
        config,
        [0.0, 0.5, 0.0, 0.0],
        [1.0, 0.5, math.nan, math.nan],
        outcome="diverged",
        diverged_step=200,
        diverged_loss="critic",
    )
    for step, value in zip(result.steps[2:], result.metrics["success_rate"][2:], strict=True):
        report(step, {"success_rate": value, "final_distance": math.nan})
    return result


def always_succeed(config, report=None):
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    return fake_result(config, [0.0, 1.0, 1.0, 1.0], [1.0, 0.0, 0.0, 0.0])


def test_keys_start_round_by_round_so_a_partial_study_stays_paired(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    path = write_ci_spec(
        tmp_path / "ci.yaml", storage=url, trials_per_method=2, seeds=[0, 1], random_episodes=0
    )
    spec, plan = prepare(str(path), max_concurrent=1)
    assert [e.key for e in plan.entries][:2] == ["linear/0/0", "linear/0/1"]  # plan order
    assert launch(spec, plan, train=always_succeed) == 0
    started = sorted(load(url).get_trials(), key=lambda t: t.datetime_start)
    assert [t.user_attrs["key"] for t in started] == [
        f"{method}/{config}/{seed}"
        for config in (0, 1)
        for seed in (0, 1)
        for method in ("linear", "pixel")
    ]


def test_exception_and_divergence_are_recorded_then_relaunch_reruns_failed(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec, plan = prepare(str(write_ci_spec(tmp_path / "ci.yaml", storage=url)))
    assert launch(spec, plan, train=raise_or_diverge) == 1
    trials = {t.user_attrs["key"]: t for t in load(url).get_trials()}
    failed, diverged = trials["pixel/0/0"], trials["linear/0/0"]
    assert failed.state == TrialState.FAIL
    assert failed.user_attrs["outcome"] == "failed"
    assert failed.user_attrs["error"] == "ValueError: exploded on purpose"
    assert "raise_or_diverge" in failed.user_attrs["traceback"]
    assert failed.intermediate_values == {0: 0.0}  # what it reported before failing
    assert diverged.state == TrialState.COMPLETE
    assert diverged.value == pytest.approx(normalized_auc(GRID, [0.0, 0.5, 0.0, 0.0]))
    assert diverged.user_attrs["outcome"] == "diverged"
    assert (diverged.user_attrs["diverged_step"], diverged.user_attrs["diverged_loss"]) == (
        200,
        "critic",
    )
    assert curve_of(diverged)["final_distance"] == [1.0, 0.5, None, None]
    assert diverged.intermediate_values == {0: 0.0, 100: 0.5, 200: 0.0, 300: 0.0}

    capsys.readouterr()
    spec_path = str(tmp_path / "ci.yaml")
    assert cli.main(["status", spec_path]) == 0
    out = capsys.readouterr().out
    assert "failed: pixel/0/0 (trial" in out and "ValueError: exploded on purpose" in out
    rows = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line}
    assert rows["linear"] == ["1", "1", "1", "0", "0", "0"]
    assert rows["pixel"] == ["1", "0", "0", "0", "1", "0"]

    assert launch(spec, plan, train=always_succeed) == 0  # re-runs the failed key only
    trials = load(url).get_trials()
    assert len(trials) == 3
    rerun = trials[-1]
    assert rerun.user_attrs["key"] == "pixel/0/0"
    assert rerun.user_attrs["supersedes"] == [failed.number]
    assert rerun.state == TrialState.COMPLETE
    assert trials[diverged.number].datetime_complete == diverged.datetime_complete


def resume_marker(config, report=None):
    """Resumes from a marker file in its checkpoint_dir (as a checkpoint), else writes one."""
    marker = Path(config.checkpoint_dir) / "checkpoint.pt"
    resumed_from = int(marker.read_text()) if marker.exists() else None
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text("100")
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    return fake_result(
        config, [0.0, 1.0, 1.0, 1.0], [1.0, 0.0, 0.0, 0.0], resumed_from=resumed_from
    )


@pytest.mark.parametrize("keep", [None, True])
def test_a_new_study_with_the_same_spec_starts_every_trial_from_step_0(tmp_path, keep):
    """Checkpoints belong to one study: a new database with the same spec and checkpoint
    root resumes nothing; finished trials' checkpoints are removed unless kept."""
    root = tmp_path / "checkpoints"
    execution = yaml.safe_load(CI_SPEC.read_text())["execution"]
    if keep is not None:
        execution["keep_checkpoints"] = keep
    for studies, database in enumerate(("first.db", "second.db"), start=1):
        url = f"sqlite:///{tmp_path / database}"
        spec_path = write_ci_spec(
            tmp_path / "ci.yaml", storage=url, checkpoints=str(root), execution=execution
        )
        assert launch(*prepare(str(spec_path)), train=resume_marker) == 0
        trials = load(url).get_trials()
        assert [t.user_attrs["resumed_from"] for t in trials] == [None, None]
        assert len(list(root.rglob("checkpoint.pt"))) == (2 * studies if keep else 0)
    if keep:  # one folder per study
        assert len({p.relative_to(root).parts[0] for p in root.rglob("checkpoint.pt")}) == 2


def test_more_torch_threads_than_cpus_is_refused_with_the_fix(tmp_path):
    """threads_per_trial x trials at once above Ray's CPUs runs every trial several times
    slower: refused (exit 2) before the study is touched, naming the fields to change."""
    import io

    url = f"sqlite:///{tmp_path / 'study.db'}"
    execution = {**yaml.safe_load(CI_SPEC.read_text())["execution"], "threads_per_trial": 2}
    spec_path = write_ci_spec(tmp_path / "ci.yaml", storage=url, execution=execution)
    stream = io.StringIO()
    assert launch(*prepare(str(spec_path)), train=always_succeed, stream=stream) == 2
    message = stream.getvalue().strip()
    assert len(message.splitlines()) == 1, message
    assert message.startswith("sweeper launch: execution: threads_per_trial 2 x 2 trials")
    assert "2 CPUs" in message and "--threads-per-trial 2" in message
    assert not (tmp_path / "study.db").exists()
    # the fix it names fits (this module's Ray has 2 CPUs: one trial at a time)
    assert launch(*prepare(str(spec_path), threads_per_trial=2), train=always_succeed) == 0


@pytest.mark.parametrize(
    ("threads", "cpus_per_trial", "max_concurrent"), [(2, 1, 2), (2, 1, 1), (4, 1, 1), (3, 2, 2)]
)
def test_the_fix_for_too_many_threads_on_a_local_ray_fits_it(
    threads, cpus_per_trial, max_concurrent
):
    """A local Ray has max_concurrent x cpus_per_trial CPUs: fewer trials at once shrink it
    too, so the refusal names reserving CPUs (which fits), never --max-concurrent."""
    from sweeper.run._resources import local_cpus, oversubscription
    from sweeper.spec import Execution

    execution = Execution(
        threads_per_trial=threads, cpus_per_trial=cpus_per_trial, max_concurrent=max_concurrent
    )
    message = oversubscription(threads, max_concurrent, local_cpus(execution), local=True)
    assert f"cpus_per_trial: {threads}, or --threads-per-trial {threads}" in message
    assert "--max-concurrent" not in message
    one_at_a_time = Execution(
        threads_per_trial=threads, cpus_per_trial=cpus_per_trial, max_concurrent=1
    )
    assert oversubscription(threads, 1, local_cpus(one_at_a_time), local=True) is not None
    reserved = Execution(
        threads_per_trial=threads, cpus_per_trial=threads, max_concurrent=max_concurrent
    )
    assert oversubscription(threads, max_concurrent, local_cpus(reserved), local=True) is None
    # a cluster's CPUs stay as they are: fewer at once is a fix there
    assert "--max-concurrent 1" in oversubscription(2, 2, 2.0)


def test_progress_display():
    import io

    from sweeper.run._progress import LaunchProgress

    keys = ["pixel/0/0", "pixel/1/0", "vae/0/0", "vae/1/0"]
    stream = io.StringIO()
    progress = LaunchProgress("s", keys, env_steps=1000, stream=stream, tty=True)
    for key in keys[1:]:
        progress.set_state(key, "left")  # pixel/0/0 was done before this launch
    progress.eta(now=0.0)  # the clock starts: 1000 steps done
    progress.set_state("pixel/1/0", "diverged")
    progress.set_state("vae/0/0", "running")
    progress.set_step("vae/0/0", 500)
    rate, eta = progress.eta(now=10.0)
    assert rate == 50.0  # 500 steps in 10 s (pixel/1/0 ran in no launch this one saw)
    assert eta == pytest.approx((4000 - 2500) / 50.0)
    assert progress.lines(now=10.0) == [
        "s: 2/4 trials done (1 diverged), 1 running, 0 failed | 50 env steps/s | ETA 30 s",
        "  pixel  2/2 done",
        "  vae    0/2 done  running 0/0 @ 500",
    ]
    progress.refresh(force=True)
    progress.refresh(force=True)  # redrawn in place: cursor up 3 lines, clear
    assert stream.getvalue().count("\x1b[3F\x1b[J") == 1
    plain = io.StringIO()
    progress = LaunchProgress("s", keys, env_steps=1000, stream=plain, tty=False)
    progress.refresh(force=True)
    progress.note("pixel/0/0 completed")
    assert "\x1b" not in plain.getvalue()
    assert plain.getvalue().splitlines()[1] == "pixel/0/0 completed"
    with pytest.raises(ValueError, match="state must be one of"):
        progress.set_state("pixel/0/0", "done")


def test_unreachable_ray_address_exits_2_and_writes_nothing(tmp_path):
    import subprocess

    done = subprocess.run(
        [sys.executable, "-m", "sweeper.cli", "launch", str(CI_SPEC), "--address", "127.0.0.1:1"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert "sweeper launch: execution.address: cannot reach" in done.stderr
    assert "nothing answers at 127.0.0.1:1" in done.stderr
    assert "RAY_AUTH_MODE" not in done.stderr  # no token hint when nothing listens
    assert list(tmp_path.iterdir()) == []


LOCAL_RAY = """
import json
from sweeper.run._execution import start_ray
import ray, psutil  # Ray vendors psutil
start_ray(None, num_cpus=1)
node = ray._private.worker._global_node
family = {node_pid.pid for node_pid in psutil.Process().children(recursive=True)}
listening = sorted({c.laddr.ip for c in psutil.net_connections("inet")
                    if c.status == "LISTEN" and c.pid in family | {psutil.Process().pid}})
print(json.dumps({"node_ip": node.node_ip_address, "gcs": node.gcs_address,
                  "listening": listening, "system_config": node._ray_params._system_config}))
ray.shutdown()
"""


def test_a_local_ray_listens_on_the_loopback_only_without_metrics():
    """Nothing a local study starts is reachable from another machine."""
    import ipaddress
    import json
    import subprocess

    done = subprocess.run(
        [sys.executable, "-c", LOCAL_RAY], capture_output=True, text=True, timeout=180, check=True
    )
    ray_node = json.loads(done.stdout.splitlines()[-1])
    assert ray_node["node_ip"] == "127.0.0.1"
    assert ray_node["gcs"].startswith("127.0.0.1:")
    assert ray_node["listening"]
    for ip in ray_node["listening"]:
        address = ipaddress.ip_address(ip)
        assert (getattr(address, "ipv4_mapped", None) or address).is_loopback, ray_node
    assert ray_node["system_config"].get("enable_metrics_collection") is False


def test_a_refused_connection_names_token_authentication(monkeypatch):
    from sweeper.run._resources import cannot_reach_message

    refused = ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    message = cannot_reach_message("10.0.0.1:6379", refused)
    assert message.startswith(
        "sweeper launch: execution.address: cannot reach the Ray cluster at '10.0.0.1:6379': "
        "Failed to connect to Ray cluster at 10.0.0.1:6379; if Ray's lines above say "
        "InvalidAuthToken"
    )
    assert "set RAY_AUTH_MODE=token" in message
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # already in token mode: the token is wrong
    assert "RAY_AUTH_MODE" not in cannot_reach_message("10.0.0.1:6379", refused)
    assert cannot_reach_message(None, RuntimeError("no\n  room")) == (
        "sweeper launch: execution.address: cannot reach local Ray: no room"
    )


def test_pool_counts_only_workers_that_started():
    """A pool larger than the cluster (a node was lost) hands trials only to started
    actors, so no trial waits on an actor that can never be placed."""
    import time

    from sweeper.run._execution import Finished, WorkerPool

    config = prepare(CI_SPEC)[1].entries[0].trial_config
    pool = WorkerPool(3, cpus=1, train=always_succeed)  # the module's Ray has 2 CPUs
    try:
        deadline = time.monotonic() + 60
        wait_until(lambda: pool.idle >= 2, 60, "2 idle workers", interval=0.2)
        time.sleep(1.0)
        assert pool.idle == 2
        finished, pending = [], ["a", "b", "c"]
        while len(finished) < 3 and time.monotonic() < deadline:
            while pending and pool.idle:
                pool.submit(pending.pop(0), config)
            finished += [e.token for e in pool.poll(0.5) if isinstance(e, Finished)]
        assert sorted(finished) == ["a", "b", "c"]
    finally:
        pool.shutdown()


def _wait_idle(pool, count: int, seconds: float = 60) -> None:
    wait_until(lambda: pool.idle >= count, seconds, f"{count} idle workers", interval=0.2)
    assert pool.idle == count


def test_workers_import_the_agent_and_env_before_their_first_trial():
    """Warm workers: torch, the agent and the env module load while the driver starts up."""
    from sweeper.run._execution import WorkerPool

    def loaded(worker) -> list[str]:
        wanted = ("torch", "agent.trial", "agent.envs.point_reach")
        return [name for name in wanted if name in sys.modules]

    pool = WorkerPool(1, env="point_reach")
    try:
        _wait_idle(pool, 1)
        actor = pool._slots[0].actor
        assert ray.get(actor.__ray_call__.remote(loaded)) == [
            "torch",
            "agent.trial",
            "agent.envs.point_reach",
        ]
    finally:
        pool.shutdown()


def test_a_failing_warm_up_does_not_kill_the_worker():
    """The warm-up import failing (here: an unknown env) leaves the actor up; the trial
    then reports the error, instead of the pool replacing the actor forever."""
    from conftest import tiny

    from sweeper.run._execution import Errored, Finished, WorkerPool

    pool = WorkerPool(1, env="no_such_env")
    try:
        _wait_idle(pool, 1)
        actor = pool._slots[0].actor
        pool.submit("doomed", tiny(env="no_such_env"))
        ended = []
        wait_until(
            lambda: (
                ended.extend(e for e in pool.poll(0.5) if isinstance(e, Errored | Finished))
                or ended
            ),
            120,
            "the trial's end",
        )
        (event,) = ended
        assert isinstance(event, Errored) and event.token == "doomed"
        assert "no_such_env" in event.error, event.error
        assert pool._slots[0].actor is actor  # the same actor, idle again
        assert pool.idle == 1
    finally:
        pool.shutdown()


def wait_for_go(config, report=None):
    """A trial that reports step 0, then waits for a file ``go`` in its checkpoint_dir."""
    go = Path(config.checkpoint_dir) / "go"
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    deadline = time.monotonic() + 120
    while not go.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    return always_succeed(config, report)


def test_shrink_kills_idle_workers_only_down_to_the_size(tmp_path):
    from conftest import tiny

    from sweeper.run._execution import Finished, Reported, WorkerPool

    pool = WorkerPool(2, train=wait_for_go)
    try:
        _wait_idle(pool, 2)
        pool.shrink(5)
        assert len(pool) == 2
        pool.submit("busy", tiny(checkpoint_dir=str(tmp_path), total_steps=300))
        wait_until(
            lambda: any(isinstance(e, Reported) for e in pool.poll(0.5)), 120, "the busy trial"
        )
        pool.shrink(1)  # the idle worker goes, the busy one stays
        assert len(pool) == 1 and pool.idle == 0
        pool.shrink(0)  # no idle worker left to kill
        assert len(pool) == 1
        (tmp_path / "go").touch()
        finished = []
        wait_until(
            lambda: (
                finished.extend(e.token for e in pool.poll(0.5) if isinstance(e, Finished))
                or finished
            ),
            120,
            "the busy trial to finish",
        )
        assert finished == ["busy"]
        _wait_idle(pool, 1)
    finally:
        pool.shutdown()


def test_the_driver_measures_the_random_agent_once_per_study(tmp_path, monkeypatch, capsys):
    """The 0 of the normalised scores: measured before the first trial with the spec's env
    settings, stored in the study, not measured again on a relaunch; random_episodes: 0
    skips it."""
    from agent.envs import make_env
    from encoders.diagnostics.exploration import random_exploration
    from sweeper.run import _random_agent as random_agent

    url = f"sqlite:///{tmp_path / 'study.db'}"
    env = {"name": "point_reach", "image_size": 32, "options": {"success_threshold": 0.5}}
    path = write_ci_spec(tmp_path / "ci.yaml", storage=url, random_episodes=40, env=env)
    spec, plan = prepare(str(path))
    assert launch(spec, plan, train=always_succeed) == 0
    measured = load(url).user_attrs["random_agent"]

    def by_hand(**options) -> float:  # 40 random episodes from the study seed, on its env
        made = make_env("point_reach", obs_mode="state", image_size=32, **options)
        try:
            return float(random_exploration(made, 40, seed=spec.seed, progress=False).value[0])
        finally:
            made.close()

    assert measured["success_rate"] == by_hand(success_threshold=0.5)
    assert by_hand(success_threshold=0.5) != by_hand()  # the spec's env options count
    assert (measured["episodes"], measured["seed"]) == (40, spec.seed)
    first = load(url).get_trials()[0].datetime_start
    assert "random agent: success rate" in capsys.readouterr().err

    calls = []
    monkeypatch.setattr(random_agent, "measure_random_agent", calls.append)
    assert launch(spec, plan, train=always_succeed) == 0  # a relaunch: nothing to measure
    assert calls == []
    assert load(url).user_attrs["random_agent"] == measured
    assert load(url).get_trials()[0].datetime_start == first

    url = f"sqlite:///{tmp_path / 'none.db'}"
    spec, plan = prepare(str(write_ci_spec(tmp_path / "none.yaml", storage=url, random_episodes=0)))
    assert launch(spec, plan, train=always_succeed) == 0
    assert "random_agent" not in load(url).user_attrs


def test_an_interrupted_launch_says_which_trials_resume_from_a_checkpoint(tmp_path):
    """Issue 21: Ctrl-C before any checkpoint was written said every trial would resume."""
    import io
    import types

    import torch

    from sweeper.run._driver import Driver, Job

    path = write_ci_spec(tmp_path / "ci.yaml", checkpoints=str(tmp_path / "ck"))
    spec, plan = prepare(str(path))
    interrupted = []
    store = types.SimpleNamespace(interrupt=lambda trial_id, why, _: interrupted.append(trial_id))
    pool = types.SimpleNamespace(shutdown=lambda: None)
    progress = types.SimpleNamespace(close=lambda: None)
    stream = io.StringIO()
    driver = Driver(spec, store, pool, progress, beat=None, stream=stream)
    for number, entry in enumerate(plan.entries):
        driver.jobs[entry.key] = Job(entry, trial_id=number, number=number)
    first = plan.entries[0]
    folder = Path(first.trial_config.checkpoint_dir)
    folder.mkdir(parents=True)
    torch.save({"step": 250}, folder / "checkpoint.pt")
    assert driver.stop() == 130
    assert interrupted == [0, 1]
    assert stream.getvalue().strip().splitlines() == [
        "sweeper launch: stopped; 2 trials in flight interrupted; the next launch:",
        f"  {first.key}: resumes from step 250 (its checkpoint)",
        f"  {plan.entries[1].key}: restarts from step 0 (no checkpoint written yet)",
    ]
