"""``sweeper status SPEC``: the per-method ledger of a study (done, running, failed, left).

Counts are per plan key (``sweeper.storage.ledger``): a key re-run after a crash is
counted once, by its current trial. Reads only; never creates the study or its file.
"""

from __future__ import annotations

import argparse
import sys
from typing import TextIO


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``sweeper status``."""
    from sweeper.cli import add_spec_arguments

    add_spec_arguments(parser)


def run(args: argparse.Namespace, stream: TextIO | None = None) -> int:
    """``sweeper status``: print the ledger; exit 0, or 2 on a bad spec or storage."""
    from sweeper.launch import prepare
    from sweeper.storage import StorageError, redact

    stream = sys.stdout if stream is None else stream
    try:
        spec, plan = prepare(args.spec, storage=args.storage)
        lines = status_lines(spec.study, spec.storage_url, plan.keys(), plan.hash)
    except (ValueError, StorageError) as e:
        print(f"sweeper status: {e}", file=sys.stderr)
        return 2
    print(f"study {spec.study!r} in {redact(spec.storage_url)}", file=stream)
    print("\n".join(lines), file=stream)
    return 0


def status_lines(study: str, url: str, keys: list[str], plan_hash: str) -> list[str]:
    """The ledger table and notes of ``study`` in ``url`` for the planned ``keys``."""
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    from sweeper.storage import (
        StorageError,
        StudyStore,
        current_trials,
        database_error,
        ledger,
        open_storage,
        resolve_url,
        sqlite_path,
    )

    path = sqlite_path(resolve_url(url))
    if path is not None and not path.exists():
        return [*_table(ledger(keys, [], False)), "not launched yet (no database file)"]
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        storage = open_storage(url, create=False)
    except (SQLAlchemyError, optuna.exceptions.StorageInternalError) as e:
        raise database_error("cannot read", url, e) from None
    try:
        store = StudyStore.find(storage, study)
        if store is None:
            return [*_table(ledger(keys, [], False)), "not launched yet (no such study)"]
        attrs = store.attrs
        if attrs.get("plan_hash") not in (None, plan_hash):
            raise StorageError(
                f"study {study!r} was launched with another plan (plan_hash "
                f"{attrs['plan_hash'][:12]}, this spec gives {plan_hash[:12]})"
            )
        trials = store.trials()
        alive = store.driver_alive()
    finally:
        storage.remove_session()
        storage.engine.dispose()
    lines = _table(ledger(keys, trials, alive))
    confirm = attrs.get("confirm")
    if confirm:  # the confirmation stage (sweeper confirm), counted apart
        lines.append(
            f"confirmation stage: top {confirm['top_k']} configurations per method on seeds "
            f"{', '.join(map(str, confirm['seeds']))}"
        )
        lines += _table(ledger(confirm["keys"], trials, alive))
        keys = [*keys, *confirm["keys"]]
    driver = attrs.get("driver")
    if alive:
        lines.append(f"driver: running (host {driver['host']}, pid {driver['pid']})")
    else:
        lines.append("driver: not running")
    current = current_trials(trials)
    for key in keys:
        trial = current.get(key)
        if trial is None or trial.state.name != "FAIL":
            continue
        if trial.user_attrs.get("outcome") == "interrupted":
            lines.append(f"interrupted: {key} (trial {trial.number}); a launch resumes it")
        else:
            error = str(trial.user_attrs.get("error", "no error recorded")).splitlines()[0]
            lines.append(f"failed: {key} (trial {trial.number}): {error}")
    if not alive and any(t.state.name == "RUNNING" for t in current.values()):
        lines.append("trials marked RUNNING have no live driver; a launch resumes them")
    return lines


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
