"""Crashes: a worker killed mid-trial, a driver killed mid-study, Ctrl-C; the ledger stays exact."""

from __future__ import annotations

import contextlib
import errno
import functools
import io
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import optuna
import psycopg
import pytest
import ray
import sqlalchemy
from conftest import assert_uninterrupted_curve, wait_until, write_ci_spec
from optuna.trial import TrialState

from agent import train
from agent.checkpoint import saved_step
from agent.config import TrialResult
from sweeper.plan._entries import build_plan
from sweeper.run._launch import launch, prepare, study_attrs
from sweeper.run._signals import raise_if_stopped, stop_on_signals
from sweeper.storage import StudyStore, curve_of, open_storage, trial_attr
from sweeper.storage._open import open_study

optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake trains below


def trials_of(url: str, name: str) -> list[optuna.trial.FrozenTrial]:
    """The study's trials, or [] while the driver has not created it yet (for polling; read
    a result with ``stored_trials``)."""
    try:
        return stored_trials(url, name)
    except (KeyError, sqlalchemy.exc.SQLAlchemyError, optuna.exceptions.StorageInternalError):
        return []


def stored_trials(url: str, name: str) -> list[optuna.trial.FrozenTrial]:
    """The study's trials; an error if the study cannot be read."""
    storage = open_storage(url, create=False)  # the driver creates the tables
    try:
        return optuna.load_study(study_name=name, storage=storage).get_trials()
    finally:
        storage.engine.dispose()


def check_exact_budget(trials, keys: list[str]) -> dict[str, optuna.trial.FrozenTrial]:
    """Every planned key COMPLETE exactly once; return key -> its COMPLETE trial."""
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    counts = Counter(t.user_attrs["key"] for t in complete)
    assert sorted(counts) == sorted(keys)
    assert set(counts.values()) == {1}, counts
    assert not [t for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    return {t.user_attrs["key"]: t for t in complete}


@pytest.mark.slow
def test_worker_killed_mid_trial_is_resumed_with_the_same_curve(tmp_path, local_ray):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec_path = write_ci_spec(
        tmp_path / "spec.yaml",
        study="faults",
        methods={"pixel": {}},
        seeds=[0, 1],
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        budget={"env_steps": 300},
        execution={"retries": 1, "checkpoint_every": 100},
    )
    spec, plan = prepare(str(spec_path))
    victim = plan.entries[0]
    checkpoints = tmp_path / "checkpoints"  # the study's folder is named when it starts
    codes = []
    driver = threading.Thread(target=lambda: codes.append(launch(spec, plan)))
    driver.start()
    try:

        def running_worker():
            trial = next(
                (t for t in trials_of(url, "faults") if t.user_attrs.get("key") == victim.key), None
            )
            checkpointed = any(checkpoints.glob(f"*/{victim.key}/checkpoint.pt"))
            if trial is None or trial.state != TrialState.RUNNING or not checkpointed:
                return None
            return trial_attr(trial, "worker")

        worker = wait_until(running_worker, 240, "a checkpoint of the victim trial")
        os.kill(worker["pid"], signal.SIGKILL)
    finally:
        driver.join(timeout=300)
    assert codes == [0]
    trials = stored_trials(url, "faults")
    assert len(trials) == 2  # a retry stays in its Optuna trial
    by_key = check_exact_budget(trials, plan.keys())
    retried = by_key[victim.key]
    assert retried.user_attrs["attempts"] == 2
    assert len(trial_attr(retried, "worker_deaths")) == 1
    assert "ActorDiedError" in trial_attr(retried, "worker_deaths")[0]
    assert trial_attr(retried, "worker")["pid"] != worker["pid"]
    assert retried.user_attrs["resumed_from"] >= 100
    assert by_key[plan.entries[1].key].user_attrs["attempts"] == 1

    assert_uninterrupted_curve(retried, victim.trial_config)


def start_driver(spec: Path, address: str, log: Path) -> subprocess.Popen:
    """`sweeper launch spec --address ADDR` in its own process group, as from a terminal."""
    return subprocess.Popen(
        [sys.executable, "-m", "sweeper.cli", "launch", str(spec), "--address", address],
        stdout=log.open("a"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=spec.parent,
        # Ctrl-C at its default, as from a terminal, even when pytest runs with SIGINT
        # ignored (a background job of a shell without job control), which a child inherits
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the point
def test_a_ctrl_c_that_lands_in_a_finalizer_still_stops_the_launch():
    # CI once lost a Ctrl-C this way: it arrived while SQLAlchemy ran a weakref callback,
    # Python printed "Exception ignored" and the launch ran on to exit 0
    class SignalsWhileFinalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)  # the handler runs here, inside the finalizer

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        with stop_on_signals():
            raise_if_stopped()  # nothing asked yet
            SignalsWhileFinalized()  # dropped at once: __del__ swallows the KeyboardInterrupt
            with pytest.raises(KeyboardInterrupt):
                raise_if_stopped()
        raise_if_stopped()  # forgotten once the launch is over
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        # started with SIGINT ignored (nohup ... & from a script), it stays ignored
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with stop_on_signals():
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def kill_group(process: subprocess.Popen, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, sig)


@pytest.mark.slow
def test_driver_killed_then_ctrl_c_then_relaunch_finishes_exactly(tmp_path, local_ray):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec = write_ci_spec(
        tmp_path / "spec.yaml",
        study="driver",
        trials_per_method=2,
        # long enough that the second driver still has a trial in flight when its Ctrl-C
        # arrives on a busy machine (at 200 steps it could finish them all first)
        budget={"env_steps": 500},
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
    )
    keys = prepare(str(spec))[1].keys()
    log = tmp_path / "driver.log"

    def checkpoints_of(key: str) -> list[Path]:
        return list((tmp_path / "checkpoints").glob(f"*/{key}/checkpoint.pt"))

    def done_and_checkpointed():
        trials = trials_of(url, "driver")
        running = [
            t
            for t in trials
            if t.state == TrialState.RUNNING and checkpoints_of(t.user_attrs["key"])
        ]
        return running and any(t.state == TrialState.COMPLETE for t in trials)

    # 1. SIGKILL the driver after a trial ends, while another runs past its first
    # checkpoint (Ray then kills its actors).
    first = start_driver(spec, local_ray, log)
    try:
        wait_until(done_and_checkpointed, 240, "a complete trial and a checkpointed running one")
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        kill_group(first, signal.SIGKILL)
    finished = {
        t.number: t.datetime_complete
        for t in stored_trials(url, "driver")
        if t.state == TrialState.COMPLETE
    }
    left = [t for t in stored_trials(url, "driver") if t.state == TrialState.RUNNING]
    stale = {t.number for t in left}
    assert stale  # the killed driver left trials RUNNING
    # a dead driver's trial is re-run from its checkpoint, not from step 0
    resumable = {t.user_attrs["key"] for t in left if checkpoints_of(t.user_attrs["key"])}
    assert resumable
    saved = {key: saved_step(str(checkpoints_of(key)[0].parent)) for key in resumable}

    # 2. Relaunch, then Ctrl-C it while trials run: exit 130, in-flight trials interrupted.
    second = start_driver(spec, local_ray, log)
    try:
        # dispatched is enough (the driver interrupts what it has in flight); waiting for
        # the worker's first report as well left too short a window with warm workers
        def running_now():
            return [
                t
                for t in trials_of(url, "driver")
                if t.state == TrialState.RUNNING and t.number not in stale
            ]

        wait_until(running_now, 240, "a trial running under the second driver")
        kill_group(second, signal.SIGINT)  # as a terminal does: the whole group
        assert second.wait(timeout=120) == 130, log.read_text()
    finally:
        kill_group(second, signal.SIGKILL)
    trials = stored_trials(url, "driver")
    assert not [t for t in trials if t.state == TrialState.RUNNING]
    reaped = [t for t in trials if t.user_attrs.get("outcome") == "interrupted"]
    assert any("its driver stopped" in t.user_attrs["error"] for t in reaped)  # left by run 1
    assert any("stopped by the user" in t.user_attrs["error"] for t in reaped)  # run 2's Ctrl-C

    # 3. Relaunch to the end: finished trials are not re-run, the budget is exact.
    third = start_driver(spec, local_ray, log)
    try:
        assert third.wait(timeout=300) == 0, log.read_text()
    finally:
        kill_group(third, signal.SIGKILL)
    trials = stored_trials(url, "driver")
    by_key = check_exact_budget(trials, keys)
    for number, when in finished.items():
        assert trials[number].state == TrialState.COMPLETE
        assert trials[number].datetime_complete == when
    for trial in trials:
        if "superseded_by" in trial.user_attrs:
            successor = trials[trial.user_attrs["superseded_by"]]
            assert successor.user_attrs["key"] == trial.user_attrs["key"]
            assert trial.number in successor.user_attrs["supersedes"]
    assert all(curve_of(t)["step"] == [0, 100, 200, 300, 400, 500] for t in by_key.values())
    for key in resumable:
        # the step of the checkpoint the killed driver's trial left
        assert by_key[key].user_attrs["resumed_from"] == saved[key], key


RACER = """
import os, sys, time
from pathlib import Path
from agent.config import TrialResult
from sweeper.run._launch import launch, prepare
from sweeper.storage import StudyStore

spec_path, ready, go = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
claim = StudyStore.claim_driver


def claim_when_released(self):
    ready.write_text(repr(time.time()))  # waiting from now on: Ray joined, study opened
    while not os.path.exists(go):  # spin: both launches claim within microseconds
        pass
    claim(self)


def quick(config, report=None):
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    time.sleep(0.5)
    steps = (0, config.total_steps)
    metrics = {"success_rate": (0.0, 1.0), "final_distance": (1.0, 0.0)}
    return TrialResult(steps=steps, metrics=metrics, auc=0.5)


StudyStore.claim_driver = claim_when_released
spec, plan = prepare(spec_path)
sys.exit(launch(spec, plan, train=quick))
"""


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_two_launches_released_together_run_the_budget_once(tmp_path, local_ray, backend, request):
    """One launch drives, the other exits 3 (busy) with one line; 4 keys, 4 trials."""
    url = (
        f"sqlite:///{tmp_path / 'study.db'}"
        if backend == "sqlite"
        else request.getfixturevalue("pg_url")
    )
    spec = write_ci_spec(
        tmp_path / "spec.yaml",
        study="race",
        trials_per_method=2,
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        execution={"address": local_ray},
    )
    keys = prepare(str(spec))[1].keys()
    assert len(keys) == 4
    ready = [tmp_path / f"ready{i}" for i in range(2)]
    go = tmp_path / "go"
    racers = [
        subprocess.Popen(
            [sys.executable, "-c", RACER, str(spec), str(ready[i]), str(go)],
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
        )
        for i in range(2)
    ]
    try:
        # released only once both wait at the claim (each has joined Ray, opened the study)
        both_waiting = wait_until(
            lambda: all(p.exists() for p in ready) or any(r.poll() is not None for r in racers),
            240,
            "both launches at the claim",
        )
        assert both_waiting and all(p.exists() for p in ready), "a racer ended before the claim"
        released = time.time()
        go.touch()
        results = sorted((r.communicate(timeout=240)[1], r.returncode)[::-1] for r in racers)
    finally:
        for racer in racers:
            racer.kill()
    waited = [float(p.read_text()) for p in ready]
    assert all(since < released for since in waited)  # both waited for the release
    assert [code for code, _ in results] == [0, 3], results
    busy = results[1][1].strip()
    assert len(busy.splitlines()) == 1, busy
    assert busy.startswith("sweeper launch: another `sweeper launch` drives this study")
    trials = stored_trials(url, "race")
    check_exact_budget(trials, keys)
    assert len(trials) == 4


def steady(config, report=None):
    """A trial that evaluates every 1.5 s and checkpoints (a marker file) after each."""
    from agent.config import TrialResult

    marker = Path(config.checkpoint_dir) / "checkpoint.pt"
    resumed_from = int(marker.read_text()) if marker.exists() else None
    steps = list(range(0, config.total_steps + 1, config.eval_every))
    for step in steps:
        if resumed_from is None or step > resumed_from:
            time.sleep(1.5)
            marker.parent.mkdir(parents=True, exist_ok=True)
            # atomically, as a real checkpoint: a worker stopped mid-write leaves the old one
            marker.with_suffix(".tmp").write_text(str(step))
            marker.with_suffix(".tmp").replace(marker)
        report(step, {"success_rate": 0.0, "final_distance": 1.0})
    metrics = {"success_rate": (0.0,) * len(steps), "final_distance": (1.0,) * len(steps)}
    return TrialResult(steps=tuple(steps), metrics=metrics, auc=0.0, resumed_from=resumed_from)


@pytest.mark.slow
def test_a_stopped_worker_is_noticed_and_its_trial_retried(tmp_path, local_ray):
    """A worker that stops answering (SIGSTOP: a frozen process or node) is treated as
    dead after execution.stall_timeout: its trial re-runs from its checkpoint, exactly once."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec_path = write_ci_spec(
        tmp_path / "spec.yaml",
        study="stall",
        seeds=[0, 1],
        methods={"pixel": {}},
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        # a healthy worker answers within milliseconds: a retry is never taken for a stall
        execution={"retries": 1, "stall_timeout": 15},
    )
    spec, plan = prepare(str(spec_path))
    victim = plan.entries[0]
    codes = []
    driver = threading.Thread(target=lambda: codes.append(launch(spec, plan, train=steady)))
    driver.start()
    stopped = None
    try:

        def reporting_worker():
            trials = trials_of(url, "stall")
            trial = next((t for t in trials if t.user_attrs.get("key") == victim.key), None)
            if trial is None or 100 not in trial.intermediate_values:
                return None
            return trial_attr(trial, "worker")

        stopped = wait_until(reporting_worker, 120, "a report of the victim trial")["pid"]
        os.kill(stopped, signal.SIGSTOP)
        driver.join(timeout=90)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(stopped, signal.SIGCONT)  # lets a hung driver finish
        driver.join(timeout=120)
    assert codes == [0]
    trials = stored_trials(url, "stall")
    by_key = check_exact_budget(trials, plan.keys())
    assert len(trials) == 2
    retried = by_key[victim.key]
    assert retried.user_attrs["attempts"] == 2
    assert "no answer" in trial_attr(retried, "worker_deaths")[0]
    assert retried.user_attrs["resumed_from"] >= 100


CONFIRMER = """
import sys, time, zlib
from pathlib import Path
from agent.config import TrialResult
from sweeper.run._confirm import confirm
from sweeper.run._launch import launch, prepare

spec_path, address, stage = sys.argv[1], sys.argv[2], sys.argv[3]


def steady(config, report=None):
    # a success rate fixed by the config and seed; an evaluation every second, each followed
    # by a checkpoint (a marker file) that a re-run resumes from
    level = (zlib.crc32(f"{config.sac}/{config.method}/{config.seed}".encode()) % 100) / 100
    marker = Path(config.checkpoint_dir) / "checkpoint.pt"
    resumed_from = int(marker.read_text()) if marker.exists() else None
    steps = list(range(0, config.total_steps + 1, config.eval_every))
    for step in steps:
        if stage == "confirm" and (resumed_from is None or step > resumed_from):
            time.sleep(1.0)
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.write_text(str(step))
        report(step, {"success_rate": level, "final_distance": 1 - level})
    metrics = {"success_rate": (level,) * len(steps), "final_distance": (1 - level,) * len(steps)}
    return TrialResult(steps=tuple(steps), metrics=metrics, auc=level, resumed_from=resumed_from)


spec, plan = prepare(spec_path, address=address)
if stage == "search":
    sys.exit(launch(spec, plan, train=steady))
sys.exit(confirm(spec, plan, 2, 2, train=steady))
"""


@pytest.mark.slow
def test_confirm_stage_ledger_is_exact_under_a_worker_kill_and_a_driver_relaunch(
    tmp_path, local_ray
):
    """The confirmation stage has the search's semantics: a killed worker's trial re-runs from
    its checkpoint in the same trial; a killed driver's trials are re-run by the next
    `sweeper confirm`; every confirm key is COMPLETE exactly once, the search untouched."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec = write_ci_spec(
        tmp_path / "spec.yaml",
        study="confirm",
        trials_per_method=3,
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        budget={"env_steps": 300},
        execution={"retries": 1, "max_concurrent": 2},
        random_episodes=10,
    )
    search_keys = prepare(str(spec))[1].keys()
    log = tmp_path / "driver.log"

    def driver(stage: str) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", CONFIRMER, str(spec), local_ray, stage],
            stdout=log.open("a"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=tmp_path,
        )

    search = driver("search")
    assert search.wait(timeout=240) == 0, log.read_text()
    searched = {t.number: t.datetime_complete for t in stored_trials(url, "confirm")}
    assert len(searched) == len(search_keys) == 6

    def confirming():
        return [t for t in trials_of(url, "confirm") if t.user_attrs.get("stage") == "confirm"]

    # 1. SIGKILL a worker of the confirm stage after its trial's first checkpoint
    first = driver("confirm")
    try:

        def checkpointed_worker():
            for trial in confirming():
                if trial.state == TrialState.RUNNING and 100 in trial.intermediate_values:
                    return trial.user_attrs["key"], trial_attr(trial, "worker")["pid"]
            return None

        victim, pid = wait_until(checkpointed_worker, 120, "a confirm trial's checkpoint")
        os.kill(pid, signal.SIGKILL)

        # 2. once the victim is done (re-run in its trial), SIGKILL the driver mid-stage
        def victim_done_and_another_running():
            trials = confirming()
            done = [t for t in trials if t.user_attrs["key"] == victim]
            running = [
                t for t in trials if t.state == TrialState.RUNNING and "worker" in t.user_attrs
            ]
            return done and done[0].state == TrialState.COMPLETE and running

        wait_until(victim_done_and_another_running, 120, "the victim done, another running")
        kill_group(first, signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        kill_group(first, signal.SIGKILL)
    stale = {t.number for t in confirming() if t.state == TrialState.RUNNING}
    assert stale  # the killed driver left confirm trials RUNNING
    retried = next(t for t in confirming() if t.user_attrs["key"] == victim)
    assert retried.user_attrs["attempts"] == 2 and len(trial_attr(retried, "worker_deaths")) == 1
    assert retried.user_attrs["resumed_from"] >= 100

    # 3. relaunch the stage to the end: exact, nothing re-chosen, the search untouched
    second = driver("confirm")
    try:
        assert second.wait(timeout=240) == 0, log.read_text()
    finally:
        kill_group(second, signal.SIGKILL)
    trials = stored_trials(url, "confirm")
    chosen = optuna.load_study(study_name="confirm", storage=url).user_attrs["confirm"]
    assert len(chosen["keys"]) == 2 * 2 * 2 and chosen["seeds"] == [1, 2]
    by_key = check_exact_budget(trials, [*search_keys, *chosen["keys"]])
    for number, when in searched.items():
        assert trials[number].datetime_complete == when
    assert by_key[victim].number == retried.number  # a worker death keeps its trial
    for number in stale:  # a dead driver's trial is superseded, once
        successor = trials[trials[number].user_attrs["superseded_by"]]
        assert successor.user_attrs["key"] == trials[number].user_attrs["key"]
        assert successor.state == TrialState.COMPLETE


def instant(config, report=None):
    """A trial that reports once and finishes at once."""
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    metrics = {"success_rate": (0.0, 1.0), "final_distance": (1.0, 0.0)}
    return TrialResult(steps=(0, config.total_steps), metrics=metrics, auc=0.5)


def disk_full(connection, cursor, statement, *args):
    """An engine hook: recording a trial's value fails as on a full disk, with SQLite's
    message or PostgreSQL's code (53100)."""
    if statement.lstrip().upper().startswith("INSERT INTO TRIAL_VALUES"):
        if connection.dialect.name == "sqlite":
            raise sqlite3.OperationalError("database or disk is full")
        raise psycopg.errors.DiskFull("could not extend file: No space left on device")


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_full_disk_mid_launch_exits_2_with_one_line_and_a_relaunch_finishes(
    tmp_path, local_ray, backend, request
):
    url = (
        f"sqlite:///{tmp_path / 'study.db'}"
        if backend == "sqlite"
        else request.getfixturevalue("pg_url")
    )
    spec_path = write_ci_spec(
        tmp_path / "spec.yaml",
        study="full",
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        execution={"address": local_ray},  # the default grace (60 s): a full disk is not waited for
    )
    spec, plan = prepare(str(spec_path))
    stream = io.StringIO()
    sqlalchemy.event.listen(sqlalchemy.engine.Engine, "before_cursor_execute", disk_full)
    try:
        code = launch(spec, plan, train=instant, stream=stream)
    finally:
        sqlalchemy.event.remove(sqlalchemy.engine.Engine, "before_cursor_execute", disk_full)
    assert code == 2
    errors = [line for line in stream.getvalue().splitlines() if "disk is full" in line]
    assert len(errors) == 1 and errors[0].startswith("sweeper launch: "), stream.getvalue()
    assert "free space" in errors[0]
    trials = stored_trials(url, "full")
    assert not [t for t in trials if t.state == TrialState.COMPLETE]
    assert [t for t in trials if t.state == TrialState.RUNNING]  # left for the next launch

    assert launch(spec, plan, train=instant, stream=io.StringIO()) == 0  # nothing was lost
    check_exact_budget(stored_trials(url, "full"), plan.keys())


def one_trial_spec(tmp_path: Path, study: str, url: str | None = None, **execution) -> Path:
    """The CI spec cut to one key (pixel/0/0), its storage and checkpoints in ``tmp_path``."""
    return write_ci_spec(
        tmp_path / "spec.yaml",
        study=study,
        methods={"pixel": {}},
        storage=url or f"sqlite:///{tmp_path / 'study.db'}",
        checkpoints=str(tmp_path / "checkpoints"),
        execution=execution,
    )


@pytest.mark.slow
def test_a_corrupt_checkpoint_found_on_resume_is_said_in_the_output_and_the_record(
    tmp_path, local_ray
):
    """The trial restarts from step 0 (its ledger exact), and says so where the user looks:
    a line of the launch and the trial's ``notices`` attr (it was a warning in Ray's worker
    log only)."""
    spec, plan = prepare(str(one_trial_spec(tmp_path, "corrupt")))
    attrs = study_attrs(spec, plan)
    with open_study(spec.storage_url, spec.study, write=True, attrs=attrs) as store:
        store.claim_driver()  # gives the study its uid, which names its checkpoints
        (entry,) = build_plan(spec, study_uid=store.study_uid).entries
        store.release_driver()
    checkpoint = Path(entry.trial_config.checkpoint_dir) / "checkpoint.pt"
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"a checkpoint a disk fault left half-written")
    stream = io.StringIO()
    assert launch(spec, plan, stream=stream) == 0, stream.getvalue()
    (trial,) = check_exact_budget(stored_trials(spec.storage_url, "corrupt"), plan.keys()).values()
    (notice,) = trial.user_attrs["notices"]
    assert notice.startswith(f"discarded its corrupt checkpoint {checkpoint}: ")
    assert notice.endswith("; the trial restarts from step 0")
    assert f"{entry.key}: {notice}" in stream.getvalue().splitlines()
    assert trial.user_attrs["resumed_from"] is None


def die(config, report=None):
    """A trial whose worker dies (SIGKILL) after its first report, every time."""
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.slow
def test_more_worker_deaths_than_retries_fail_the_trial_and_a_relaunch_reruns_it(
    tmp_path, local_ray
):
    spec, plan = prepare(str(one_trial_spec(tmp_path, "deaths", retries=1)))
    stream = io.StringIO()
    assert launch(spec, plan, train=die, stream=stream) == 1, stream.getvalue()
    (failed,) = stored_trials(spec.storage_url, "deaths")
    assert failed.state == TrialState.FAIL and failed.user_attrs["outcome"] == "failed"
    assert failed.user_attrs["attempts"] == 2  # the first run and its one retry
    deaths = trial_attr(failed, "worker_deaths")
    assert len(deaths) == 2 and all("ActorDiedError" in death for death in deaths), deaths
    assert failed.user_attrs["error"] == f"worker died 2 times; last: {deaths[-1]}"
    assert "1 trial failed" in stream.getvalue()

    assert launch(spec, plan, train=instant, stream=io.StringIO()) == 0  # re-run, counted once
    trials = stored_trials(spec.storage_url, "deaths")
    (rerun,) = check_exact_budget(trials, plan.keys()).values()
    assert rerun.number != failed.number and rerun.user_attrs["supersedes"] == [failed.number]
    assert rerun.user_attrs["attempts"] == 1
    assert trials[failed.number].state == TrialState.FAIL


class FailingFile(io.FileIO):
    """A checkpoint file whose writes fail after the first kilobyte with ENOSPC, as on a
    disk that fills up mid-write (as tests/test_checkpoint.py fails them)."""

    def write(self, data: bytes) -> int:
        if self.tell() + len(data) > 1000:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


def failing_after_first_checkpoint(config, report=None, record=None, code=errno.ENOSPC):
    """agent.train on a checkpoint directory that fills up (ENOSPC: mid-write) or turns
    read-only (EROFS: the file cannot be opened for writing) after the first checkpoint."""
    from agent import storage_io

    opened = []

    class FailingDisk:  # the os module, as agent.storage_io sees it
        def __getattr__(self, name):
            return getattr(os, name)

        def fdopen(self, fd, mode):
            opened.append(fd)
            if len(opened) == 1:
                return os.fdopen(fd, mode)
            if code == errno.ENOSPC:
                return FailingFile(fd, "wb")
            os.close(fd)
            raise OSError(code, os.strerror(code))

    storage_io.os = FailingDisk()
    try:
        return train(config, report=report)
    finally:
        storage_io.os = os


@pytest.mark.slow
@pytest.mark.parametrize(
    ("code", "problem"),
    [
        (errno.ENOSPC, "is full (No space left on device): free space"),
        (errno.EROFS, "is read-only (Read-only file system): make it writable"),
    ],
)
def test_a_full_or_read_only_checkpoint_dir_fails_the_trial_and_a_relaunch_resumes(
    tmp_path, local_ray, code, problem
):
    """A real trial (300 steps, checkpoints at 100 and 200) whose second checkpoint meets a
    full or read-only directory: its error is the one line, the first checkpoint is kept
    with no partial file beside it, and the next launch resumes from it."""
    spec, plan = prepare(str(one_trial_spec(tmp_path, "ckfull")))
    stream = io.StringIO()
    trial = functools.partial(failing_after_first_checkpoint, code=code)
    assert launch(spec, plan, train=trial, stream=stream) == 1
    (failed,) = stored_trials(spec.storage_url, "ckfull")
    assert failed.state == TrialState.FAIL and failed.user_attrs["outcome"] == "failed"
    (kept,) = (tmp_path / "checkpoints").glob("*/pixel/0/0/*")  # nothing else in the folder
    assert kept.name == "checkpoint.pt"
    assert failed.user_attrs["error"] == (
        f"OSError: checkpoint directory {kept.parent} {problem} or set checkpoints: in the spec"
    )
    assert sorted(failed.intermediate_values) == [0, 100, 200]  # what it reported first

    assert launch(spec, plan, stream=io.StringIO()) == 0  # agent.train, the disk freed
    (resumed,) = check_exact_budget(stored_trials(spec.storage_url, "ckfull"), plan.keys()).values()
    assert resumed.user_attrs["supersedes"] == [failed.number]
    assert resumed.user_attrs["resumed_from"] == 100
    assert curve_of(resumed)["step"] == [0, 100, 200, 300]


def takeover_record() -> dict:
    """The driver record of a live driver on another host that took the study over."""
    return {"host": "elsewhere", "pid": 1, "started": None, "heartbeat": time.time() + 3600}


@pytest.mark.slow
def test_a_launch_that_ends_first_ends_its_calibration(tmp_path, local_ray, monkeypatch):
    """A launch that ends before it reads its estimate (here another driver is alive: exit
    3) stops the calibration thread and waits for it: a thread still in torch or MuJoCo when
    the process exits aborts it ("terminate called without an active exception"), which
    made a busy racer exit -6 instead of 3 under load."""
    from sweeper.plan._estimate import InBackground
    from sweeper.run import _launch as launcher

    monkeypatch.setattr(launcher, "CALIBRATION_SECONDS", 600.0)  # still calibrating at the end
    spec, plan = prepare(str(one_trial_spec(tmp_path, "busy", address=local_ray)))
    storage = open_storage(spec.storage_url)
    try:
        store = StudyStore.open_or_create(storage, "busy", launcher.study_attrs(spec, plan))
        storage.set_study_user_attr(store.study_id, "driver", takeover_record())
    finally:
        storage.engine.dispose()
    stream = io.StringIO()
    assert launch(spec, plan, train=hold, stream=stream) == 3, stream.getvalue()
    assert "another `sweeper launch` drives this study" in stream.getvalue()
    calibrating = [t for t in threading.enumerate() if t.name == InBackground.THREAD_NAME]
    assert not calibrating


def hold(config, report=None):
    """A trial that reports step 0, then waits for a file ``release`` beside the checkpoint
    root (at most 120 s), then finishes."""
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    release = Path(config.checkpoint_dir).parents[3].parent / "release"
    deadline = time.monotonic() + 120
    while not release.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    return instant(config, report)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_driver_taken_over_stops_with_exit_3_at_its_next_heartbeat(
    tmp_path, local_ray, backend, request, monkeypatch
):
    """A driver on another host that judged this one dead (see test_storage) claimed the
    study: this driver's next heartbeat finds it and the launch stops, exit 3, one line, the
    new driver's record and the trial in flight left to it."""
    from sweeper.run import _launch as launcher
    from sweeper.storage import _writer as writer

    monkeypatch.setattr(launcher, "HEARTBEAT_SECONDS", 0.2)
    url = None if backend == "sqlite" else request.getfixturevalue("pg_url")
    spec, plan = prepare(str(one_trial_spec(tmp_path, "taken", url)))
    stream = io.StringIO()
    codes = []
    running = threading.Thread(
        target=lambda: codes.append(launch(spec, plan, train=hold, stream=stream))
    )
    running.start()
    try:

        def reporting():
            trials = trials_of(spec.storage_url, "taken")
            return trials and 0 in trials[0].intermediate_values

        wait_until(reporting, 120, "the trial's first report")
        storage = open_storage(spec.storage_url, create=False)
        try:
            store = StudyStore.find(storage, "taken")
            with store._locked() as connection:  # as a claim writes it
                writer._write_study_attr(connection, store.study_id, "driver", takeover_record())
        finally:
            storage.engine.dispose()
        running.join(timeout=120)
    finally:
        (tmp_path / "release").touch()
        running.join(timeout=120)
    assert codes == [3], stream.getvalue()
    (line,) = [x for x in stream.getvalue().splitlines() if "another" in x]
    assert line.startswith("sweeper launch: stopped: another `sweeper launch` drives this study")
    assert "host elsewhere" in line
    (trial,) = stored_trials(spec.storage_url, "taken")
    assert trial.state == TrialState.RUNNING  # the new driver's to reap, not this one's
    study = optuna.load_study(study_name="taken", storage=spec.storage_url)
    assert study.user_attrs["driver"]["host"] == "elsewhere"  # left alone


MIDWAY = """
import sys, time
from pathlib import Path
import torch
from agent.config import TrialResult
from sweeper.run._launch import launch, prepare

spec_path, address, stage = sys.argv[1], sys.argv[2], sys.argv[3]


def midway(config, report=None):
    # checkpoints at step 100 (a file holding its step, as a checkpoint does), reports it,
    # then holds there ("hold") or runs to the end ("finish"); a re-run resumes from it
    marker = Path(config.checkpoint_dir) / "checkpoint.pt"
    resumed_from = torch.load(marker)["step"] if marker.exists() else None
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    if resumed_from is None:
        marker.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"step": 100}, marker)
    report(100, {"success_rate": 0.5, "final_distance": 0.5})
    deadline = time.monotonic() + 300
    while stage == "hold" and time.monotonic() < deadline:
        time.sleep(0.1)
    steps = (0, 100, 200, 300)
    metrics = {"success_rate": (0.0, 0.5, 1.0, 1.0), "final_distance": (1.0, 0.5, 0.0, 0.0)}
    return TrialResult(steps=steps, metrics=metrics, auc=0.5, resumed_from=resumed_from)


spec, plan = prepare(spec_path, address=address)
sys.exit(launch(spec, plan, train=midway))
"""


@pytest.mark.slow
def test_sigterm_mid_study_interrupts_the_trials_in_flight_and_a_relaunch_resumes_them(
    tmp_path, local_ray
):
    """SIGTERM to the driver (a service manager stopping it) while two trials run past their
    checkpoint: exit 130, both FAIL as interrupted, the driver says each resumes from its
    checkpoint; the next launch resumes each from it in a new trial."""
    spec = write_ci_spec(
        tmp_path / "spec.yaml",
        study="sigterm",
        storage=f"sqlite:///{tmp_path / 'study.db'}",
        checkpoints=str(tmp_path / "checkpoints"),
    )
    keys = prepare(str(spec))[1].keys()
    url = prepare(str(spec))[0].storage_url

    def driver(stage: str, log: Path) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", MIDWAY, str(spec), local_ray, stage],
            stdout=log.open("w"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=tmp_path,
        )

    def both_past_their_checkpoint():
        trials = trials_of(url, "sigterm")
        running = [t for t in trials if t.state == TrialState.RUNNING]
        return len(running) == 2 and all(100 in t.intermediate_values for t in running)

    first = driver("hold", tmp_path / "first.log")
    try:
        wait_until(both_past_their_checkpoint, 240, "two trials past their checkpoint")
        first.send_signal(signal.SIGTERM)  # the driver alone, not its process group
        assert first.wait(timeout=120) == 130, (tmp_path / "first.log").read_text()
    finally:
        kill_group(first, signal.SIGKILL)
    said = (tmp_path / "first.log").read_text().strip().splitlines()[-3:]
    assert said == [
        "sweeper launch: stopped; 2 trials in flight interrupted; the next launch:",
        "  linear/0/0: resumes from step 100 (its checkpoint)",
        "  pixel/0/0: resumes from step 100 (its checkpoint)",
    ]
    interrupted = stored_trials(url, "sigterm")
    assert [t.state for t in interrupted] == [TrialState.FAIL] * 2
    for trial in interrupted:
        assert trial.user_attrs["outcome"] == "interrupted"
        assert trial.user_attrs["error"] == "interrupted: stopped by the user"

    second = driver("finish", tmp_path / "second.log")
    try:
        assert second.wait(timeout=240) == 0, (tmp_path / "second.log").read_text()
    finally:
        kill_group(second, signal.SIGKILL)
    by_key = check_exact_budget(stored_trials(url, "sigterm"), keys)
    before = {t.user_attrs["key"]: t.number for t in interrupted}
    for key, trial in by_key.items():
        assert trial.user_attrs["supersedes"] == [before[key]]
        assert trial.user_attrs["resumed_from"] == 100, key  # from its checkpoint


def held_at_100(config, report=None):
    """Checkpoints (a marker file) and reports step 100, then waits for a file ``release``
    beside the checkpoint root (at most 120 s) and finishes; a re-run resumes from the
    marker."""
    marker = Path(config.checkpoint_dir) / "checkpoint.pt"
    resumed_from = int(marker.read_text()) if marker.exists() else None
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text("100")
    report(100, {"success_rate": 0.5, "final_distance": 0.5})
    release = Path(config.checkpoint_dir).parents[3].parent / "release"
    deadline = time.monotonic() + 120
    while not release.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    steps = (0, 100, 200, 300)
    metrics = {"success_rate": (0.0, 0.5, 1.0, 1.0), "final_distance": (1.0, 0.5, 0.0, 0.0)}
    return TrialResult(steps=steps, metrics=metrics, auc=0.5, resumed_from=resumed_from)


@contextlib.contextmanager
def write_locked(path: Path):
    """Another process's write lock on the SQLite file ``path`` while the block runs."""
    connection = sqlite3.connect(path, isolation_level=None)
    connection.execute("BEGIN IMMEDIATE")
    try:
        yield
    finally:
        connection.execute("ROLLBACK")
        connection.close()


def past_its_checkpoint(url: str, study: str):
    """The study's one trial once it is RUNNING and has reported step 100."""
    trials = trials_of(url, study)
    running = [t for t in trials if t.state == TrialState.RUNNING]
    return running and 100 in running[0].intermediate_values and running[0]


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_database_lost_past_the_grace_stops_the_launch_and_a_relaunch_resumes(
    tmp_path, local_ray, backend, request, monkeypatch
):
    """SQLite locked by another process, PostgreSQL gone (its proxy down), past
    execution.storage_grace while the driver records a result: exit 2 with one line naming
    the cause and the fix; the trial stays RUNNING, and the next launch resumes it."""
    from pg_proxy import Proxy

    from sweeper.storage import _urls as urls

    monkeypatch.setattr(urls, "SQLITE_TIMEOUT", 0.2)  # SQLite's own wait on a lock
    if backend == "sqlite":
        url = read_url = f"sqlite:///{tmp_path / 'study.db'}"
        outage = functools.partial(write_locked, tmp_path / "study.db")
    else:
        read_url = request.getfixturevalue("pg_url")
        proxy = Proxy(("127.0.0.1", 5432))
        url = read_url.replace("127.0.0.1:5432", f"127.0.0.1:{proxy.port}")

        @contextlib.contextmanager
        def outage():
            proxy.down()
            try:
                yield
            finally:
                proxy.up()

    spec, plan = prepare(str(one_trial_spec(tmp_path, "outage", url, storage_grace=2)))
    stream = io.StringIO()
    codes = []
    running = threading.Thread(
        target=lambda: codes.append(launch(spec, plan, train=held_at_100, stream=stream))
    )
    running.start()
    try:
        held = wait_until(lambda: past_its_checkpoint(read_url, "outage"), 120, "step 100")
        with outage():
            (tmp_path / "release").touch()  # the trial ends: its result meets the outage
            running.join(timeout=120)
    finally:
        (tmp_path / "release").touch()
        running.join(timeout=120)
    assert codes == [2], stream.getvalue()
    (line,) = [x for x in stream.getvalue().splitlines() if "storage_grace" in x]
    assert line.startswith("sweeper launch: storage: lost ")
    assert "for over 2 s (execution.storage_grace)" in line
    assert line.endswith(
        "bring the database back, then launch again to resume the trials in flight"
    )
    (left,) = stored_trials(read_url, "outage")
    assert left.number == held.number and left.state == TrialState.RUNNING

    assert launch(spec, plan, train=held_at_100, stream=io.StringIO()) == 0
    trials = stored_trials(read_url, "outage")
    (resumed,) = check_exact_budget(trials, plan.keys()).values()
    assert resumed.user_attrs["supersedes"] == [held.number]
    assert resumed.user_attrs["resumed_from"] == 100
    assert trials[held.number].user_attrs["error"] == "interrupted: its driver stopped"


@pytest.mark.slow
def test_a_locked_sqlite_database_is_waited_for_within_the_grace(tmp_path, local_ray, monkeypatch):
    """A lock held by another process while the driver records a result: the write meets
    "database is locked", is tried again, and lands once the lock is gone; exit 0."""
    from sweeper.storage import _urls as urls

    monkeypatch.setattr(urls, "SQLITE_TIMEOUT", 0.2)
    spec, plan = prepare(str(one_trial_spec(tmp_path, "locked")))
    locked = []

    def met(context):  # the driver's own writes, not its heartbeat's (which skips a beat)
        heartbeat = threading.current_thread().name == "sweeper-heartbeat"
        if "database is locked" in str(context.original_exception) and not heartbeat:
            locked.append(context.statement)

    stream = io.StringIO()
    codes = []
    running = threading.Thread(
        target=lambda: codes.append(launch(spec, plan, train=held_at_100, stream=stream))
    )
    running.start()
    sqlalchemy.event.listen(sqlalchemy.engine.Engine, "handle_error", met)
    try:
        wait_until(lambda: past_its_checkpoint(spec.storage_url, "locked"), 120, "step 100")
        with write_locked(tmp_path / "study.db"):
            (tmp_path / "release").touch()
            wait_until(lambda: locked, 60, "the driver's write to meet the lock")
        running.join(timeout=120)
    finally:
        sqlalchemy.event.remove(sqlalchemy.engine.Engine, "handle_error", met)
        (tmp_path / "release").touch()
        running.join(timeout=120)
    assert codes == [0], stream.getvalue()
    (trial,) = check_exact_budget(stored_trials(spec.storage_url, "locked"), plan.keys()).values()
    assert trial.value == 0.5 and trial.user_attrs["attempts"] == 1
    assert sorted(trial.intermediate_values) == [0, 100, 200, 300]
