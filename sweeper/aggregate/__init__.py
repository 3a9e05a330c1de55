"""``sweeper aggregate SPEC``: per-method learning curves, the AUC table, figures, a report.

Reads the study once (``load_study_frame``, a few SQL queries over Optuna's tables) into a
tidy frame with one row per (trial, evaluation step), then writes under ``--out``
(default ``runs/<study>/aggregate``):

- ``frame.csv``: the tidy frame; ``curves.csv``: per-method mean/std/n at every step of
  every metric; ``auc_table.csv``: the per-method AUC table; ``improvement.csv``: paired
  probability of improvement between methods;
- ``curves.png`` (a panel per metric: mean ± std per method), ``trials.png`` (a panel per
  metric and method, a line per trial coloured by its AUC), ``auc.png`` (trial AUCs, IQM
  and its 95 % CI);
- ``report.md``, which embeds the figures;

and saves the curves, the AUC figure and the table (a section of the study note) into the
study, where optuna-dashboard shows them (``--no-dashboard`` skips this, the only write).

Which trials count: a plan key may have several Optuna trials (an interrupted or failed
attempt, then its re-run); its *current* trial (the highest number, as in
``sweeper.storage.current_trials``) counts, the others stay in ``frame.csv`` with
``counted = False``. AUC statistics and mean curves use the counted COMPLETE trials
(diverged ones included: their curve is filled with zeros after the divergence).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

# Each module imports pandas, matplotlib, optuna and plotly where used, so that importing
# the package (``sweeper --help``) stays light.
from sweeper.aggregate.dashboard import (
    NOTE_BEGIN,
    NOTE_END,
    replace_note_section,
    save_to_dashboard,
)
from sweeper.aggregate.figures import draw_figures, metric_label
from sweeper.aggregate.frame import (
    TRIAL_COLUMNS,
    StudyInfo,
    load_study_frame,
    methods_of,
    scored,
    study_info,
    trial_rows,
)
from sweeper.aggregate.report import report_markdown, table_markdown
from sweeper.aggregate.tables import (
    AUC_COLUMNS,
    CONFIDENCE,
    RESAMPLES,
    auc_table,
    improvement_table,
    method_curves,
)

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "AUC_COLUMNS",
    "CONFIDENCE",
    "NOTE_BEGIN",
    "NOTE_END",
    "RESAMPLES",
    "TRIAL_COLUMNS",
    "AggregateResult",
    "StudyInfo",
    "aggregate",
    "auc_table",
    "improvement_table",
    "load_study_frame",
    "methods_of",
    "metric_label",
    "replace_note_section",
    "scored",
    "study_info",
    "table_markdown",
    "trial_rows",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``sweeper aggregate``."""
    from sweeper.cli import add_spec_arguments

    add_spec_arguments(parser)
    parser.add_argument(
        "--out", metavar="DIR", help="output folder (default: runs/<study>/aggregate)"
    )
    parser.add_argument(
        "--no-dashboard",
        action="store_true",
        help="do not save the comparison figures and note into the study for optuna-dashboard",
    )


def run(args: argparse.Namespace) -> int:
    """``sweeper aggregate``: exit 0, or 2 with a one-line message on a bad spec or study."""
    from sweeper.cli import spec_from_args

    try:
        spec = spec_from_args(args)
        out = Path(args.out) if args.out else spec.run_dir / "aggregate"
        result = aggregate(
            spec.storage_url, spec.study, out, seed=spec.seed, dashboard=not args.no_dashboard
        )
    except ValueError as e:  # SpecError, StorageError, an unknown or empty study
        print(f"sweeper aggregate: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(result.files)} files to {out}; report: {result.report}")
    return 0


# ---- the whole command ---------------------------------------------------------------


@dataclass(frozen=True)
class AggregateResult:
    """What ``aggregate`` computed and wrote."""

    frame: pd.DataFrame
    curves: pd.DataFrame
    table: pd.DataFrame
    improvement: pd.DataFrame
    files: tuple[Path, ...]
    report: Path


def aggregate(
    storage_url: str,
    study_name: str,
    out: Path,
    *,
    seed: int = 0,
    dashboard: bool = True,
    progress: Callable[[str], None] | None = None,
) -> AggregateResult:
    """Read the study, compute curves and statistics, write CSV, PNG and the report to
    ``out``; with ``dashboard``, also save the comparison into the study."""
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    from sweeper.storage import StudyStore, open_storage

    say = progress or (lambda message: print(message, file=sys.stderr, flush=True))
    start = time.perf_counter()
    frame = load_study_frame(storage_url, study_name)
    say(
        f"read {frame['trial'].nunique()} trials, {len(frame)} rows of study {study_name!r} "
        f"in {time.perf_counter() - start:.1f} s"
    )
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = open_storage(storage_url, create=False)
    try:
        store = StudyStore.find(storage, study_name)
        alive = store is not None and store.driver_alive()
        curves = method_curves(frame)
        table = auc_table(frame, driver_alive=alive, seed=seed)
        improvement = improvement_table(frame)
        out.mkdir(parents=True, exist_ok=True)
        files = [out / n for n in ("frame.csv", "curves.csv", "auc_table.csv", "improvement.csv")]
        for path, data in zip(files, (frame, curves, table, improvement), strict=True):
            data.to_csv(path, index=False)
        say(f"computed the AUC table and curves; drawing figures in {out}")
        figures = draw_figures(frame, curves, table, out)
        report = out / "report.md"
        report.write_text(report_markdown(frame, table, improvement, alive), encoding="utf-8")
        if dashboard and store is not None:
            try:
                save_to_dashboard(storage, store.study_id, frame, curves, table, improvement)
                say("saved the comparison figures and note into the study (optuna-dashboard)")
            except (SQLAlchemyError, optuna.exceptions.StorageInternalError) as e:
                # e.g. a read-only database: the files are written, say so and go on
                say(f"warning: could not save the comparison into the study: {e}")
    finally:
        storage.remove_session()
        storage.engine.dispose()
    say(f"aggregated in {time.perf_counter() - start:.1f} s")
    return AggregateResult(frame, curves, table, improvement, (*files, *figures, report), report)
