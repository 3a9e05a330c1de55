"""The study's one writer, the sweep driver: ``StudyStore`` and the driver's claim.

``StudyStore`` is the driver's handle on one study (readers get one from
``sweeper.storage._open.open_study`` too, and only read): creating the study, claiming it as its
one driver in a transaction that holds the study's lock, the ``Heartbeat`` thread that
keeps the claim fresh, ``sync`` (a WAITING current trial for every plan key not done, in
one transaction), and every trial's start, reports, completion or failure. A write that
meets a database outage is tried again for up to ``grace`` seconds (``retried``). A driver
record is judged live by ``driver_alive``: on its host by its process, elsewhere by its
heartbeat.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import secrets
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from agent.config import Outcome
from sweeper.storage._attrs import SYSTEM_ATTRS, shown
from sweeper.storage._errors import (
    RESUME,
    StorageError,
    StudyBusy,
    check_plan,
    is_database_error,
    is_outage,
    write_error,
)
from sweeper.storage._ledger import current_trials
from sweeper.storage._params import FIXED_PARAMS_ATTR, fixed_params, method_choices, registered

if TYPE_CHECKING:  # optuna and sqlalchemy are imported where used: `sweeper --help` stays light
    import optuna
    from optuna.trial import FrozenTrial
    from sqlalchemy.engine import Connection

    from sweeper.storage._migrate import Upgrade

#: a driver whose heartbeat is older than this is considered dead
DRIVER_STALE_SECONDS = 60.0
#: seconds the driver retries a write while the database is unreachable (the default of
#: the spec's ``execution.storage_grace``)
STORAGE_GRACE = 60.0
#: the longest wait between two tries of a write during an outage
RETRY_MAX_DELAY = 5.0


def json_safe(values: Iterable[float]) -> list[float | None]:
    """Floats with NaN/inf as None: user attrs are JSON, and the dashboard's parser rejects NaN."""
    return [float(v) if math.isfinite(v) else None for v in values]


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
_T = TypeVar("_T")


def retry_outages(call: Callable[[], _T], url: str, grace: float, then: str = RESUME) -> _T:
    """``call()``, run again with growing pauses while the database ``url`` is out
    (``is_outage``) and ``grace`` s have not run out; then, or at once for any other
    database error, ``write_error``'s one-line StorageError (``then``: what to do once the
    cause is fixed). Opening a study and every ``StudyStore`` write go through here."""
    deadline = time.monotonic() + grace
    delay = 0.25
    while True:
        try:
            return call()
        except Exception as e:
            if not is_database_error(e):
                raise
            if not is_outage(e) or time.monotonic() + delay > deadline:
                raise write_error(url, e, grace, then) from None
        time.sleep(delay)
        delay = min(2 * delay, RETRY_MAX_DELAY)


def retried(method: _Method) -> _Method:
    """A ``StudyStore`` method retried through an outage for the store's ``grace``
    (``retry_outages``)."""

    @functools.wraps(method)
    def again(self: StudyStore, *args: Any, **kwargs: Any) -> Any:
        return retry_outages(lambda: method(self, *args, **kwargs), self.storage.url, self.grace)

    return again  # type: ignore[return-value]


class StudyStore:
    """The driver's handle on one study: every write the sweep makes goes through here.

    A write (and a read of attrs or trials) that meets a database outage is tried again
    for up to ``grace`` seconds (``retried``); a write the database refuses raises a
    one-line StorageError naming the cause and the fix.
    """

    def __init__(
        self,
        storage: optuna.storages.RDBStorage,
        study_id: int,
        grace: float = STORAGE_GRACE,
    ) -> None:
        self.storage = storage
        self.study_id = study_id
        self.grace = grace

    # -- study ------------------------------------------------------------------------

    @classmethod
    def find(
        cls,
        storage: optuna.storages.RDBStorage,
        name: str,
        grace: float = STORAGE_GRACE,
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
        if stored.get("plan_hash") is None:  # new, or a creation cut short before its attrs
            if store.trials():
                raise StorageError(
                    f"storage: study {name!r} has trials but no plan_hash: it was not "
                    "written by sweeper; choose another study name"
                )
            for key, value in attrs.items():
                storage.set_study_user_attr(study_id=store.study_id, key=key, value=value)
        else:
            check_plan(name, stored, attrs["plan_hash"])
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

    def upgrade(self) -> Upgrade:
        """Rewrite the trials recorded in an older format in today's
        (``sweeper.storage._migrate``), in one transaction holding the study's lock;
        StudyBusy while a driver runs the study (it writes in the format its code knows:
        ``sweeper publish`` upgrades its copy, which no driver runs)."""
        from sweeper.storage._migrate import rewrite

        with self._locked() as connection:
            driver = _read_study_attr(connection, self.study_id, "driver")
            if driver_alive(driver):
                raise StudyBusy(busy_message(driver))
            fixed = _read_study_attr(connection, self.study_id, FIXED_PARAMS_ATTR) or {}
            plan = _read_study_attr(connection, self.study_id, "plan") or []
            done = rewrite(connection, self.study_id, fixed, [k.split("/")[0] for k in plan])
            if done.fixed != fixed:
                _write_study_attr(connection, self.study_id, FIXED_PARAMS_ATTR, done.fixed)
        return done

    # -- trials -----------------------------------------------------------------------

    def sync(self, entries: Sequence[Any], plan_hash: str) -> list[tuple[Any, FrozenTrial]]:
        """Give every plan entry that is not done a WAITING current trial; return them.

        ``entries`` are ``sweeper.plan._entries.PlanEntry``. Call it only as the study's driver. A
        key whose current trial is FAIL, interrupted, or RUNNING (left by a dead driver)
        gets a fresh trial that lists the old ones in ``supersedes``; the new trials are
        created in one transaction (``add_waiting_many``). Then every trial that is WAITING
        or RUNNING but not its key's current one (a dead driver's, or an orphan of a setup
        or race cut short) is failed as ``interrupted`` with ``superseded_by`` its
        successor, so nothing looks live or pending forever. COMPLETE and PRUNED keys are
        counted done.
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
            if current is None or current.state not in (
                TrialState.COMPLETE,
                TrialState.PRUNED,
                TrialState.WAITING,
            ):
                attrs = {
                    "method": entry.method,
                    "config_id": entry.config_id,
                    "seed": entry.seed,
                    "key": entry.key,
                    "stage": getattr(entry, "stage", "search"),
                    "plan_hash": plan_hash,
                    "precision": entry.trial_config.precision,
                    "attempts": 0,
                }
                if entry.key in by_key:
                    attrs["supersedes"] = sorted(t.number for t in by_key[entry.key])
                fresh.append((entry, attrs))
        created = self.add_waiting_many(self._registered(entries, fresh))
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
            if current.state not in (TrialState.COMPLETE, TrialState.PRUNED):
                todo.append((entry, current))
        for trial in by_key.get("", []):  # not ours; it would look live or pending forever
            if trial.state in live:
                self.interrupt(trial._trial_id, "it has no plan key", None)
        return todo

    def _registered(
        self, entries: Sequence[Any], fresh: Sequence[tuple[Any, Mapping[str, Any]]]
    ) -> list[tuple[dict[str, Any], dict[str, tuple[Any, ...]], Mapping[str, Any]]]:
        """The ``(params, choices, user_attrs)`` the ``fresh`` entries' trials are created
        with (``sweeper.storage._params``: the params that vary and ``method``), after the
        constant ones are kept in the study attr ``fixed_params`` (merged with what is
        there, so a stage with fewer methods drops none)."""
        if not fresh:
            return []
        stored = self.attrs
        fixed = fixed_params((e.params, e.choices) for e in entries)
        known = stored.get(FIXED_PARAMS_ATTR) or {}
        if {**known, **fixed} != known:
            self.set_study_attr(FIXED_PARAMS_ATTR, dict(sorted({**known, **fixed}.items())))
        planned = [key.split("/")[0] for key in stored.get("plan") or []]
        methods = method_choices([*planned, *(e.method for e in entries)])
        return [(*registered(e.params, e.choices, e.method, methods), attrs) for e, attrs in fresh]

    def interrupt(self, trial_id: int, why: str, successor: int | None) -> None:
        """FAIL a RUNNING trial as ``interrupted`` (its key is re-run, from its checkpoint)."""
        attrs: dict[str, Any] = {
            "outcome": Outcome.INTERRUPTED,
            "error": f"interrupted: {why}",
        }
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
                {
                    "number": first + i,
                    "study_id": self.study_id,
                    "state": TrialState.WAITING,
                }
                for i in range(len(trials))
            ]
            returning = table.c.trial_id
            ids = (
                connection.execute(
                    insert(table).returning(returning, sort_by_parameter_order=True),
                    rows,
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
                        distributions[key] = (
                            distribution,
                            distribution_to_json(distribution),
                        )
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
        """Set attrs of a trial that is not finished: user attrs, but ``SYSTEM_ATTRS`` as
        system attrs, each with a user attr in words under its key (``shown``: what the
        trial's page shows; ``sweeper.storage._attrs.trial_attr`` reads the value)."""
        for key, value in attrs.items():
            if key in SYSTEM_ATTRS:
                self.storage.set_trial_system_attr(trial_id, key, value)
                if (words := shown(key, value)) is not None:
                    self.storage.set_trial_user_attr(trial_id, key, words)
            else:
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
    def prune(self, trial_id: int, attrs: Mapping[str, Any]) -> None:
        """Set ``attrs``, then PRUNED: stopped at a rung of successive halving."""
        from optuna.trial import TrialState

        self.set_attrs(trial_id, attrs)
        self.storage.set_trial_state_values(trial_id, TrialState.PRUNED)

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
