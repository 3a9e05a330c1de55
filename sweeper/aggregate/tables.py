"""Per-method tables of a study: learning curves, the AUC table with intervals, the paired
probability of improvement. Statistics and resampling come from ``sweeper.stats``."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from sweeper.aggregate.frame import methods_of, scored, study_info, trial_rows

if TYPE_CHECKING:
    import pandas as pd

#: bootstrap resamples for every interval
RESAMPLES = 2000
CONFIDENCE = 0.95
#: columns of ``auc_table`` computed from the done trials' AUCs (empty when there are none)
AUC_COLUMNS = (
    "mean",
    "std",
    "median",
    "iqm",
    "iqm_low",
    "iqm_high",
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
    (ddof=1), median, iqm with ``iqm_low``/``iqm_high`` (95 % stratified bootstrap,
    ``RESAMPLES`` resamples seeded by ``seed``), and the best trial (number, key, AUC,
    searched hyperparameters as ``name=value`` pairs).
    """
    import numpy as np
    import pandas as pd

    from sweeper.stats import iqm, stratified_bootstrap_ci
    from sweeper.storage import key_status

    trials = trial_rows(frame)
    current = trials[trials["counted"]]
    planned = study_info(frame).attrs.get("plan") or current["key"].tolist()
    by_key = dict(
        zip(current["key"], zip(current["state"], current["outcome"], strict=True), strict=True)
    )
    done = trial_rows(scored(frame))
    samples = {m: g["auc"].to_numpy() for m, g in done.groupby("method")}
    intervals = stratified_bootstrap_ci(
        samples, iqm, confidence=CONFIDENCE, resamples=RESAMPLES, seed=seed
    )
    table = []
    for method in methods_of(frame):
        keys = [k for k in planned if k.split("/")[0] == method]
        row: dict[str, Any] = {"method": method, "planned": len(keys)}
        row.update(dict.fromkeys(("done", "diverged", "running", "failed", "left"), 0))
        for key in keys:
            state, outcome = by_key.get(key, (None, None))
            status = key_status(state, outcome, driver_alive)
            row[status] += 1
            row["diverged"] += status == "done" and outcome == "diverged"
        values = samples.get(method, np.array([]))
        row.update(dict.fromkeys(AUC_COLUMNS), n=values.size)
        if values.size:
            best = done[done["method"] == method].sort_values("auc", ascending=False).iloc[0]
            params = {k: best[f"params_{k}"] for k in study_info(frame).searched}
            row.update(
                mean=values.mean(),
                std=values.std(ddof=1) if values.size > 1 else math.nan,
                median=float(np.median(values)),
                iqm=iqm(values),
                iqm_low=intervals[method][0],
                iqm_high=intervals[method][1],
                best_trial=int(best["trial"]),
                best_key=best["key"],
                best_auc=float(best["auc"]),
                best_params=", ".join(f"{k}={v}" for k, v in params.items() if pd.notna(v)),
            )
        table.append(row)
    return pd.DataFrame(table).astype({"best_trial": "Int64"})


def improvement_table(frame: pd.DataFrame) -> pd.DataFrame:
    """Paired probability of improvement for every ordered pair of methods.

    ``probability`` = P(AUC of ``method`` > AUC of ``versus``) + 0.5 P(equal), over the
    ``pairs`` (config_id, seed) where both methods have a done trial
    (``sweeper.stats.probability_of_improvement``); NaN when they share none.
    """
    import pandas as pd

    from sweeper.stats import probability_of_improvement

    done = trial_rows(scored(frame))
    wide = done.pivot_table(index=["config_id", "seed"], columns="method", values="auc")
    methods = [m for m in methods_of(frame) if m in wide]
    rows = []
    for x in methods:
        for y in methods:
            if x == y:
                continue
            pairs = wide[[x, y]].dropna()
            p = probability_of_improvement(pairs[x], pairs[y]) if len(pairs) else math.nan
            rows.append({"method": x, "versus": y, "probability": p, "pairs": len(pairs)})
    return pd.DataFrame(rows, columns=["method", "versus", "probability", "pairs"])
