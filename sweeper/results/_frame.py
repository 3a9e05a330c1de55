"""Reading a study: the tidy frame (one row per trial and evaluation step) and which of its
trials enter the statistics."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from sweeper.storage import (
    CURVE_ATTR,
    FIXED_PARAMS_ATTR,
    METHOD_PARAM,
    applies_to,
    current_numbers,
    read_rows,
)

if TYPE_CHECKING:
    from sweeper.storage import StudyRows

TRIAL_COLUMNS = (
    "trial",
    "key",
    "stage",
    "method",
    "config_id",
    "seed",
    "state",
    "outcome",
    "counted",
    "attempts",
    "auc",
    "diverged_step",
    "diverged_loss",
    "error",
    "seconds",
    "reward_scale",
    "fit_latent_dim",
    "fit_active_dims",
    "fit_kl",
)
#: the ``fit_`` columns: from the user attr ``encoder_fit`` of trials with a learned encoder
FIT_COLUMNS = {"fit_latent_dim": "latent_dim", "fit_active_dims": "active_dims", "fit_kl": "kl"}


@dataclass(frozen=True)
class StudyInfo:
    """What ``load_study_frame`` knows about the study besides its rows."""

    name: str
    attrs: dict[str, Any]  # the study user attrs (spec, plan, env, metric_names, ...)
    metrics: tuple[str, ...]  # metric columns, in the study's metric_names order
    searched: tuple[str, ...]  # params with more than one choice
    videos: dict[int, dict[str, str]]  # trial number -> its videos (file name -> artifact id)

    def __deepcopy__(self, memo: dict) -> StudyInfo:
        # pandas deep-copies frame.attrs after every operation; this is read-only
        return self


def study_info(frame: pd.DataFrame) -> StudyInfo:
    """The ``StudyInfo`` of a frame from ``load_study_frame``."""
    return frame.attrs["study"]


def load_study_frame(storage_url: str, study_name: str) -> pd.DataFrame:
    """The study as a tidy frame: one row per (trial, evaluation step).

    Columns: ``TRIAL_COLUMNS`` (trial = Optuna trial number, state = Optuna state name,
    auc = the trial's value, stage = ``"search"`` or ``"confirm"``), ``step``, one column
    per reported metric (from the trial's curve, ``sweeper.storage.curve_of``; a trial
    without one falls back to its intermediate values as ``success_rate``), then
    ``params_<name>`` per hyperparameter (the registered ones and the study's constants,
    ``sweeper.storage._params``; the ``method`` param is the ``method`` column). A trial
    with no evaluation yet has one row with ``step`` missing.
    ``study_info(frame)`` is the ``StudyInfo``.

    Read-only, with ``sweeper.storage._open.read_rows`` (one query per Optuna table). Raises
    ValueError when the storage cannot be read, has no such study, or the study no trials.
    """
    return _build_frame(study_name, read_rows(storage_url, study_name))


def _build_frame(study_name: str, raw: StudyRows) -> pd.DataFrame:
    """Join the raw Optuna tables of ``read_rows`` into the tidy frame of ``load_study_frame``."""
    from optuna.distributions import json_to_distribution

    trials, values, user_attrs = raw.trials, raw.values, raw.user_attrs
    params, intermediate, study_attrs = raw.params, raw.intermediate, raw.study_attrs

    attrs_by_trial: dict[int, dict[str, Any]] = {}
    for trial_id, key, value_json in user_attrs.itertuples(index=False):
        attrs_by_trial.setdefault(trial_id, {})[key] = json.loads(value_json)
    for trial_id, key, value_json in raw.system_attrs.itertuples(index=False):
        # the curve, the encoder's fit...: over their user attrs, words or written before
        attrs_by_trial.setdefault(trial_id, {})[key] = json.loads(value_json)
    special = {"FINITE": None, "INF_POS": math.inf, "INF_NEG": -math.inf, "NAN": math.nan}
    auc = {
        t: v if special[kind] is None else special[kind]
        for t, v, kind in values.itertuples(index=False)
    }
    fallback: dict[int, dict[int, float]] = {}  # intermediate values of trials with no curve
    with_curve = {t for t, attrs in attrs_by_trial.items() if attrs.get(CURVE_ATTR)}
    intermediate = intermediate[~intermediate["trial_id"].isin(with_curve)]
    for t, step, v, kind in intermediate.itertuples(index=False):
        fallback.setdefault(t, {})[int(step)] = v if special[kind] is None else special[kind]
    distributions: dict[str, Any] = {}  # distribution_json -> distribution, parsed once
    params_by_trial: dict[int, dict[str, Any]] = {}
    searched: dict[str, None] = {}  # params with a choice (not fixed by the spec)
    for t, name, internal, dist_json in params.itertuples(index=False):
        if name == METHOD_PARAM:  # the trial's method: the ``method`` column already
            continue
        if dist_json not in distributions:
            distributions[dist_json] = json_to_distribution(dist_json)
        distribution = distributions[dist_json]
        params_by_trial.setdefault(t, {})[name] = distribution.to_external_repr(internal)
        if len(getattr(distribution, "choices", (0, 1))) > 1:
            searched[name] = None
    study = {k: json.loads(v) for k, v in study_attrs.itertuples(index=False)}
    fixed = study.get(FIXED_PARAMS_ATTR) or {}  # constants, not registered as trial params

    rows, parsed, metric_names = [], [], {}
    for trial_id, number, state in trials.sort_values("number").itertuples(index=False):
        attrs = attrs_by_trial.get(trial_id, {})
        row = {c: attrs.get(c) for c in TRIAL_COLUMNS}
        row["stage"] = attrs.get("stage") or stage_of(attrs.get("key"))
        fit = attrs.get("encoder_fit") or {}
        row.update({column: fit.get(name) for column, name in FIT_COLUMNS.items()})
        row.update(trial=int(number), state=str(state), auc=auc.get(trial_id))
        mine = params_by_trial.get(trial_id, {})
        if attrs.get("key") is not None:  # a plan key's trial: its constants too
            constants = {k: v for k, v in fixed.items() if applies_to(k, attrs.get("method"))}
            mine = {**constants, **mine}
        row.update({f"params_{k}": v for k, v in mine.items()})
        curve = attrs.get(CURVE_ATTR)
        if not curve:
            points = sorted(fallback.get(trial_id, {}).items())
            curve = {"step": [s for s, _ in points], "success_rate": [v for _, v in points]}
        steps = np.asarray(curve["step"], dtype=np.int64)
        columns = {}
        for name, column in curve.items():
            if name == "step":
                continue
            if len(column) != steps.size:
                raise ValueError(
                    f"trial {number} ({attrs.get('key')}): curve[{name!r}] has {len(column)} "
                    f"values for {steps.size} steps"
                )
            metric_names[name] = None
            columns[name] = np.asarray(column, dtype=np.float64)  # null (NaN) -> nan
        if not steps.size:  # a trial without evaluations keeps one row, step -1 (missing)
            steps, columns = np.array([-1]), {}
        parsed.append((steps, columns))
        rows.append(row)
    if not rows:
        raise ValueError(f"study {study_name!r} has no trials yet: nothing to aggregate")

    order = [m for m in study.get("metric_names", []) if m in metric_names]
    metrics = order + [m for m in metric_names if m not in order]
    steps = np.concatenate([steps for steps, _ in parsed])
    values = {
        name: np.concatenate([c.get(name, np.full(t.size, np.nan)) for t, c in parsed])
        for name in metrics
    }
    head = pd.DataFrame(rows)
    for column in head.columns[head.columns.str.startswith("params_")]:  # keep 16 an int
        head[column] = pd.Series([r.get(column) for r in rows], dtype=object)
    repeats = [t.size for t, _ in parsed]
    frame = head.iloc[np.repeat(np.arange(len(rows)), repeats)].reset_index(drop=True)
    frame["step"] = pd.Series(steps).where(steps >= 0).astype("Int64")
    frame = pd.concat([frame, pd.DataFrame(values)], axis=1)
    params_columns = [c for c in frame.columns if c.startswith("params_")]
    frame = frame[[*TRIAL_COLUMNS, "step", *metrics, *sorted(params_columns)]]
    for column in ("config_id", "seed", "attempts", "diverged_step", "fit_latent_dim",
                   "fit_active_dims"):  # fmt: skip
        frame[column] = frame[column].astype("Int64")
    for column in ("auc", "reward_scale", "fit_kl"):
        frame[column] = frame[column].astype("float64")
    current = set(current_numbers(zip(head["key"], head["trial"], strict=True)).values())
    frame["counted"] = frame["key"].notna() & frame["trial"].isin(current)
    videos = {
        int(number): attrs_by_trial[trial_id]["videos"]
        for trial_id, number, _ in trials.itertuples(index=False)
        if (attrs_by_trial.get(trial_id) or {}).get("videos")
    }
    frame.attrs["study"] = StudyInfo(
        study_name, study, tuple(metrics), tuple(sorted(searched)), videos
    )
    return frame


def stage_of(key: str | None) -> str:
    """A key's stage: ``"confirm"`` for ``confirm/...`` keys, else ``"search"`` (trials
    written before stages were recorded have no ``stage`` attr)."""
    return "confirm" if key is not None and key.startswith("confirm/") else "search"


def stage_frame(frame: pd.DataFrame, stage: str) -> pd.DataFrame:
    """The rows of one stage (``"search"`` or ``"confirm"``), the study info kept."""
    return frame[frame["stage"] == stage]


def trial_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per trial: the trial-level columns and params of the tidy frame."""
    columns = [c for c in frame.columns if c in TRIAL_COLUMNS or c.startswith("params_")]
    return frame.drop_duplicates("trial")[columns].reset_index(drop=True)


def scored(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows of the trials that enter the statistics: counted, COMPLETE, with a finite AUC."""

    keep = frame["counted"] & (frame["state"] == "COMPLETE") & np.isfinite(frame["auc"])
    return frame[keep]


def methods_of(frame: pd.DataFrame) -> list[str]:
    """Methods in the spec's order (study attr ``spec``), then any others seen."""
    study = study_info(frame).attrs
    declared = list((study.get("spec") or {}).get("methods", {}))
    declared += [k.split("/")[0] for k in study.get("plan", [])]
    return list(dict.fromkeys(declared + frame["method"].dropna().unique().tolist()))


def by_auc(trials: pd.DataFrame) -> pd.DataFrame:
    """Trial rows best first: highest AUC first, ties to the lower trial number, trials
    without an AUC last. Every "best trial" of the report and the dashboard is the first
    row of this order, so a tie is broken the same way everywhere."""
    return trials.sort_values(
        ["auc", "trial"], ascending=[False, True], na_position="last", kind="stable"
    )


def random_success(frame: pd.DataFrame) -> float | None:
    """The random agent's measured success rate (study attr ``random_agent``), or None."""
    value = (study_info(frame).attrs.get("random_agent") or {}).get("success_rate")
    return None if value is None else float(value)
