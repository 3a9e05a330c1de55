"""`sweeper launch` stopped at start-up: a database it cannot write, a damaged one, a full
disk or a lost server as the study is opened, a SIGTERM while Ray starts. Each ends with
one line of its own and a documented exit code, not a traceback."""

from __future__ import annotations

import io
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import CI_SPEC, DAMAGE, PUBLISHED, ROOT, damage, wait_until, write_ci_spec
from pg_proxy import Proxy
from sqlalchemy import event
from sqlalchemy.engine import Engine

from sweeper import cli
from sweeper.run import _launch as launcher
from sweeper.run._launch import prepare
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


def no_ray(*args, **kwargs):
    raise AssertionError("Ray was started")


@pytest.mark.parametrize("how", DAMAGE)
def test_a_damaged_database_exits_2_before_ray_starts(tmp_path, monkeypatch, capsys, how):
    """A study file truncated, overwritten or not a database at all: one line naming the
    damage and the ways back, before Ray starts (it was 30-146 lines of tracebacks after)."""
    database = tmp_path / "study.db"
    shutil.copy(PUBLISHED / "study.db", database)
    damage(database, how)
    before = database.read_bytes()
    monkeypatch.setattr(launcher, "start_ray", no_ray)
    spec = ROOT / "studies" / "fetch_reach_cpu.yaml"
    assert cli.main(["launch", str(spec), "--storage", f"sqlite:///{database}"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"sweeper launch: storage: the database sqlite:///{database} is damaged")
    assert "restore it from a backup or from the study's last published copy" in err
    assert database.read_bytes() == before and sorted(tmp_path.iterdir()) == [database]


class NoWorkers:
    """A worker pool that never starts: the launch stops before it is used."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def shutdown(self) -> None:
        pass


def test_a_full_disk_as_the_database_is_created_exits_2_with_one_line(tmp_path, monkeypatch,
                                                                       capsys):  # fmt: skip
    """The database is created once Ray runs (a launch refused before writes nothing): a
    full disk then is one line naming it and the fix, exit 2. Ray and its workers are
    stood in for: the study is opened before any is used."""
    monkeypatch.setattr(launcher, "start_ray", lambda *args, **kwargs: False)
    monkeypatch.setattr(launcher, "pool_size", lambda *args: 1)
    monkeypatch.setattr(launcher, "WorkerPool", NoWorkers)
    monkeypatch.setattr(launcher, "start_estimate", lambda *args: None)

    def full(connection, cursor, statement, *args):
        if statement.lstrip().upper().startswith("CREATE"):
            raise sqlite3.OperationalError("database or disk is full")

    url = f"sqlite:///{tmp_path / 'study.db'}"
    event.listen(Engine, "before_cursor_execute", full)
    try:
        assert cli.main(["launch", str(CI_SPEC), "--storage", url]) == 2
    finally:
        event.remove(Engine, "before_cursor_execute", full)
    err = capsys.readouterr().err
    assert err == (
        f"sweeper launch: storage: cannot write {url}: its disk is full (database or disk is "
        "full); free space, then launch again\n"
    )


def test_a_postgresql_server_gone_as_the_launch_starts_is_waited_for(tmp_path, monkeypatch,
                                                                     pg_url):  # fmt: skip
    """The server goes away once the launch's checks passed: it is waited for, for
    execution.storage_grace, before Ray starts; past the grace, one line and exit 2 (it was
    a traceback after Ray started)."""
    proxy = Proxy(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")
    short, long = (
        prepare(str(write_ci_spec(tmp_path / f"{grace}.yaml", storage=url,
                                  execution={"storage_grace": grace})))  # checks the server
        for grace in (2, 30)
    )  # fmt: skip
    monkeypatch.setattr(launcher, "start_ray", no_ray)
    proxy.down()
    stream = io.StringIO()
    assert launcher.launch(*short, stream=stream) == 2
    (line,) = stream.getvalue().splitlines()
    assert line.startswith(
        f"sweeper launch: storage: lost postgresql://postgres@127.0.0.1:{proxy.port}"
    )
    assert "for over 2 s (execution.storage_grace)" in line
    assert line.endswith("bring the database back, then try again")

    started = []

    def ray_after_the_outage(*args, **kwargs):  # the launch goes on: stop it there
        started.append(time.monotonic())
        raise ConnectionError("no Ray in this test")

    monkeypatch.setattr(launcher, "start_ray", ray_after_the_outage)
    monkeypatch.setattr(launcher, "start_estimate", lambda *args: None)
    threading.Timer(1.0, proxy.up).start()
    start = time.monotonic()
    assert launcher.launch(*long, stream=io.StringIO()) == 2  # Ray's stand-in refused
    assert started and started[0] - start >= 1.0  # Ray started once the server was back


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
