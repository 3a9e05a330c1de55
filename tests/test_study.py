"""sweeper.storage._open and the storage errors of issues 15 and 35: read-only readers, a missing,
empty or damaged database, a database outage shorter than the grace (while the study is
opened too), a full disk."""

from __future__ import annotations

import argparse
import contextlib
import shutil
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

import optuna
import pytest
from conftest import CI_SPEC, DAMAGE, PG_ADMIN, PUBLISHED, ROOT, damage
from pg_proxy import Proxy
from sqlalchemy import event
from sqlalchemy.engine import Engine
from synthetic_study import Special, write_synthetic_study

from sweeper import cli, dashboard
from sweeper.plan._entries import build_plan
from sweeper.results import cli_aggregate as aggregate
from sweeper.results import cli_status as status
from sweeper.spec._models import load_spec
from sweeper.storage import STORAGE_GRACE, StorageError, check_intact, open_storage
from sweeper.storage._open import NoStudy, open_study, read_rows

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
        args = argparse.Namespace(spec=[CI_SPEC], storage=url, out=str(out), no_dashboard=False)
        assert aggregate.run([spec], args) == 0
        err = capsys.readouterr().err
        assert "warning: the comparison was not saved into the study" in err
        assert snapshot(media) == before  # same files, bytes and mtimes
    assert (out / "report.md").is_file() and (out / "auc_table.csv").is_file()


def test_status_and_plan_list_methods_in_the_spec_order(tmp_path, capsys):
    """The order its author wrote the methods in (the CI spec: pixel, then linear), not the
    plan's by name: ``sweeper status`` listed them sorted, ``sweeper plan`` as written."""
    from sweeper.plan.cli_plan import plan_lines

    spec = spec_at(f"sqlite:///{tmp_path / 'none.db'}")
    written = list(spec.methods)
    assert written == ["pixel", "linear"] and sorted(written) != written
    assert status.run(spec, argparse.Namespace()) == 0
    table = capsys.readouterr().out.splitlines()[2:]  # after the study line and the header
    assert [line.split()[0] for line in table[:2]] == written
    lines = plan_lines(spec, build_plan(spec), set(), dict.fromkeys(written, 60.0))
    assert [line.split()[0] for line in lines[2:4]] == written  # after the summary, the header


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


def test_readers_use_read_only_transactions_on_postgresql(pg_url, tmp_path, capsys):
    """On PostgreSQL a reader's session is read-only: a write is refused by the server, and
    status and aggregate (without the dashboard's copy) connect only that way and change
    nothing."""
    import psycopg
    from sqlalchemy.pool import Pool

    storage = open_storage(pg_url)
    study = write_synthetic_study(storage, "ci", methods=("pixel", "linear"), configs=1, seeds=(0,))
    study.set_user_attr("plan_hash", build_plan(spec_at(pg_url)).hash)
    storage.engine.dispose()

    def tables() -> dict[str, list[tuple]]:
        names = ["studies", "study_user_attributes", "trials", "trial_values",
                 "trial_user_attributes", "trial_params", "trial_intermediate_values"]  # fmt: skip
        schema = pg_url.rsplit("%3D", 1)[1]
        with psycopg.connect(PG_ADMIN, options=f"-csearch_path={schema}") as connection:
            return {n: sorted(connection.execute(f"SELECT * FROM {n}").fetchall()) for n in names}

    before = tables()
    with open_study(pg_url, "ci", write=False) as store:
        assert len(store.trials()) == 2
        with pytest.raises(StorageError, match="read-only transaction"):
            store.set_study_attr("mine", 1)

    sessions = []

    def read_only(dbapi_connection, record):  # every connection the commands open
        with dbapi_connection.cursor() as cursor:
            cursor.execute("SHOW transaction_read_only")
            sessions.append(cursor.fetchone()[0])
        dbapi_connection.rollback()

    event.listen(Pool, "connect", read_only)
    try:
        spec = spec_at(pg_url)
        assert status.run(spec, argparse.Namespace()) == 0
        assert "driver: not running" in capsys.readouterr().out
        out = str(tmp_path / "out")
        args = argparse.Namespace(spec=[CI_SPEC], storage=pg_url, out=out, no_dashboard=True)
        assert aggregate.run([spec], args) == 0
    finally:
        event.remove(Pool, "connect", read_only)
    assert sessions and set(sessions) == {"on"}, sessions
    assert (tmp_path / "out" / "auc_table.csv").is_file()
    assert tables() == before


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


def test_a_postgresql_outage_shorter_than_the_grace_is_retried(pg_url):
    proxy = Proxy(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")
    plan = build_plan(spec_at(url))
    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}, grace=20) as store:
        (_, trial), _ = store.sync(plan.entries, plan.hash)
        store.start(trial._trial_id)
        failed = []

        def back_after_a_failed_try(context):  # the database returns once a try met it gone
            failed.append(context.original_exception)
            proxy.up()

        proxy.down()
        event.listen(store.storage.engine, "handle_error", back_after_a_failed_try, once=True)
        store.complete(trial._trial_id, 0.5, {"outcome": "completed"})  # during the outage
        assert len(failed) == 1  # it met the outage, and was tried again
    done = optuna.load_study(study_name="ci", storage=pg_url).trials[trial.number]
    assert done.state.name == "COMPLETE" and done.value == 0.5

    with open_study(url, "ci", write=True, attrs={"plan_hash": plan.hash}, grace=2) as store:
        [(_, trial)] = store.sync(plan.entries, plan.hash)
        proxy.down()  # for good: longer than the grace
        start = time.monotonic()
        with pytest.raises(StorageError) as info:
            store.start(trial._trial_id)
        assert time.monotonic() - start < STORAGE_GRACE / 2  # its grace (2 s), not the default
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

        tries = []

        def tried(context):
            tries.append(context.statement)

        event.listen(store.storage.engine, "before_cursor_execute", full)
        event.listen(store.storage.engine, "handle_error", tried)
        with pytest.raises(StorageError) as info:
            store.complete(trial._trial_id, 0.5, {"outcome": "completed"})
        assert len(tries) == 1, tries  # a full disk is not waited for: not tried again
        event.remove(store.storage.engine, "handle_error", tried)
        event.remove(store.storage.engine, "before_cursor_execute", full)
        assert store.trials()[trial.number].state.name == "RUNNING"  # nothing half-written
    message = str(info.value)
    assert "\n" not in message and "its disk is full" in message and "free space" in message


# ---- issue 35: a fault while the study is opened; a damaged file ------------------------
@pytest.mark.parametrize("how", DAMAGE)
def test_a_damaged_study_is_one_line_saying_how_to_get_it_back(tmp_path, capsys, how):
    """status, aggregate and publish of a damaged copy of a finished study: exit 2 and one
    line naming the damage and the ways back; nothing is written, and an earlier published
    copy is left as it was. (Two pages overwritten used to pass unseen: status and
    aggregate exited 0, publish shipped the damaged file.)"""
    runs, published = tmp_path / "runs", tmp_path / "published"
    for folder in (runs, published):
        folder.mkdir()
        shutil.copy(PUBLISHED / "study.db", folder / "study.db")  # published: the last copy
    database = runs / "study.db"
    damage(database, how)
    before = snapshot(runs), snapshot(published)
    spec = [str(ROOT / "studies" / "fetch_reach_cpu.yaml"), "--storage", f"sqlite:///{database}"]
    for command, *options in (["status"], ["aggregate", "--out", str(tmp_path / "aggregate")],
                              ["publish", "--out", str(published)]):  # fmt: skip
        assert cli.main([command, *spec, *options]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1, err
        assert err.startswith(f"sweeper {command}: storage: the database sqlite:///{database} is "
                              "damaged (")  # fmt: skip
        assert "restore it from a backup or from the study's last published copy" in err
    assert (snapshot(runs), snapshot(published)) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["published", "runs"]


def test_the_check_for_damage_is_cheap():
    """``quick_check`` of a finished study of MBs takes milliseconds (integrity_check,
    which publish runs on its copy, ~10 ms)."""
    start = time.perf_counter()
    check_intact(f"sqlite:///{PUBLISHED / 'study.db'}")
    assert time.perf_counter() - start < 1


def test_publishing_an_unfinished_study_says_the_copy_is_partial(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    storage = open_storage(url)
    study = write_synthetic_study(storage, "ci", methods=("pixel", "linear"), configs=1,
                                  seeds=(0,), special=Special(running="linear/0/0"))  # fmt: skip
    plan = build_plan(spec_at(url))
    study.set_user_attr("plan_hash", plan.hash)
    study.set_user_attr("plan", plan.keys())
    storage.engine.dispose()
    out = tmp_path / "published"
    assert cli.main(["publish", str(CI_SPEC), "--storage", url, "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == (
        "the study is unfinished (1 of 2 trials done): the published copy is partial; "
        "publish again once it ends"
    )
    assert (out / "study.db").is_file() and not (out / "study.db.partial").exists()


def test_an_outage_while_the_study_is_opened_is_retried_for_the_grace(pg_url):
    """A PostgreSQL server gone as a launch opens its study is waited for, as one gone
    later is: the study opens once it is back; gone for longer than the grace, one line."""
    proxy = Proxy(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")
    attrs = {"plan_hash": build_plan(spec_at(url)).hash}
    proxy.down()
    threading.Timer(1.0, proxy.up).start()
    start = time.monotonic()
    with open_study(url, "ci", write=True, attrs=attrs, grace=30) as store:
        assert store.attrs["plan_hash"] == attrs["plan_hash"]
    assert time.monotonic() - start >= 1.0  # it waited for the server
    proxy.down()  # for good
    for write in (True, False):  # the launch's writer, and its read before Ray starts
        start = time.monotonic()
        with (
            pytest.raises(StorageError) as info,
            open_study(url, "ci", write=write, attrs=attrs, grace=2),
        ):
            pass
        assert time.monotonic() - start < STORAGE_GRACE / 2  # its grace, not the default
        message = str(info.value)
        assert "\n" not in message and message.startswith("storage: lost postgresql")
        assert "for over 2 s (execution.storage_grace)" in message


def test_a_full_disk_while_the_database_is_created_is_one_line(tmp_path):
    url = f"sqlite:///{tmp_path / 'study.db'}"

    def full(connection, cursor, statement, *args):
        if statement.lstrip().upper().startswith("CREATE"):
            raise sqlite3.OperationalError("database or disk is full")

    event.listen(Engine, "before_cursor_execute", full)
    try:
        with pytest.raises(StorageError) as info, open_study(url, "ci", write=True, attrs={}):
            pass
    finally:
        event.remove(Engine, "before_cursor_execute", full)
    assert str(info.value) == (
        f"storage: cannot write {url}: its disk is full (database or disk is full); free "
        "space, then launch again"
    )


def test_status_says_where_each_running_trial_is_while_its_driver_runs(tmp_path, capsys):
    import datetime

    from sweeper.storage import StudyStore

    url = f"sqlite:///{tmp_path / 'study.db'}"
    storage = open_storage(url)
    study = write_synthetic_study(storage, "ci", methods=("pixel", "linear"), configs=1,
                                  seeds=(0,), steps=(0, 100, 200, 300),
                                  special=Special(running="linear/0/0"))  # fmt: skip
    spec = spec_at(url)
    plan_hash = build_plan(spec).hash
    study.set_user_attr("plan_hash", plan_hash)
    assert status.run(spec, argparse.Namespace()) == 0  # no driver: nothing runs
    assert "running:" not in capsys.readouterr().out
    StudyStore.open_or_create(storage, "ci", {"plan_hash": plan_hash}).claim_driver()  # alive
    assert status.run(spec, argparse.Namespace()) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-2].startswith("driver: running")
    assert printed[-1].startswith("running: linear/0/0 (trial 1): step 200 of 300, started ")
    storage.engine.dispose()

    trial = study.trials[1]
    later = trial.datetime_start + datetime.timedelta(minutes=65)
    assert status.running_line("linear/0/0", trial, 300, later).endswith(
        "step 200 of 300, started 1 h 5 min ago"
    )
    trial.user_attrs["paused_at"] = 200  # successive halving: waits at its rung
    assert "step 200 of 300, at its rung," in status.running_line("k", trial, 300, later)
    trial.user_attrs["curve"] = None  # before its first evaluation
    assert "(trial 1): no evaluation yet, started" in status.running_line("k", trial, 300, later)
