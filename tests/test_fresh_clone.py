"""What a fresh clone on another machine needs: nothing of one machine in the repo, and every
read-only command working on every shipped spec without VGG's weights file."""

from __future__ import annotations

import os
import re
import subprocess

import pytest
from conftest import ROOT

from agent.calibrate import Calibration, TrialCosts
from encoders.options import VGG_WEIGHTS_ENV_VAR
from sweeper import cli
from sweeper.run import _launch as launcher

#: an absolute path of a development machine: a folder under work, root or tmp at the root of
#: the file system (Ray's own tmp/ray is a fact about Ray; a container's home is the image's)
MACHINE_PATH = re.compile(r"(?<![A-Za-z0-9_.~/:-])/(?:work|root|tmp(?!/ray\b))/[A-Za-z0-9_.-]+")
SPECS = sorted((ROOT / "studies").glob("*.yaml"))


def tracked() -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    return [p for p in out.stdout.decode().split("\0") if p]


def test_the_machine_path_pattern_finds_machine_paths_only():
    top = "/"  # written so that this file does not name such a path itself
    found = [
        f"see {top}work/gcrl-runs", f"cd {top}root/x", f"in {top}tmp/study-tree",
        f"`{top}work/main/.venv/bin/python`",
    ]  # fmt: skip
    fine = [
        "Ray's /tmp/ray/session_latest", "sqlite:////tmp/x.db", "../study-tree", "docs/work/x",
        "WORKDIR /home/sweeper/work",
    ]  # fmt: skip
    assert all(MACHINE_PATH.search(text) for text in found)
    assert not any(MACHINE_PATH.search(text) for text in fine)


def test_no_tracked_link_leaves_the_repo_and_no_file_names_a_machine_path():
    links, paths = [], []
    for name in tracked():
        path = ROOT / name
        if path.is_symlink():
            target = os.readlink(path)
            if os.path.isabs(target) or not path.resolve().is_relative_to(ROOT.resolve()):
                links.append(f"{name} -> {target}")
            continue
        if path.suffix in {".db", ".png", ".mp4", ".gif", ".pth"} or not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if MACHINE_PATH.search(line) and not (name.startswith("tests/") and "tmp_path" in line):
                paths.append(f"{name}:{number}: {line.strip()[:100]}")
    assert not links, f"tracked links out of the repo: {links}"
    assert not paths, "tracked files name paths of one machine:\n" + "\n".join(paths)


@pytest.fixture
def no_vgg_weights(monkeypatch, tmp_path):
    """A fresh machine: no GCRL_VGG16_WEIGHTS, no runs/ (the working directory is empty),
    and a calibration that costs nothing (``tests/test_estimate.py`` times the real one)."""
    monkeypatch.delenv(VGG_WEIGHTS_ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(Calibration, "costs", lambda self, config: TrialCosts(1.0, 0.01, 0.1, 0.01))


def no_ray(*args, **kwargs):
    raise AssertionError("Ray was started")


@pytest.mark.parametrize("spec", SPECS, ids=[p.stem for p in SPECS])
def test_every_shipped_spec_plans_and_reads_without_vgg_weights(spec, no_vgg_weights, capsys):
    assert cli.main(["plan", str(spec)]) == 0
    out = capsys.readouterr().out
    assert "gradient samples per env step" in out
    has_vgg = "vgg" in spec.read_text()
    vgg_rows = [line for line in out.splitlines() if line.startswith("vgg ")]
    if has_vgg:
        assert len(vgg_rows) == 1 and " unknown  needs its file: methods.vgg.weights_path" in out
        assert f"${VGG_WEIGHTS_ENV_VAR}" in vgg_rows[0]
        assert "not counted above: vgg" in out
    assert cli.main(["status", str(spec)]) == 0
    assert "not launched yet" in capsys.readouterr().out
    assert cli.main(["aggregate", str(spec)]) == 2  # nothing to aggregate: one line
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "launch the study first" in err


@pytest.mark.parametrize("spec", [p for p in SPECS if "vgg" in p.read_text()], ids=lambda p: p.stem)
def test_a_launch_without_vgg_weights_refuses_in_one_line_before_ray(
    spec, no_vgg_weights, monkeypatch, capsys
):
    monkeypatch.setattr(launcher, "start_ray", no_ray)
    assert cli.main(["launch", str(spec)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "methods.vgg.weights_path: required field is missing" in err
    assert f"${VGG_WEIGHTS_ENV_VAR}" in err
    assert not (ROOT / "runs").is_symlink()
