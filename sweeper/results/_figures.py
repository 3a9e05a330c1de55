"""Figures of a study as PNG (matplotlib): learning curves, every trial's curves, AUCs."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from agent.config import Outcome
from sweeper.results._frame import methods_of, random_success, scored, study_info, trial_rows
from sweeper.results._tables import CONFIDENCE, Tables

#: trials per panel above which lines are drawn without antialiasing (25 % faster)
DENSE = 200


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


def draw_figures(frame: pd.DataFrame, tables: Tables, out: Path) -> list[Path]:
    """Write the PNG figures; return their paths."""
    title = study_info(frame).name
    random = random_success(frame)
    return [
        draw_efficiency(tables.efficiency, out / "efficiency.png", title, env_of(frame), random),
        draw_profiles(tables.profiles, out / "profiles.png", title),
        _draw_mean_curves(frame, tables.curves, out / "curves.png"),
        _draw_trial_curves(frame, out / "trials.png"),
        _draw_auc(frame, tables.table, out / "auc.png"),
    ]


def _method_colours(methods: list[str]) -> dict[str, str]:
    return {m: f"C{i % 10}" for i, m in enumerate(methods)}


#: a line style per method (cycled), so methods whose curves coincide stay apart
LINE_STYLES = ("solid", (0, (5, 2)), (0, (1, 1.5)), (0, (5, 2, 1, 2)))
#: the same dashes for plotly (the dashboard's figures)
PLOTLY_DASHES = ("solid", "dash", "dot", "dashdot")


def line_style(index: int) -> Any:
    """The matplotlib line style of the ``index``-th method."""
    return LINE_STYLES[(index // 10 + index) % len(LINE_STYLES)]


def line_width(index: int, count: int) -> float:
    """Wider for the earlier methods, so a later line on top of an earlier one (two methods
    with the same profile) leaves the earlier one showing at its edges."""
    return 1.2 + 1.8 * (count - 1 - index) / max(count - 1, 1)


def clip_band(metric: str, low: Any, high: Any) -> tuple[Any, Any]:
    """A ± band clipped to the metric's range: rates to [0, 1], distances below at 0."""
    if metric.endswith("_rate"):
        return np.clip(low, 0.0, 1.0), np.clip(high, 0.0, 1.0)
    if "distance" in metric:
        return np.maximum(low, 0.0), high
    return low, high


def random_label(success: float) -> str:
    """The legend entry of the random agent's line."""
    return f"random agent ({success:.2f})"


def _draw_random(axes: Any, success: float | None) -> None:
    """The random agent's measured success rate as a grey dotted line across ``axes``."""
    if success is not None:
        axes.axhline(success, color="0.35", ls=":", lw=1.2, label=random_label(success))


def draw_efficiency(
    efficiency: pd.DataFrame,
    path: Path,
    title: str,
    env: str | None = None,
    random: float | None = None,
) -> Path:
    """Sample-efficiency curves: per method the IQM of the success rate with its band;
    ``random``: the random agent's success rate, drawn as a line."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7.5, 4.8), layout="constrained")
    axes = figure.add_subplot()
    methods = list(dict.fromkeys(efficiency["method"]))
    for index, (method, colour) in enumerate(_method_colours(methods).items()):
        part = efficiency[efficiency["method"] == method]
        steps = part["step"].to_numpy(dtype=float)
        label = f"{method} (n = {int(part['n'].max())})"
        axes.plot(steps, part["iqm"], color=colour, ls=line_style(index), label=label)
        axes.fill_between(steps, part["low"], part["high"], color=colour, alpha=0.2, lw=0)
    _draw_random(axes, random)
    if methods:
        axes.legend(title="method (done trials)", fontsize="small")
    else:
        axes.text(0.5, 0.5, "no done trial yet", ha="center", transform=axes.transAxes)
    axes.set_title(f"{title}: IQM success rate, {CONFIDENCE:.0%} bootstrap bands")
    axes.set_xlabel("environment steps")
    _style_axes(axes, "success_rate", env)
    figure.savefig(path, dpi=110)
    return path


PROFILE_SCORES = {"auc": "AUC of success rate", "final_success": "final success rate"}


def draw_profiles(
    profiles: pd.DataFrame, path: Path, title: str, labels: dict[str, str] = PROFILE_SCORES
) -> Path:
    """Performance profiles: a panel per score (``labels``: score -> axis label), per method
    the fraction of trials above tau."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11, 4.6), layout="constrained")
    grid = figure.subplots(1, len(labels), sharey=True)
    methods = list(dict.fromkeys(profiles["method"]))
    colours = _method_colours(methods)
    for axes, (score, label) in zip(grid, labels.items(), strict=True):
        for index, method in enumerate(methods):
            part = profiles[(profiles["method"] == method) & (profiles["score"] == score)]
            if part.empty:
                continue
            n = int(part["n"].max())
            axes.plot(
                part["tau"],
                part["fraction"],
                color=colours[method],
                ls=line_style(index),
                lw=line_width(index, len(methods)),
                label=f"{method} ({n})",
            )
            axes.fill_between(
                part["tau"], part["low"], part["high"], color=colours[method], alpha=0.2, lw=0
            )
        axes.set_xlabel(f"{label} threshold tau")
        if len(profiles):
            axes.set_xlim(profiles["tau"].min(), profiles["tau"].max())
        axes.set_ylim(-0.03, 1.03)
        axes.grid(alpha=0.3)
    grid[0].set_ylabel("fraction of trials above tau")
    if methods:
        grid[-1].legend(title="method (done trials)", fontsize="small")
    figure.suptitle(f"{title}: performance profiles, {CONFIDENCE:.0%} bootstrap bands")
    figure.savefig(path, dpi=110)
    return path


def env_of(frame: pd.DataFrame) -> str | None:
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
            axes.plot(steps, mean, color=colour, ls=line_style(index), label=label)
            low, high = clip_band(metric, mean - std, mean + std)
            axes.fill_between(steps, low, high, color=colour, alpha=0.2, lw=0)
        if metric == "success_rate":
            _draw_random(axes, random_success(frame))
        axes.set_title(metric.replace("_", " "))
        _style_axes(axes, metric, env_of(frame))
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
        failed = (states == "FAIL") & (outcomes != Outcome.INTERRUPTED)  # re-run later
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
            _style_axes(axes, metric, env_of(frame))
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


#: matplotlib's default colour cycle (tab10) as RGB, so dashboard and PNG colours agree
PALETTE = [
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
