"""sweeper.storage: URLs, SQLite under a concurrent reader, PostgreSQL, the keyed ledger."""

from __future__ import annotations

import json
import os
import socket
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass, field

import optuna
import pytest
from conftest import wait_until
from optuna.trial import TrialState

from agent.config import TrialConfig
from sweeper.storage import (
    DRIVER_STALE_SECONDS,
    Counts,
    StorageError,
    StudyBusy,
    StudyStore,
    check_storage,
    current_trials,
    curve_of,
    database_error,
    is_database_error,
    is_outage,
    ledger,
    open_storage,
    process_start,
    resolve_url,
    trial_attr,
)

optuna.logging.set_verbosity(optuna.logging.WARNING)


@dataclass(frozen=True)
class Entry:
    """The part of sweeper.plan._entries.PlanEntry the store reads."""

    method: str
    config_id: int
    seed: int
    params: dict = field(default_factory=lambda: {"lr": 1e-3})
    choices: dict = field(default_factory=lambda: {"lr": (1e-3, 1e-4)})
    trial_config: TrialConfig = field(default_factory=TrialConfig)

    @property
    def key(self) -> str:
        return f"{self.method}/{self.config_id}/{self.seed}"


ENTRIES = [Entry(m, c, 0) for m in ("pixel", "vae") for c in range(2)]


@pytest.fixture
def sqlite_url(tmp_path):
    return f"sqlite:///{tmp_path / 'sub' / 'study.db'}"


def test_database_error_is_one_line_without_the_password():
    class Wrapped(Exception):  # as SQLAlchemy wraps the driver's error
        orig = OSError("connection refused\n\tIs the server running?")

    error = database_error("cannot read", "postgresql://u:secret@h/db", Wrapped("long text"))
    assert isinstance(error, StorageError)
    assert str(error) == "storage: cannot read postgresql://u:***@h/db: connection refused"
    assert str(database_error("cannot connect to", "sqlite:///x.db", KeyError())) == (
        "storage: cannot connect to sqlite:///x.db: KeyError"
    )


def test_resolve_url_uses_psycopg3_for_postgresql():
    assert resolve_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"
    assert resolve_url("postgresql+psycopg://u@h/db") == "postgresql+psycopg://u@h/db"
    assert resolve_url("sqlite:///a.db") == "sqlite:///a.db"


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("sqlite:///:memory:", "in-memory"),
        ("postgresql://postgres@127.0.0.1:1/test", "cannot connect"),
        ("postgresql://postgres@127.0.0.1:5432/no_such_db_xyz", 'database "no_such_db_xyz"'),
        ("nosuchdialect://x/y", "cannot use"),
    ],
)
def test_check_storage_names_the_field(url, message):
    with pytest.raises(StorageError, match="storage") as info:
        check_storage(url)
    assert message in str(info.value)


def test_check_storage_writes_nothing(tmp_path):
    check_storage(f"sqlite:///{tmp_path / 'a' / 'b' / 'study.db'}")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(StorageError, match="not a file"):
        check_storage(f"sqlite:///{tmp_path / 'dir.db'}")


READER = """
import json, os, sys, time
import optuna
storage = optuna.storages.RDBStorage(sys.argv[1], skip_compatibility_check=True,
                                     skip_table_creation=True)  # as optuna-dashboard opens it
reads, errors = 0, []
while not os.path.exists(sys.argv[2]):
    try:
        for study in storage.get_all_studies():
            storage.get_all_trials(study._study_id)
            storage.get_study_user_attrs(study._study_id)
        reads += 1
        if reads == 1:
            open(sys.argv[3], "w").close()  # reading: the writer may start
    except Exception as e:
        errors.append(repr(e))
print(json.dumps({"reads": reads, "errors": errors[:3], "n_errors": len(errors)}))
"""


def test_sqlite_no_lost_write_with_a_dashboard_reading(sqlite_url, tmp_path):
    """The driver's writes all land while another process reads the file in a loop."""
    storage = open_storage(sqlite_url)
    path = tmp_path / "sub" / "study.db"
    assert sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store = StudyStore.open_or_create(storage, "hammer", {"plan_hash": "h"})
    stop, ready = tmp_path / "stop", tmp_path / "ready"
    reader = subprocess.Popen(
        [sys.executable, "-c", READER, sqlite_url, str(stop), str(ready)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        # the reader imports optuna first; write only once it is reading, so they overlap
        wait_until(lambda: ready.exists() or reader.poll() is not None, 120, "the reader")
        assert ready.exists(), "the reader process never read the study"
        numbers = []
        for trial_number in range(4):
            trial = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": f"m/{trial_number}/0"})
            store.start(trial._trial_id)
            curve = {"step": [], "success_rate": []}
            for step in range(60):  # one write pair per report, as the driver does
                store.report(trial._trial_id, {step * 10: step / 100})
                curve["step"].append(step * 10)
                curve["success_rate"].append(step / 100)
                store.set_attrs(trial._trial_id, {"curve": curve})
            store.complete(trial._trial_id, 0.5 + trial_number, {"outcome": "completed"})
            numbers.append(trial.number)
    finally:
        stop.touch()
        out, _ = reader.communicate(timeout=60)
    result = json.loads(out)
    assert result["n_errors"] == 0, result["errors"]
    assert result["reads"] > 10
    trials = StudyStore.find(open_storage(sqlite_url), "hammer").trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 4
    assert [t.value for t in trials] == [0.5, 1.5, 2.5, 3.5]
    for trial in trials:
        assert trial.intermediate_values == {s * 10: s / 100 for s in range(60)}
        assert curve_of(trial)["step"] == [s * 10 for s in range(60)]


def test_the_curve_is_a_system_attr_and_an_older_user_attr_curve_still_reads(sqlite_url):
    """The driver's curve goes to the trial's system attrs (optuna-dashboard's trial table
    does not show them); a trial written before, with the curve as a user attr, still
    reads, for ``curve_of`` and for aggregate's ``read_rows``."""
    from sweeper.storage._open import read_rows

    store = StudyStore.open_or_create(open_storage(sqlite_url), "curves", {"plan_hash": "h"})
    curves = [{"step": [0, 10], "success_rate": [0.0, float(n)]} for n in range(2)]
    new = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": "m/0/0"})
    store.start(new._trial_id)
    store.set_attrs(new._trial_id, {"curve": curves[0], "outcome": "here"})
    old = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": "m/1/0"})
    store.storage.set_trial_user_attr(old._trial_id, "curve", curves[1])  # as written before
    new, old = store.trials()
    assert "curve" not in new.user_attrs and new.user_attrs["outcome"] == "here"
    assert [curve_of(new), curve_of(old)] == curves
    rows = read_rows(sqlite_url, "curves").system_attrs
    assert rows["trial_id"].tolist() == [new._trial_id] and rows["key"].tolist() == ["curve"]
    assert json.loads(rows["value_json"][0]) == curves[0]


def test_machine_readable_attrs_are_system_attrs_with_words_for_the_trial_page(sqlite_url):
    """The worker, machines, videos, encoder fit and worker deaths are system attrs (what
    ``trial_attr`` and ``read_rows`` read), each with a user attr in words under its key
    (what optuna-dashboard's trial page shows: no JSON to parse); a trial written before,
    with them as user attrs, reads the same."""
    from sweeper.results._frame import load_study_frame
    from sweeper.storage._open import read_rows

    store = StudyStore.open_or_create(open_storage(sqlite_url), "words", {"plan_hash": "h"})
    machine = {"cpu": "GenuineIntel 6 85", "cpu_name": "Xeon", "kernels": "AVX2"}
    attrs = {
        "worker": {"node": "10.0.0.2", "pid": 4242},
        "machines": [{"from_step": 0, **machine, "torch": "2.13.0+cpu"}],
        "videos": {"episode-step300.mp4": "0f1e"},
        "encoder_fit": {"latent_dim": 8, "active_dims": 3, "kl": 0.123456},
        "worker_deaths": ["ActorDiedError: gone", "no answer in 60 s"],
    }
    new = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": "vae/0/0", "method": "vae"})
    store.start(new._trial_id)
    store.set_attrs(new._trial_id, attrs)
    old = store.add_waiting({"lr": 1e-3}, {"lr": (1e-3,)}, {"key": "vae/1/0", "method": "vae"})
    for key, value in attrs.items():  # as written before
        store.storage.set_trial_user_attr(old._trial_id, key, value)
    new, old = store.trials()
    assert {key: trial_attr(new, key) for key in attrs} == attrs
    assert {key: trial_attr(old, key) for key in attrs} == attrs
    assert new.user_attrs == {
        "key": "vae/0/0",
        "method": "vae",
        "worker": "pid 4242 on 10.0.0.2",
        "machines": "from step 0: Xeon (GenuineIntel 6 85), kernels AVX2, torch 2.13.0+cpu",
        "videos": "episode-step300.mp4 (the trial's artifacts)",
        "encoder_fit": "latent_dim 8, active_dims 3, kl 0.1235",
        "worker_deaths": "ActorDiedError: gone; no answer in 60 s",
    }
    rows = read_rows(sqlite_url, "words").system_attrs
    assert sorted(rows["key"]) == sorted(attrs) and set(rows["trial_id"]) == {new._trial_id}
    frame = load_study_frame(sqlite_url, "words").drop_duplicates("trial")
    assert frame["fit_active_dims"].tolist() == [3, 3]  # read from both
    assert frame["fit_kl"].tolist() == pytest.approx([0.123456] * 2)


def _lifecycle(url: str) -> None:
    """Create, run, reap, resume: what a driver and a relaunch do, against ``url``."""
    storage = open_storage(url)
    store = StudyStore.open_or_create(storage, "life", {"plan_hash": "h1", "plan": ["..."]})
    todo = store.sync(ENTRIES, "h1")
    assert [entry.key for entry, _ in todo] == [e.key for e in ENTRIES]
    assert all(trial.state == TrialState.WAITING for _, trial in todo)
    assert store.sync(ENTRIES, "h1") == [(e, t) for e, t in todo]  # idempotent
    ids = {entry.key: trial._trial_id for entry, trial in todo}
    for key in ("pixel/0/0", "pixel/1/0", "vae/0/0"):
        store.start(ids[key])
    store.report(ids["pixel/0/0"], {0: 0.0, 100: 1.0})
    store.complete(ids["pixel/0/0"], 0.5, {"outcome": "completed"})
    store.fail(ids["pixel/1/0"], {"outcome": "failed", "error": "ValueError: boom"})
    # vae/0/0 stays RUNNING: its driver "dies" here.
    assert ledger([e.key for e in ENTRIES], store.trials(), driver_alive=True) == {
        "pixel": Counts(planned=2, done=1, failed=1),
        "vae": Counts(planned=2, running=1, left=1),
    }
    assert ledger([e.key for e in ENTRIES], store.trials(), driver_alive=False)["vae"] == Counts(
        planned=2, left=2
    )

    relaunch = StudyStore.open_or_create(open_storage(url), "life", {"plan_hash": "h1"})
    todo = relaunch.sync(ENTRIES, "h1")
    assert [entry.key for entry, _ in todo] == ["pixel/1/0", "vae/0/0", "vae/1/0"]
    trials = relaunch.trials()
    by_number = {t.number: t for t in trials}
    reaped = next(t for t in trials if t._trial_id == ids["vae/0/0"])
    assert reaped.state == TrialState.FAIL
    assert reaped.user_attrs["outcome"] == "interrupted"
    successor = by_number[reaped.user_attrs["superseded_by"]]
    assert successor.user_attrs["key"] == "vae/0/0"
    assert successor.user_attrs["supersedes"] == [reaped.number]
    assert successor.state == TrialState.WAITING
    assert successor.params == {"lr": 1e-3, "method": "vae"}  # and no constant params
    failed_successor = current_trials(trials)["pixel/1/0"]
    assert failed_successor.state == TrialState.WAITING
    assert failed_successor.user_attrs["attempts"] == 0
    # counted once per key whatever the history
    assert ledger([e.key for e in ENTRIES], trials, driver_alive=False) == {
        "pixel": Counts(planned=2, done=1, left=1),
        "vae": Counts(planned=2, left=2),
    }
    with pytest.raises(StorageError, match="another plan"):
        StudyStore.open_or_create(open_storage(url), "life", {"plan_hash": "h2"})


def test_lifecycle_sqlite(sqlite_url):
    _lifecycle(sqlite_url)


def test_lifecycle_postgresql(pg_url):
    _lifecycle(pg_url)
    assert "postgresql+psycopg" in str(open_storage(pg_url).engine.url)


def test_driver_lock(sqlite_url):
    store = StudyStore.open_or_create(open_storage(sqlite_url), "lock", {"plan_hash": "h"})
    assert not store.driver_alive()
    store.claim_driver()
    assert store.driver_alive()
    store.claim_driver()  # the same process may claim again
    live_other = {"host": socket.gethostname(), "pid": os.getppid(), "heartbeat": 1e12}
    store.storage.set_study_user_attr(store.study_id, "driver", live_other)
    with pytest.raises(StudyBusy, match=f"pid {os.getppid()}"):
        store.claim_driver()
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    store.storage.set_study_user_attr(
        store.study_id, "driver", {**live_other, "pid": int(dead.stdout)}
    )
    store.claim_driver()  # its pid is gone
    store.storage.set_study_user_attr(store.study_id, "driver", {**live_other, "heartbeat": 0})
    store.claim_driver()  # its heartbeat is stale
    store.release_driver()
    assert store.attrs["driver"] is None


CLAIMER = """
import json, os, sys
from pathlib import Path
import optuna
from sweeper.storage import StudyBusy, StudyStore, open_storage
optuna.logging.set_verbosity(optuna.logging.WARNING)
url, folder, me, rounds = sys.argv[1], Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
other = "1" if me == "0" else "0"
store = StudyStore.find(open_storage(url, create=False), "race")


def wait_for(path):
    while not path.exists():  # spin: both claimers are released within microseconds
        pass


results = []
for i in range(rounds):
    (folder / f"ready-{i}-{me}").touch()
    wait_for(folder / f"go-{i}")
    try:
        store.claim_driver()
        results.append("ok")
    except StudyBusy:
        results.append("busy")
    (folder / f"tried-{i}-{me}").touch()
    wait_for(folder / f"tried-{i}-{other}")  # the winner holds the claim until both tried
    if results[-1] == "ok":
        store.release_driver()
    (folder / f"done-{i}-{me}").touch()
    wait_for(folder / f"done-{i}-{other}")
print(json.dumps(results))
"""


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_two_processes_released_together_never_both_claim(backend, request, tmp_path):
    """The claim is one atomic step: of two claimers released in the same microsecond,
    exactly one becomes the driver, round after round."""
    url = request.getfixturevalue("sqlite_url" if backend == "sqlite" else "pg_url")
    StudyStore.open_or_create(open_storage(url), "race", {"plan_hash": "h"})
    rounds = 6
    claimers = [
        subprocess.Popen(
            [sys.executable, "-c", CLAIMER, url, str(tmp_path), me, str(rounds)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for me in ("0", "1")
    ]
    try:
        for i in range(rounds):  # released once both wait, each round
            wait_until(
                lambda i=i: (
                    all((tmp_path / f"ready-{i}-{me}").exists() for me in "01")
                    or any(c.poll() is not None for c in claimers)
                ),
                120,
                f"both claimers at round {i}",
            )
            (tmp_path / f"go-{i}").touch()
        outcomes = [json.loads(c.communicate(timeout=120)[0]) for c in claimers]
    finally:
        for claimer in claimers:
            claimer.kill()
    for round_ in zip(*outcomes, strict=True):
        assert sorted(round_) == ["busy", "ok"], outcomes


def test_a_live_driver_is_not_taken_over_whatever_its_heartbeat(sqlite_url):
    """On its own host a driver is alive while its process is (pid and start time), even if
    its heartbeat is old (a setup longer than DRIVER_STALE_SECONDS); a reused pid is not."""
    store = StudyStore.open_or_create(open_storage(sqlite_url), "live", {"plan_hash": "h"})
    driver = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        record = {"host": socket.gethostname(), "pid": driver.pid, "heartbeat": time.time() - 3600}
        started = process_start(driver.pid)
        assert started is not None
        store.storage.set_study_user_attr(store.study_id, "driver", {**record, "started": started})
        with pytest.raises(StudyBusy, match=f"pid {driver.pid}"):
            store.claim_driver()
        assert store.driver_alive()
        reused = {**record, "started": started - 1}  # the same pid, another process
        store.storage.set_study_user_attr(store.study_id, "driver", reused)
        assert not store.driver_alive()
        store.claim_driver()
    finally:
        driver.kill()
        driver.wait()


def test_the_heartbeat_beats_while_the_driver_is_busy(sqlite_url):
    """A thread keeps the record fresh while the driver's own thread is busy (a long sync)."""
    store = StudyStore.open_or_create(open_storage(sqlite_url), "beat", {"plan_hash": "h"})
    store.claim_driver()
    first = store.attrs["driver"]["heartbeat"]
    with store.heartbeats(interval=0.1) as beat:
        # this thread never beats: only the heartbeat thread can move the record on, twice
        wait_until(lambda: store.attrs["driver"]["heartbeat"] > first, 60, "a beat")
        second = store.attrs["driver"]["heartbeat"]
        wait_until(lambda: store.attrs["driver"]["heartbeat"] > second, 60, "another beat")
        beat.check()  # nobody else: no error
        taken = {"host": "elsewhere", "pid": 1, "heartbeat": time.time() + 3600}
        store.storage.set_study_user_attr(store.study_id, "driver", taken)
        wait_until(lambda: beat.error is not None, 60, "the beat that finds the other driver")
        with pytest.raises(StudyBusy, match="host elsewhere"):
            beat.check()  # another driver took the study over: this one must stop
    assert store.attrs["driver"] == taken  # and its record is left alone


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_driver_on_another_host_is_alive_while_its_heartbeat_is_fresh(backend, request):
    """On another host only the heartbeat tells: younger than DRIVER_STALE_SECONDS blocks a
    claim, older is a dead driver's record and is taken over."""
    url = request.getfixturevalue("sqlite_url" if backend == "sqlite" else "pg_url")
    store = StudyStore.open_or_create(open_storage(url), "hosts", {"plan_hash": "h"})
    # its pid is this process's: on this host it would be alive whatever its heartbeat
    elsewhere = {"host": "elsewhere", "pid": os.getpid(), "started": process_start(os.getpid())}
    now = time.time()
    for age in (0.0, DRIVER_STALE_SECONDS - 5):
        record = {**elsewhere, "heartbeat": now - age}
        store.storage.set_study_user_attr(store.study_id, "driver", record)
        with pytest.raises(StudyBusy, match="host elsewhere"):
            store.claim_driver()
        assert store.attrs["driver"] == record  # refused: left as it was
    stale = {**elsewhere, "heartbeat": now - DRIVER_STALE_SECONDS - 5}
    store.storage.set_study_user_attr(store.study_id, "driver", stale)
    assert not store.driver_alive()
    store.claim_driver()  # taken over
    mine = store.attrs["driver"]
    assert (mine["host"], mine["pid"]) == (socket.gethostname(), os.getpid())
    assert mine["heartbeat"] >= now


def test_the_heartbeat_skips_a_beat_while_the_database_is_out(pg_url):
    """A beat that cannot reach the database is skipped, not fatal: once PostgreSQL is back
    (its proxy up) the next beats land, and the driver was never told to stop."""
    from pg_proxy import Proxy

    proxy = Proxy(("127.0.0.1", 5432))
    url = pg_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")
    store = StudyStore.open_or_create(open_storage(url), "outage", {"plan_hash": "h"})
    store.claim_driver()
    direct = StudyStore.find(open_storage(pg_url), "outage")  # reads past the proxy
    missed = []
    beat_once = store.heartbeat

    def heartbeat():
        try:
            beat_once()
        except Exception as e:
            missed.append(e)
            raise

    store.heartbeat = heartbeat  # what the heartbeat thread calls
    with store.heartbeats(interval=0.1) as beat:
        proxy.down()
        wait_until(lambda: len(missed) >= 2, 60, "beats missed during the outage")
        back = time.time()
        proxy.up()
        wait_until(lambda: direct.attrs["driver"]["heartbeat"] > back, 60, "a beat after it")
        beat.check()  # no error: the outage did not stop the driver
    assert all(is_database_error(e) and is_outage(e) for e in missed), missed


def test_sync_repairs_orphans_of_an_interrupted_setup(sqlite_url):
    """Trials that are WAITING or RUNNING but no key's current trial (left by a setup cut
    short or by an older race) are failed as interrupted, pointing to their successor."""
    store = StudyStore.open_or_create(open_storage(sqlite_url), "orphans", {"plan_hash": "h"})
    entry = ENTRIES[0]
    attrs = {"key": entry.key, "method": entry.method, "config_id": 0, "seed": 0}
    orphan = store.add_waiting(entry.params, entry.choices, attrs)
    current = store.add_waiting(entry.params, entry.choices, attrs)
    stray = store.add_waiting(entry.params, entry.choices, {})  # no key at all
    todo = store.sync(ENTRIES, "h")
    assert todo[0][1].number == current.number
    trials = {t.number: t for t in store.trials()}
    assert trials[orphan.number].state == TrialState.FAIL
    assert trials[orphan.number].user_attrs["outcome"] == "interrupted"
    assert trials[orphan.number].user_attrs["superseded_by"] == current.number
    assert trials[stray.number].state == TrialState.FAIL
    assert [t.state for t in store.trials()].count(TrialState.WAITING) == len(ENTRIES)


TAKEOVER = """
import sys
from sweeper import storage
from sweeper.storage import _writer as writer
writer.DRIVER_STALE_SECONDS = 0.0
store = storage.StudyStore.find(storage.open_storage(sys.argv[1], create=False), "big")
try:
    store.claim_driver()
    print("taken over")
except storage.StudyBusy:
    print("busy")
"""


def test_sync_creates_5000_trials_in_bulk_on_postgresql(pg_url):
    """The plan's trials are created in bulk: 5,000 keys in a fraction of the time Optuna's
    one trial per call takes on the same machine at the same moment (measured first), so
    the bound holds however loaded the machine is."""
    entries = [Entry(m, c, s) for m in ("pixel", "vae") for c in range(250) for s in range(10)]
    store = StudyStore.open_or_create(open_storage(pg_url), "big", {"plan_hash": "h"})
    store.claim_driver()
    # Optuna's way, one trial per call, measured here and now (whatever the machine's load)
    single = StudyStore.open_or_create(open_storage(pg_url), "single", {"plan_hash": "h"})
    start = time.perf_counter()
    for entry in entries[:50]:
        single.add_waiting(entry.params, entry.choices, {"key": entry.key})
    one_by_one = (time.perf_counter() - start) / 50 * len(entries)
    start = time.perf_counter()
    todo = store.sync(entries, "h")
    seconds = time.perf_counter() - start
    print(f"sync of {len(entries)} entries: {seconds:.1f} s; one by one: {one_by_one:.0f} s")
    assert seconds < one_by_one / 5
    assert [entry.key for entry, _ in todo] == [e.key for e in entries]
    trials = store.trials()
    assert len(trials) == 5000 and {t.state for t in trials} == {TrialState.WAITING}
    assert sorted(t.number for t in trials) == list(range(5000))
    last = todo[-1][1]
    assert last.params == {"lr": 1e-3, "method": "vae"}
    assert last.user_attrs == {
        "method": "vae",
        "config_id": 249,
        "seed": 9,
        "key": "vae/249/9",
        "plan_hash": "h",
        "precision": "fp32",
        "attempts": 0,
        "stage": "search",
    }
    takeover = subprocess.run(  # even with every heartbeat counted stale
        [sys.executable, "-c", TAKEOVER, pg_url], capture_output=True, text=True, timeout=120
    )
    assert takeover.stdout.strip() == "busy", takeover.stderr[-2000:]
    again = store.sync(entries, "h")
    assert [t.number for _, t in again] == [t.number for _, t in todo]
    store.start(last._trial_id)  # Optuna reads and writes what was created in bulk
    store.complete(last._trial_id, 0.5, {"outcome": "completed"})
    assert optuna.load_study(study_name="big", storage=open_storage(pg_url)).trials[-1].value == 0.5
