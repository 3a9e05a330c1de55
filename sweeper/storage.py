"""The study database: one Optuna study per spec, written only by the sweep driver.

Conventions (docs/architecture.md, "Storage conventions"): one Optuna trial per plan key
``"{method}/{config_id}/{seed}"``; a key that has to be run again (its driver died, it was
interrupted, or it failed) gets a fresh trial, and the trial with the highest number is the
key's *current* trial. ``ledger`` counts keys, never trials, so the counts are exact.

SQLite files are switched to WAL journal mode and opened with a long busy timeout, so
optuna-dashboard (or ``sweeper status``) can read a study while the driver writes it.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import secrets
import socket
import sqlite3
import subprocess
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from agent.config import Outcome

if TYPE_CHECKING:  # optuna and sqlalchemy are imported where used: `sweeper --help` stays light
    import optuna
    from optuna.trial import FrozenTrial
    from sqlalchemy.engine import Connection

#: seconds a SQLite connection waits for a lock before giving up
SQLITE_TIMEOUT = 60.0
#: a driver whose heartbeat is older than this is considered dead
DRIVER_STALE_SECONDS = 60.0
#: seconds the driver retries a write while the database is unreachable (the default of
#: the spec's ``execution.storage_grace``)
STORAGE_GRACE = 60.0
#: the longest wait between two tries of a write during an outage
RETRY_MAX_DELAY = 5.0
#: distributions whose versions the study records
VERSIONED_PACKAGES = (
    "gcrl-sweeper",
    "torch",
    "numpy",
    "mujoco",
    "gymnasium",
    "gymnasium-robotics",
    "metaworld",
    "optuna",
    "ray",
    "sqlalchemy",
)


class StorageError(ValueError):
    """A storage URL that cannot be used, or a study that does not match its spec."""


class StudyBusy(RuntimeError):
    """Another live driver runs the study."""


def resolve_url(url: str) -> str:
    """The SQLAlchemy URL to connect with.

    ``postgresql://`` means psycopg 3 here (the installed driver); SQLAlchemy would pick
    psycopg2, which is not installed.
    """
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


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


def write_error(url: str, error: BaseException, grace: float) -> StorageError:
    """The one-line StorageError of a write the database refused, naming the cause and the
    fix; the trials in flight stay RUNNING and the next launch resumes them."""
    reason = reason_of(error)
    where = redact(url)
    resume = "launch again to resume the trials in flight"
    state = getattr(getattr(database_cause(error), "orig", None), "sqlstate", None)
    if "disk is full" in reason or state == "53100":  # SQLite's and PostgreSQL's full disk
        return StorageError(
            f"storage: cannot write {where}: its disk is full ({reason}); free space, then {resume}"
        )
    if "readonly" in reason or "read-only" in reason:
        return StorageError(
            f"storage: cannot write {where}: it is read-only ({reason}); make it writable or "
            f"give another --storage, then {resume}"
        )
    if is_outage(error):
        return StorageError(
            f"storage: lost {where} for over {grace:g} s (execution.storage_grace): {reason}; "
            f"bring the database back, then {resume}"
        )
    return StorageError(f"storage: cannot use {where}: {reason}")


def sqlite_path(url: str) -> Path | None:
    """The file of a ``sqlite:///`` URL, None for other backends."""
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
    from sqlalchemy import create_engine, text
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
    resolved = resolve_url(url)
    # a host that drops packets must not hang the launch
    connect_args = {"connect_timeout": 10} if resolved.startswith("postgresql") else {}
    try:
        engine = create_engine(resolved, connect_args=connect_args)
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
        engine_kwargs = read_only_engine_kwargs(resolved)
    elif path is not None:
        if create:
            path.parent.mkdir(parents=True, exist_ok=True)
            # WAL is a property of the database file: once set, every later connection (the
            # dashboard's too) reads without blocking the writer and is never blocked by it.
            with sqlite3.connect(path, timeout=SQLITE_TIMEOUT) as connection:
                connection.execute("PRAGMA journal_mode=WAL")
            connection.close()
        engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT}}
    else:
        engine_kwargs = {"pool_pre_ping": True}

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


def check_writable(url: str) -> None:
    """Raise a StorageError naming the file and the fix unless the driver can write an
    existing SQLite database (``check_storage`` checks its folder): SQLite opens a file it
    cannot write read-only, and the first write would fail after Ray and the workers
    started. Opening the file for writing changes nothing in it."""
    path = sqlite_path(resolve_url(url))
    if path is None:
        return
    for file in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
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
            f"{uri}&immutable=1", uri=True, timeout=SQLITE_TIMEOUT, check_same_thread=False
        )
    return connection


def code_revision() -> str:
    """The git commit of this checkout (``-dirty`` if tracked files changed), or "unknown"."""
    root = Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        )
        if commit.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "diff", "--quiet", "HEAD"], cwd=root, capture_output=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return commit.stdout.strip() + ("-dirty" if dirty.returncode == 1 else "")


def package_versions() -> dict[str, str]:
    """Installed versions of the packages a result depends on."""
    versions = {}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def json_safe(values: Iterable[float]) -> list[float | None]:
    """Floats with NaN/inf as None: user attrs are JSON, and the dashboard's parser rejects NaN."""
    return [float(v) if math.isfinite(v) else None for v in values]


@dataclass(frozen=True)
class Counts:
    """One method's line of the ledger; every planned key is in exactly one of
    done / running / failed / left."""

    planned: int = 0
    done: int = 0  # COMPLETE (diverged ones included)
    diverged: int = 0
    running: int = 0
    failed: int = 0  # FAIL after the retry limit or an exception; relaunch re-runs it
    left: int = 0  # not started, waiting, or interrupted (relaunch resumes it)


def current_numbers(trials: Iterable[tuple[str | None, int]]) -> dict[str, int]:
    """Key -> the number of the key's current trial, from ``(key, number)`` pairs: the
    highest-numbered trial of a key is its current one (a re-run gets a fresh trial)."""
    current: dict[str, int] = {}
    for key, number in trials:
        if key is not None and number > current.get(key, -1):
            current[key] = number
    return current


def current_trials(trials: Iterable[FrozenTrial]) -> dict[str, FrozenTrial]:
    """Key -> the key's current trial (``current_numbers``)."""
    trials = list(trials)
    numbers = current_numbers((t.user_attrs.get("key"), t.number) for t in trials)
    by_number = {t.number: t for t in trials}
    return {key: by_number[number] for key, number in numbers.items()}


class KeyStatus(StrEnum):
    """The ledger column of a plan key (``Counts`` has one field per member)."""

    DONE = "done"
    RUNNING = "running"
    FAILED = "failed"
    LEFT = "left"


def key_status(state: str | None, outcome: Any, driver_alive: bool) -> KeyStatus:
    """The ledger column of a plan key: done, running, failed or left, from its
    current trial's state name and ``outcome`` attr (``state=None``: no trial yet).

    A RUNNING trial counts as running only while a driver is alive; otherwise its driver
    died and the key is left for the next launch, like an interrupted one.
    """
    if state is None or state == "WAITING":
        return KeyStatus.LEFT
    if state == "COMPLETE":
        return KeyStatus.DONE
    if state == "RUNNING":
        return KeyStatus.RUNNING if driver_alive else KeyStatus.LEFT
    return KeyStatus.LEFT if outcome == Outcome.INTERRUPTED else KeyStatus.FAILED


def tally(
    keys: Iterable[str], current: Mapping[str, tuple[str | None, Any]], driver_alive: bool
) -> Counts:
    """The ledger line of ``keys``: ``current`` maps a key to its current trial's state name
    and ``outcome`` attr (a key without a trial is missing)."""
    line = dict.fromkeys(Counts.__dataclass_fields__, 0)
    for key in keys:
        state, outcome = current.get(key, (None, None))
        status = key_status(state, outcome, driver_alive)
        line["planned"] += 1
        line[status] += 1
        line["diverged"] += status == KeyStatus.DONE and outcome == Outcome.DIVERGED
    return Counts(**line)


def ledger(
    plan_keys: Sequence[str], trials: Iterable[FrozenTrial], driver_alive: bool
) -> dict[str, Counts]:
    """Per-method counts of the planned keys (method = the key's first part, after the
    ``confirm/`` of a confirmation key)."""
    current = {
        key: (trial.state.name, trial.user_attrs.get("outcome"))
        for key, trial in current_trials(trials).items()
    }
    by_method: dict[str, list[str]] = {}
    for key in plan_keys:
        by_method.setdefault(key.removeprefix("confirm/").split("/")[0], []).append(key)
    return {method: tally(keys, current, driver_alive) for method, keys in by_method.items()}


#: the name optuna-dashboard shows for the study's objective (not "Objective 0")
OBJECTIVE_NAME = "AUC"


def name_objective(study) -> None:
    """Name the study's objective ``OBJECTIVE_NAME`` (Optuna marks this API experimental)."""
    import warnings

    from optuna.exceptions import ExperimentalWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        study.set_metric_names([OBJECTIVE_NAME])


_Method = TypeVar("_Method", bound=Callable[..., Any])


def retried(method: _Method) -> _Method:
    """Run a ``StudyStore`` method again, with growing pauses, while the database is out
    (``is_outage``) and the store's ``grace`` has not run out; then, or at once for any
    other database error, raise ``write_error``'s one-line StorageError."""

    @functools.wraps(method)
    def again(self: StudyStore, *args: Any, **kwargs: Any) -> Any:
        deadline = time.monotonic() + self.grace
        delay = 0.25
        while True:
            try:
                return method(self, *args, **kwargs)
            except Exception as e:
                if not is_database_error(e):
                    raise
                if not is_outage(e) or time.monotonic() + delay > deadline:
                    raise write_error(self.storage.url, e, self.grace) from None
            time.sleep(delay)
            delay = min(2 * delay, RETRY_MAX_DELAY)

    return again  # type: ignore[return-value]


def plan_mismatch(name: str, stored: str, given: str) -> StorageError:
    """The error for a study launched with another plan: two plans in one study would mix
    two budgets."""
    return StorageError(
        f"study {name!r} in this storage was launched with another plan "
        f"(plan_hash {stored[:12]}, this spec gives {given[:12]}): the spec's methods, "
        "budget, seeds or search space changed. Use a new study name, or restore the old spec."
    )


class StudyStore:
    """The driver's handle on one study: every write the sweep makes goes through here.

    A write (and a read of attrs or trials) that meets a database outage is tried again
    for up to ``grace`` seconds (``retried``); a write the database refuses raises a
    one-line StorageError naming the cause and the fix.
    """

    def __init__(
        self, storage: optuna.storages.RDBStorage, study_id: int, grace: float = STORAGE_GRACE
    ) -> None:
        self.storage = storage
        self.study_id = study_id
        self.grace = grace

    # -- study ------------------------------------------------------------------------

    @classmethod
    def find(
        cls, storage: optuna.storages.RDBStorage, name: str, grace: float = STORAGE_GRACE
    ) -> StudyStore | None:
        """The study called ``name``, or None if there is none."""
        try:
            return cls(storage, storage.get_study_id_from_name(name), grace)
        except KeyError:
            return None

    @classmethod
    def open_or_create(
        cls,
        storage: optuna.storages.RDBStorage,
        name: str,
        attrs: Mapping[str, Any],
        grace: float = STORAGE_GRACE,
    ) -> StudyStore:
        """Load study ``name`` or create it with study user attrs ``attrs``.

        ``attrs["plan_hash"]`` must match the stored one: mixing two plans in one study
        would mix two budgets, so a mismatch is a StorageError.
        """
        import optuna
        from optuna.exceptions import DuplicatedStudyError
        from optuna.study import StudyDirection

        store = cls.find(storage, name, grace)
        if store is None:
            try:
                study_id = storage.create_new_study([StudyDirection.MAXIMIZE], name)
                name_objective(optuna.Study(study_name=name, storage=storage))
            except DuplicatedStudyError:  # another driver created it meanwhile
                study_id = storage.get_study_id_from_name(name)
            store = cls(storage, study_id, grace)
        stored = store.attrs
        if "plan_hash" not in stored:  # new, or a creation cut short before its attrs
            if store.trials():
                raise StorageError(
                    f"storage: study {name!r} has trials but no plan_hash: it was not "
                    "written by sweeper; choose another study name"
                )
            for key, value in attrs.items():
                storage.set_study_user_attr(study_id=store.study_id, key=key, value=value)
        elif stored["plan_hash"] != attrs["plan_hash"]:
            raise plan_mismatch(name, stored["plan_hash"], attrs["plan_hash"])
        return store

    @property
    @retried
    def attrs(self) -> dict[str, Any]:
        """The study's user attrs."""
        return self.storage.get_study_user_attrs(self.study_id)

    @retried
    def set_study_attr(self, key: str, value: Any) -> None:
        """Set one study user attr (as the driver only)."""
        self.storage.set_study_user_attr(self.study_id, key, value)

    @retried
    def trials(self) -> list[FrozenTrial]:
        """All trials, oldest first."""
        return self.storage.get_all_trials(self.study_id, deepcopy=False)

    # -- driver lock ------------------------------------------------------------------

    def driver_alive(self, now: float | None = None) -> bool:
        """Whether a live driver holds this study (see ``driver_alive``)."""
        return driver_alive(self.attrs.get("driver"), now)

    @retried
    def claim_driver(self) -> None:
        """Become the study's driver, or raise StudyBusy if another one is alive.

        Reading the driver record, judging it and writing ours is one transaction holding
        the study's lock: otherwise two launches released together both read "no driver"
        and both run the whole plan. The first claim also gives the study its ``study_uid``
        (see ``study_uid``), under the same lock so it is written once.
        """
        with self._locked() as connection:
            driver = _read_study_attr(connection, self.study_id, "driver")
            if driver and not _is_this_process(driver) and driver_alive(driver):
                raise StudyBusy(busy_message(driver))
            _write_study_attr(connection, self.study_id, "driver", _this_driver())
            if _read_study_attr(connection, self.study_id, "study_uid") is None:
                uid = secrets.token_hex(8)
                _write_study_attr(connection, self.study_id, "study_uid", uid)

    @property
    def study_uid(self) -> str:
        """The study's random identity, set by its first driver: its checkpoints are kept
        under it and carry it, so a new database with the same spec resumes none of them."""
        return self.attrs["study_uid"]

    def heartbeat(self) -> None:
        """Record that this driver is alive; StudyBusy if another driver took the study
        over meanwhile (this one looked dead), whose record is then left alone."""
        with self._locked() as connection:
            driver = _read_study_attr(connection, self.study_id, "driver")
            if driver and not _is_this_process(driver):
                raise StudyBusy(busy_message(driver))
            _write_study_attr(connection, self.study_id, "driver", _this_driver())

    def release_driver(self) -> None:
        """Say that no driver runs the study any more (unless another one took it over).

        A database that cannot be written now leaves the record as it is: this process
        ends, and a later launch takes the study over as a dead driver's."""
        try:
            with self._locked() as connection:
                driver = _read_study_attr(connection, self.study_id, "driver")
                if not driver or _is_this_process(driver):
                    _write_study_attr(connection, self.study_id, "driver", None)
        except Exception as e:
            if not is_database_error(e):
                raise

    @contextlib.contextmanager
    def heartbeats(self, interval: float) -> Iterator[Heartbeat]:
        """Beat every ``interval`` s on a thread of its own while the block runs, so a long
        setup (creating thousands of trials) or a slow loop never looks like a dead driver."""
        beat = Heartbeat(self, interval)
        beat.start()
        try:
            yield beat
        finally:
            beat.stop()

    @contextlib.contextmanager
    def _locked(self) -> Iterator[Connection]:
        """A transaction that holds the study's write lock until it commits: SQLite's
        ``BEGIN IMMEDIATE`` (the file's write lock), or the study row ``FOR UPDATE``."""
        from optuna.storages._rdb.models import StudyModel
        from sqlalchemy import select

        engine = self.storage.engine
        with engine.connect() as connection:
            if engine.dialect.name == "sqlite":
                connection.exec_driver_sql("BEGIN IMMEDIATE")
            else:
                studies = StudyModel.__table__
                query = select(studies.c.study_id).where(studies.c.study_id == self.study_id)
                connection.execute(query.with_for_update())
            yield connection
            connection.commit()

    # -- trials -----------------------------------------------------------------------

    def sync(self, entries: Sequence[Any], plan_hash: str) -> list[tuple[Any, FrozenTrial]]:
        """Give every plan entry that is not done a WAITING current trial; return them.

        ``entries`` are ``sweeper.plan.PlanEntry``. Call it only as the study's driver. A
        key whose current trial is FAIL, interrupted, or RUNNING (left by a dead driver)
        gets a fresh trial that lists the old ones in ``supersedes``; the new trials are
        created in one transaction (``add_waiting_many``). Then every trial that is WAITING
        or RUNNING but not its key's current one (a dead driver's, or an orphan of a setup
        or race cut short) is failed as ``interrupted`` with ``superseded_by`` its
        successor, so nothing looks live or pending forever. COMPLETE keys are counted done.
        """
        from optuna.trial import TrialState

        trials = self.trials()
        latest = current_trials(trials)
        by_key: dict[str, list[FrozenTrial]] = {}
        for trial in trials:
            by_key.setdefault(trial.user_attrs.get("key", ""), []).append(trial)
        fresh = []
        for entry in entries:
            current = latest.get(entry.key)
            if current is None or current.state not in (TrialState.COMPLETE, TrialState.WAITING):
                attrs = {
                    "method": entry.method,
                    "config_id": entry.config_id,
                    "seed": entry.seed,
                    "key": entry.key,
                    "stage": getattr(entry, "stage", "search"),
                    "plan_hash": plan_hash,
                    "attempts": 0,
                }
                if entry.key in by_key:
                    attrs["supersedes"] = sorted(t.number for t in by_key[entry.key])
                fresh.append((entry, attrs))
        created = self.add_waiting_many([(e.params, e.choices, attrs) for e, attrs in fresh])
        latest.update({e.key: trial for (e, _), trial in zip(fresh, created, strict=True)})
        live = (TrialState.RUNNING, TrialState.WAITING)
        todo = []
        for entry in entries:
            current = latest[entry.key]
            for trial in by_key.get(entry.key, []):
                if trial.number != current.number and trial.state in live:
                    running = trial.state == TrialState.RUNNING
                    why = (
                        "its driver stopped" if running else "a newer trial of its key replaced it"
                    )
                    self.interrupt(trial._trial_id, why, current.number)
            if current.state != TrialState.COMPLETE:
                todo.append((entry, current))
        for trial in by_key.get("", []):  # not ours; it would look live or pending forever
            if trial.state in live:
                self.interrupt(trial._trial_id, "it has no plan key", None)
        return todo

    def interrupt(self, trial_id: int, why: str, successor: int | None) -> None:
        """FAIL a RUNNING trial as ``interrupted`` (its key is re-run, from its checkpoint)."""
        attrs: dict[str, Any] = {"outcome": Outcome.INTERRUPTED, "error": f"interrupted: {why}"}
        if successor is not None:
            attrs["superseded_by"] = successor
        self.fail(trial_id, attrs)

    @retried
    def add_waiting(
        self,
        params: Mapping[str, Any],
        choices: Mapping[str, Sequence[Any]],
        user_attrs: Mapping[str, Any],
    ) -> FrozenTrial:
        """Create a WAITING trial with its params and user attrs in one transaction."""
        from optuna.distributions import CategoricalDistribution
        from optuna.trial import FrozenTrial, TrialState

        template = FrozenTrial(
            number=-1,
            state=TrialState.WAITING,
            value=None,
            values=None,
            datetime_start=None,
            datetime_complete=None,
            params=dict(params),
            distributions={k: CategoricalDistribution(tuple(choices[k])) for k in params},
            user_attrs=dict(user_attrs),
            system_attrs={},
            intermediate_values={},
            trial_id=-1,
        )
        trial_id = self.storage.create_new_trial(self.study_id, template_trial=template)
        return self.storage.get_trial(trial_id)

    @retried
    def add_waiting_many(
        self,
        trials: Sequence[tuple[Mapping[str, Any], Mapping[str, Sequence[Any]], Mapping[str, Any]]],
    ) -> list[FrozenTrial]:
        """Create WAITING trials, each ``(params, choices, user_attrs)`` as ``add_waiting``
        takes them, in one transaction: thousands in seconds where Optuna's one trial per
        call takes ~30 ms each, and an interrupted setup leaves all of them or none.

        The rows are Optuna's own (its tables, its JSON), numbered as Optuna numbers them.
        """
        from optuna.distributions import CategoricalDistribution, distribution_to_json
        from optuna.storages._rdb.models import (
            TrialModel,
            TrialParamModel,
            TrialUserAttributeModel,
        )
        from optuna.trial import TrialState
        from sqlalchemy import func, insert, select

        if not trials:
            return []
        table = TrialModel.__table__
        distributions: dict[tuple[Any, ...], tuple[CategoricalDistribution, str]] = {}
        with self._locked() as connection:
            count = select(func.count()).where(table.c.study_id == self.study_id)
            first = connection.execute(count).scalar_one()
            rows = [
                {"number": first + i, "study_id": self.study_id, "state": TrialState.WAITING}
                for i in range(len(trials))
            ]
            returning = table.c.trial_id
            ids = (
                connection.execute(
                    insert(table).returning(returning, sort_by_parameter_order=True), rows
                )
                .scalars()
                .all()
            )
            params, attrs = [], []
            for trial_id, (values, choices, user_attrs) in zip(ids, trials, strict=True):
                for name, value in values.items():
                    key = tuple(choices[name])
                    if key not in distributions:
                        distribution = CategoricalDistribution(key)
                        distributions[key] = (distribution, distribution_to_json(distribution))
                    distribution, text = distributions[key]
                    params.append({
                        "trial_id": trial_id,
                        "param_name": name,
                        "param_value": distribution.to_internal_repr(value),
                        "distribution_json": text,
                    })  # fmt: skip
                attrs += [
                    {"trial_id": trial_id, "key": key, "value_json": json.dumps(value)}
                    for key, value in user_attrs.items()
                ]
            if params:
                connection.execute(insert(TrialParamModel.__table__), params)
            if attrs:
                connection.execute(insert(TrialUserAttributeModel.__table__), attrs)
        made = {trial._trial_id: trial for trial in self.trials()}
        return [made[trial_id] for trial_id in ids]

    @retried
    def start(self, trial_id: int) -> None:
        """WAITING -> RUNNING."""
        from optuna.trial import TrialState

        if not self.storage.set_trial_state_values(trial_id, TrialState.RUNNING):
            raise StorageError(f"trial {trial_id} was started by someone else")

    @retried
    def set_attrs(self, trial_id: int, attrs: Mapping[str, Any]) -> None:
        """Set user attrs of a trial that is not finished."""
        for key, value in attrs.items():
            self.storage.set_trial_user_attr(trial_id, key, value)

    @retried
    def report(self, trial_id: int, points: Mapping[int, float]) -> None:
        """Intermediate values ``step -> success_rate`` (re-writing a step overwrites it)."""
        for step, value in points.items():
            self.storage.set_trial_intermediate_value(trial_id, int(step), float(value))

    @retried
    def complete(self, trial_id: int, value: float, attrs: Mapping[str, Any]) -> None:
        """Set ``attrs``, then COMPLETE with objective ``value``."""
        from optuna.trial import TrialState

        self.set_attrs(trial_id, attrs)
        self.storage.set_trial_state_values(trial_id, TrialState.COMPLETE, [float(value)])

    @retried
    def fail(self, trial_id: int, attrs: Mapping[str, Any]) -> None:
        """Set ``attrs``, then FAIL."""
        from optuna.trial import TrialState

        self.set_attrs(trial_id, attrs)
        self.storage.set_trial_state_values(trial_id, TrialState.FAIL)


class Heartbeat:
    """The driver's heartbeat on a thread and database connection of its own
    (``StudyStore.heartbeats``). A beat that finds another driver's record (this one was
    judged dead and taken over) stops beating; ``check`` then raises its StudyBusy, so
    the driver stops instead of running the plan a second time. A database error skips
    one beat: the next one, ``interval`` s later, tries again."""

    def __init__(self, store: StudyStore, interval: float) -> None:
        self._store, self._interval = store, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sweeper-heartbeat", daemon=True)
        self.error: StudyBusy | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def check(self) -> None:
        """Raise StudyBusy if another driver has taken the study over."""
        if self.error is not None:
            raise self.error

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            try:
                self._store.heartbeat()
            except StudyBusy as e:
                self.error = e
                return
            except Exception:  # an outage: the next beat retries
                continue


def driver_alive(driver: Mapping[str, Any] | None, now: float | None = None) -> bool:
    """Whether the ``driver`` record names a live driver.

    On this host the process decides: alive while its pid runs and, when the record has
    its start time, is the same process (a pid is reused after a reboot or wrap-around),
    however old the heartbeat. On another host (or for a record without a start time)
    the heartbeat decides: younger than ``DRIVER_STALE_SECONDS``.
    """
    if not driver:
        return False
    now = time.time() if now is None else now
    fresh = now - float(driver.get("heartbeat", 0)) <= DRIVER_STALE_SECONDS
    if driver.get("host") != socket.gethostname():
        return fresh
    pid = int(driver["pid"])
    if not _pid_alive(pid):
        return False
    if driver.get("started") is None:
        return fresh
    started = process_start(pid)
    return started is None or started == driver["started"]


def process_start(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot, from /proc), None if unknown:
    with the pid it names one process for good."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # field 22; the name may hold spaces


def busy_message(driver: Mapping[str, Any]) -> str:
    """Why a launch cannot drive the study now, and what to do."""
    return (
        f"another `sweeper launch` drives this study (host {driver.get('host')}, "
        f"pid {driver.get('pid')}); stop it first, or wait {DRIVER_STALE_SECONDS:.0f} s "
        "after it died on another host"
    )


def _this_driver() -> dict[str, Any]:
    pid = os.getpid()
    return {
        "host": socket.gethostname(),
        "pid": pid,
        "started": process_start(pid),
        "heartbeat": time.time(),
    }


def _is_this_process(driver: Mapping[str, Any]) -> bool:
    return driver.get("host") == socket.gethostname() and driver.get("pid") == os.getpid()


def _read_study_attr(connection: Connection, study_id: int, key: str) -> Any:
    """A study user attr read inside ``connection``'s transaction (None if unset)."""
    from optuna.storages._rdb.models import StudyUserAttributeModel
    from sqlalchemy import select

    table = StudyUserAttributeModel.__table__
    query = select(table.c.value_json).where(table.c.study_id == study_id, table.c.key == key)
    value = connection.execute(query).scalar_one_or_none()
    return None if value is None else json.loads(value)


def _write_study_attr(connection: Connection, study_id: int, key: str, value: Any) -> None:
    """Set a study user attr inside ``connection``'s transaction, as Optuna stores it."""
    from optuna.storages._rdb.models import StudyUserAttributeModel

    table = StudyUserAttributeModel.__table__
    where = (table.c.study_id == study_id) & (table.c.key == key)
    text = json.dumps(value)
    if connection.execute(table.update().where(where).values(value_json=text)).rowcount == 0:
        connection.execute(table.insert().values(study_id=study_id, key=key, value_json=text))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
