"""sweeper.study and the storage errors of issue 15: read-only readers, a missing or empty
database, a database outage shorter than the grace, a full disk."""

from __future__ import annotations

import argparse
import contextlib
import socket
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

import optuna
import pytest
from conftest import CI_SPEC
from sqlalchemy import event
from synthetic_study import write_synthetic_study

from sweeper import aggregate, dashboard, status
from sweeper.plan import build_plan
from sweeper.spec import load_spec
from sweeper.storage import StorageError, open_storage
from sweeper.study import NoStudy, open_study, read_rows

optuna.logging.set_verbosity(optuna.logging.WARNING)


def spec_at(url: str):
    """The CI spec (keys pixel/0/0 and linear/0/0) on storage ``url``."""
    return load_spec(CI_SPEC).with_overrides(storage=url)


def finished_study(folder: Path) -> str:
    """A finished CI-shaped study in a WAL-mode SQLite file under ``folder``; its URL."""
    url = f"sqlite:///{folder / 'study.db'}"
    storage = open_storage(url)  # the driver's open: WAL mode
    study = write_synthetic_study(storage, "ci", methods=("pixel", "linear"), configs=1, seeds=(0,))
    study.set_user_attr("plan_hash", build_plan(spec_at(url)).hash)  # as launched from it
    storage.remove_session()
    storage.engine.dispose()  # the last connection: SQLite folds the -wal in and removes it
    return url


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir())}


@contextlib.contextmanager
def immutable(*paths: Path):
    """``chattr +i``: not even root can change, create or delete these while the block
    runs (read-only media, honestly)."""
    done = subprocess.run(["chattr", "+i", *map(str, paths)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"chattr +i is not available here: {done.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", *map(str, paths)], check=True)


def test_status_and_aggregate_read_a_finished_study_on_read_only_media(tmp_path, capsys):
    media = tmp_path / "media"
    media.mkdir()
    url = finished_study(media)
    spec = spec_at(url)
    before = snapshot(media)
    assert list(before) == ["study.db"]  # closed cleanly: no -wal or -shm to read with
    out = tmp_path / "out"
    with immutable(media / "study.db", media):
        with pytest.raises(sqlite3.OperationalError):  # a writer cannot even open it
            sqlite3.connect(media / "study.db").execute("SELECT 1 FROM studies").fetchone()
        assert status.run(spec, argparse.Namespace()) == 0
        printed = capsys.readouterr().out
        rows = {line.split()[0]: line.split()[1:] for line in printed.splitlines()[1:]}
        assert rows["pixel"][:2] == ["1", "1"] and rows["linear"][0] == "1"  # planned, done
        assert "driver: not running" in printed
        args = argparse.Namespace(out=str(out), no_dashboard=False)
        assert aggregate.run([spec], args) == 0
        err = capsys.readouterr().err
        assert "warning: the comparison was not saved into the study" in err
        assert snapshot(media) == before  # same files, bytes and mtimes
    assert (out / "report.md").is_file() and (out / "auc_table.csv").is_file()


def test_a_reader_cannot_write(tmp_path):
    """Without chattr: the read-only connection itself (SQLite ``mode=ro``) refuses."""
    url = finished_study(tmp_path)
    before = snapshot(tmp_path)
    with open_study(url, "ci", write=False) as store:
        assert len(store.trials()) == 2
        with pytest.raises(StorageError, match="readonly"):
            store.set_study_attr("mine", 1)
    assert len(read_rows(url, "ci").trials) == 2
    after = snapshot(tmp_path)
    assert after["study.db"] == before["study.db"]  # same bytes and mtime
    # a WAL reader may leave an empty -wal and the -shm index where it can create them
    assert after.get("study.db-wal", (b"",))[0] == b""


def test_plan_hash_is_checked_where_asked(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    plan = build_plan(spec_at(url))
    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}) as store:
        assert store.attrs["plan_hash"] == plan.hash
    with open_study(url, "ci", write=False, plan_hash=plan.hash):
        pass
    mismatch = pytest.raises(StorageError, match="launched with another plan")
    with mismatch, open_study(url, "ci", write=False, plan_hash="0" * 64):
        pass
    mismatch = pytest.raises(StorageError, match="launched with another plan")
    with mismatch, open_study(url, "ci", write=True, attrs={"plan_hash": "1" * 64}):
        pass


@pytest.mark.parametrize("content", ["missing", "zero bytes", "an empty SQLite database"])
def test_dashboard_on_a_missing_or_empty_database_is_one_line(tmp_path, capsys, content):
    path = tmp_path / "study.db"
    if content == "zero bytes":
        path.touch()
    elif content == "an empty SQLite database":
        sqlite3.connect(path).execute("PRAGMA user_version = 1").connection.commit()
    before = snapshot(tmp_path)
    spec = spec_at(f"sqlite:///{path}")
    assert dashboard.run(spec, argparse.Namespace(host="127.0.0.1", port=0)) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "exceeding max length" not in err
    assert str(path) in err and "`sweeper launch SPEC`" in err
    assert ("no database file" if content == "missing" else "no Optuna study") in err
    assert snapshot(tmp_path) == before  # nothing created or changed
    assert status.run(spec, argparse.Namespace()) == 0  # status: "not launched yet"
    assert "not launched yet (no " in capsys.readouterr().out
    assert snapshot(tmp_path) == before
    with pytest.raises(NoStudy):
        read_rows(spec.storage_url, "ci")


class Proxy:
    """A TCP proxy to PostgreSQL that can be taken down: open connections are cut and new
    ones refused (nothing listens), as when the server or the network goes away."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        probe = socket.socket()
        probe.bind(("127.0.0.1", 0))
        self.port = probe.getsockname()[1]
        probe.close()
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self.up()

    def up(self) -> None:
        self._listener = socket.socket()
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", self.port))
        self._listener.listen()
        threading.Thread(target=self._accept, args=(self._listener,), daemon=True).start()

    def down(self) -> None:
        with contextlib.suppress(OSError):  # wakes the accept() blocked on it (Linux)
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        with self._lock:
            for s in self._sockets:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
            self._sockets.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.target)
            with self._lock:
                self._sockets += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        with contextlib.suppress(OSError):
            sink.shutdown(socket.SHUT_RDWR)


def test_a_postgresql_outage_shorter_than_the_grace_is_retried(pg_url):
    proxy = Proxy(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")
    plan = build_plan(spec_at(url))
    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}, grace=20) as store:
        (_, trial), _ = store.sync(plan.entries, plan.hash)
        store.start(trial._trial_id)
        proxy.down()
        threading.Timer(3.0, proxy.up).start()
        start = time.monotonic()
        store.complete(trial._trial_id, 0.5, {"outcome": "completed"})  # during the outage
        assert 2.5 < time.monotonic() - start < 20
    done = optuna.load_study(study_name="ci", storage=pg_url).trials[trial.number]
    assert done.state.name == "COMPLETE" and done.value == 0.5

    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}, grace=2) as store:
        [(_, trial)] = store.sync(plan.entries, plan.hash)
        proxy.down()  # for good: longer than the grace
        start = time.monotonic()
        with pytest.raises(StorageError) as info:
            store.start(trial._trial_id)
        assert time.monotonic() - start < 10
    message = str(info.value)
    assert "\n" not in message and "for over 2 s (execution.storage_grace)" in message
    assert "launch again" in message and "postgres@127.0.0.1" in message


def test_a_full_disk_under_sqlite_is_one_line_and_not_retried(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    plan = build_plan(spec_at(url))
    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}) as store:
        (_, trial), _ = store.sync(plan.entries, plan.hash)
        store.start(trial._trial_id)

        def full(connection, cursor, statement, *args):
            if statement.lstrip().upper().startswith(("INSERT", "UPDATE")):
                raise sqlite3.OperationalError("database or disk is full")

        event.listen(store.storage.engine, "before_cursor_execute", full)
        start = time.monotonic()
        with pytest.raises(StorageError) as info:
            store.complete(trial._trial_id, 0.5, {"outcome": "completed"})
        assert time.monotonic() - start < 5  # a full disk is not waited for
        event.remove(store.storage.engine, "before_cursor_execute", full)
        assert store.trials()[trial.number].state.name == "RUNNING"  # nothing half-written
    message = str(info.value)
    assert "\n" not in message and "its disk is full" in message and "free space" in message
