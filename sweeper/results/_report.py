"""The Markdown report and the study note's section."""

from __future__ import annotations

import itertools
import math
import time
from typing import Any

import pandas as pd

from sweeper.results._frame import methods_of, random_success, scored, study_info, trial_rows
from sweeper.results._tables import CONFIDENCE, RESAMPLES, Tables
from sweeper.spec import plural


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _interval(row: dict[str, Any], name: str, digits: int = 3) -> str:
    """``point [low, high]`` of column ``name`` and its ``_low``/``_high`` columns."""
    low, high = row[f"{name}_low"], row[f"{name}_high"]
    return f"{_fmt(row[name], digits)} [{_fmt(low, digits)}, {_fmt(high, digits)}]"


#: fewer done trials (or pairs) than this and an interval is not to be trusted: rliable's
#: guidance (Agarwal et al. 2021) is at least 5 runs per method, preferably 10
MIN_RELIABLE = 5


def few_trials_warning(table: pd.DataFrame) -> str:
    """One line naming the methods with fewer than ``MIN_RELIABLE`` done trials (their
    intervals are not reliable); "" when there are none."""
    few = [f"{r.method} ({r.n})" for r in table.itertuples() if 0 < r.n < MIN_RELIABLE]
    if not few:
        return ""
    return (
        f"**Small samples:** {', '.join(few)} done trials, fewer than {MIN_RELIABLE}: their "
        "intervals are not reliable (rliable's guidance: 5 or more runs per method, "
        "preferably 10)."
    )


def _named(method: str, controls: tuple[str, ...]) -> str:
    """A method's name, "(control)" after it when it is one of ``controls``."""
    return f"{method} (control)" if method in controls else method


def table_markdown(
    table: pd.DataFrame,
    improvement: pd.DataFrame,
    pairs: bool = False,
    controls: tuple[str, ...] = (),
) -> str:
    """The AUC table (ledger, every statistic with its interval, compute, best trial) and
    the probability-of-improvement matrix with intervals, as Markdown; with ``pairs``, the
    probabilities as a row per pair of methods instead (``improvement_pairs_markdown``).
    The methods in ``controls`` are named as controls (the study note)."""
    lines = [
        "| method | planned | done | diverged | running | failed | left "
        f"| IQM AUC [{CONFIDENCE:.0%} CI] | mean [CI] | median [CI] | optimality gap [CI] | std "
        "| wall h (s per trial) | CPU h | GPU h | best trial |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for row in table.to_dict("records"):
        if row["n"]:
            stats = " | ".join(
                _interval(row, name) for name in ("iqm", "mean", "median", "optimality_gap")
            )
            compute = (
                f"{_fmt(row['wall_s'] / 3600, 2)} ({_fmt(row['wall_s_per_trial'], 0)}) "
                f"| {_fmt(row['cpu_s'] / 3600, 2)} | {_fmt(row['gpu_s'] / 3600, 2)}"
            )
            best = (
                f"#{row['best_trial']} {row['best_key']}: {_fmt(row['best_auc'])} "
                f"({row['best_params']})"
            )
        else:
            stats, compute, best = " | ".join("–" * 4), "– | – | –", "–"
        lines.append(
            f"| {_named(row['method'], controls)} | {row['planned']} | {row['done']} "
            f"| {row['diverged']} "
            f"| {row['running']} | {row['failed']} | {row['left']} | {stats} "
            f"| {_fmt(row['std'])} | {compute} | {best} |"
        )
    if warning := few_trials_warning(table):
        lines += ["", warning]
    methods = table["method"].tolist()
    if pairs and (rows := improvement_pairs_markdown(table, improvement, controls)):
        lines += [
            "",
            "Probability of improvement P(method > over), paired by SAC configuration and seed, "
            f"with its {CONFIDENCE:.0%} CI, the better-ranked method first:",
            "",
            rows,
        ]
        if "*\n" in rows:
            lines += ["", f"\\* fewer than {MIN_RELIABLE} pairs: not reliable."]
    elif len(methods) > 1 and not pairs:
        lookup = {(r.method, r.versus): r for r in improvement.itertuples()}
        lines += [
            "",
            "Probability of improvement P(row > column), paired by SAC configuration and seed, "
            f"with its {CONFIDENCE:.0%} CI (number of pairs in brackets):",
            "",
            "| | " + " | ".join(methods) + " |",
            "|---|" + "---:|" * len(methods),
        ]
        few_pairs = False
        for x in methods:
            cells = []
            for y in methods:
                r = lookup.get((x, y))
                if r is None or not r.pairs:
                    cells.append("–")
                else:
                    mark = "*" if r.pairs < MIN_RELIABLE else ""
                    few_pairs = few_pairs or bool(mark)
                    cells.append(
                        f"{_fmt(r.probability, 2)} [{_fmt(r.low, 2)}, {_fmt(r.high, 2)}] "
                        f"({r.pairs}{mark})"
                    )
            lines.append(f"| {x} | " + " | ".join(cells) + " |")
        if few_pairs:
            lines += [
                "",
                f"\\* fewer than {MIN_RELIABLE} pairs: that probability and its interval are "
                "not reliable.",
            ]
    return "\n".join(lines)


def terminal_table(tables: Tables) -> list[str]:
    """The per-method table ``sweeper aggregate`` prints, then ``verdict``'s line: per
    method (in the spec's order) the IQM AUC and the IQM final success (the last point of
    the sample-efficiency curve, ``tables.efficiency``), each with its interval, and its
    done and planned trials."""
    efficiency = tables.efficiency.sort_values("step", kind="stable")
    final = efficiency.groupby("method").tail(1).set_index("method")
    ci = f"[{CONFIDENCE:.0%} CI]"
    rows = [("method", f"IQM AUC {ci}", f"IQM final success {ci}", "n (done/planned)")]
    for row in tables.table.to_dict("records"):
        auc = _interval(row, "iqm") if row["n"] else "–"
        success = "–"
        if row["method"] in final.index:
            point = final.loc[row["method"]]
            success = f"{_fmt(point['iqm'])} [{_fmt(point['low'])}, {_fmt(point['high'])}]"
        rows.append((row["method"], auc, success, f"{row['done']}/{row['planned']}"))
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
             for row in rows]  # fmt: skip
    return [*lines, verdict(tables.table)]


def verdict(table: pd.DataFrame) -> str:
    """Which method has the highest IQM AUC, and whether its interval separates it from the
    next method's (lies above it) or not, in one line."""
    done = table[table["n"] > 0].sort_values("iqm", ascending=False, kind="stable")
    if done.empty:
        return "No method has a done trial yet."
    best = done.iloc[0].to_dict()
    text = f"Highest IQM AUC: {best['method']}, {_interval(best, 'iqm')}"
    if len(done) == 1:
        return f"{text}; no other method has a done trial."
    following = done.iloc[1].to_dict()
    other = f"that of the next, {following['method']}, {_interval(following, 'iqm')}"
    if best["iqm_low"] > following["iqm_high"]:
        return f"{text}; its {CONFIDENCE:.0%} interval lies above {other}."
    return (
        f"{text}; its {CONFIDENCE:.0%} interval overlaps {other}: this study does not "
        "separate the two."
    )


def ranking_sentence(
    table: pd.DataFrame,
    improvement: pd.DataFrame,
    random: float | None = None,
    controls: tuple[str, ...] = (),
) -> str:
    """The ranking in one sentence, from the tables' own evidence: the methods by IQM AUC
    with their intervals, and for each method over the next one the paired probability of
    improvement (the share of paired trials it beats the next one in) with its interval,
    called a clear lead only when that interval lies above 0.5. The methods in
    ``controls`` are named as controls (the study note)."""
    done = table[table["n"] > 0].sort_values("iqm", ascending=False, kind="stable")
    if done.empty:
        return "No method has a done trial yet, so there is no ranking."
    ranked = list(done.itertuples())
    order = ", ".join(
        f"{_named(r.method, controls)} {_fmt(r.iqm, 2)} [{_fmt(r.iqm_low, 2)}, "
        f"{_fmt(r.iqm_high, 2)}]"
        for r in ranked
    )
    text = f"Ranked by IQM AUC ({CONFIDENCE:.0%} CI): {order}"
    lookup = {(r.method, r.versus): r for r in improvement.itertuples()}
    claims = []
    for better, worse in itertools.pairwise(ranked):
        r = lookup.get((better.method, worse.method))
        if r is None or not r.pairs or math.isnan(r.probability):
            claims.append(f"{better.method} and {worse.method} share no done pair")
            continue
        pairs = plural(r.pairs, "paired trial")
        evidence = f"{_fmt(r.probability, 2)} [{_fmt(r.low, 2)}, {_fmt(r.high, 2)}] of {pairs}"
        if r.pairs < MIN_RELIABLE:
            evidence += f", fewer than {MIN_RELIABLE}"
        if r.low > 0.5:
            claims.append(f"{better.method} is clearly ahead of {worse.method} (wins {evidence})")
        else:
            claims.append(
                f"{better.method} is not clearly ahead of {worse.method} (wins {evidence}: "
                "the interval reaches 0.5)"
            )
    if claims:
        text += "; " + "; ".join(claims)
    if random is not None:
        text += f"; a random agent succeeds in {_fmt(random, 2)} of episodes"
    return text + "."


def improvement_pairs_markdown(
    table: pd.DataFrame, improvement: pd.DataFrame, controls: tuple[str, ...] = ()
) -> str:
    """The probability of improvement as one line per pair of methods, the better-ranked
    (by IQM AUC) first, in a fixed-width block: readable where the matrix is too wide and
    a Markdown table's cells run together (optuna-dashboard's note). "" when no pair. The
    methods in ``controls`` are named as controls."""
    done = table[table["n"] > 0].sort_values("iqm", ascending=False, kind="stable")
    methods = done["method"].tolist()
    lookup = {(r.method, r.versus): r for r in improvement.itertuples()}
    rows = [("method", "over", "P(improvement)", f"{CONFIDENCE:.0%} CI", "pairs")]
    for i, x in enumerate(methods):
        for y in methods[i + 1 :]:
            r = lookup.get((x, y))
            if r is None or not r.pairs:
                continue
            mark = "*" if r.pairs < MIN_RELIABLE else ""
            interval = f"[{_fmt(r.low, 2)}, {_fmt(r.high, 2)}]"
            named = _named(x, controls), _named(y, controls)
            rows.append((*named, _fmt(r.probability, 2), interval, f"{r.pairs}{mark}"))
    if len(rows) == 1:
        return ""
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    text = ["   ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]  # fmt: skip
    return "\n".join(["```text", *text, "```"])


DEFINITIONS = f"""\
How to read this: a trial's AUC is the area under its success-rate curve over the evaluation
grid divided by the grid's length (0: never succeeds, 1: always). Statistics use each plan
key's current trial when it is done (COMPLETE; diverged trials count, with zero success after
the divergence). IQM: mean of the middle 50 % of a method's AUCs (robust to outlier trials,
more precise than the median). Optimality gap: mean shortfall of the AUCs below 1 (lower is
better). Every interval is a {CONFIDENCE:.0%} percentile bootstrap, {RESAMPLES} resamples of the
method's own trials (stratified by method), seeded. Probability of improvement of A over B:
over the (SAC configuration, seed) pairs where both are done, the fraction where A's AUC is
higher, ties counting one half; its interval resamples the pairs whole. Compute: wall time of
the done trials (every run of a trial, the encoder fit included), and the CPU and GPU time
reserved for them (wall x the spec's cpus_per_trial, gpus_per_trial)."""


def fits_markdown(frame: pd.DataFrame) -> str:
    """Per method with a learned reward encoder, what its trials' fits gave: active latent
    dimensions (``encoders.vae.active_dims``), the last epoch's KL and the reward scale,
    and how many fits collapsed (no active dimension); "" when no trial recorded a fit."""
    fits = trial_rows(scored(frame)).dropna(subset=["fit_active_dims"])
    if fits.empty:
        return ""
    lines = [
        "## Learned encoders' fits",
        "",
        "A latent dimension is active when its posterior mean varies over the fit's frames "
        "(variance above 0.01, `encoders.vae.ACTIVE_VARIANCE`, against the prior's 1; Burda "
        "et al. 2016). A fit without any collapsed onto its prior: its encoding barely moves "
        "with the image, and the reward rests on what little it moves, magnified to about 1 "
        "by `reward_scale: auto`.",
        "",
        "| method | fits | active dims (of latent) | collapsed | KL, last epoch (median) "
        "| reward scale (median) |",
        "|---|---:|---|---:|---:|---:|",
    ]
    for method in methods_of(frame):
        rows = fits[fits["method"] == method]
        if rows.empty:
            continue
        active = ", ".join(
            f"{a}/{d}" for a, d in zip(rows["fit_active_dims"], rows["fit_latent_dim"], strict=True)
        )
        collapsed = int((rows["fit_active_dims"] == 0).sum())
        lines.append(
            f"| {method} | {len(rows)} | {active} | {collapsed} "
            f"| {_fmt(float(rows['fit_kl'].median()), 2)} "
            f"| {_fmt(float(rows['reward_scale'].median()), 2)} |"
        )
    return "\n".join(lines)


def report_markdown(frame: pd.DataFrame, tables: Tables, driver_alive: bool) -> str:
    """The study's report.md: ledger, statistics, figures, data files."""
    study = study_info(frame).attrs
    trials = trial_rows(frame)
    table = tables.table
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
            f"**Partial study** ({status}): {plural(int(table['running'].sum()), 'trial')} "
            f"running and {int(table['left'].sum())} left; the statistics cover done trials "
            "only.",
            "",
        ]
    warning = few_trials_warning(table)
    small = [warning, ""] if warning else []  # repeated beside the figures it concerns
    lines += [
        ranking_sentence(table, tables.improvement, random_success(frame)),
        "",
        "## AUC per method",
        "",
        table_markdown(table, tables.improvement),
        "",
        DEFINITIONS,
        "",
        "![AUC per method](auc.png)",
        "",
        *small,
        "## Sample efficiency",
        "",
        f"IQM of the success rate at each evaluation step over the done trials, with "
        f"{CONFIDENCE:.0%} bootstrap bands (whole curves resampled)"
        + (
            "; the grey dotted line is a random agent's success rate, measured by the driver:"
            if random_success(frame) is not None
            else ":"
        ),
        "",
        "![IQM success rate per method](efficiency.png)",
        "",
        *small,
        "## Performance profiles",
        "",
        "Fraction of a method's done trials whose AUC (left) or final success rate (right) is "
        f"above tau, with {CONFIDENCE:.0%} bootstrap bands; a curve above another everywhere "
        "dominates it:",
        "",
        "![performance profiles](profiles.png)",
        "",
        "## Learning curves of every metric",
        "",
        "![mean and std of every metric per method](curves.png)",
        "",
        "Every trial (grey dashed: unfinished; red dotted: failed):",
        "",
        "![every trial's curves coloured by AUC](trials.png)",
        "",
    ]
    fits = fits_markdown(frame)
    lines += [fits, ""] if fits else []
    lines += [
        "Data: `frame.csv` (one row per trial and evaluation step), `curves.csv` (mean, std), "
        "`efficiency.csv` (IQM and band), `profiles.csv`, `auc_table.csv`, `improvement.csv`.",
        "",
    ]
    return "\n".join(lines)


def confirm_markdown(confirm: pd.DataFrame, seeds: int) -> str:
    """The confirmation stage's section: per method the best configuration's search AUC and
    its AUC on fresh seeds as two numbers, then every chosen configuration."""
    lines = [
        "## Confirmation on fresh seeds (against the winner's curse)",
        "",
        "The best of many configurations is partly the luckiest, so its search AUC overstates "
        f"it. `sweeper confirm` re-ran each method's "
        f"{plural(int(confirm['rank'].max()), 'best configuration')} (by search AUC, the mean "
        f"over their search seeds) on {plural(seeds, 'fresh seed')} the search never used; "
        "these trials are left out of every statistic above.",
        "",
        "| method | best configuration found | its search AUC | how good it is on new seeds: "
        f"confirm AUC [{CONFIDENCE:.0%} CI] (seeds done) | drop |",
        "|---|---:|---:|---:|---:|",
    ]
    best = confirm[confirm["rank"] == 1]
    for row in best.to_dict("records"):
        lines.append(
            f"| {row['method']} | config {row['config_id']} | {_fmt(row['search_auc'])} "
            f"| {_interval(row, 'confirm_auc')} ({row['n']} of {row['planned']}) "
            f"| {_fmt(row['drop'])} |"
        )
    lines += [
        "",
        "Every confirmed configuration (confirm AUC: the mean over its done fresh seeds, "
        "its interval a bootstrap over those seeds; drop: search minus confirm AUC):",
        "",
        "| method | rank | config | search AUC | confirm AUC [CI] | drop | planned | done "
        "| running | failed | left |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in confirm.to_dict("records"):
        lines.append(
            f"| {row['method']} | {row['rank']} | {row['config_id']} | {_fmt(row['search_auc'])} "
            f"| {_interval(row, 'confirm_auc')} | {_fmt(row['drop'])} | {row['planned']} "
            f"| {row['done']} | {row['running']} | {row['failed']} | {row['left']} |"
        )
    lines += ["", "Data: `confirm_table.csv`.", ""]
    return "\n".join(lines)
