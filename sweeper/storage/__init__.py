"""The study database: one Optuna study per spec, written only by the sweep driver.

Conventions: docs/architecture.md, "Storage conventions". One file per job:

- ``urls``: database URLs, their checks, and the one place that says how a URL is
  connected to, for the writer and readers alike (``engine_arguments``, ``open_engine``:
  SQLite in WAL mode with a long busy timeout; readers' connections read-only);
- ``errors``: ``StorageError``, ``StudyBusy``, which database errors are outages and which
  say the file is damaged, and the one-line message of each;
- ``provenance``: the code's revision and the package versions a study records;
- ``attrs``: which trial attrs are Optuna system attrs (the curve, the worker, machines,
  videos, the encoder's fit, worker deaths), what the trial's page shows of them in words,
  and ``trial_attr``, which reads them back, from studies written before too;
- ``ledger``: the ledger rules, pure functions over (key, state, outcome): a key's current
  trial, its ledger column, the per-method counts;
- ``writer``: ``StudyStore`` (the driver's claim, heartbeats, sync and trial writes, each
  retried through an outage), ``Heartbeat``, and whether a driver record is alive;
- ``migrate``: the rewrite of trials recorded in an older format in today's
  (``StudyStore.upgrade``, run by ``sweeper publish`` on its copy).

Opening a study (for the driver or a reader) is ``sweeper.study.open_study``. The names
are re-exported here; a module constant (``DRIVER_STALE_SECONDS``, ``SQLITE_TIMEOUT``...)
is read in its own module, so a test that changes one sets it there.
"""

from sweeper.storage.attrs import (
    CURVE_ATTR,
    SYSTEM_ATTRS,
    curve_of,
    describe_machine,
    trial_attr,
)
from sweeper.storage.errors import (
    StorageError,
    StudyBusy,
    check_plan,
    damaged_error,
    database_cause,
    database_error,
    is_damaged,
    is_database_error,
    is_outage,
    reason_of,
    redact,
    write_error,
)
from sweeper.storage.ledger import (
    DONE_STATES,
    Counts,
    KeyStatus,
    current_numbers,
    current_trials,
    key_status,
    ledger,
    tally,
)
from sweeper.storage.provenance import (
    VERSIONED_PACKAGES,
    code_revision,
    package_versions,
)
from sweeper.storage.urls import (
    SQLITE_TIMEOUT,
    check_intact,
    check_storage,
    check_writable,
    connect_read_only,
    damage,
    engine_arguments,
    open_engine,
    open_storage,
    read_only_engine_kwargs,
    resolve_url,
    sqlite_path,
)
from sweeper.storage.writer import (
    DRIVER_STALE_SECONDS,
    OBJECTIVE_NAME,
    RETRY_MAX_DELAY,
    STORAGE_GRACE,
    Heartbeat,
    StudyStore,
    busy_message,
    driver_alive,
    json_safe,
    name_objective,
    process_start,
    retried,
    retry_outages,
)

__all__ = [
    "CURVE_ATTR",
    "DONE_STATES",
    "DRIVER_STALE_SECONDS",
    "OBJECTIVE_NAME",
    "RETRY_MAX_DELAY",
    "SQLITE_TIMEOUT",
    "STORAGE_GRACE",
    "SYSTEM_ATTRS",
    "VERSIONED_PACKAGES",
    "Counts",
    "Heartbeat",
    "KeyStatus",
    "StorageError",
    "StudyBusy",
    "StudyStore",
    "busy_message",
    "check_intact",
    "check_plan",
    "check_storage",
    "check_writable",
    "code_revision",
    "connect_read_only",
    "current_numbers",
    "current_trials",
    "curve_of",
    "damage",
    "damaged_error",
    "database_cause",
    "database_error",
    "describe_machine",
    "driver_alive",
    "engine_arguments",
    "is_damaged",
    "is_database_error",
    "is_outage",
    "json_safe",
    "key_status",
    "ledger",
    "name_objective",
    "open_engine",
    "open_storage",
    "package_versions",
    "process_start",
    "read_only_engine_kwargs",
    "reason_of",
    "redact",
    "resolve_url",
    "retried",
    "retry_outages",
    "sqlite_path",
    "tally",
    "trial_attr",
    "write_error",
]
