"""The study database's errors and their one-line messages.

``StorageError`` (an unusable URL, a study that does not match its spec, a write the
database refused) and ``StudyBusy`` (another live driver); which exceptions the database
raised (``is_database_error``), which of them are an outage a retry may get past
(``is_outage``) and which say the SQLite file is damaged (``is_damaged``); the one line
each says, the database driver's own reason first (``reason_of``), with the URL's password
hidden (``redact``). Readers and the writer raise the same errors.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Mapping
from typing import Any


class StorageError(ValueError):
    """A storage URL that cannot be used, or a study that does not match its spec."""


class StudyBusy(RuntimeError):
    """Another live driver runs the study."""


def redact(url: str) -> str:
    """``url`` without its password, for messages."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:
        return url.split("@")[-1]


def database_error(action: str, url: str, error: BaseException) -> StorageError:
    """``storage: {action} {url}: {reason}`` for an error the database raised, on one line:
    the driver's own message (SQLAlchemy keeps it as ``orig``), first line, password hidden.
    """
    return StorageError(f"storage: {action} {redact(url)}: {reason_of(error)}")


def reason_of(error: BaseException) -> str:
    """The database driver's own message of ``error``, first line. Optuna wraps every
    SQLAlchemy error of a commit in a StorageInternalError whose text ("... e.g. exceeding
    max length") guesses wrong; the cause it wraps says what happened."""
    cause = database_cause(error)
    text = str(getattr(cause, "orig", None) or cause).strip()
    return text.splitlines()[0] if text else type(cause).__name__


def database_cause(error: BaseException) -> BaseException:
    """``error`` without Optuna's StorageInternalError around it."""
    while type(error).__name__ == "StorageInternalError" and error.__cause__ is not None:
        error = error.__cause__
    return error


def is_database_error(error: BaseException) -> bool:
    """Whether the database (or the connection to it) raised ``error``."""
    from sqlalchemy.exc import SQLAlchemyError

    return isinstance(database_cause(error), SQLAlchemyError | sqlite3.Error)


def is_outage(error: BaseException) -> bool:
    """Whether ``error`` is a lost, refused or busy connection, which a retry may get past,
    rather than a fault of the database itself (a full disk, a read-only file, bad data).

    PostgreSQL: errors without an SQLSTATE (the client could not connect or lost the
    connection), class 08 (connection exception), 57P (the server shuts down or starts up)
    and 40 (a deadlock or serialisation failure: the transaction was rolled back). SQLite:
    a lock that outlasted the busy timeout.
    """
    from sqlalchemy.exc import DBAPIError

    cause = database_cause(error)
    if isinstance(cause, DBAPIError) and cause.connection_invalidated:
        return True
    orig = getattr(cause, "orig", cause)
    if isinstance(orig, sqlite3.OperationalError):
        return "database is locked" in str(orig)
    if type(orig).__module__.startswith("psycopg"):
        state = getattr(orig, "sqlstate", None)
        return state is None or state.startswith(("08", "57P", "40"))
    return False


#: SQLite's result codes of a damaged file: SQLITE_CORRUPT, SQLITE_NOTADB
DAMAGED_CODES = (11, 26)
#: what a write error's message tells the user to do once the cause is fixed
RESUME = "launch again to resume the trials in flight"


def is_damaged(error: BaseException) -> bool:
    """Whether ``error`` says the SQLite file is damaged (malformed, or not a database):
    no retry gets past that."""
    cause = database_cause(error)
    orig = getattr(cause, "orig", None) or cause
    if not isinstance(orig, sqlite3.DatabaseError):
        return False
    return (getattr(orig, "sqlite_errorcode", 0) & 0xFF) in DAMAGED_CODES  # the primary code


def damaged_error(url: str, detail: str) -> StorageError:
    """The one-line StorageError of a damaged SQLite database and the ways back."""
    detail = " ".join(detail.split())
    detail = detail if len(detail) <= 120 else detail[:117] + "..."
    return StorageError(
        f"storage: the database {redact(url)} is damaged ({detail}): restore it from a backup "
        "or from the study's last published copy (`sweeper publish` writes study.db), or give "
        "another --storage"
    )


def write_error(url: str, error: BaseException, grace: float, then: str = RESUME) -> StorageError:
    """The one-line StorageError of a write (or an open) the database refused, naming the
    cause and the fix, ``then`` what to do after it; the trials in flight stay RUNNING and
    the next launch resumes them."""
    reason = reason_of(error)
    where = redact(url)
    if is_damaged(error):
        return damaged_error(url, reason)
    state = getattr(getattr(database_cause(error), "orig", None), "sqlstate", None)
    if "disk is full" in reason or state == "53100":  # SQLite's and PostgreSQL's full disk
        return StorageError(
            f"storage: cannot write {where}: its disk is full ({reason}); free space, then {then}"
        )
    if "readonly" in reason or "read-only" in reason:
        return StorageError(
            f"storage: cannot write {where}: it is read-only ({reason}); make it writable or "
            f"give another --storage, then {then}"
        )
    if is_outage(error):
        return StorageError(
            f"storage: lost {where} for over {grace:g} s (execution.storage_grace): {reason}; "
            f"bring the database back, then {then}"
        )
    return StorageError(f"storage: cannot use {where}: {reason}")


def check_plan(name: str, attrs: Mapping[str, Any], plan_hash: str) -> None:
    """Raise StorageError unless study ``name`` (its user ``attrs``) was launched with the
    plan ``plan_hash``: two plans in one study would mix two budgets. A study without a
    plan hash passes. The driver (``StudyStore.open_or_create``) and readers
    (``sweeper.storage._open.open_study``) both check here."""
    stored = attrs.get("plan_hash")
    if stored is not None and stored != plan_hash:
        raise StorageError(
            f"study {name!r} in this storage was launched with another plan "
            f"(plan_hash {stored[:12]}, this spec gives {plan_hash[:12]}): the spec's methods, "
            "budget, seeds or search space changed. Use a new study name, or restore the old "
            "spec."
        )
