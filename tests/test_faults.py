"""Crashes: a worker killed mid-trial, a driver killed mid-study, Ctrl-C; the ledger stays exact."""

from __future__ import annotations

import contextlib
import dataclasses
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
import pytest
import ray
import sqlalchemy
import torch
from conftest import wait_until, write_ci_spec
from optuna.trial import TrialState

from agent import train
from agent.config import TrialResult
from sweeper.launcher import launch, prepare
from sweeper.storage import open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the fake trains below


def trials_of(url: str, name: str) -> list[optuna.trial.FrozenTrial]:
    """The study's trials, or [] while the driver has not created it yet."""
    try:
        storage = open_storage(url, create=False)  # the driver creates the tables
        try:
            return optuna.load_study(study_name=name, storage=storage).get_trials()
        finally:
            storage.engine.dispose()
    except (KeyError, sqlalchemy.exc.SQLAlchemyError, optuna.exceptions.StorageInternalError):
        return []


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
            return trial.user_attrs.get("worker")

        worker = wait_until(running_worker, 240, "a checkpoint of the victim trial")
        os.kill(worker["pid"], signal.SIGKILL)
    finally:
        driver.join(timeout=300)
    assert codes == [0]
    trials = trials_of(url, "faults")
    assert len(trials) == 2  # a retry stays in its Optuna trial
    by_key = check_exact_budget(trials, plan.keys())
    retried = by_key[victim.key]
    assert retried.user_attrs["attempts"] == 2
    assert len(retried.user_attrs["worker_deaths"]) == 1
    assert "ActorDiedError" in retried.user_attrs["worker_deaths"][0]
    assert retried.user_attrs["worker"]["pid"] != worker["pid"]
    assert retried.user_attrs["resumed_from"] >= 100
    assert by_key[plan.entries[1].key].user_attrs["attempts"] == 1

    torch.set_num_threads(1)
    reference = train(dataclasses.replace(victim.trial_config, checkpoint_dir=None))
    curve = retried.user_attrs["curve"]
    assert curve["step"] == list(reference.steps)
    for name, values in reference.metrics.items():
        assert curve[name] == list(values), name
    assert retried.value == reference.auc
    assert retried.intermediate_values == dict(
        zip(reference.steps, reference.metrics["success_rate"], strict=True)
    )


def start_driver(spec: Path, address: str, log: Path) -> subprocess.Popen:
    """`sweeper launch spec --address ADDR` in its own process group, as from a terminal."""
    return subprocess.Popen(
        [sys.executable, "-m", "sweeper.cli", "launch", str(spec), "--address", address],
        stdout=log.open("a"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=spec.parent,
    )


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
        budget={"env_steps": 200},
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
    )
    keys = prepare(str(spec))[1].keys()
    log = tmp_path / "driver.log"

    def done():
        return [t for t in trials_of(url, "driver") if t.state == TrialState.COMPLETE]

    def done_and_running():
        trials = trials_of(url, "driver")
        running = [t for t in trials if t.state == TrialState.RUNNING and "worker" in t.user_attrs]
        return running and any(t.state == TrialState.COMPLETE for t in trials)

    # 1. SIGKILL the driver after a trial ends, while others run (Ray then kills its actors).
    first = start_driver(spec, local_ray, log)
    try:
        wait_until(done_and_running, 240, "a complete trial and a running one")
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        kill_group(first, signal.SIGKILL)
    finished = {t.number: t.datetime_complete for t in done()}
    stale = {t.number for t in trials_of(url, "driver") if t.state == TrialState.RUNNING}
    assert stale  # the killed driver left trials RUNNING

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
    trials = trials_of(url, "driver")
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
    trials = trials_of(url, "driver")
    by_key = check_exact_budget(trials, keys)
    for number, when in finished.items():
        assert trials[number].state == TrialState.COMPLETE
        assert trials[number].datetime_complete == when
    for trial in trials:
        if "superseded_by" in trial.user_attrs:
            successor = trials[trial.user_attrs["superseded_by"]]
            assert successor.user_attrs["key"] == trial.user_attrs["key"]
            assert trial.number in successor.user_attrs["supersedes"]
    assert all(t.user_attrs["curve"]["step"] == [0, 100, 200] for t in by_key.values())


RACER = """
import sys, time
from agent.config import TrialResult
from sweeper.launcher import launch, prepare
from sweeper.storage import StudyStore

spec_path, release = sys.argv[1], float(sys.argv[2])
claim = StudyStore.claim_driver


def claim_when_released(self):
    while time.time() < release:  # both launches claim in the same millisecond
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
    release = time.time() + 25  # both have joined Ray and opened the study by then
    racers = [
        subprocess.Popen(
            [sys.executable, "-c", RACER, str(spec), str(release)],
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
        )
        for _ in range(2)
    ]
    results = sorted((r.wait(timeout=240), r.stderr.read()) for r in racers)
    assert time.time() > release + 0.5  # the race really happened at the release
    assert [code for code, _ in results] == [0, 3], results
    busy = results[1][1].strip()
    assert len(busy.splitlines()) == 1, busy
    assert busy.startswith("sweeper launch: another `sweeper launch` drives this study")
    trials = trials_of(url, "race")
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
            marker.write_text(str(step))
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
        execution={"retries": 1, "stall_timeout": 4},
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
            return trial.user_attrs.get("worker")

        stopped = wait_until(reporting_worker, 120, "a report of the victim trial")["pid"]
        os.kill(stopped, signal.SIGSTOP)
        driver.join(timeout=90)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(stopped, signal.SIGCONT)  # lets a hung driver finish
        driver.join(timeout=120)
    assert codes == [0]
    trials = trials_of(url, "stall")
    by_key = check_exact_budget(trials, plan.keys())
    assert len(trials) == 2
    retried = by_key[victim.key]
    assert retried.user_attrs["attempts"] == 2
    assert "no answer" in retried.user_attrs["worker_deaths"][0]
    assert retried.user_attrs["resumed_from"] >= 100


CONFIRMER = """
import sys, time, zlib
from pathlib import Path
from agent.config import TrialResult
from sweeper.confirmation import confirm
from sweeper.launcher import launch, prepare

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
    searched = {t.number: t.datetime_complete for t in trials_of(url, "confirm")}
    assert len(searched) == len(search_keys) == 6

    def confirming():
        return [t for t in trials_of(url, "confirm") if t.user_attrs.get("stage") == "confirm"]

    # 1. SIGKILL a worker of the confirm stage after its trial's first checkpoint
    first = driver("confirm")
    try:

        def checkpointed_worker():
            for trial in confirming():
                if trial.state == TrialState.RUNNING and 100 in trial.intermediate_values:
                    return trial.user_attrs["key"], trial.user_attrs["worker"]["pid"]
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
    assert retried.user_attrs["attempts"] == 2 and len(retried.user_attrs["worker_deaths"]) == 1
    assert retried.user_attrs["resumed_from"] >= 100

    # 3. relaunch the stage to the end: exact, nothing re-chosen, the search untouched
    second = driver("confirm")
    try:
        assert second.wait(timeout=240) == 0, log.read_text()
    finally:
        kill_group(second, signal.SIGKILL)
    trials = trials_of(url, "confirm")
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
    """An SQLite engine hook: recording a trial's value fails as on a full disk."""
    if statement.lstrip().upper().startswith("INSERT INTO TRIAL_VALUES"):
        raise sqlite3.OperationalError("database or disk is full")


@pytest.mark.slow
def test_a_full_disk_mid_launch_exits_2_with_one_line_and_a_relaunch_finishes(tmp_path, local_ray):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec_path = write_ci_spec(
        tmp_path / "spec.yaml",
        study="full",
        storage=url,
        checkpoints=str(tmp_path / "checkpoints"),
        execution={"address": local_ray},
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
    assert not [t for t in trials_of(url, "full") if t.state == TrialState.COMPLETE]

    assert launch(spec, plan, train=instant, stream=io.StringIO()) == 0  # nothing was lost
    check_exact_budget(trials_of(url, "full"), plan.keys())
