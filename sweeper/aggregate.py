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
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pandas, matplotlib, optuna and plotly are imported where used
    import pandas as pd

#: first lines of the study note's section written by ``sweeper aggregate``
NOTE_BEGIN = "<!-- sweeper aggregate: begin (rewritten by every run) -->"
NOTE_END = "<!-- sweeper aggregate: end -->"
#: bootstrap resamples for the IQM confidence interval
RESAMPLES = 2000
CONFIDENCE = 0.95
#: trials per panel above which lines are drawn without antialiasing (25 % faster)
DENSE = 200
TRIAL_COLUMNS = (
    "trial",
    "key",
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
)
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
        from sweeper.artifacts import artifact_location

        result = aggregate(
            spec.storage_url,
            spec.study,
            out,
            seed=spec.seed,
            dashboard=not args.no_dashboard,
            artifacts=artifact_location(spec),
        )
    except ValueError as e:  # SpecError, StorageError, an unknown or empty study
        print(f"sweeper aggregate: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(result.files)} files to {out}; report: {result.report}")
    return 0


# ---- reading -------------------------------------------------------------------------


@dataclass(frozen=True)
class StudyInfo:
    """What ``load_study_frame`` knows about the study besides its rows."""

    name: str
    attrs: dict[str, Any]  # the study user attrs (spec, plan, env, metric_names, ...)
    metrics: tuple[str, ...]  # metric columns, in the study's metric_names order
    searched: tuple[str, ...]  # params with more than one choice

    def __deepcopy__(self, memo: dict) -> StudyInfo:
        # pandas deep-copies frame.attrs after every operation; this is read-only
        return self


def study_info(frame: pd.DataFrame) -> StudyInfo:
    """The ``StudyInfo`` of a frame from ``load_study_frame``."""
    return frame.attrs["study"]


def load_study_frame(storage_url: str, study_name: str) -> pd.DataFrame:
    """The study as a tidy frame: one row per (trial, evaluation step).

    Columns: ``TRIAL_COLUMNS`` (trial = Optuna trial number, state = Optuna state name,
    auc = the trial's value), ``step``, one column per reported metric (from the ``curve``
    user attr; a trial without one falls back to its intermediate values as
    ``success_rate``), then ``params_<name>`` per hyperparameter. A trial with no
    evaluation yet has one row with ``step`` missing. ``study_info(frame).name`` is the
    ``StudyInfo`` (``study_info(frame)``).

    The study is read with one query per Optuna table, not per trial (Optuna's
    ``get_trials`` takes ~15 s for 2,000 trials x 50 points). Reading a live study is safe:
    a trial written between two queries shows up partly (no key yet: not counted) or not
    at all. Raises ValueError when the storage cannot be read or has no such study.
    """
    import pandas as pd
    from sqlalchemy import create_engine, inspect, text
    from sqlalchemy.exc import SQLAlchemyError

    from sweeper.storage import SQLITE_TIMEOUT, database_error, redact, resolve_url, sqlite_path

    url = resolve_url(storage_url)
    path = sqlite_path(url)
    if path is not None and not path.is_file():
        raise ValueError(f"storage: no database file at {path}: launch the study first")
    connect_args = {"timeout": SQLITE_TIMEOUT} if path is not None else {}
    engine = create_engine(url, connect_args=connect_args)
    try:
        with engine.connect() as connection:
            if not inspect(connection).has_table("studies"):
                raise ValueError(f"storage: {redact(storage_url)} holds no Optuna studies")
            study_id = connection.execute(
                text("SELECT study_id FROM studies WHERE study_name = :name"),
                {"name": study_name},
            ).scalar()
            if study_id is None:
                names = connection.execute(text("SELECT study_name FROM studies")).scalars()
                raise ValueError(
                    f"study {study_name!r} not found in {redact(storage_url)}; "
                    f"it has: {', '.join(sorted(names)) or 'no studies'}"
                )

            def query(sql: str) -> pd.DataFrame:
                return pd.read_sql_query(text(sql), connection, params={"study": study_id})

            of_study = "JOIN trials t ON t.trial_id = x.trial_id WHERE t.study_id = :study"
            trials = query("SELECT trial_id, number, state FROM trials WHERE study_id = :study")
            values = query(
                f"SELECT x.trial_id, x.value, x.value_type FROM trial_values x {of_study} "
                "AND x.objective = 0"
            )
            user_attrs = query(
                f"SELECT x.trial_id, x.key, x.value_json FROM trial_user_attributes x {of_study}"
            )
            params = query(
                "SELECT x.trial_id, x.param_name, x.param_value, x.distribution_json "
                f"FROM trial_params x {of_study}"
            )
            intermediate = query(
                "SELECT x.trial_id, x.step, x.intermediate_value, x.intermediate_value_type "
                f"FROM trial_intermediate_values x {of_study}"
            )
            study_attrs = query(
                "SELECT key, value_json FROM study_user_attributes WHERE study_id = :study"
            )
    except SQLAlchemyError as e:  # unreachable server, locked or corrupt file
        raise database_error("cannot read", storage_url, e) from None
    finally:
        engine.dispose()
    return _build_frame(study_name, trials, values, user_attrs, params, intermediate, study_attrs)


def _build_frame(study_name, trials, values, user_attrs, params, intermediate, study_attrs):
    """Join the raw Optuna tables into the tidy frame of ``load_study_frame``."""
    import numpy as np
    import pandas as pd
    from optuna.distributions import json_to_distribution

    attrs_by_trial: dict[int, dict[str, Any]] = {}
    for trial_id, key, value_json in user_attrs.itertuples(index=False):
        attrs_by_trial.setdefault(trial_id, {})[key] = json.loads(value_json)
    special = {"FINITE": None, "INF_POS": math.inf, "INF_NEG": -math.inf, "NAN": math.nan}
    auc = {
        t: v if special[kind] is None else special[kind]
        for t, v, kind in values.itertuples(index=False)
    }
    fallback: dict[int, dict[int, float]] = {}  # intermediate values of trials with no curve
    with_curve = {t for t, attrs in attrs_by_trial.items() if attrs.get("curve")}
    intermediate = intermediate[~intermediate["trial_id"].isin(with_curve)]
    for t, step, v, kind in intermediate.itertuples(index=False):
        fallback.setdefault(t, {})[int(step)] = v if special[kind] is None else special[kind]
    distributions: dict[str, Any] = {}  # distribution_json -> distribution, parsed once
    params_by_trial: dict[int, dict[str, Any]] = {}
    searched: dict[str, None] = {}  # params with a choice (not fixed by the spec)
    for t, name, internal, dist_json in params.itertuples(index=False):
        if dist_json not in distributions:
            distributions[dist_json] = json_to_distribution(dist_json)
        distribution = distributions[dist_json]
        params_by_trial.setdefault(t, {})[name] = distribution.to_external_repr(internal)
        if len(getattr(distribution, "choices", (0, 1))) > 1:
            searched[name] = None

    rows, parsed, metric_names = [], [], {}
    for trial_id, number, state in trials.sort_values("number").itertuples(index=False):
        attrs = attrs_by_trial.get(trial_id, {})
        row = {c: attrs.get(c) for c in TRIAL_COLUMNS}
        row.update(trial=int(number), state=str(state), auc=auc.get(trial_id))
        row.update({f"params_{k}": v for k, v in params_by_trial.get(trial_id, {}).items()})
        curve = attrs.get("curve")
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

    study = {k: json.loads(v) for k, v in study_attrs.itertuples(index=False)}
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
    for column in ("config_id", "seed", "attempts", "diverged_step"):
        frame[column] = frame[column].astype("Int64")
    frame["auc"] = frame["auc"].astype("float64")
    # A key's current trial is its highest-numbered one (sweeper.storage.current_trials).
    latest = frame.groupby("key")["trial"].transform("max")
    frame["counted"] = frame["key"].notna() & (frame["trial"] == latest)
    frame.attrs["study"] = StudyInfo(study_name, study, tuple(metrics), tuple(sorted(searched)))
    return frame


# ---- statistics ----------------------------------------------------------------------


def trial_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per trial: the trial-level columns and params of the tidy frame."""
    columns = [c for c in frame.columns if c in TRIAL_COLUMNS or c.startswith("params_")]
    return frame.drop_duplicates("trial")[columns].reset_index(drop=True)


def scored(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows of the trials that enter the statistics: counted, COMPLETE, with a finite AUC."""
    import numpy as np

    keep = frame["counted"] & (frame["state"] == "COMPLETE") & np.isfinite(frame["auc"])
    return frame[keep]


def methods_of(frame: pd.DataFrame) -> list[str]:
    """Methods in the spec's order (study attr ``spec``), then any others seen."""
    study = study_info(frame).attrs
    declared = list((study.get("spec") or {}).get("methods", {}))
    declared += [k.split("/")[0] for k in study.get("plan", [])]
    return list(dict.fromkeys(declared + frame["method"].dropna().unique().tolist()))


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
    artifacts: str | None = None,
) -> AggregateResult:
    """Read the study, compute curves and statistics, write CSV, PNG and the report to
    ``out``; with ``dashboard``, also save the comparison into the study; with the study's
    ``artifacts`` location, add pictures to the report (``sweeper.frames``)."""
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
        figures = _draw_figures(frame, curves, table, out)
        report = out / "report.md"
        text = _report(frame, table, improvement, alive)
        if artifacts is not None:  # final frames per method, the env's view (sweeper.frames)
            from sweeper.frames import report_pictures

            text += report_pictures(frame, storage, artifacts, out)
        report.write_text(text, encoding="utf-8")
        if dashboard and store is not None:
            try:
                _save_to_dashboard(storage, store.study_id, frame, curves, table, improvement)
                say("saved the comparison figures and note into the study (optuna-dashboard)")
            except (SQLAlchemyError, optuna.exceptions.StorageInternalError) as e:
                # e.g. a read-only database: the files are written, say so and go on
                say(f"warning: could not save the comparison into the study: {e}")
    finally:
        storage.remove_session()
        storage.engine.dispose()
    say(f"aggregated in {time.perf_counter() - start:.1f} s")
    return AggregateResult(frame, curves, table, improvement, (*files, *figures, report), report)


# ---- figures ---------------------------------------------------------------------------


def metric_label(metric: str, env: str | None = None) -> str:
    """Axis label with units: ``success_rate`` -> "success rate (fraction of episodes)"."""
    if metric.endswith("_rate"):
        return metric[: -len("_rate")].replace("_", " ") + " rate (fraction of episodes)"
    name = metric.replace("_", " ")
    if "angle" in metric:
        return f"{name} (rad)"
    if "distance" in metric:
        return f"{name} ({'arena units' if env == 'point_reach' else 'm'})"
    return name


def _draw_figures(
    frame: pd.DataFrame, curves: pd.DataFrame, table: pd.DataFrame, out: Path
) -> list[Path]:
    """Write the PNG figures; return their paths."""
    return [
        _draw_mean_curves(frame, curves, out / "curves.png"),
        _draw_trial_curves(frame, out / "trials.png"),
        _draw_auc(frame, table, out / "auc.png"),
    ]


def _env(frame: pd.DataFrame) -> str | None:
    return study_info(frame).attrs.get("env")


def _panels(title: str, rows: int, columns: int, *, gap: float, right: float = 0.3, **kwargs: Any):
    """A figure of ``rows x columns`` panels of 3.3 x 2.4 inches, ``gap`` inches apart
    horizontally, ``right`` inches free on the right. Fixed margins, no layout engine:
    constrained layout takes seconds on a big grid."""
    from matplotlib.figure import Figure

    panel_w, panel_h, left, bottom, top, gap_h = 3.3, 2.4, 1.0, 1.05, 0.75, 0.4
    width = left + columns * panel_w + (columns - 1) * gap + right
    height = bottom + rows * panel_h + (rows - 1) * gap_h + top
    figure = Figure(figsize=(width, height))
    margins = {
        "left": left / width,
        "right": 1 - right / width,
        "bottom": bottom / height,
        "top": 1 - top / height,
        "wspace": gap / panel_w,
        "hspace": gap_h / panel_h,
    }
    grid = figure.subplots(rows, columns, squeeze=False, sharex=True, gridspec_kw=margins, **kwargs)
    for axes in grid[-1]:
        axes.set_xlabel("environment steps")
    figure.suptitle(title, y=1 - 0.12 / height, fontsize="large")
    return figure, grid


def _style_axes(axes, metric: str, env: str | None) -> None:
    axes.set_ylabel(metric_label(metric, env).replace(" (", "\n("))  # the unit below
    axes.grid(alpha=0.3)
    if metric.endswith("_rate"):
        axes.set_ylim(-0.03, 1.03)


def _draw_mean_curves(frame, curves, path: Path) -> Path:
    """One panel per metric; per method the mean over done trials with a ± std band."""
    metrics = study_info(frame).metrics
    columns = min(len(metrics), 3)
    title = f"{study_info(frame).name}: learning curves, mean ± std over done trials"
    figure, grid = _panels(title, math.ceil(len(metrics) / columns), columns, gap=1.0)
    for axes in grid.flat[len(metrics) :]:
        axes.set_visible(False)
    for axes, metric in zip(grid.flat, metrics, strict=False):
        for index, method in enumerate(methods_of(frame)):
            part = curves[(curves["method"] == method) & (curves["metric"] == metric)]
            if part.empty:
                continue
            steps = part["step"].to_numpy(dtype=float)
            mean, std = part["mean"].to_numpy(), part["std"].fillna(0).to_numpy()
            colour = f"C{index % 10}"
            label = f"{method} (n = {int(part['n'].max())})"
            axes.plot(steps, mean, color=colour, label=label)
            axes.fill_between(steps, mean - std, mean + std, color=colour, alpha=0.2, lw=0)
        axes.set_title(metric.replace("_", " "))
        _style_axes(axes, metric, _env(frame))
    handles, labels = grid[0, 0].get_legend_handles_labels()
    if handles:
        figure.legend(
            handles,
            labels,
            title="method (done trials)",
            loc="lower center",
            ncols=min(len(handles), 4),
        )
    else:
        grid[0, 0].text(0.5, 0.5, "no done trial yet", ha="center", transform=grid[0, 0].transAxes)
    figure.savefig(path, dpi=110)
    return path


def _draw_trial_curves(frame, path: Path) -> Path:
    """A row per metric, a column per method, a line per trial: done trials coloured by
    their AUC, unfinished (running or interrupted) ones grey dashed, failed ones red dotted."""
    import matplotlib as mpl
    import numpy as np
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    methods, metrics = methods_of(frame), study_info(frame).metrics
    title = f"{study_info(frame).name}: every trial's curves, coloured by its AUC"
    figure, grid = _panels(title, len(metrics), len(methods), gap=0.25, right=1.4, sharey="row")
    current = frame[frame["counted"]].dropna(subset=["step"]).sort_values(["trial", "step"])
    aucs = current.loc[current["state"] == "COMPLETE", "auc"].dropna()
    low, high = (aucs.min(), aucs.max()) if len(aucs) else (0.0, 1.0)
    if high - low < 0.02:  # one value (or nearly): a readable scale around it
        low, high = max(low - 0.05, 0.0), min(high + 0.05, 1.0)
    norm, cmap = mpl.colors.Normalize(low, high), mpl.colormaps["viridis"]
    # state -> (colour, line style, legend label); done trials take their AUC's colour
    looks = {"RUNNING": ("0.5", "dashed", "unfinished"), "FAIL": ("tab:red", "dotted", "failed")}
    shown = set()
    for column, method in enumerate(methods):
        part = current[current["method"] == method]
        grid[0, column].set_title(f"{method}: no trial yet")
        if part.empty:
            continue
        # each trial's rows are contiguous: split the columns at the trial boundaries
        starts = np.flatnonzero(np.diff(part["trial"].to_numpy(), prepend=-1))
        states, outcomes = part["state"].to_numpy()[starts], part["outcome"].to_numpy()[starts]
        failed = (states == "FAIL") & (outcomes != "interrupted")  # interrupted: re-run later
        states = np.where(states == "COMPLETE", states, np.where(failed, "FAIL", "RUNNING"))
        colours = [
            cmap(norm(a)) if s == "COMPLETE" else looks[s][0]
            for s, a in zip(states, part["auc"].to_numpy()[starts], strict=True)
        ]
        styles = ["solid" if s == "COMPLETE" else looks[s][1] for s in states]
        shown.update(s for s in states if s != "COMPLETE")
        steps = part["step"].to_numpy(dtype=float)
        for row, metric in enumerate(metrics):
            points = np.column_stack([steps, part[metric].to_numpy(dtype=float)])
            lines = [p[np.isfinite(p[:, 1])] for p in np.split(points, starts[1:])]
            axes = grid[row, column]
            collection = LineCollection(
                lines,
                colors=colours,
                linestyles=styles,
                lw=1,
                antialiaseds=len(lines) <= DENSE,  # a dense cloud looks the same without
            )
            axes.add_collection(collection)
            axes.autoscale()
            _style_axes(axes, metric, _env(frame))
            if column:
                axes.set_ylabel("")
        names, counts = np.unique(states, return_counts=True)
        words = {"COMPLETE": "done", "FAIL": "failed", "RUNNING": "unfinished"}
        summary = ", ".join(f"{n} {words[s]}" for s, n in zip(names, counts, strict=True))
        grid[0, column].set_title(f"{method}: {summary}")
    if shown:
        handles = [
            Line2D([], [], color=looks[s][0], linestyle=looks[s][1], label=looks[s][2])
            for s in sorted(shown, reverse=True)
        ]
        figure.legend(handles=handles, loc="lower center", ncols=2)
    inch = 1 / figure.get_figwidth()  # in figure widths
    bar_axes = figure.add_axes((grid[0, -1].get_position().x1 + 0.3 * inch, 0.2, 0.15 * inch, 0.6))
    bar = figure.colorbar(mpl.cm.ScalarMappable(norm, cmap), cax=bar_axes)
    bar.set_label("trial AUC (normalised area under success rate)")
    figure.savefig(path, dpi=100)
    return path


def _draw_auc(frame, table: pd.DataFrame, path: Path) -> Path:
    import numpy as np
    from matplotlib.figure import Figure

    figure = Figure(figsize=(1.6 * len(table) + 3, 4.5), layout="constrained")
    axes = figure.add_subplot()
    done = trial_rows(scored(frame))
    rng = np.random.default_rng(0)  # jitter only
    for x, row in enumerate(table.itertuples()):
        values = done.loc[done["method"] == row.method, "auc"].to_numpy()
        jitter = rng.uniform(-0.15, 0.15, values.size)
        axes.scatter(x + jitter, values, s=14, color="0.55", label="trial AUC")
        if row.n:
            interval = [[row.iqm - row.iqm_low], [row.iqm_high - row.iqm]]
            label = f"IQM with {CONFIDENCE:.0%} bootstrap CI"
            axes.errorbar(x, row.iqm, yerr=interval, fmt="D", color="C3", capsize=6, label=label)
            axes.plot(x, row.mean, "_", color="C0", markersize=18, mew=2, label="mean")
    handles, labels = axes.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))  # one legend entry per kind
    axes.legend(unique.values(), unique.keys(), loc="best", fontsize="small")
    axes.set_xticks(
        range(len(table)),
        [f"{m}\n(n = {n})" for m, n in zip(table["method"], table["n"], strict=True)],
    )
    axes.set_xlim(-0.6, len(table) - 0.4)
    axes.set_xlabel("method (done trials)")
    axes.set_ylabel("AUC of success rate (normalised, 0..1)")
    axes.set_title(f"{study_info(frame).name}: AUC per method")
    axes.grid(axis="y", alpha=0.3)
    figure.savefig(path, dpi=110)
    return path


# ---- report and dashboard --------------------------------------------------------------


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


_DEFINITIONS = f"""\
How to read this: a trial's AUC is the area under its success-rate curve over the evaluation
grid divided by the grid's length (0: never succeeds, 1: always). Statistics use each plan
key's current trial when it is done (COMPLETE; diverged trials count, with zero success after
the divergence). IQM: mean of the middle 50 % of a method's AUCs. Its confidence interval:
percentile bootstrap, {RESAMPLES} resamples of the method's own trials (stratified by method),
seeded. Probability of improvement of A over B: over the (SAC configuration, seed) pairs where
both are done, the fraction where A's AUC is higher, ties counting one half."""


def _report(frame, table, improvement, driver_alive: bool) -> str:
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
    lines += ["## AUC per method", "", table_markdown(table, improvement), "", _DEFINITIONS, ""]
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


def _save_to_dashboard(storage, study_id: int, frame, curves, table, improvement) -> None:
    """Plotly figures (curves per metric, AUC) and a note section into the study."""
    import optuna
    import plotly.graph_objects as go
    from optuna_dashboard import get_note, save_note, save_plotly_graph_object

    study = optuna.load_study(study_name=study_info(frame).name, storage=storage)
    colours = [f"rgba{(*rgb, 1)}" for rgb in _PALETTE]
    for metric in study_info(frame).metrics:
        figure = go.Figure()
        for index, method in enumerate(methods_of(frame)):
            part = curves[(curves["method"] == method) & (curves["metric"] == metric)]
            if part.empty:
                continue
            steps = part["step"].astype(int).tolist()  # lists: plain JSON, no binary arrays
            mean = part["mean"].tolist()
            std = part["std"].fillna(0).tolist()
            colour = colours[index % len(colours)]
            band = colour.replace(", 1)", ", 0.2)")
            figure.add_trace(
                go.Scatter(
                    x=steps + steps[::-1],
                    y=[m + s for m, s in zip(mean, std, strict=True)]
                    + [m - s for m, s in zip(mean[::-1], std[::-1], strict=True)],
                    fill="toself",
                    fillcolor=band,
                    line={"width": 0},
                    hoverinfo="skip",
                    legendgroup=method,
                    showlegend=False,
                    name=f"{method} ± std",
                )
            )
            figure.add_trace(
                go.Scatter(
                    x=steps,
                    y=mean,
                    name=f"{method} (n = {int(part['n'].max())})",
                    line={"color": colour},
                    legendgroup=method,
                )
            )
        figure.update_layout(
            title=f"{metric.replace('_', ' ')}: mean ± std over done trials per method",
            xaxis_title="environment steps",
            yaxis_title=metric_label(metric, _env(frame)),
        )
        save_plotly_graph_object(study, figure, graph_object_id=f"sweeper-curves-{metric}")
    done = table[table["n"] > 0]
    aucs = trial_rows(scored(frame))
    auc_figure = go.Figure(
        go.Box(
            x=aucs["method"].tolist(),
            y=aucs["auc"].tolist(),
            text=aucs["key"].tolist(),
            boxpoints="all",
            jitter=0.4,
            pointpos=0,
            name="trial AUCs",
            marker={"color": "rgba(127, 127, 127, 0.7)"},
            line={"color": "rgba(127, 127, 127, 0.7)"},
        )
    )
    auc_figure.add_trace(
        go.Scatter(
            x=done["method"].tolist(),
            y=done["iqm"].tolist(),
            mode="markers",
            marker={"size": 12, "symbol": "diamond", "color": "rgba(214, 39, 40, 1)"},
            error_y={
                "type": "data",
                "symmetric": False,
                "array": (done["iqm_high"] - done["iqm"]).tolist(),
                "arrayminus": (done["iqm"] - done["iqm_low"]).tolist(),
            },
            name=f"IQM with {CONFIDENCE:.0%} bootstrap CI",
        )
    )
    auc_figure.update_layout(
        title=f"AUC per method: IQM with {CONFIDENCE:.0%} stratified bootstrap CI",
        xaxis_title="method",
        yaxis_title="AUC of success rate (normalised, 0..1)",
    )
    save_plotly_graph_object(study, auc_figure, graph_object_id="sweeper-auc")
    section = "\n".join(
        [
            NOTE_BEGIN,
            "## Method comparison (sweeper aggregate)",
            "",
            table_markdown(table, improvement),
            "",
            _DEFINITIONS,
            NOTE_END,
        ]
    )
    save_note(study, replace_note_section(get_note(study), section))


#: matplotlib's default colour cycle (tab10) as RGB, so dashboard and PNG colours agree
_PALETTE = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
]


def replace_note_section(note: str, section: str) -> str:
    """``note`` with its sweeper section (between the markers) replaced by ``section``,
    or ``section`` appended; what the user wrote around it is kept."""
    begin, end = note.find(NOTE_BEGIN), note.find(NOTE_END)
    if begin >= 0 and end > begin:
        return note[:begin] + section + note[end + len(NOTE_END) :]
    return f"{note.rstrip()}\n\n{section}" if note.strip() else section
