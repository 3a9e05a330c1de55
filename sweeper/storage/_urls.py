"""Database URLs: what they name, whether they can be used, and how they are opened.

The one place that says how a URL is connected to, for the writer and for readers alike:
``engine_arguments`` gives the SQLAlchemy engine's arguments, which ``open_engine`` (the
engines this project builds) and ``open_storage`` (Optuna's storage, which builds its own
engine from a URL and these arguments) both use. ``postgresql://`` means psycopg 3
(``resolve_url``), an SQLite file is put in WAL journal mode and opened with a long busy
timeout so a reader can read a study while the driver writes it, and a reader's
connections are read-only, kept from writing by the database itself
(``read_only_engine_kwargs``, ``connect_read_only``). ``check_storage`` and
``check_writable`` check a URL before a launch writes anything; ``check_intact`` and
``damage`` check an SQLite file for damage.
"""

from __future__ import annotations

import functools
import os
import sqlite3
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sweeper.storage._errors import (
    StorageError,
    damaged_error,
    database_error,
    is_damaged,
    redact,
)

if TYPE_CHECKING:  # optuna and sqlalchemy are imported where used: `sweeper --help` stays light
    import optuna
    from sqlalchemy.engine import Engine

#: seconds a SQLite connection waits for a lock before giving up
SQLITE_TIMEOUT = 60.0


def resolve_url(url: str) -> str:
    """The SQLAlchemy URL to connect with.

    ``postgresql://`` means psycopg 3 here (the installed driver); SQLAlchemy would pick
    psycopg2, which is not installed.
    """
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


def sqlite_path(url: str) -> Path | None:
    """The file of a ``sqlite:///`` URL, None for other backends (any URL the spec takes)."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return None
    if not parsed.database or parsed.database == ":memory:":
        raise StorageError(
            f"storage: {url!r} is an in-memory SQLite database, which loses the study when "
            "the driver exits; give a file, e.g. sqlite:///runs/study.db"
        )
    return Path(parsed.database)


def check_storage(url: str) -> None:
    """Raise a StorageError naming ``storage`` unless ``url`` can be used; write nothing.

    SQLite: the file's directory must exist or be creatable, and be writable. Any other
    backend: a connection is opened and ``SELECT 1`` run.
    """
    from sqlalchemy import text
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError

    try:
        path = sqlite_path(resolve_url(url))
    except (ArgumentError, ValueError) as e:
        if isinstance(e, StorageError):
            raise
        raise StorageError(f"storage: {url!r} is not a database URL ({e})") from None
    if path is not None:
        if path.exists() and not path.is_file():
            raise StorageError(f"storage: {path} exists and is not a file")
        parent = path.parent.absolute()
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise StorageError(f"storage: cannot create {path}: {parent} is not writable")
        return
    try:
        # a host that drops packets must not hang the launch
        engine = open_engine(url, connect_timeout=10)
    except (ArgumentError, NoSuchModuleError, ImportError) as e:
        raise StorageError(f"storage: cannot use {redact(url)}: {e}") from None
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
    except Exception as e:
        raise database_error("cannot connect to", url, e) from None
    finally:
        engine.dispose()


def open_storage(
    url: str, create: bool = True, *, read_only: bool = False
) -> optuna.storages.RDBStorage:
    """An Optuna RDB storage for ``url``.

    ``create``: create the tables (and the SQLite file) if needed, as the driver does;
    readers pass False. Optuna's first open also inserts version rows, so a reader
    opening a database while it is being created can collide with the driver: the driver
    retries, a reader gets the SQLAlchemy error. ``read_only``: every connection is
    read-only (``read_only_engine_kwargs``), so nothing can be written, and a finished
    SQLite study on read-only media can be read.
    """
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    resolved = resolve_url(url)
    path = sqlite_path(resolved)
    if read_only:
        create = False
    elif path is not None and create:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:  # a full disk, a file in the way
            raise StorageError(f"storage: cannot create {path.parent}: {e.strerror}") from None
        # WAL is a property of the database file: once set, every later connection (the
        # dashboard's too) reads without blocking the writer and is never blocked by it.
        with sqlite3.connect(path, timeout=SQLITE_TIMEOUT) as connection:
            connection.execute("PRAGMA journal_mode=WAL")
        connection.close()
    engine_kwargs = engine_arguments(resolved, read_only=read_only)

    def build() -> optuna.storages.RDBStorage:
        return optuna.storages.RDBStorage(
            resolved, engine_kwargs=engine_kwargs, skip_table_creation=not create
        )

    for _ in range(4 if create else 0):
        try:
            return build()
        except (SQLAlchemyError, optuna.exceptions.StorageInternalError):
            time.sleep(0.5)
    return build()


def engine_arguments(url: str, *, read_only: bool = False) -> dict[str, Any]:
    """The ``create_engine`` arguments for ``url``: how a writer or a reader connects.

    A reader (``read_only``): connections the database keeps from writing
    (``read_only_engine_kwargs``). The writer: SQLite with a busy timeout of
    ``SQLITE_TIMEOUT`` s (it waits out a reader's lock instead of failing), any other
    database with ``pool_pre_ping`` (a pooled connection the server dropped is replaced).
    """
    resolved = resolve_url(url)
    if read_only:
        return read_only_engine_kwargs(resolved)
    if sqlite_path(resolved) is not None:
        return {"connect_args": {"timeout": SQLITE_TIMEOUT}}
    return {"pool_pre_ping": True}


def open_engine(
    url: str, *, read_only: bool = False, connect_timeout: float | None = None
) -> Engine:
    """The SQLAlchemy engine of ``url``, connected as ``engine_arguments`` says.

    ``connect_timeout``: the seconds a PostgreSQL connection may take to open (other
    databases ignore it). Raises SQLAlchemy's ``ArgumentError`` or ``NoSuchModuleError``,
    or ``ImportError``, for a URL that cannot be used.
    """
    from sqlalchemy import create_engine

    resolved = resolve_url(url)
    kwargs = engine_arguments(resolved, read_only=read_only)
    if connect_timeout is not None and resolved.startswith("postgresql"):
        kwargs["connect_args"] = {
            **kwargs.get("connect_args", {}),
            "connect_timeout": connect_timeout,
        }
    return create_engine(resolved, **kwargs)


def check_writable(url: str) -> None:
    """Raise a StorageError naming the file and the fix unless the driver can write an
    existing SQLite database (``check_storage`` checks its folder): SQLite opens a file it
    cannot write read-only, and the first write would fail after Ray and the workers
    started. Opening the file for writing changes nothing in it."""
    path = sqlite_path(resolve_url(url))
    if path is None:
        return
    for file in (
        path,
        path.with_name(path.name + "-wal"),
        path.with_name(path.name + "-shm"),
    ):
        if not file.is_file():
            continue
        try:
            with file.open("r+b"):
                pass
        except OSError as e:
            raise StorageError(
                f"storage: cannot write the database file {file} ({e.strerror}): make it "
                "writable (chmod u+w, chattr -i, a read-write mount) or give another --storage"
            ) from None


def check_intact(url: str) -> None:
    """Raise a StorageError naming the damage and the ways back when ``url`` is an SQLite
    file that exists and is damaged (overwritten, truncated, not a database at all)."""
    path = sqlite_path(resolve_url(url))
    if path is not None and path.is_file() and (problem := damage(path)):
        raise damaged_error(url, problem)


def damage(path: Path, *, thorough: bool = False) -> str | None:
    """What is damaged in the SQLite file ``path`` (its first fault, one line), or None.

    SQLite's ``PRAGMA quick_check`` (the file's structure, in one pass: about a millisecond
    for the MBs of docs/studies/fetch_reach_cpu/study.db), or with ``thorough`` its
    ``integrity_check`` (indexes too: what a published copy is checked with). Reads only.
    A database error that is not damage (a lock) is raised as it is, for a retry.
    """
    pragma = "integrity_check" if thorough else "quick_check"
    try:
        connection = connect_read_only(path)
        try:
            (verdict,) = connection.execute(f"PRAGMA {pragma}(1)").fetchone()
        finally:
            connection.close()
    except sqlite3.DatabaseError as e:
        if not is_damaged(e):
            raise
        verdict = str(e)
    if verdict == "ok":
        return None
    # a first line "*** in database main ***" names the database; the next one the fault
    lines = [line for line in verdict.splitlines() if not line.startswith("***")]
    return f"{pragma}: {(lines or [verdict])[0]}"


def read_only_engine_kwargs(url: str) -> dict[str, Any]:
    """``create_engine`` arguments for a reader that the database itself keeps from
    writing: SQLite opened with ``mode=ro`` (``connect_read_only``), a PostgreSQL session
    whose transactions are read-only."""
    from sqlalchemy.engine import make_url

    resolved = resolve_url(url)
    path = sqlite_path(resolved)
    if path is not None:
        return {"creator": functools.partial(connect_read_only, path)}
    options = make_url(resolved).query.get("options", "")
    if not isinstance(options, str):  # given twice in the URL
        options = " ".join(options)
    options = f"{options} -c default_transaction_read_only=on".strip()
    return {"pool_pre_ping": True, "connect_args": {"options": options}}


def connect_read_only(path: Path) -> sqlite3.Connection:
    """A read-only connection to the SQLite file ``path`` (SQLite refuses every write).

    A database in WAL mode needs its ``-shm`` file to be read; a live driver always has
    one. When it is absent and cannot be created (read-only media, so no driver can write
    there either), the file is opened ``immutable``: read without locks.
    """
    uri = f"{path.absolute().as_uri()}?mode=ro"
    connection = sqlite3.connect(uri, uri=True, timeout=SQLITE_TIMEOUT, check_same_thread=False)
    try:
        connection.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.OperationalError as e:
        connection.close()
        if "unable to open" not in str(e):
            raise
        connection = sqlite3.connect(
            f"{uri}&immutable=1",
            uri=True,
            timeout=SQLITE_TIMEOUT,
            check_same_thread=False,
        )
    return connection
