"""A study run with successive halving: what each of its numbers compares.

The main AUC table of such a study is the full-budget comparison of each method's
surviving configurations (its COMPLETE trials). ``halving_table`` adds the first-rung
comparison over every configuration (each counted search trial, COMPLETE or PRUNED, its
curve cut at the first rung: still paired, every method the same configurations and
seeds) and the env steps spent against the full study's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from sweeper.plan import HALVING_ATTR, auc_until
from sweeper.results._frame import methods_of, stage_frame, study_info
from sweeper.results._stats import iqm, stratified_bootstrap

HALVING_COLUMNS = (
    "method",
    "rung",
    "n",
    "rung_iqm",
    "rung_iqm_low",
    "rung_iqm_high",
    "survivors",
    "env_steps",
    "full_env_steps",
    "compute_fraction",
)


def halving_table(
    frame: pd.DataFrame, *, reps: int = 2000, seed: int = 0, confidence: float = 0.95
) -> pd.DataFrame | None:
    """Per method: the first rung, its IQM AUC until that rung over every configuration
    with its bootstrap interval, the configurations that survived to the full budget, and
    env steps spent (each trial's last evaluated step) against every key at the full
    budget; None for a study without halving decisions."""
    info = study_info(frame)
    decisions = info.attrs.get(HALVING_ATTR)
    if not decisions:
        return None
    rung = min(int(step) for step in decisions)
    search = stage_frame(frame, "search")
    search = search[search["counted"] & search["state"].isin(["COMPLETE", "PRUNED"])]
    budget = int(frame["step"].max())
    samples: dict[str, np.ndarray] = {}
    rows = []
    planned = info.attrs.get("plan") or []
    for method in methods_of(frame):
        trials = search[search["method"] == method]
        if trials.empty:
            continue
        aucs, spent = [], 0
        for _, trial in trials.groupby("trial"):
            steps = trial["step"].astype(int).tolist()
            spent += steps[-1]
            if rung in steps:
                aucs.append(auc_until(steps, trial["success_rate"].tolist(), rung))
        samples[method] = np.asarray(aucs)
        keys = [k for k in planned if k.split("/")[0] == method] or trials["key"].unique()
        rows.append(
            {
                "method": method,
                "rung": rung,
                "n": len(aucs),
                "survivors": int((trials.drop_duplicates("trial")["state"] == "COMPLETE").sum()),
                "env_steps": spent,
                "full_env_steps": len(keys) * budget,
            }
        )
    intervals = stratified_bootstrap(
        iqm, {m: v for m, v in samples.items() if v.size}, reps=reps, seed=seed,
        confidence=confidence,
    )  # fmt: skip
    for row in rows:
        interval = intervals.get(row["method"])
        row["rung_iqm"], row["rung_iqm_low"], row["rung_iqm_high"] = (
            (float(interval[0]), interval[1], interval[2]) if interval else (np.nan,) * 3
        )
        row["compute_fraction"] = row["env_steps"] / row["full_env_steps"]
    return pd.DataFrame(rows, columns=list(HALVING_COLUMNS))


def halving_markdown(table: pd.DataFrame) -> str:
    """The report's section on successive halving: what each number compares."""
    lines = [
        "## Successive halving",
        "",
        "This study stopped configurations at rungs (`halving` in its spec), the same number "
        "for every method. The AUC table above is the **full-budget comparison of each "
        "method's surviving configurations**. Below, the **first-rung comparison over every "
        f"configuration** (each trial's AUC until step {int(table['rung'].iloc[0]):,}, still "
        "paired) and the **compute spent** against the full study's:",
        "",
        "| method | trials at the rung | IQM AUC until the rung [95% CI] | survivors | env "
        "steps spent | of the full study |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for row in table.to_dict("records"):
        lines.append(
            f"| {row['method']} | {row['n']} | {row['rung_iqm']:.3f} [{row['rung_iqm_low']:.3f}"
            f", {row['rung_iqm_high']:.3f}] | {row['survivors']} | {row['env_steps']:,} | "
            f"{row['compute_fraction']:.0%} |"
        )
    return "\n".join(lines)
