"""The study database: one Optuna study per spec, written only by the sweep driver.

What a study holds: docs/contracts.md, "Storage conventions". One private module per job:

- ``_urls``: database URLs, their checks, and the one place that says how a URL is
  connected to, for the writer and readers alike (``engine_arguments``, ``open_engine``:
  SQLite in WAL mode with a long busy timeout; readers' connections read-only);
- ``_open``: ``open_study``, every open of a study (the writer's ``StudyStore`` or a
  read-only reader), and ``read_rows``, a study's tables read in one query each;
- ``_errors``: ``StorageError``, ``StudyBusy``, which database errors are outages and which
  say the file is damaged, and the one-line message of each;
- ``_provenance``: the code's revision and the package versions a study records;
- ``_attrs``: which trial attrs are Optuna system attrs (the curve, the worker, machines,
  videos, the encoder's fit, worker deaths), what the trial's page shows of them in words,
  and ``trial_attr``, which reads them back, from studies written before too;
- ``_params``: which of a plan entry's parameters become Optuna params;
- ``_ledger``: the ledger rules, pure functions over (key, state, outcome): a key's current
  trial, its ledger column, the per-method counts, the keys done;
- ``_writer``: ``StudyStore`` (the driver's claim, heartbeats, sync and trial writes, each
  retried through an outage), ``Heartbeat``, and whether a driver record is alive;
- ``_migrate``: the rewrite of trials recorded in an older format in today's
  (``StudyStore.upgrade``, run by ``sweeper publish`` on its copy);
- ``_artifacts``: where a study's videos live and their upload.

The public names are re-exported here; a module constant (``DRIVER_STALE_SECONDS``,
``SQLITE_TIMEOUT``...) is read in its own module, so a test that changes one sets it there.
"""

from sweeper.storage._artifacts import (
    ArtifactStore,
    artifact_location,
    artifacts_in,
    trial_artifacts,
    upload_once,
)
from sweeper.storage._attrs import (
    CURVE_ATTR,
    SYSTEM_ATTRS,
    curve_of,
    describe_machine,
    trial_attr,
)
from sweeper.storage._errors import (
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
from sweeper.storage._ledger import (
    DONE_STATES,
    Counts,
    KeyStatus,
    current_numbers,
    current_trials,
    finished,
    key_status,
    ledger,
    measured_seconds,
    tally,
)
from sweeper.storage._migrate import Upgrade
from sweeper.storage._open import (
    NoStudy,
    StudyRows,
    open_for_reading,
    open_study,
    read_rows,
    stored_files,
)
from sweeper.storage._params import FIXED_PARAMS_ATTR, METHOD_PARAM, applies_to
from sweeper.storage._provenance import (
    VERSIONED_PACKAGES,
    code_revision,
    package_versions,
)
from sweeper.storage._urls import (
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
from sweeper.storage._writer import (
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
    "FIXED_PARAMS_ATTR",
    "METHOD_PARAM",
    "OBJECTIVE_NAME",
    "RETRY_MAX_DELAY",
    "SQLITE_TIMEOUT",
    "STORAGE_GRACE",
    "SYSTEM_ATTRS",
    "VERSIONED_PACKAGES",
    "ArtifactStore",
    "Counts",
    "Heartbeat",
    "KeyStatus",
    "NoStudy",
    "StorageError",
    "StudyBusy",
    "StudyRows",
    "StudyStore",
    "Upgrade",
    "applies_to",
    "artifact_location",
    "artifacts_in",
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
    "finished",
    "is_damaged",
    "is_database_error",
    "is_outage",
    "json_safe",
    "key_status",
    "ledger",
    "measured_seconds",
    "name_objective",
    "open_engine",
    "open_for_reading",
    "open_storage",
    "open_study",
    "package_versions",
    "process_start",
    "read_only_engine_kwargs",
    "read_rows",
    "reason_of",
    "redact",
    "resolve_url",
    "retried",
    "retry_outages",
    "sqlite_path",
    "stored_files",
    "tally",
    "trial_artifacts",
    "trial_attr",
    "upload_once",
    "write_error",
]
