"""`sweeper launch` stopped at start-up: a database it cannot write, a SIGTERM while Ray
starts. Each ends with one line of its own and a documented exit code, not a traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import CI_SPEC, ROOT, wait_until

from sweeper import cli, launcher
from sweeper.storage import open_storage

LIGHT_HELP = """
import sys
from sweeper import cli
try:
    cli.main(sys.argv[1:])
    code = "returned"
except SystemExit as exit:
    code = exit.code
print(code, [m for m in ("torch", "ray", "optuna", "mujoco", "matplotlib") if m in sys.modules],
      file=sys.stderr)
"""

COMMANDS = ["launch", "status", "aggregate", "confirm", "dashboard", "diagnose", "plan", "rerun",
            "publish"]  # fmt: skip


@pytest.mark.parametrize("command", [[], *([c] for c in COMMANDS)])
def test_help_is_light(command):
    """`sweeper [COMMAND] --help` prints the usage, exits 0 and imports no torch, Ray,
    Optuna, MuJoCo or matplotlib."""
    done = subprocess.run(
        [sys.executable, "-c", LIGHT_HELP, *command, "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert done.stderr.strip().splitlines()[-1] == "0 []", done.stderr
    assert done.stdout.startswith(f"usage: sweeper {' '.join(command)}".rstrip()), done.stdout
    for other in COMMANDS if not command else []:  # the top-level help lists every command
        assert other in done.stdout


def test_a_read_only_database_exits_2_before_ray_starts(tmp_path, monkeypatch, capsys):
    """SQLite opens a file it cannot write read-only, so the first write would fail after
    Ray and the workers started; the launch refuses it first, naming the file and the fix."""
    database = tmp_path / "study.db"
    url = f"sqlite:///{database}"
    open_storage(url).engine.dispose()  # an empty study database
    # tests run as root, who writes a chmod 444 file anyway; nobody writes an immutable one
    if subprocess.run(["chattr", "+i", str(database)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i does not work on this file system")
    try:

        def no_ray(*args, **kwargs):
            raise AssertionError("Ray was started")

        monkeypatch.setattr(launcher, "start_ray", no_ray)
        before = database.read_bytes()
        assert cli.main(["launch", str(CI_SPEC), "--storage", url]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert err.startswith(f"sweeper launch: storage: cannot write the database file {database}")
        assert "chattr -i" in err and "--storage" in err
        assert database.read_bytes() == before
    finally:
        subprocess.run(["chattr", "-i", str(database)], check=True)


def descendants(pid: int) -> list[str]:
    """The command lines of every process below ``pid``."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(parent, []).append(int(entry.name))
    lines, todo = [], list(children.get(pid, []))
    while todo:
        child = todo.pop()
        todo += children.get(child, [])
        try:
            lines.append((Path("/proc") / str(child) / "cmdline").read_text().replace("\0", " "))
        except OSError:
            continue
    return lines


@pytest.mark.parametrize(
    "moment",
    [
        "gcs_server",  # Ray's first process is starting
        "raylet",  # the driver connects to its node next (Ray's core worker)
        "TrialWorker",  # Ray is up, the worker actors start while the study opens
    ],
)
def test_sigterm_during_start_up_exits_130_with_one_line(tmp_path, moment):
    """SIGTERM while Ray starts stops the launch like Ctrl-C: exit 130 and one line; before
    the study is opened, nothing is written. (Ray's start-up used to exit 15, and its core
    worker printed a C++ stack dump.)"""
    database = tmp_path / "study.db"
    process = subprocess.Popen(
        [sys.executable, "-m", "sweeper.cli", "launch", str(CI_SPEC), "--storage",
         f"sqlite:///{database}"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        wait_until(lambda: any(moment in line for line in descendants(process.pid)), 180, moment)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == 130, err
    assert "SIGTERM received" not in err and "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("sweeper launch: stopped"), err
    if moment != "TrialWorker":
        assert not database.exists()
