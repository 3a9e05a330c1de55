"""One study, opened in one place: by the driver to write it, by ``sweeper status``,
``dashboard`` and ``aggregate`` to read it.

``open_study`` is a context manager: it opens the storage, finds (or, for the driver,
creates) the study, checks its plan hash, and disposes of the engine on exit. A reader's
connections are read-only (``sweeper.storage._urls.open_engine``): it never
writes, and reads a finished SQLite study on read-only media. ``read_rows`` is the fast
reader of a whole study: one SQL query per Optuna table, not one per trial. The study's
rules (the current trial of a key, the per-key ledger) are ``sweeper.storage._ledger``'s
``current_numbers``, ``current_trials``, ``key_status``, ``tally`` and ``ledger``. This
module sits above ``sweeper.storage``: it uses its URLs, errors and ``StudyStore``, and
nothing there imports it.

Nothing to read (no database file, a database without Optuna's tables, no study of that
name) is a ``NoStudy``, whose message says how to create the study. A damaged SQLite file
is a StorageError that says how to get the study back (``check_intact``), and an outage
while the study is opened is retried for the grace, as one later (``retry_outages``).
"""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sweeper.storage._attrs import SYSTEM_ATTRS
from sweeper.storage._errors import (
    StorageError,
    check_plan,
    damaged_error,
    database_error,
    is_damaged,
    reason_of,
    redact,
)
from sweeper.storage._urls import check_intact, open_engine, open_storage, resolve_url, sqlite_path
from sweeper.storage._writer import STORAGE_GRACE, StudyStore, retry_outages

if TYPE_CHECKING:  # pandas and sqlalchemy are imported where used: `sweeper --help` stays light
    import pandas as pd
    from sqlalchemy.engine import Connection

    from sweeper.spec import StudySpec

#: how a study comes to be, for the messages of ``NoStudy``
CREATE_HINT = "launch the study first (`sweeper launch SPEC`)"


class NoStudy(StorageError):
    """There is no such study to read; ``why`` says what is missing: ``"no database file"``,
    ``"no Optuna tables"`` or ``"no such study"``."""

    def __init__(self, message: str, why: str) -> None:
        super().__init__(message)
        self.why = why


@contextlib.contextmanager
def open_study(
    url: str,
    name: str,
    *,
    write: bool,
    create: bool = True,
    attrs: Mapping[str, Any] | None = None,
    plan_hash: str | None = None,
    grace: float = STORAGE_GRACE,
) -> Iterator[StudyStore]:
    """The study ``name`` in ``url`` while the block runs.

    ``write=False``: read-only connections; raises NoStudy when there is nothing to read.
    ``write=True, create=True`` (the driver): the database and the study are created if
    needed, with study user attrs ``attrs``, whose ``plan_hash`` must match the stored one.
    ``write=True, create=False`` (optuna-dashboard, which edits notes): an existing study,
    else NoStudy. ``plan_hash``: the study must have been launched with this plan (a study
    without one passes). An SQLite file is checked for damage first (``check_intact``).
    Database outages are retried for ``grace`` seconds, while opening as later
    (``StudyStore``). Raises StorageError (a ValueError) with a one-line message.
    """
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if write and create and attrs is None:
        raise ValueError("open_study(write=True) needs the study's attrs")
    then = "launch again" if write and create else "try again"
    store = retry_outages(
        lambda: _open(url, name, write=write, create=create, attrs=attrs, grace=grace),
        url,
        grace,
        then,
    )
    try:
        if plan_hash is not None:
            check_plan(name, store.attrs, plan_hash)
        yield store
    finally:
        _close(store.storage)


def _open(
    url: str,
    name: str,
    *,
    write: bool,
    create: bool,
    attrs: Mapping[str, Any] | None,
    grace: float,
) -> StudyStore:
    """One try at opening the study (``open_study``); a database error is raised as it is,
    for ``retry_outages`` to retry or to put in one line."""
    if write and create:
        check_intact(url)
        storage = open_storage(url)
    else:
        with _reader(url) as connection:
            _study_id(connection, url, name)
        storage = open_storage(url, create=False, read_only=not write)
    try:
        if write and create:
            return StudyStore.open_or_create(storage, name, attrs or {}, grace)
        store = StudyStore.find(storage, name, grace)
        if store is None:  # deleted since the check above
            raise NoStudy(f"study {name!r} not found in {redact(url)}", "no such study")
        return store
    except BaseException:
        _close(storage)
        raise


def _close(storage: Any) -> None:
    storage.remove_session()
    storage.engine.dispose()


#: ``SYSTEM_ATTRS`` as an SQL list of literals (fixed names, no quotes in them)
_SYSTEM_KEYS = ", ".join(f"'{key}'" for key in sorted(SYSTEM_ATTRS))


@dataclass(frozen=True)
class StudyRows:
    """A whole study as Optuna stores it, one frame per table (``read_rows``)."""

    trials: pd.DataFrame  # trial_id, number, state
    values: pd.DataFrame  # trial_id, value, value_type (objective 0)
    user_attrs: pd.DataFrame  # trial_id, key, value_json
    system_attrs: pd.DataFrame  # trial_id, key, value_json: the SYSTEM_ATTRS (trial_attr)
    params: pd.DataFrame  # trial_id, param_name, param_value, distribution_json
    intermediate: pd.DataFrame  # trial_id, step, intermediate_value, intermediate_value_type
    study_attrs: pd.DataFrame  # key, value_json


def read_rows(url: str, name: str) -> StudyRows:
    """Study ``name`` read with one query per Optuna table, read-only.

    Optuna's ``get_trials`` takes ~15 s for 2,000 trials x 50 points; this a fraction of a
    second. Reading a live study is safe: a trial written between two queries shows up
    partly (no key yet) or not at all. Raises NoStudy, or StorageError when the database
    cannot be read.
    """
    import pandas as pd
    from sqlalchemy import text
    from sqlalchemy.exc import SQLAlchemyError

    try:
        with _reader(url) as connection:
            study_id = _study_id(connection, url, name)

            def query(sql: str) -> pd.DataFrame:
                return pd.read_sql_query(text(sql), connection, params={"study": study_id})

            of_study = "JOIN trials t ON t.trial_id = x.trial_id WHERE t.study_id = :study"
            return StudyRows(
                trials=query("SELECT trial_id, number, state FROM trials WHERE study_id = :study"),
                values=query(
                    f"SELECT x.trial_id, x.value, x.value_type FROM trial_values x {of_study} "
                    "AND x.objective = 0"
                ),
                user_attrs=query(
                    f"SELECT x.trial_id, x.key, x.value_json FROM trial_user_attributes x "
                    f"{of_study}"
                ),
                system_attrs=query(
                    f"SELECT x.trial_id, x.key, x.value_json FROM trial_system_attributes x "
                    f"{of_study} AND x.key IN ({_SYSTEM_KEYS})"
                ),
                params=query(
                    "SELECT x.trial_id, x.param_name, x.param_value, x.distribution_json "
                    f"FROM trial_params x {of_study}"
                ),
                intermediate=query(
                    "SELECT x.trial_id, x.step, x.intermediate_value, x.intermediate_value_type "
                    f"FROM trial_intermediate_values x {of_study}"
                ),
                study_attrs=query(
                    "SELECT key, value_json FROM study_user_attributes WHERE study_id = :study"
                ),
            )
    except (SQLAlchemyError, sqlite3.Error) as e:  # a locked file, a server gone meanwhile
        if is_damaged(e):
            raise damaged_error(url, reason_of(e)) from None
        raise database_error("cannot read", url, e) from None


@contextlib.contextmanager
def _reader(url: str) -> Iterator[Connection]:
    """A read-only connection to ``url``'s database, which must hold Optuna's tables and,
    SQLite, be intact (``check_intact``). Raises NoStudy or StorageError for a URL or file
    that is not there; a database error as it is (the callers put it in one line)."""
    from sqlalchemy import inspect
    from sqlalchemy.exc import ArgumentError

    resolved = resolve_url(url)
    try:
        path = sqlite_path(resolved)
        engine = open_engine(resolved, read_only=True)
    except (ArgumentError, ImportError) as e:
        raise StorageError(f"storage: cannot use {redact(url)}: {e}") from None
    if path is not None and not path.is_file():
        engine.dispose()
        raise NoStudy(
            f"storage: no database file at {path}: no study is there; {CREATE_HINT}",
            "no database file",
        )
    try:
        check_intact(url)
        with engine.connect() as connection:
            if not inspect(connection).has_table("studies"):
                raise NoStudy(
                    f"storage: {redact(url)} holds no Optuna study (an empty database); "
                    f"{CREATE_HINT}",
                    "no Optuna tables",
                )
            yield connection
    finally:
        engine.dispose()


def _study_id(connection: Connection, url: str, name: str) -> int:
    """The id of study ``name``; NoStudy listing the studies there when there is none."""
    from sqlalchemy import text

    found = connection.execute(
        text("SELECT study_id FROM studies WHERE study_name = :name"), {"name": name}
    ).scalar()
    if found is None:
        names = connection.execute(text("SELECT study_name FROM studies")).scalars()
        raise NoStudy(
            f"study {name!r} not found in {redact(url)}; "
            f"it has: {', '.join(sorted(names)) or 'no studies'}",
            "no such study",
        )
    return int(found)


@contextlib.contextmanager
def open_for_reading(spec: StudySpec) -> Iterator[StudyStore | NoStudy]:
    """The one way a reading command opens its study: read-only, once, for the whole
    command, with the spec's grace for outages. Yields the store, or the ``NoStudy`` that
    says why there is none yet (not launched). Raises StorageError when the database
    cannot be read. The plan's hash is the caller's to check (``check_plan``), once it has
    built the plan (``stored_files``)."""
    with contextlib.ExitStack() as stack:
        try:
            store: StudyStore | NoStudy = stack.enter_context(
                open_study(
                    spec.storage_url, spec.study, write=False, grace=spec.execution.storage_grace
                )
            )
        except NoStudy as e:
            store = e
        yield store


def stored_files(spec: StudySpec, store: StudyStore | NoStudy) -> StudySpec:
    """For readers that check the plan (``status``, ``plan``, ``rerun``): ``spec`` with the
    file options it gives no value here (vgg's ``weights_path`` in a shell without
    ``$GCRL_VGG16_WEIGHTS``) taken from the spec stored in the open study: the path is part
    of the plan and its hash, so a reader takes a study launched where it was set. No
    study, or none stored: ``spec`` as it is."""
    unset = [item for item in spec.missing_files() if item.unset]
    if not unset or isinstance(store, NoStudy):
        return spec
    stored = (store.attrs.get("spec") or {}).get("methods") or {}
    data = spec.model_dump(mode="json")
    for item in unset:
        _, method, name = item.at.split(".")
        value = (stored.get(method) or {}).get(name)
        if value is not None:
            data["methods"][method][name] = value
    from sweeper.spec import parse_spec

    return parse_spec(data, source="the study's stored spec")
