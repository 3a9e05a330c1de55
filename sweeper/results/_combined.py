"""``sweeper aggregate A.yaml B.yaml ...``: one report over several studies (envs).

Each study's trials are scored on its own scale (``sweeper.results._normalize``: 0 = the
random agent's success rate, 1 = the study's best control), then pooled per method: IQM,
mean, median and optimality gap of the normalised AUC and final success rate, each with a
95 % stratified bootstrap interval in which every study is a stratum (a study's trials are
resampled among themselves, so each study keeps its weight in every replicate), and
performance profiles of the normalised scores with the same resampling. Every study's own
AUC table (ledger, statistics, compute, best trial) and paired probability of improvement
follow. A study that cannot be normalised is listed with the reason and left out of the
pooled statistics, never an error.

Written to ``out``: ``anchors.csv`` (per study: env, random rate, control, its IQM AUC and
final success, problem), ``normalized_scores.csv`` (per trial of the normalised studies),
``normalized_table.csv`` (per method and score), ``normalized_profiles.csv``,
``study_tables.csv`` and ``study_improvement.csv`` (every study's tables with a ``study``
column), ``normalized.png``, ``normalized_profiles.png`` and ``report.md``.

Studies that share an env are also joined by encoder, configuration and seed with the
gradient budget as an axis (``sweeper.results._budget``): ``budget_table.csv``,
``budget_controls.csv``, ``budget.png`` and a section of ``report.md``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from sweeper.results._budget import BudgetReport, budget_report
from sweeper.results._frame import load_study_frame, methods_of, stage_frame, study_info
from sweeper.results._normalize import (
    SCORES,
    Anchors,
    normalized_scores,
    study_anchors,
    trial_scores,
)
from sweeper.results._report import _fmt, _interval, table_markdown
from sweeper.results._stats import SUMMARIES, Group, several, stratified_bootstrap
from sweeper.results._tables import (
    CONFIDENCE,
    RESAMPLES,
    auc_table,
    improvement_table,
    profile_frame,
)
from sweeper.spec import plural
from sweeper.storage import driver_alive

#: thresholds of the normalised profiles: a method may beat its study's control (tau > 1)
NORMALIZED_TAUS = tuple(i / 100 for i in range(0, 151))
SCORE_LABELS = {"auc": "normalised AUC", "final_success": "normalised final success"}


@dataclass(frozen=True)
class CombinedResult:
    """What ``aggregate_studies`` computed and wrote."""

    anchors: pd.DataFrame  # one row per study
    scores: pd.DataFrame  # normalised scores, one row per trial of a normalised study
    table: pd.DataFrame  # per method and score: pooled statistics with intervals
    profiles: pd.DataFrame
    study_tables: pd.DataFrame  # every study's auc_table, with a ``study`` column
    files: tuple[Path, ...]
    report: Path
    budget: BudgetReport | None = None  # the studies share an env: the budget join


def normalized_table(scores: pd.DataFrame, methods: list[str], *, seed: int = 0) -> pd.DataFrame:
    """Per method and score (``SCORES``): the studies and trials it pools, and
    ``sweeper.results._stats.SUMMARIES`` of the normalised score (optimality gap below 1, the best
    control) each with ``_low``/``_high``: a stratified bootstrap, each study a stratum."""
    rows = []
    for score in SCORES:
        groups = {
            m: Group((part[f"{score}_norm"].to_numpy(),), part["study"].to_numpy())
            for m, part in scores.groupby("method")
        }
        intervals = stratified_bootstrap(
            several(*SUMMARIES.values()),
            groups,
            reps=RESAMPLES,
            seed=seed,
            confidence=CONFIDENCE,
        )
        for method in methods:
            if method not in groups:
                continue
            part = scores[scores["method"] == method]
            row: dict[str, Any] = {
                "method": method,
                "score": score,
                "studies": part["study"].nunique(),
                "n": len(part),
            }
            for index, name in enumerate(SUMMARIES):
                point, low, high = (float(v[index]) for v in intervals[method])
                row.update({name: point, f"{name}_low": low, f"{name}_high": high})
            rows.append(row)
    columns = ["method", "score", "studies", "n"]
    columns += [f"{n}{s}" for n in SUMMARIES for s in ("", "_low", "_high")]
    return pd.DataFrame(rows, columns=columns)


def normalized_profiles(scores: pd.DataFrame, methods: list[str], *, seed: int = 0):
    """Performance profiles of the normalised scores, resampled within studies."""
    values = {
        s: {m: p[f"{s}_norm"].to_numpy() for m, p in scores.groupby("method")} for s in SCORES
    }
    strata = {s: {m: p["study"].to_numpy() for m, p in scores.groupby("method")} for s in SCORES}
    return profile_frame(values, methods, seed=seed, strata=strata, taus=NORMALIZED_TAUS)


def anchors_frame(anchors: Sequence[Anchors]) -> pd.DataFrame:

    return pd.DataFrame(
        [
            {
                "study": a.study,
                "env": a.env,
                "random_success": a.random,
                "control": a.control,
                "control_iqm_auc": a.control_auc,
                "control_iqm_final_success": a.control_final_success,
                "normalized": a.problem is None,
                "problem": a.problem,
            }
            for a in anchors
        ]
    )


def aggregate_studies(
    studies: Sequence[tuple[str, str]],
    out: Path,
    *,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> CombinedResult:
    """Read every ``(storage_url, study_name)``, normalise, pool, write the combined report
    to ``out``. Reads only. Raises ValueError for a study that cannot be read."""
    say = progress or (lambda message: print(message, file=sys.stderr, flush=True))
    start = time.perf_counter()
    labels = _labels([name for _, name in studies])
    frames, anchors, normalized, tables, improvements = [], [], [], [], []
    for (url, name), label in zip(studies, labels, strict=True):
        frame = stage_frame(load_study_frame(url, name), "search")  # confirm: its own report
        scores = trial_scores(frame)
        anchor = study_anchors(frame, scores)
        anchors.append(anchor)
        normalized.append(normalized_scores(scores, anchor).assign(study=label, env=anchor.env))
        alive = driver_alive(study_info(frame).attrs.get("driver"))
        tables.append(auc_table(frame, driver_alive=alive, seed=seed).assign(study=label))
        improvements.append(improvement_table(frame, seed=seed).assign(study=label))
        frames.append(frame)
        why = f"not normalised: {anchor.problem}" if anchor.problem else "normalised"
        say(f"read study {label!r} ({plural(frame['trial'].nunique(), 'trial')}): {why}")
    methods = list(dict.fromkeys(m for frame in frames for m in methods_of(frame)))
    scores = pd.concat(normalized, ignore_index=True)
    table = normalized_table(scores, methods, seed=seed)
    profiles = normalized_profiles(scores, methods, seed=seed)
    say(f"pooled the normalised scores in {time.perf_counter() - start:.1f} s; writing to {out}")

    out.mkdir(parents=True, exist_ok=True)
    anchor_rows = anchors_frame(anchors).assign(study=labels)
    study_tables = pd.concat(tables, ignore_index=True)
    written = {
        "anchors.csv": anchor_rows,
        "normalized_scores.csv": scores,
        "normalized_table.csv": table,
        "normalized_profiles.csv": profiles,
        "study_tables.csv": study_tables,
        "study_improvement.csv": pd.concat(improvements, ignore_index=True),
    }
    for file, data in written.items():
        data.to_csv(out / file, index=False)
    figures = [
        draw_normalized(table, out / "normalized.png"),
        _draw_profiles(profiles, out / "normalized_profiles.png"),
    ]
    budget = None
    envs = {a.env for a in anchors}
    if len(envs) == 1 and None not in envs:  # one env: the gradient budget as an axis
        budget = budget_report(list(zip(labels, frames, strict=True)), out, seed=seed)
        figures += budget.files
    report = out / "report.md"
    text = combined_markdown(
        anchor_rows, table, tables, improvements, budget.markdown if budget else None
    )
    report.write_text(text, encoding="utf-8")
    say(f"aggregated {len(studies)} studies in {time.perf_counter() - start:.1f} s")
    files = (*(out / f for f in written), *figures, report)
    return CombinedResult(anchor_rows, scores, table, profiles, study_tables, files, report, budget)


def _labels(names: list[str]) -> list[str]:
    """Study names, made unique (two storages may hold studies of the same name)."""
    return [
        n if names.count(n) == 1 else f"{n}#{names[:i].count(n) + 1}" for i, n in enumerate(names)
    ]


def _draw_profiles(profiles: pd.DataFrame, path: Path) -> Path:
    from sweeper.results._figures import draw_profiles

    return draw_profiles(profiles, path, "all studies, normalised", SCORE_LABELS)


def draw_normalized(table: pd.DataFrame, path: Path) -> Path:
    """Per method and score: IQM of the normalised score with its interval, and the mean."""
    from matplotlib.figure import Figure

    methods = list(dict.fromkeys(table["method"]))
    figure = Figure(figsize=(1.2 * len(methods) + 6, 4.5), layout="constrained")
    grid = figure.subplots(1, len(SCORES), sharey=True)
    for axes, score in zip(grid, SCORES, strict=True):
        part = table[table["score"] == score].set_index("method")
        for x, method in enumerate(methods):
            if method not in part.index:
                continue
            row = part.loc[method]
            error = [[row["iqm"] - row["iqm_low"]], [row["iqm_high"] - row["iqm"]]]
            axes.errorbar(x, row["iqm"], yerr=error, fmt="D", color=f"C{x % 10}", capsize=6)
            axes.plot(x, row["mean"], "_", color="0.3", markersize=16, mew=2)
        axes.axhline(0, color="0.5", lw=1, ls=":")
        axes.axhline(1, color="0.5", lw=1, ls="--")
        axes.set_xticks(range(len(methods)), methods)
        axes.set_xlim(-0.6, len(methods) - 0.4)
        axes.set_title(SCORE_LABELS[score])
        axes.grid(axis="y", alpha=0.3)
    grid[0].set_ylabel("0: random agent, 1: best control of the study")
    figure.suptitle(
        f"IQM (diamond, {CONFIDENCE:.0%} stratified bootstrap CI) and mean (bar) over studies"
    )
    figure.savefig(path, dpi=110)
    return path


NORMALIZATION = f"""\
How to read this: every study is scored on its own scale. 0 is the random agent's success rate
on the study's env (the share of the spec's `random_episodes`, default 100, uniformly random
episodes that reach the goal at any step, measured once by the driver before the study's first
trial); 1 is the study's best control method (`state`, the state oracle, or `true_reward`,
images with the true reward, whichever has the higher IQM AUC). A trial's normalised AUC is
(AUC - random) / (control's IQM AUC - random), its normalised final success (final success -
random) / (control's IQM final success - random), the final success being the success rate at
the last evaluation. Above 1: better than the control; below 0: worse than acting at random.
Statistics pool every normalised study's done trials of a method; their {CONFIDENCE:.0%}
intervals are percentile bootstraps ({RESAMPLES} resamples) that resample each study's trials
among themselves (each study a stratum, so it keeps its weight). Methods run on different sets
of studies (column *studies*) are not directly comparable. Optimality gap: mean shortfall
below 1 (the control)."""


def combined_markdown(
    anchors: pd.DataFrame,
    table: pd.DataFrame,
    study_tables: list[pd.DataFrame],
    improvements: list[pd.DataFrame],
    budget: str | None = None,
) -> str:
    """The combined report: anchors, pooled normalised statistics, figures, the gradient
    budget section (``budget``, when the studies share an env), every study's own
    tables."""
    names = ", ".join(f"`{s}` ({e})" for s, e in zip(anchors["study"], anchors["env"], strict=True))
    lines = [
        f"# {len(anchors)} studies: normalised comparison",
        "",
        f"Studies: {names}; written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
        "",
        "## Anchors of each study",
        "",
        "| study | env | random agent (0) | best control (1) | its IQM AUC "
        "| its IQM final success | normalised |",
        "|---|---|---:|---|---:|---:|---|",
    ]
    for row in anchors.to_dict("records"):
        status = "yes" if row["normalized"] else f"**no**: {row['problem']}"
        lines.append(
            f"| {row['study']} | {_fmt(row['env'])} | {_fmt(row['random_success'])} "
            f"| {_fmt(row['control'])} | {_fmt(row['control_iqm_auc'])} "
            f"| {_fmt(row['control_iqm_final_success'])} | {status} |"
        )
    skipped = anchors[~anchors["normalized"]]
    if len(skipped):
        lines += [
            "",
            f"**{len(skipped)} of {len(anchors)} studies are not normalised** and are left out "
            f"of the pooled statistics: {', '.join(skipped['study'])} (reasons above). Their "
            "own tables are below.",
        ]
    lines += ["", "## Normalised scores per method, pooled over studies", ""]
    if table.empty:
        lines.append("No study could be normalised: no pooled statistics.")
    else:
        lines += [
            f"| method | score | studies | trials | IQM [{CONFIDENCE:.0%} CI] | mean [CI] "
            "| median [CI] | optimality gap [CI] |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in table.to_dict("records"):
            stats = " | ".join(
                _interval(row, n) for n in ("iqm", "mean", "median", "optimality_gap")
            )
            lines.append(
                f"| {row['method']} | {SCORE_LABELS[row['score']]} | {row['studies']} "
                f"| {row['n']} | {stats} |"
            )
    lines += [
        "",
        NORMALIZATION,
        "",
        "![normalised IQM per method](normalized.png)",
        "",
        "## Performance profiles of the normalised scores",
        "",
        "Fraction of a method's trials (all normalised studies) whose normalised AUC (left) or "
        f"final success (right) is above tau, with {CONFIDENCE:.0%} stratified bootstrap bands:",
        "",
        "![normalised performance profiles](normalized_profiles.png)",
        "",
    ]
    if budget is not None:
        lines.append(budget)
    lines += [
        "## Each study's own tables (AUC, not normalised)",
        "",
    ]
    for name, table_s, improvement in zip(
        anchors["study"], study_tables, improvements, strict=True
    ):
        lines += [f"### `{name}`", "", table_markdown(table_s, improvement), ""]
    lines += [
        "Data: `anchors.csv`, `normalized_scores.csv` (one row per trial of a normalised "
        "study), `normalized_table.csv`, `normalized_profiles.csv`, `study_tables.csv`, "
        "`study_improvement.csv`.",
        "",
    ]
    return "\n".join(lines)
