"""``sweeper status SPEC``: the per-method ledger of a study (done, running, failed, left),
and where each running trial is.

Counts are per plan key (``sweeper.storage._ledger``): a key re-run after a crash is
counted once, by its current trial. Reads only, on read-only connections opened once
(``sweeper.storage.open_for_reading``); never creates the study or its file.
"""

from __future__ import annotations

import argparse
import datetime
import sys
from typing import TYPE_CHECKING, TextIO

from agent.config import Outcome
from sweeper.plan import build_plan, format_duration, in_spec_order
from sweeper.spec import plural
from sweeper.storage import (
    NoStudy,
    StudyStore,
    check_plan,
    current_trials,
    curve_of,
    ledger,
    open_for_reading,
    redact,
    stored_files,
)

if TYPE_CHECKING:
    from optuna.trial import FrozenTrial

    from sweeper.spec import StudySpec


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``sweeper status`` has no options of its own (``sweeper.cli`` adds the spec and
    --storage)."""


def run(spec: StudySpec, args: argparse.Namespace, stream: TextIO | None = None) -> int:
    """``sweeper status``: print the ledger; exit 0, or 2 when the study cannot be read or
    was launched with another plan."""
    stream = sys.stdout if stream is None else stream
    try:
        with open_for_reading(spec) as store:
            lines = status_lines(spec, store)
    except ValueError as e:  # StorageError, a plan the spec cannot give
        print(f"sweeper status: {e}", file=sys.stderr)
        return 2
    print(f"study {spec.study!r} in {redact(spec.storage_url)}", file=stream)
    print("\n".join(lines), file=stream)
    return 0


def status_lines(spec: StudySpec, store: StudyStore | NoStudy) -> list[str]:
    """The ledger table and notes of the study of ``spec``, opened as ``store`` (or the
    ``NoStudy`` saying why there is none), the methods in the spec's order. Raises
    StorageError when the study was launched with another plan."""
    plan = build_plan(stored_files(spec, store))
    methods = list(spec.methods)
    keys = in_spec_order(plan.keys(), methods)
    if isinstance(store, NoStudy):
        return [*_table(ledger(keys, [], False)), f"not launched yet ({store.why})"]
    check_plan(spec.study, store.attrs, plan.hash)
    attrs = store.attrs
    trials = store.trials()
    alive = store.driver_alive()
    lines = _table(ledger(keys, trials, alive))
    confirm = attrs.get("confirm")
    if confirm:  # the confirmation stage (sweeper confirm), counted apart
        lines.append(
            f"confirmation stage: top {plural(confirm['top_k'], 'configuration')} per method "
            f"on {plural(len(confirm['seeds']), 'fresh seed')} "
            f"({', '.join(map(str, confirm['seeds']))})"
        )
        confirm_keys = in_spec_order(confirm["keys"], methods)
        lines += _table(ledger(confirm_keys, trials, alive))
        keys = [*keys, *confirm_keys]
    driver = attrs.get("driver")
    current = current_trials(trials)
    if alive:
        lines.append(f"driver: running (host {driver['host']}, pid {driver['pid']})")
        now = datetime.datetime.now()  # Optuna's datetimes are the writer's local time
        for key in keys:
            trial = current.get(key)
            if trial is not None and trial.state.name == "RUNNING":
                lines.append(running_line(key, trial, spec.budget.env_steps, now))
    else:
        lines.append("driver: not running")
    for key in keys:
        trial = current.get(key)
        if trial is None or trial.state.name != "FAIL":
            continue
        if trial.user_attrs.get("outcome") == Outcome.INTERRUPTED:
            lines.append(f"interrupted: {key} (trial {trial.number}); a launch resumes it")
        else:
            error = str(trial.user_attrs.get("error", "no error recorded")).splitlines()[0]
            lines.append(f"failed: {key} (trial {trial.number}): {error}")
    if not alive and any(t.state.name == "RUNNING" for t in current.values()):
        lines.append("trials marked RUNNING have no live driver; a launch resumes them")
    return lines


def running_line(key: str, trial: FrozenTrial, env_steps: int, now: datetime.datetime) -> str:
    """Where a running trial is: the env step of its last evaluation (a trial reports at
    evaluations only), and how long ago it started."""
    curve = curve_of(trial)
    step = curve["step"][-1] if curve else None
    where = "no evaluation yet" if step is None else f"step {step:,} of {env_steps:,}"
    if step is not None and step == trial.user_attrs.get("paused_at"):
        where += ", at its rung"  # successive halving: it waits there for the decision
    since = format_duration((now - trial.datetime_start).total_seconds())
    return f"running: {key} (trial {trial.number}): {where}, started {since} ago"


def _table(counts: dict) -> list[str]:
    columns = ("planned", "done", "diverged", "running", "failed", "left")
    width = max([len("method"), len("total"), *(len(m) for m in counts)])
    header = f"{'method':<{width}}" + "".join(f"{c:>10}" for c in columns)
    rows = [header]
    totals = dict.fromkeys(columns, 0)
    for method, line in counts.items():
        values = [getattr(line, c) for c in columns]
        rows.append(f"{method:<{width}}" + "".join(f"{v:>10}" for v in values))
        for c, v in zip(columns, values, strict=True):
            totals[c] += v
    rows.append(f"{'total':<{width}}" + "".join(f"{totals[c]:>10}" for c in columns))
    return rows
