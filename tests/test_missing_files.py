"""A method's files are needed only where its trials run (issue 22): status reads a spec
without them; launch and confirm refuse it with one line (exit 2), or a launch with
``--skip-missing`` runs the other methods, the plan and its hash whole, and a later launch
with the files runs the rest. A recorded trial's emptied checkpoint folders go too."""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path

import optuna
import ray
from conftest import write_ci_spec
from optuna.trial import TrialState

from agent.config import TrialResult
from encoders.options import VGG_WEIGHTS_ENV_VAR
from sweeper import cli
from sweeper.plan._entries import build_plan
from sweeper.run import _launch as launcher
from sweeper.run._driver import remove_checkpoint
from sweeper.run._progress import LaunchProgress
from sweeper.run.cli_launch import skip_lines
from sweeper.spec._models import check_files, load_spec, parse_spec
from sweeper.spec._yaml import load_yaml
from sweeper.storage import open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake train below

REQUIRED = (
    "methods.vgg.weights_path: required field is missing; VGG16 ImageNet weights in "
    f"torchvision format, vgg16-397923af.pth (or set ${VGG_WEIGHTS_ENV_VAR})"
)


def vgg_spec(tmp_path: Path, weights: Path | None, seeds: tuple[int, ...] = (0,)) -> Path:
    """The CI spec with a vgg method (``weights``: its weights_path; None: not given)."""
    vgg = {"input_size": 32} | ({} if weights is None else {"weights_path": str(weights)})
    return write_ci_spec(
        tmp_path / "spec.yaml",
        study="files",
        methods={"pixel": {}, "linear": {"latent_dim": 16}, "vgg": vgg},
        seeds=list(seeds),
        storage=f"sqlite:///{tmp_path / 'study.db'}",
        checkpoints=str(tmp_path / "checkpoints"),
    )


def no_ray(*args, **kwargs):
    raise AssertionError("Ray was started")


def status_rows(capsys, spec: Path) -> dict[str, list[str]]:
    """``sweeper status``'s table: method -> planned, done, diverged, running, failed, left."""
    capsys.readouterr()
    assert cli.main(["status", str(spec)]) == 0
    out = capsys.readouterr().out
    return {line.split()[0]: line.split()[1:] for line in out.splitlines()[2:] if line}


def test_status_reads_a_spec_without_its_files_and_launch_and_confirm_refuse_it(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.delenv(VGG_WEIGHTS_ENV_VAR, raising=False)
    monkeypatch.setattr(launcher, "start_ray", no_ray)
    spec = vgg_spec(tmp_path, weights=None)
    assert "weights_path" not in load_spec(spec).methods["vgg"].space  # it reads
    assert status_rows(capsys, spec)["vgg"] == ["1", "0", "0", "0", "0", "1"]

    # where trials run: one line naming the field, exit 2, nothing written
    assert cli.main(["launch", str(spec)]) == 2
    err = capsys.readouterr().err
    assert err == f"sweeper launch: {spec}: {REQUIRED}; or --skip-missing to launch without vgg\n"
    assert cli.main(["confirm", str(spec), "--top-k", "1", "--seeds", "1"]) == 2
    assert capsys.readouterr().err == f"sweeper confirm: {spec}: {REQUIRED}\n"
    # a path is needed to skip: it is part of the plan, so the skipped trials can run later
    assert cli.main(["launch", str(spec), "--skip-missing"]) == 2
    err = capsys.readouterr().err
    assert "methods.vgg.weights_path: required field is missing; --skip-missing needs" in err
    assert len(err.splitlines()) == 1

    missing = tmp_path / "nowhere" / "vgg16.pth"
    spec = vgg_spec(tmp_path, weights=missing)
    assert status_rows(capsys, spec)["vgg"] == ["1", "0", "0", "0", "0", "1"]
    assert cli.main(["launch", str(spec)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sweeper launch: {spec}: methods.vgg.weights_path: file not found: ")
    assert str(missing) in err and len(err.splitlines()) == 1
    assert not (tmp_path / "study.db").exists()
    # on a cluster the file lives on the workers: not checked here
    clustered = parse_spec(load_yaml(spec.read_text()) | {"execution": {"address": "auto"}})
    assert check_files(clustered, "spec") == frozenset()


def test_status_reads_a_study_launched_where_the_files_path_was_set(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(VGG_WEIGHTS_ENV_VAR, "/data/vgg16-397923af.pth")
    spec = vgg_spec(tmp_path, weights=None)
    launched = load_spec(spec)  # its weights_path from the variable, as the launch had it
    study = optuna.create_study(study_name="files", storage=open_storage(launched.storage_url))
    study.set_user_attr("spec", launched.model_dump(mode="json"))  # what a launch stores
    study.set_user_attr("plan_hash", build_plan(launched).hash)
    monkeypatch.delenv(VGG_WEIGHTS_ENV_VAR)  # another shell: the path is not set there
    assert status_rows(capsys, spec)["vgg"] == ["1", "0", "0", "0", "0", "1"]
    other = tmp_path / "other.yaml"  # a spec that really is another plan is still refused
    other.write_text(spec.read_text().replace("latent_dim: 16", "latent_dim: 32"))
    assert cli.main(["status", str(other)]) == 2
    assert "was launched with another plan" in capsys.readouterr().err


def test_plan_hashes_do_not_depend_on_whether_the_file_is_there(tmp_path, monkeypatch):
    """The hash the code before this change gave (it refused a missing file unless the spec
    named a cluster, whose address is not in the hash)."""
    monkeypatch.setenv(VGG_WEIGHTS_ENV_VAR, "/nonexistent/vgg16-397923af.pth")
    data = load_yaml((Path(__file__).parent.parent / "studies" / "fetch_reach.yaml").read_text())
    expected = "a3d09008216c18d4cabc5d674ddf0b3288d5e702346487861b68d60d37c071f9"
    assert build_plan(parse_spec(data)).hash == expected
    data["execution"]["address"] = "auto"
    assert build_plan(parse_spec(data)).hash == expected
    weights = tmp_path / "vgg16-397923af.pth"
    weights.write_bytes(b"")
    monkeypatch.setenv(VGG_WEIGHTS_ENV_VAR, str(weights))  # another path: another plan
    assert build_plan(parse_spec(data)).hash != expected


def instant(config, report=None):
    """A trial that reports once and finishes at once (vgg's included: no weights read)."""
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    metrics = {"success_rate": (0.0, 1.0), "final_distance": (1.0, 0.0)}
    return TrialResult(steps=(0, config.total_steps), metrics=metrics, auc=0.5)


def test_skip_missing_runs_the_other_methods_and_a_launch_with_the_files_runs_the_rest(
    tmp_path, monkeypatch, capsys, local_ray
):
    monkeypatch.chdir(tmp_path)
    real_launch = launcher.launch
    monkeypatch.setattr(
        launcher, "launch", lambda spec, plan, **kw: real_launch(spec, plan, train=instant, **kw)
    )
    weights = tmp_path / "vgg16.pth"
    spec = vgg_spec(tmp_path, weights=weights, seeds=(0, 1))
    plan = build_plan(load_spec(spec))

    assert cli.main(["launch", str(spec), "--skip-missing"]) == 0
    err = capsys.readouterr().err
    assert "sweeper launch: skipping vgg: methods.vgg.weights_path: file not found: " in err
    assert (
        "this launch runs 2 of 3 methods (linear, pixel), 2 trials each as planned: 4 of the "
        "plan's 6 trials; the 2 of vgg stay left" in err
    )
    assert "0 of 6 trials done, 4 to run; vgg not run now (2 trials" in err
    study = optuna.load_study(study_name="files", storage=open_storage(load_spec(spec).storage_url))
    assert study.user_attrs["plan_hash"] == plan.hash  # the whole plan's: the study resumes
    assert status_rows(capsys, spec) == {
        "linear": ["2", "2", "0", "0", "0", "0"],
        "pixel": ["2", "2", "0", "0", "0", "0"],
        "vgg": ["2", "0", "0", "0", "0", "2"],
        "total": ["6", "4", "0", "0", "0", "2"],
        "driver:": ["not", "running"],
    }

    with monkeypatch.context() as patch:  # nothing this launch can run: no Ray
        patch.setattr(launcher, "start_ray", no_ray)
        assert cli.main(["launch", str(spec), "--skip-missing"]) == 0
    assert "4 of 6 trials done, 0 to run; vgg not run now (2 trials" in capsys.readouterr().err

    weights.write_bytes(b"the fake trains read nothing")  # the files are here now
    assert cli.main(["launch", str(spec)]) == 0
    assert "4 of 6 trials done, 2 to run" in capsys.readouterr().err
    trials = optuna.load_study(
        study_name="files", storage=open_storage(load_spec(spec).storage_url)
    ).get_trials()
    assert sorted(t.user_attrs["key"] for t in trials) == sorted(plan.keys())  # each once
    assert all(t.state == TrialState.COMPLETE for t in trials)


def test_skip_lines_say_the_budget():
    data = load_yaml((Path(__file__).parent.parent / "studies" / "fetch_reach.yaml").read_text())
    data["methods"]["vgg"] = {"weights_path": "/nonexistent/vgg16.pth"}
    spec = parse_spec(data)
    skip = check_files(spec, "spec", skip_missing=True)
    assert skip == {"vgg"}
    lines = skip_lines(spec, build_plan(spec), skip)
    assert lines == [
        "sweeper launch: skipping vgg: methods.vgg.weights_path: file not found: "
        "'/nonexistent/vgg16.pth' (VGG16 ImageNet weights in torchvision format, "
        "vgg16-397923af.pth)",
        "sweeper launch: this launch runs 7 of 8 methods (pixel, linear, conv, vae, cvae, "
        "true_reward, state), 20 trials each as planned: 140 of the plan's 160 trials; the 20 "
        "of vgg stay left in the study (`sweeper status` counts them) for a launch with the "
        "files",
    ]


def test_a_recorded_trials_emptied_checkpoint_folders_are_removed(tmp_path):
    spec = load_spec(
        write_ci_spec(
            tmp_path / "spec.yaml",
            methods={"pixel": {}},
            seeds=[0, 1],
            checkpoints=str(tmp_path / "checkpoints"),
        )
    )
    first, second = build_plan(spec, study_uid="u").entries
    for entry in (first, second):
        folder = Path(entry.trial_config.checkpoint_dir)
        folder.mkdir(parents=True)
        (folder / "checkpoint.pt").write_bytes(b"x")
    progress = LaunchProgress("ci", [], 300, io.StringIO())
    study = tmp_path / "checkpoints" / "ci-u"
    remove_checkpoint(first, progress)
    assert sorted(os.listdir(study / "pixel" / "0")) == ["1"]  # the other seed's is kept
    remove_checkpoint(second, progress)
    assert os.listdir(study) == []  # pixel/0 emptied: removed; the study's folder stays


def test_a_checkpoint_is_written_when_its_emptied_parent_is_removed_meanwhile(
    tmp_path, monkeypatch
):
    from agent import storage_io

    real = storage_io.tempfile.mkstemp
    calls = []

    def removed_once(*args, **kwargs):
        calls.append(kwargs["dir"])
        if len(calls) == 1:  # the driver removed the emptied folder between mkdir and here
            os.rmdir(kwargs["dir"])
            raise FileNotFoundError(kwargs["dir"])
        return real(*args, **kwargs)

    monkeypatch.setattr(storage_io.tempfile, "mkstemp", removed_once)
    location = str(tmp_path / "pixel" / "0" / "1" / "checkpoint.pt")
    storage_io.write_atomic(location, lambda f: f.write(b"data"))
    assert Path(location).read_bytes() == b"data" and len(calls) == 2


def test_only_runs_the_named_methods_and_a_later_launch_the_rest(
    tmp_path, monkeypatch, capsys, local_ray
):
    """``--only`` runs one arm of a study at a time: the plan and its hash whole, the other
    methods' trials left for a later launch; an unknown name is one line, exit 2."""
    monkeypatch.chdir(tmp_path)
    real_launch = launcher.launch
    monkeypatch.setattr(
        launcher, "launch", lambda spec, plan, **kw: real_launch(spec, plan, train=instant, **kw)
    )
    spec = write_ci_spec(
        tmp_path / "spec.yaml", study="arms",
        methods={"pixel": {}, "pixel_tau": {"encoder": "pixel", "sac": {"critic_tau": 0.01}}},
        storage=f"sqlite:///{tmp_path / 'study.db'}", checkpoints=str(tmp_path / "checkpoints"),
    )  # fmt: skip
    with monkeypatch.context() as patch:
        patch.setattr(launcher, "start_ray", no_ray)
        assert cli.main(["launch", str(spec), "--only", "pixel_tua"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "sweeper launch: --only: no method 'pixel_tua' in the spec; did you mean "
        "'pixel_tau'? methods: pixel, pixel_tau\n"
    )
    assert cli.main(["launch", str(spec), "--only", "pixel_tau"]) == 0
    assert "0 of 2 trials done, 1 to run; pixel not run now (1 trial," in capsys.readouterr().err
    assert status_rows(capsys, spec)["pixel"] == ["1", "0", "0", "0", "0", "1"]
    assert status_rows(capsys, spec)["pixel_tau"] == ["1", "1", "0", "0", "0", "0"]
    assert cli.main(["launch", str(spec)]) == 0
    assert "1 of 2 trials done, 1 to run" in capsys.readouterr().err
    study = optuna.load_study(study_name="arms", storage=open_storage(load_spec(spec).storage_url))
    assert study.user_attrs["plan_hash"] == build_plan(load_spec(spec)).hash
    assert sorted(t.user_attrs["key"] for t in study.get_trials()) == ["pixel/0/0", "pixel_tau/0/0"]


def test_max_trials_starts_that_many_round_by_round_and_a_later_launch_the_rest(
    tmp_path, monkeypatch, capsys, local_ray
):
    """``--max-trials N`` starts N of the trials left, a round's methods together (what a
    machine lent for a few hours can finish, still paired); the rest stay left; 0 is
    refused by the parser (exit 2) before anything runs."""
    monkeypatch.chdir(tmp_path)
    real_launch = launcher.launch
    monkeypatch.setattr(
        launcher, "launch", lambda spec, plan, **kw: real_launch(spec, plan, train=instant, **kw)
    )
    spec = write_ci_spec(
        tmp_path / "spec.yaml", study="some", seeds=[0, 1],
        methods={"pixel": {}, "pixel_tau": {"encoder": "pixel", "sac": {"critic_tau": 0.01}}},
        storage=f"sqlite:///{tmp_path / 'study.db'}", checkpoints=str(tmp_path / "checkpoints"),
    )  # fmt: skip
    with monkeypatch.context() as patch:
        patch.setattr(launcher, "start_ray", no_ray)
        try:
            cli.main(["launch", str(spec), "--max-trials", "0"])
        except SystemExit as exit:
            assert exit.code == 2
        assert "--max-trials: must be an integer >= 1, got 0" in capsys.readouterr().err
    assert cli.main(["launch", str(spec), "--max-trials", "2"]) == 0
    err = capsys.readouterr().err
    assert "0 of 4 trials done, 2 to run; 2 more left for a later launch (--max-trials)" in err
    assert "some: 2/2 trials done" in err  # the display counts this launch's trials
    assert "estimate: left: 2 of 4 trials" in err  # so does the estimate
    study = optuna.load_study(study_name="some", storage=open_storage(load_spec(spec).storage_url))

    def done() -> list[str]:
        trials = study.get_trials(states=[TrialState.COMPLETE])
        return sorted(t.user_attrs["key"] for t in trials)

    assert done() == ["pixel/0/0", "pixel_tau/0/0"]  # the first round: paired
    assert cli.main(["launch", str(spec), "--only", "pixel_tau", "--max-trials", "1"]) == 0
    assert done() == ["pixel/0/0", "pixel_tau/0/0", "pixel_tau/0/1"]
    assert status_rows(capsys, spec)["pixel"] == ["2", "1", "0", "0", "0", "1"]
    assert cli.main(["launch", str(spec), "--max-trials", "5"]) == 0
    assert "3 of 4 trials done, 1 to run\n" in capsys.readouterr().err
    assert len(done()) == 4
