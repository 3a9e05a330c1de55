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
- ``report.md``, which embeds the figures; for a study run with successive halving also
  ``halving.csv`` and its section (``sweeper.results._halving_replay``: the first-rung comparison
  over every configuration, the compute spent);

and saves the curves, the AUC figure and the table (a section of the study note) into the
study, where optuna-dashboard shows them (``--no-dashboard`` skips this, the only write).

Which trials count: a plan key may have several Optuna trials (an interrupted or failed
attempt, then its re-run); its *current* trial (the highest number, as in
``sweeper.storage.current_trials``) counts, the others stay in ``frame.csv`` with
``counted = False``. AUC statistics and mean curves use the counted COMPLETE trials
(diverged ones included: their curve is filled with zeros after the divergence).
Trials of the confirmation stage (``sweeper confirm``, ``stage = "confirm"``) stay out of
them: they are reported in a section of their own and ``confirm_table.csv``
(``confirm_table``), the chosen configurations' search AUC beside their AUC on fresh seeds.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

# Each module imports pandas, matplotlib, optuna and plotly where used, so that importing
# the package (``sweeper --help``) stays light.
from sweeper.results._dashboard_card import (
    NOTE_BEGIN,
    NOTE_END,
    replace_note_section,
    save_to_dashboard,
)
from sweeper.results._figures import draw_figures, metric_label
from sweeper.results._frame import (
    TRIAL_COLUMNS,
    StudyInfo,
    load_study_frame,
    methods_of,
    scored,
    stage_frame,
    study_info,
    trial_rows,
)
from sweeper.results._halving_replay import halving_markdown, halving_table
from sweeper.results._pictures import report_pictures
from sweeper.results._report import (
    confirm_markdown,
    report_markdown,
    table_markdown,
    terminal_table,
)
from sweeper.results._tables import (
    AUC_COLUMNS,
    CONFIDENCE,
    RESAMPLES,
    Tables,
    auc_table,
    confirm_table,
    improvement_table,
    iqm_curves,
    method_curves,
    profile_table,
    study_tables,
)
from sweeper.spec import plural
from sweeper.storage import (
    StorageError,
    artifact_location,
    driver_alive,
    is_database_error,
    open_study,
    reason_of,
    redact,
)

if TYPE_CHECKING:
    from sweeper.results._budget import BudgetReport
    from sweeper.spec import StudySpec

__all__ = [
    "AUC_COLUMNS",
    "CONFIDENCE",
    "NOTE_BEGIN",
    "NOTE_END",
    "RESAMPLES",
    "TRIAL_COLUMNS",
    "AggregateResult",
    "StudyInfo",
    "Tables",
    "aggregate",
    "auc_table",
    "confirm_table",
    "improvement_table",
    "iqm_curves",
    "load_study_frame",
    "method_curves",
    "methods_of",
    "metric_label",
    "profile_table",
    "replace_note_section",
    "scored",
    "stage_frame",
    "study_info",
    "study_tables",
    "table_markdown",
    "trial_rows",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``sweeper aggregate`` (``sweeper.cli`` adds the specs and --storage)."""
    parser.add_argument(
        "--out",
        metavar="DIR",
        help="output folder (default: runs/<study>/aggregate; for several specs "
        "runs/combined/<study>+<study>...)",
    )
    parser.add_argument(
        "--no-dashboard",
        action="store_true",
        help="do not save the comparison figures and note into the study for optuna-dashboard "
        "(several specs: nothing is saved into the studies)",
    )


def run(specs: list[StudySpec], args: argparse.Namespace) -> int:
    """``sweeper aggregate``: exit 0, or 2 with a one-line message on a study that cannot be
    read. Reads the studies read-only; the only write is the comparison saved into a single
    study for optuna-dashboard (``--no-dashboard`` skips it).

    One spec: that study's report. Several: one combined report of normalised scores over
    the studies (``sweeper.results._combined``), with the first spec's seed.
    """
    from sweeper.results._combined import aggregate_studies

    try:
        if len(specs) == 1:
            spec = specs[0]
            out = Path(args.out) if args.out else spec.run_dir / "aggregate"
            result = aggregate(
                spec.storage_url,
                spec.study,
                out,
                seed=spec.seed,
                dashboard=not args.no_dashboard,
                artifacts=artifact_location(spec),
            )
        else:
            out = Path(args.out) if args.out else combined_dir([s.study for s in specs])
            studies = [(s.storage_url, s.study) for s in specs]
            result = aggregate_studies(studies, out, seed=specs[0].seed)
    except ValueError as e:  # StorageError, an unknown or empty study
        print(f"sweeper aggregate: {e}", file=sys.stderr)
        return 2
    lines = []
    if len(specs) == 1:  # the answer first, where the command was typed
        lines += [f"study {specs[0].study!r}:", *terminal_table(result.tables), ""]
    figures = [path.name for path in result.files if path.suffix == ".png"]
    lines += [
        f"wrote {plural(len(result.files), 'file')} to {out}",
        f"  report:    {result.report}",
        f"  figures:   {', '.join(figures)}",
    ]
    if len(specs) == 1:
        storage = f" --storage {redact(args.storage[0])}" if args.storage else ""
        lines.append(f"  dashboard: sweeper dashboard {args.spec[0]}{storage}")
    budget = getattr(result, "budget", None)
    if budget is not None:  # several studies of one env: where the budget table is
        lines.append(budget_pointer(budget, out))
    print("\n".join(lines))
    return 0


def budget_pointer(budget: BudgetReport, out: Path) -> str:
    """One line saying where the gradient budget join is and what it holds."""
    left = f"; left out (configurations differ): {', '.join(budget.join.left_out)}"
    return (
        f"gradient budget: {len(budget.table)} encoder x setting rows over "
        f"{', '.join(budget.join.studies)} in {out / 'budget_table.csv'} and {out / 'budget.png'}"
        f" (report.md, section 'Gradient budget'){left if budget.join.left_out else ''}"
    )


def combined_dir(studies: list[str]) -> Path:
    """``runs/combined/<a>+<b>+...``; a long list is shortened to its first name, the count
    and a hash of all names, so the folder name stays valid."""
    import hashlib

    name = "+".join(studies)
    if len(name) > 80:
        digest = hashlib.sha256("\n".join(studies).encode()).hexdigest()[:8]
        name = f"{studies[0]}+{len(studies) - 1}-more-{digest}"
    return Path("runs") / "combined" / name


# ---- the whole command ---------------------------------------------------------------


#: the CSV files of one study's aggregation, and the tables they hold
CSV_FILES = {
    "curves.csv": "curves",
    "efficiency.csv": "efficiency",
    "profiles.csv": "profiles",
    "auc_table.csv": "table",
    "improvement.csv": "improvement",
}


@dataclass(frozen=True)
class AggregateResult:
    """What ``aggregate`` computed and wrote."""

    frame: pd.DataFrame
    tables: Tables
    files: tuple[Path, ...]
    report: Path

    @property
    def curves(self) -> pd.DataFrame:
        return self.tables.curves

    @property
    def table(self) -> pd.DataFrame:
        return self.tables.table

    @property
    def improvement(self) -> pd.DataFrame:
        return self.tables.improvement


def aggregate(
    storage_url: str,
    study_name: str,
    out: Path,
    *,
    seed: int = 0,
    dashboard: bool = True,
    progress: Callable[[str], None] | None = None,
    artifacts: str | None = None,
) -> AggregateResult:
    """Read the study, compute curves and statistics, write CSV, PNG and the report to
    ``out``; with ``dashboard``, also save the comparison into the study; with the study's
    ``artifacts`` location, add pictures to the report (``sweeper.results._pictures``).
    The study is read once, read-only (``load_study_frame``); a study that cannot be written
    (read-only media) gets a warning, not the comparison."""
    say = progress or (lambda message: print(message, file=sys.stderr, flush=True))
    start = time.perf_counter()
    frame = load_study_frame(storage_url, study_name)
    say(
        f"read {plural(frame['trial'].nunique(), 'trial')}, {plural(len(frame), 'row')} of "
        f"study {study_name!r} "
        f"in {time.perf_counter() - start:.1f} s"
    )
    search = stage_frame(frame, "search")  # the confirmation stage is reported apart
    alive = driver_alive(study_info(frame).attrs.get("driver"))
    tables = study_tables(search, driver_alive=alive, seed=seed)
    confirm = confirm_table(frame, driver_alive=alive, seed=seed)
    say(f"computed the tables in {time.perf_counter() - start:.1f} s; writing to {out}")
    files = write_tables(frame, tables, out)
    figures = draw_figures(search, tables, out)
    text = report_markdown(search, tables, alive)
    halving = halving_table(search, seed=seed)
    if halving is not None:  # successive halving: what each comparison covers
        halving.to_csv(out / "halving.csv", index=False)
        files.append(out / "halving.csv")
        text += "\n" + halving_markdown(halving) + "\n"
    if len(confirm):
        confirm.to_csv(out / "confirm_table.csv", index=False)
        files.append(out / "confirm_table.csv")
        seeds = len(study_info(frame).attrs["confirm"]["seeds"])
        text += "\n" + confirm_markdown(confirm, seeds)
    if artifacts is not None:  # final frames per method, the env's view
        pictures, written = report_pictures(search, artifacts, out)
        text += pictures
        figures += written
    report = out / "report.md"
    report.write_text(text, encoding="utf-8")
    if dashboard:
        try:
            with open_study(storage_url, study_name, write=True, create=False) as store:
                save_to_dashboard(store.storage, search, tables)
            say("saved the comparison figures and note into the study (optuna-dashboard)")
        except Exception as e:
            if not (isinstance(e, StorageError) or is_database_error(e)):
                raise
            # e.g. read-only media: the files are written, say so and go on
            say(f"warning: the comparison was not saved into the study: {reason_of(e)}")
    say(f"aggregated in {time.perf_counter() - start:.1f} s")
    return AggregateResult(frame, tables, (*files, *figures, report), report)


def write_tables(frame: pd.DataFrame, tables: Tables, out: Path) -> list[Path]:
    """``frame.csv`` and the ``CSV_FILES`` under ``out``; returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "frame.csv", index=False)
    for name, field in CSV_FILES.items():
        getattr(tables, field).to_csv(out / name, index=False)
    return [out / "frame.csv", *(out / name for name in CSV_FILES)]
