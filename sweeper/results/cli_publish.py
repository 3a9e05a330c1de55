"""``sweeper publish SPEC [--out DIR]``: a study's database, ledger, videos and report in one
folder (``docs/studies/<study>`` by default), for anyone to re-aggregate and re-run.

Safe while the study runs, so a long study can be published as it goes:

- ``study.db``: a copy of the SQLite database taken with SQLite's backup API (consistent
  while the driver writes), one self-contained file (no ``-wal``). The copy is not driven:
  its driver record is released, so readers of the copy count its RUNNING trials as a
  relaunch would (not running) wherever and whenever they read it, and the report written
  here is the report anyone gets by aggregating the copy again. Its trials recorded in an
  older format are rewritten in today's (``StudyStore.upgrade``: nothing a reader gets
  changes), on the copy only: the live study's driver writes as its code does.
- ``artifacts/``: the trials' videos, when the study keeps them in a local folder.
- ``status.txt``: ``sweeper status`` of the copy, when it was taken, and the videos of
  finished trials that are missing from ``artifacts/``.
- ``aggregate/``: ``sweeper aggregate`` of the copy (nothing saved into it for the
  dashboard: the copy holds what the driver last saved).

The copy is checked with SQLite's ``integrity_check`` before it replaces anything: a
damaged study is refused with one line, and the folder is left as it was. A study not
finished yet is published as it is, with a line saying that the copy is partial.

Only SQLite studies: a PostgreSQL study is refused with one line (copy it into SQLite with
``optuna copy-study`` first). Exit 0; or 2 with one line; or 2 after publishing, with one
line per video of a finished trial that is not in ``artifacts/`` (a video cannot be made
again without running its trial again).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import shutil
import sqlite3
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from sweeper.results.cli_aggregate import aggregate
from sweeper.results.cli_status import status_lines
from sweeper.spec import plural
from sweeper.storage import (
    DONE_STATES,
    StorageError,
    StudyStore,
    artifact_location,
    damage,
    damaged_error,
    is_damaged,
    ledger,
    open_study,
    redact,
    sqlite_path,
    trial_artifacts,
)

if TYPE_CHECKING:
    from sweeper.spec import StudySpec
    from sweeper.storage import Upgrade


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The output folder (``sweeper.cli`` adds the spec and --storage)."""
    parser.add_argument("--out", metavar="DIR", help="the folder (default: docs/studies/<study>)")


def copy_database(source: Path, target: Path) -> None:
    """``source`` copied to ``target`` with SQLite's backup API, as one file (journal mode
    DELETE), replacing ``target`` only once the copy passes SQLite's integrity check (else a
    StorageError, and ``target`` is left as it was); the source is opened read-only."""
    made = not target.parent.exists()
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(target.name + ".partial")
    partial.unlink(missing_ok=True)

    def undo() -> None:  # nothing half-written stays behind
        partial.unlink(missing_ok=True)
        if made:
            with contextlib.suppress(OSError):  # not empty: someone else's files
                target.parent.rmdir()

    try:
        live = sqlite3.connect(f"file:{source}?mode=ro", uri=True)
        copy = sqlite3.connect(partial)
        try:
            live.backup(copy)
            copy.execute("PRAGMA journal_mode=DELETE")
        finally:
            copy.close()
            live.close()
        problem = damage(partial, thorough=True)
    except sqlite3.DatabaseError as e:  # the source cannot even be read whole
        if not is_damaged(e):
            undo()
            raise
        problem = str(e)
    except BaseException:
        undo()
        raise
    if problem is not None:
        undo()
        raise damaged_error(f"sqlite:///{source}", problem)
    partial.replace(target)


def unfinished(store: StudyStore) -> tuple[int, int] | None:
    """``(done, planned)`` trials of the published copy (its plan, and the keys of a
    confirmation stage), or None when every planned trial is done. The copy is not
    driven: a trial RUNNING there is left, as a relaunch would count it."""
    attrs = store.attrs
    keys = [*(attrs.get("plan") or []), *((attrs.get("confirm") or {}).get("keys") or [])]
    counts = ledger(keys, store.trials(), driver_alive=False).values()
    done, planned = sum(c.done for c in counts), sum(c.planned for c in counts)
    return None if done == planned else (done, planned)


def settle_copy(store: StudyStore) -> Upgrade:
    """Mark the copied study as not driven (its driver record released, as a driver that
    stops releases it), then rewrite its trials recorded in an older format in today's
    (``StudyStore.upgrade``)."""
    store.set_study_attr("driver", None)
    return store.upgrade()


def missing_videos(store: StudyStore, folder: Path) -> list[str]:
    """One line per video (artifact) of a finished trial (COMPLETE or PRUNED) whose file is
    not in ``folder``: the trial, its key, the file's name and id."""
    lines = []
    for trial in store.trials():
        if trial.state.name not in DONE_STATES:
            continue
        metas = trial_artifacts(store.storage, trial._trial_id)
        for meta in sorted(metas, key=lambda meta: meta["filename"]):
            if not (folder / meta["artifact_id"]).is_file():
                lines.append(
                    f"trial {trial.number} ({trial.user_attrs.get('key')}): its video "
                    f"{meta['filename']} is missing ({folder.name}/{meta['artifact_id']})"
                )
    return lines


def write_status(
    copy: StudySpec, store: StudyStore, source: str, out: Path, missing: list[str]
) -> None:
    """``status.txt``: ``sweeper status`` of the copy (``copy``: the spec with the copy's
    storage), where and when it was taken from, the missing videos."""
    lines = status_lines(copy, store)
    taken = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    with (out / "status.txt").open("w", encoding="utf-8") as stream:
        print(f"study {copy.study!r} in {redact(copy.storage_url)}", file=stream)
        print("\n".join(lines), file=stream)
        print(f"copied from {redact(source)} at {taken}", file=stream)
        for line in missing:
            print(line, file=stream)


def run(spec: StudySpec, args: argparse.Namespace) -> int:
    """``sweeper publish``: exit 0; 2 with one line; or 2 once published, with a line per
    missing video."""
    out = Path(args.out) if args.out else Path("docs") / "studies" / spec.study
    try:
        source = sqlite_path(spec.storage_url)
        if source is None:
            raise StorageError(
                f"{redact(spec.storage_url)} is not SQLite: copy the study into a SQLite "
                "file first (optuna copy-study) and publish that with --storage"
            )
        if not source.is_file():
            raise StorageError(f"no database file at {source}: launch the study first")
        database = out / "study.db"
        if database.resolve() == source.resolve():
            raise StorageError(f"{database} is the study's own database: publish elsewhere")
        copy_database(source, database)
        url = f"sqlite:///{database}"
        videos = Path(artifact_location(spec))
        copied = videos.is_dir()
        if copied:
            shutil.copytree(videos, out / "artifacts", dirs_exist_ok=True)
        with open_study(url, spec.study, write=True, create=False) as store:  # the copy
            upgraded = settle_copy(store)
            missing = missing_videos(store, out / "artifacts")
            write_status(spec.with_overrides(storage=url), store, spec.storage_url, out, missing)
            partial = unfinished(store)
        artifacts = str(out / "artifacts") if copied else None
        result = aggregate(url, spec.study, out / "aggregate", seed=spec.seed, dashboard=False,
                           artifacts=artifacts)  # fmt: skip
    except (ValueError, OSError, sqlite3.Error) as e:  # StorageError is a ValueError
        print(f"sweeper publish: {e}", file=sys.stderr)
        return 2
    if upgraded.params or upgraded.curves or upgraded.values:
        trials, curves = plural(upgraded.params, "trial"), plural(upgraded.curves, "curve")
        print(f"rewrote the copy's older records in today's format: the params of {trials}, "
              f"{curves}, the worker, machines and videos of "
              f"{plural(upgraded.values, 'trial')}")  # fmt: skip
    print(f"published study {spec.study!r} to {out}: study.db, status.txt, "
          f"{'artifacts/, ' if copied else ''}aggregate/ (report: {result.report})")  # fmt: skip
    if partial is not None:
        done, planned = partial
        print(f"the study is unfinished ({done} of {planned} trials done): the published copy "
              "is partial; publish again once it ends")  # fmt: skip
    for line in missing:
        print(f"sweeper publish: {line}", file=sys.stderr)
    return 2 if missing else 0
