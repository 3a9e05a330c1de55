"""The Markdown report and the study note's section."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

from sweeper.aggregate.frame import study_info, trial_rows
from sweeper.aggregate.tables import CONFIDENCE, RESAMPLES

if TYPE_CHECKING:
    import pandas as pd


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def table_markdown(table: pd.DataFrame, improvement: pd.DataFrame) -> str:
    """The AUC table and the probability-of-improvement matrix as Markdown."""
    lines = [
        "| method | planned | done | diverged | running | failed | left | mean AUC | std "
        f"| median | IQM [{CONFIDENCE:.0%} CI] | best trial |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for row in table.to_dict("records"):
        interval = (
            f"{_fmt(row['iqm'])} [{_fmt(row['iqm_low'])}, {_fmt(row['iqm_high'])}]"
            if row["n"]
            else "–"
        )
        best = (
            f"#{row['best_trial']} {row['best_key']}: {_fmt(row['best_auc'])} "
            f"({row['best_params']})"
            if row["n"]
            else "–"
        )
        lines.append(
            f"| {row['method']} | {row['planned']} | {row['done']} | {row['diverged']} "
            f"| {row['running']} | {row['failed']} | {row['left']} | {_fmt(row['mean'])} "
            f"| {_fmt(row['std'])} | {_fmt(row['median'])} | {interval} | {best} |"
        )
    methods = table["method"].tolist()
    if len(methods) > 1:
        lookup = {(r.method, r.versus): r for r in improvement.itertuples()}
        lines += [
            "",
            "Probability of improvement P(row > column), paired by SAC configuration and seed "
            "(number of pairs in brackets):",
            "",
            "| | " + " | ".join(methods) + " |",
            "|---|" + "---:|" * len(methods),
        ]
        for x in methods:
            cells = [
                "–"
                if (x, y) not in lookup
                else f"{_fmt(lookup[x, y].probability, 2)} ({lookup[x, y].pairs})"
                for y in methods
            ]
            lines.append(f"| {x} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


DEFINITIONS = f"""\
How to read this: a trial's AUC is the area under its success-rate curve over the evaluation
grid divided by the grid's length (0: never succeeds, 1: always). Statistics use each plan
key's current trial when it is done (COMPLETE; diverged trials count, with zero success after
the divergence). IQM: mean of the middle 50 % of a method's AUCs. Its confidence interval:
percentile bootstrap, {RESAMPLES} resamples of the method's own trials (stratified by method),
seeded. Probability of improvement of A over B: over the (SAC configuration, seed) pairs where
both are done, the fraction where A's AUC is higher, ties counting one half."""


def report_markdown(frame, table, improvement, driver_alive: bool) -> str:
    study = study_info(frame).attrs
    trials = trial_rows(frame)
    lines = [
        f"# Study `{study_info(frame).name}`: method comparison",
        "",
        f"Env `{study.get('env', 'unknown')}`, code revision `{study.get('revision', 'unknown')}`, "
        f"{trials['trial'].nunique()} Optuna trials for {trials['key'].nunique()} plan keys; "
        f"written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
        "",
    ]
    if (table["running"] + table["left"]).sum():
        status = "a driver is running it" if driver_alive else "no driver is running it"
        lines += [
            f"**Partial study** ({status}): {int(table['running'].sum())} trials running and "
            f"{int(table['left'].sum())} left; the statistics cover done trials only.",
            "",
        ]
    lines += ["## AUC per method", "", table_markdown(table, improvement), "", DEFINITIONS, ""]
    lines += [
        "![AUC per method](auc.png)",
        "",
        "## Learning curves",
        "",
        "![mean and std of every metric per method](curves.png)",
        "",
        "Every trial (grey dashed: unfinished; red dotted: failed):",
        "",
        "![every trial's curves coloured by AUC](trials.png)",
        "",
        "Data: `frame.csv` (one row per trial and evaluation step), `curves.csv`, "
        "`auc_table.csv`, `improvement.csv`.",
        "",
    ]
    return "\n".join(lines)
