"""The ledger rules, pure functions over ``(key, state, outcome)``.

One Optuna trial per plan key ``"{method}/{config_id}/{seed}"``; a key that has to be run
again gets a fresh trial, and the trial with the highest number is the key's *current*
trial (``current_numbers``, ``current_trials``). A key's ledger column (``KeyStatus``:
done, running, failed, left) comes from its current trial alone (``key_status``), and the
ledger counts keys, never trials (``tally``, ``ledger``), so the counts are exact. The
writer's sync and every reader (``sweeper status``, ``sweeper aggregate``) count by these.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from agent.config import Outcome
from sweeper.storage._attrs import trial_attr

if TYPE_CHECKING:
    from optuna.trial import FrozenTrial


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


#: the Optuna states of a key that is done
DONE_STATES = ("COMPLETE", "PRUNED")


def key_status(state: str | None, outcome: Any, driver_alive: bool) -> KeyStatus:
    """The ledger column of a plan key: done, running, failed or left, from its
    current trial's state name and ``outcome`` attr (``state=None``: no trial yet).

    A RUNNING trial counts as running only while a driver is alive; otherwise its driver
    died and the key is left for the next launch, like an interrupted one. A PRUNED trial
    (stopped at a rung of successive halving) is done: it spent its share of the budget.
    """
    if state is None or state == "WAITING":
        return KeyStatus.LEFT
    if state in DONE_STATES:
        return KeyStatus.DONE
    if state == "RUNNING":
        return KeyStatus.RUNNING if driver_alive else KeyStatus.LEFT
    return KeyStatus.LEFT if outcome == Outcome.INTERRUPTED else KeyStatus.FAILED


def tally(
    keys: Iterable[str],
    current: Mapping[str, tuple[str | None, Any]],
    driver_alive: bool,
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


def measured_seconds(trials: Iterable[tuple[str, float]]) -> dict[str, float]:
    """Per method, the mean of its finished trials' recorded seconds (``(method, seconds)``
    pairs)."""
    by_method: dict[str, list[float]] = {}
    for method, seconds in trials:
        by_method.setdefault(method, []).append(seconds)
    return {m: sum(v) / len(v) for m, v in by_method.items()}


def finished(
    trials: Iterable[FrozenTrial], keys: Iterable[str], here: Mapping[str, str] | None = None
) -> tuple[set[str], dict[str, float]]:
    """(the ``keys`` done, per method the mean seconds of its done trials) of a study's
    ``trials``, by each key's current trial. ``here`` (``{"cpu": ..., "threads": ...}``, as
    ``agent.machine.describe`` records them): only the seconds of trials every run of which
    was recorded with that CPU and those threads count (the project's CPU kinds run one
    trial up to twice as fast as one another; a trial at 2 threads 1.6 times as fast)."""
    current = current_trials(trials)
    done = {k for k in keys if k in current and current[k].state.name == "COMPLETE"}
    seconds = [
        (k.split("/")[0], float(current[k].user_attrs["seconds"]))
        for k in sorted(done)
        if current[k].user_attrs.get("seconds") and (here is None or ran_on(current[k], here))
    ]
    return done, measured_seconds(seconds)


def ran_on(trial: FrozenTrial, here: Mapping[str, str]) -> bool:
    """Whether every run of ``trial`` was recorded with ``here``'s fields (a trial recorded
    before a field was, or without machines, was not)."""
    machines = trial_attr(trial, "machines")
    return (
        isinstance(machines, list)
        and bool(machines)
        and all(
            isinstance(run, Mapping) and all(run.get(k) == v for k, v in here.items())
            for run in machines
        )
    )
