"""Per-method tables of a study: learning curves, the AUC table with intervals, the paired
probability of improvement. Statistics and resampling come from ``sweeper.results._stats``."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from sweeper.plan import confirm_key
from sweeper.results._frame import (
    by_auc,
    methods_of,
    scored,
    stage_frame,
    study_info,
    trial_rows,
)
from sweeper.results._stats import (
    SUMMARIES,
    Group,
    iqm,
    mean,
    probability_of_improvement,
    profile_statistic,
    several,
    stratified_bootstrap,
)
from sweeper.storage import tally

#: bootstrap resamples for every interval
RESAMPLES = 2000
CONFIDENCE = 0.95
#: thresholds of the performance profiles (AUC and final success rate both lie in [0, 1])
TAUS = tuple(i / 100 for i in range(101))
#: columns of ``auc_table`` computed from the done trials' AUCs (empty when there are none)
AUC_COLUMNS = (
    "mean",
    "mean_low",
    "mean_high",
    "std",
    "median",
    "median_low",
    "median_high",
    "iqm",
    "iqm_low",
    "iqm_high",
    "optimality_gap",
    "optimality_gap_low",
    "optimality_gap_high",
    "wall_s",
    "wall_s_per_trial",
    "cpu_s",
    "gpu_s",
    "best_trial",
    "best_key",
    "best_auc",
    "best_params",
)


def method_curves(frame: pd.DataFrame) -> pd.DataFrame:
    """Per method, metric and step: ``mean``, ``std`` (ddof=1) and ``n`` over scored trials.

    ``n`` counts the trials with a value there (a diverged trial has no distances after its
    divergence, so those means cover fewer trials).
    """
    rows = scored(frame).dropna(subset=["step"])
    metrics = study_info(frame).metrics
    long = rows.melt(id_vars=["method", "step"], value_vars=metrics, var_name="metric")
    stats = long.groupby(["method", "metric", "step"], sort=False)["value"].agg(
        ["mean", "std", "count"]
    )
    stats = stats.rename(columns={"count": "n"}).reset_index()
    order = {m: i for i, m in enumerate(methods_of(frame))}
    order.update({m: i for i, m in enumerate(metrics)})
    sort = stats.assign(_method=stats["method"].map(order), _metric=stats["metric"].map(order))
    sort = sort.sort_values(["_method", "_metric", "step"])
    return sort.drop(columns=["_method", "_metric"]).reset_index(drop=True)


def auc_table(frame: pd.DataFrame, *, driver_alive: bool = True, seed: int = 0) -> pd.DataFrame:
    """The per-method AUC table.

    Ledger columns (per plan key, as ``sweeper status``): planned, done (COMPLETE),
    diverged (of done), running, failed, left (not started, waiting, interrupted, or
    RUNNING without a live driver). AUC columns over the done trials: n, mean, std
    (ddof=1), and ``sweeper.results._stats.SUMMARIES`` (mean, median, iqm, optimality_gap) each with
    ``<name>_low``/``<name>_high`` (95 % stratified bootstrap, ``RESAMPLES`` resamples
    seeded by ``seed``, one resample shared by the four); compute (``compute_columns``); and
    the best trial (number, key, AUC, searched hyperparameters as ``name=value`` pairs;
    ``sweeper.results._frame.by_auc``: ties go to the lower trial number).
    """
    trials = trial_rows(frame)
    current = trials[trials["counted"]]
    planned = study_info(frame).attrs.get("plan") or current["key"].tolist()
    by_key = dict(
        zip(current["key"], zip(current["state"], current["outcome"], strict=True), strict=True)
    )
    done = trial_rows(scored(frame))
    samples = {m: g["auc"].to_numpy() for m, g in done.groupby("method")}
    intervals = stratified_bootstrap(
        several(*SUMMARIES.values()), samples, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE
    )
    compute = compute_columns(frame)
    table = []
    for method in methods_of(frame):
        keys = [k for k in planned if k.split("/")[0] == method]
        row: dict[str, Any] = {"method": method, **asdict(tally(keys, by_key, driver_alive))}
        values = samples.get(method, np.array([]))
        row.update(dict.fromkeys(AUC_COLUMNS), n=values.size)
        if values.size:
            best = by_auc(done[done["method"] == method]).iloc[0]
            params = {k: best[f"params_{k}"] for k in study_info(frame).searched}
            for index, name in enumerate(SUMMARIES):
                point, low, high = (float(v[index]) for v in intervals[method])
                row.update({name: point, f"{name}_low": low, f"{name}_high": high})
            row.update(compute.get(method, {}))
            row.update(
                std=values.std(ddof=1) if values.size > 1 else math.nan,
                best_trial=int(best["trial"]),
                best_key=best["key"],
                best_auc=float(best["auc"]),
                best_params=", ".join(f"{k}={v}" for k, v in params.items() if pd.notna(v)),
            )
        table.append(row)
    return pd.DataFrame(table).astype({"best_trial": "Int64"})


def improvement_table(frame: pd.DataFrame, *, seed: int = 0) -> pd.DataFrame:
    """Paired probability of improvement, with its interval, for every ordered pair of methods.

    ``probability`` = P(AUC of ``method`` > AUC of ``versus``) + 0.5 P(equal), over the
    ``pairs`` (config_id, seed) where both methods have a done trial
    (``sweeper.results._stats.probability_of_improvement``); ``low``/``high``: its 95 % bootstrap
    interval, the pairs resampled whole (both AUCs of a pair together); NaN when the
    methods share no pair.
    """
    columns = ["method", "versus", "probability", "low", "high", "pairs"]
    done = trial_rows(scored(frame))
    if done.empty:
        return pd.DataFrame(columns=columns)
    wide = done.pivot_table(index=["config_id", "seed"], columns="method", values="auc")
    methods = [m for m in methods_of(frame) if m in wide]
    comparisons = [(x, y) for x in methods for y in methods if x != y]
    return paired_improvement(wide, comparisons, seed=seed)


def paired_improvement(
    wide: pd.DataFrame, comparisons: list[tuple[str, str]], *, seed: int = 0
) -> pd.DataFrame:
    """P(``x`` > ``y``) with its interval for each ``(x, y)`` of ``comparisons``, columns of
    ``wide`` (one row per pair of trials, e.g. (config_id, seed); NaN where an arm has no
    trial): the pairs where both have a score, the statistic and its resampling as
    ``improvement_table`` describes; columns method (x), versus (y), probability, low,
    high, pairs. Shared so every paired comparison of the reports is computed one way."""
    groups, sizes = {}, {}
    for x, y in comparisons:
        pairs = wide[[x, y]].dropna()
        sizes[x, y] = len(pairs)
        if len(pairs):
            groups[f"{x}>{y}"] = Group((pairs[x].to_numpy(), pairs[y].to_numpy()))
    intervals = stratified_bootstrap(
        probability_of_improvement, groups, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE
    )
    nan = (math.nan, math.nan, math.nan)
    rows = [[x, y, *map(float, intervals.get(f"{x}>{y}", nan)), n] for (x, y), n in sizes.items()]
    columns = ["method", "versus", "probability", "low", "high", "pairs"]
    return pd.DataFrame(rows, columns=columns)


def compute_columns(frame: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Compute per method over its done trials, from what the trials record: ``wall_s``
    (sum of the trials' ``seconds``: wall time of every run of the trial, resumes and the
    encoder fit included), ``wall_s_per_trial`` (their mean), and the CPU and GPU seconds
    reserved for them (``wall_s`` x the spec's ``cpus_per_trial`` / ``gpus_per_trial``)."""
    cpus, gpus = reserved_per_trial(frame)
    done = trial_rows(scored(frame)).dropna(subset=["seconds"])
    result = {}
    for method, group in done.groupby("method"):
        wall = float(group["seconds"].sum())
        result[method] = {
            "wall_s": wall,
            "wall_s_per_trial": float(group["seconds"].mean()),
            "cpu_s": wall * cpus,
            "gpu_s": wall * gpus,
        }
    return result


def reserved_per_trial(frame: pd.DataFrame) -> tuple[float, float]:
    """The CPUs and GPUs the study's spec reserved for each trial (``execution``), which
    turn a trial's wall seconds into the compute it held."""
    execution = (study_info(frame).attrs.get("spec") or {}).get("execution") or {}
    return float(execution.get("cpus_per_trial", 1.0)), float(execution.get("gpus_per_trial", 0.0))


def success_matrices(frame: pd.DataFrame, metric: str = "success_rate"):
    """Per method: the evaluation steps and a (done trials x steps) array of ``metric``;
    trials whose curve does not cover the method's full grid are left out."""
    rows = scored(frame).dropna(subset=["step"])
    result = {}
    for method, part in rows.groupby("method", sort=False):
        wide = part.pivot_table(index="trial", columns="step", values=metric, dropna=False)
        wide = wide[np.isfinite(wide.to_numpy()).all(axis=1)]
        if len(wide):
            result[method] = (wide.columns.to_numpy(dtype=np.int64), wide.to_numpy())
    return result


def iqm_curves(frame: pd.DataFrame, *, seed: int = 0) -> pd.DataFrame:
    """Sample-efficiency curves: per method and step, the IQM of ``success_rate`` over done
    trials with its 95 % bootstrap band (whole curves resampled: one trial, one unit) and
    the number of trials ``n``."""
    matrices = success_matrices(frame)
    intervals = stratified_bootstrap(
        iqm,
        {m: values for m, (_, values) in matrices.items()},
        reps=RESAMPLES,
        seed=seed,
        confidence=CONFIDENCE,
    )
    parts = [
        pd.DataFrame(
            {
                "method": method,
                "step": matrices[method][0],
                "iqm": intervals[method].point,
                "low": intervals[method].low,
                "high": intervals[method].high,
                "n": len(matrices[method][1]),
            }
        )
        for method in methods_of(frame)
        if method in matrices
    ]
    columns = ["method", "step", "iqm", "low", "high", "n"]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=columns)


def profile_table(frame: pd.DataFrame, *, seed: int = 0) -> pd.DataFrame:
    """Performance profiles: per method, score (``auc``, ``final_success``: the success rate
    at the last evaluation) and tau in ``TAUS``, the fraction of done trials whose score is
    above tau, with its 95 % bootstrap band."""
    matrices = success_matrices(frame)
    done = trial_rows(scored(frame))
    scores = {
        "auc": {m: g["auc"].to_numpy() for m, g in done.groupby("method")},
        "final_success": {m: values[:, -1] for m, (_, values) in matrices.items()},
    }
    return profile_frame(scores, methods_of(frame), seed=seed)


def profile_frame(
    scores: dict[str, dict[str, Any]],
    methods: list[str],
    *,
    seed: int = 0,
    strata=None,
    taus: tuple[float, ...] = TAUS,
) -> pd.DataFrame:
    """``profile_table``'s rows from ``scores[score][method]`` (arrays of scores), resampled
    within ``strata[score][method]`` (stratum labels) when given, at thresholds ``taus``."""
    taus = np.asarray(taus)
    parts = []
    for score, samples in scores.items():
        groups = {
            m: Group((samples[m],), None if strata is None else strata[score][m])
            for m in methods
            if m in samples and len(samples[m])
        }
        intervals = stratified_bootstrap(
            profile_statistic(taus), groups, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE
        )
        for method in groups:
            interval = intervals[method]
            parts.append(
                pd.DataFrame(
                    {
                        "method": method,
                        "score": score,
                        "tau": taus,
                        "fraction": interval.point,
                        "low": interval.low,
                        "high": interval.high,
                        "n": len(samples[method]),
                    }
                )
            )
    columns = ["method", "score", "tau", "fraction", "low", "high", "n"]
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=columns)


@dataclass(frozen=True)
class Tables:
    """Everything computed from one study's frame (each a tidy frame, written as CSV)."""

    curves: pd.DataFrame  # method_curves: mean, std, n per method, metric and step
    efficiency: pd.DataFrame  # iqm_curves: IQM of success with its band per method and step
    profiles: pd.DataFrame  # profile_table
    table: pd.DataFrame  # auc_table
    improvement: pd.DataFrame  # improvement_table


def study_tables(frame: pd.DataFrame, *, driver_alive: bool = True, seed: int = 0) -> Tables:
    """All the tables of one study, every interval seeded by ``seed``."""
    return Tables(
        curves=method_curves(frame),
        efficiency=iqm_curves(frame, seed=seed),
        profiles=profile_table(frame, seed=seed),
        table=auc_table(frame, driver_alive=driver_alive, seed=seed),
        improvement=improvement_table(frame, seed=seed),
    )


CONFIRM_COLUMNS = (
    "method",
    "rank",
    "config_id",
    "search_auc",
    "confirm_auc",
    "confirm_auc_low",
    "confirm_auc_high",
    "drop",
    "n",
    "planned",
    "done",
    "running",
    "failed",
    "left",
)


def confirm_table(frame: pd.DataFrame, *, driver_alive: bool = True, seed: int = 0):
    """The confirmation stage (``sweeper confirm``), apart from the search: per method and
    chosen configuration (``rank`` 1 = best search AUC), ``search_auc`` (the mean over its
    search seeds it was chosen on), ``confirm_auc`` (the mean over its done fresh seeds,
    with a 95 % bootstrap interval over those seeds), ``drop`` (search minus confirm AUC:
    the winner's curse), ``n`` done fresh seeds, and the stage's ledger per configuration.
    Empty when the study has no confirmation stage (study attr ``confirm``)."""
    chosen = study_info(frame).attrs.get("confirm")
    if not chosen:
        return pd.DataFrame(columns=CONFIRM_COLUMNS)
    confirm = stage_frame(frame, "confirm")
    trials = trial_rows(confirm)
    current = trials[trials["counted"]]
    by_key = dict(
        zip(current["key"], zip(current["state"], current["outcome"], strict=True), strict=True)
    )
    done = trial_rows(scored(confirm))
    samples = {
        f"{m}/{c}": g["auc"].to_numpy() for (m, c), g in done.groupby(["method", "config_id"])
    }
    intervals = stratified_bootstrap(
        mean, samples, reps=RESAMPLES, seed=seed, confidence=CONFIDENCE
    )
    rows = []
    for method in methods_of(frame):
        for rank, config_id in enumerate(chosen["configs"].get(method, []), start=1):
            row: dict[str, Any] = {"method": method, "rank": rank, "config_id": int(config_id)}
            row["search_auc"] = float(chosen["search_auc"][method][str(config_id)])
            keys = [confirm_key(method, int(config_id), s) for s in chosen["seeds"]]
            counts = tally(keys, by_key, driver_alive)
            row.update(
                {c: getattr(counts, c) for c in ("planned", "done", "running", "failed", "left")}
            )
            interval = intervals.get(f"{method}/{config_id}")
            row["n"] = len(samples.get(f"{method}/{config_id}", ()))
            if interval is None:
                row.update(confirm_auc=np.nan, confirm_auc_low=np.nan, confirm_auc_high=np.nan)
            else:
                row.update(
                    confirm_auc=float(interval.point),
                    confirm_auc_low=float(interval.low),
                    confirm_auc_high=float(interval.high),
                )
            row["drop"] = row["search_auc"] - row["confirm_auc"]
            rows.append(row)
    return pd.DataFrame(rows, columns=CONFIRM_COLUMNS)
