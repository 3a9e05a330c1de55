"""What optuna-dashboard shows of the comparison: one plotly figure and a section of the
study note, saved into the study.

The figure is the study page's one sweep card (``COMPARISON_ID``): optuna-dashboard lists
saved figures in the order a Python set of their ids iterates (``list_graph_object_ids``),
which changes with every server start under plain ``optuna-dashboard URL``, so a single
figure is the only order it keeps. The card opens on the comparison table; buttons above
it switch to the other views (``VIEWS``: curves per metric, AUC per method, profiles,
every trial), each drawn as it was as a card of its own before.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pandas as pd

from agent.config import TRUE_REWARD_METHODS
from sweeper.results._figures import (
    PALETTE,
    PLOTLY_DASHES,
    PROFILE_SCORES,
    clip_band,
    env_of,
    line_width,
    metric_label,
    random_label,
)
from sweeper.results._frame import (
    by_auc,
    methods_of,
    random_success,
    scored,
    study_info,
    trial_rows,
)
from sweeper.results._report import (
    DEFINITIONS,
    MIN_RELIABLE,
    _fmt,
    ranking_sentence,
    table_markdown,
)
from sweeper.results._tables import CONFIDENCE, Tables
from sweeper.storage import OBJECTIVE_NAME, name_objective

#: first and last lines of the study note's section written by ``sweeper aggregate``: link
#: reference definitions, the Markdown comment that renders as nothing (optuna-dashboard
#: shows an HTML comment as text)
NOTE_BEGIN = "[//]: # (sweeper aggregate: begin, rewritten by every run)"
NOTE_END = "[//]: # (sweeper aggregate: end)"
#: the markers written before, recognised so that their section is replaced, not repeated
OLD_MARKERS = (
    (
        "<!-- sweeper aggregate: begin (rewritten by every run) -->",
        "<!-- sweeper aggregate: end -->",
    ),
)
#: the graph object id of the sweep's one figure on the study page (the comparison and the
#: other views behind its buttons)
COMPARISON_ID = "sweeper-comparison"
#: the prefix of every figure id the sweep saved; ids other than ``COMPARISON_ID`` (the
#: five cards of its own each view had before) are removed when the figure is saved
FIGURE_PREFIX = "sweeper-"
#: the methods shown as controls wherever a "best" is shown (the comparison, the note):
#: they train on the true reward, so they bound the encoders rather than compete with them
CONTROLS = TRUE_REWARD_METHODS


def _dash(index: int) -> str:
    return PLOTLY_DASHES[(index // 10 + index) % len(PLOTLY_DASHES)]


def _band_traces(
    go, method: str, colour: str, steps, line, low, high, n: int, what: str, index: int = 0
):
    """A filled band from ``low`` to ``high`` and the ``line`` over it, as plotly traces.

    Every trace sets its ``mode``: plotly's default for a trace of at most 20 points is
    lines and markers, which draws a band's outline as dots in the next palette colour."""
    band = colour.replace(", 1)", ", 0.2)")
    return [
        go.Scatter(
            x=steps + steps[::-1],
            y=list(high) + list(low)[::-1],
            mode="lines",
            fill="toself",
            fillcolor=band,
            line={"width": 0, "color": band},
            hoverinfo="skip",
            legendgroup=method,
            showlegend=False,
            name=f"{method} {what}",
        ),
        go.Scatter(
            x=steps,
            y=list(line),
            mode="lines+markers",
            name=f"{method} (n = {n})",
            legendgroup=method,
            line={"color": colour, "dash": _dash(index)},
            marker={"color": colour, "size": 5},
        ),
    ]


def _random_trace(go, frame: pd.DataFrame, steps: list[int]):
    """The random agent's measured success rate as a dotted grey line, or None."""
    success = random_success(frame)
    if success is None or not steps:
        return None
    return go.Scatter(
        x=[min(steps), max(steps)],
        y=[success, success],
        mode="lines",
        name=random_label(success),
        line={"color": "rgba(90, 90, 90, 1)", "dash": "dot", "width": 1.5},
        hoverinfo="name",
    )


def _curve_figure(go, frame, tables: Tables, metric: str):
    """Per method: success rate as IQM with its bootstrap band (the default curve), every
    other metric as mean ± std (clipped to the metric's range); the random agent's success
    rate as a line on the success rate."""
    colours = [f"rgba{(*rgb, 1)}" for rgb in PALETTE]
    figure = go.Figure()
    iqm = metric == "success_rate"
    drawn: list[int] = []
    for index, method in enumerate(methods_of(frame)):
        colour = colours[index % len(colours)]
        if iqm:
            part = tables.efficiency[tables.efficiency["method"] == method]
            if part.empty:
                continue
            line, low, high = part["iqm"], part["low"], part["high"]
        else:
            curves = tables.curves
            part = curves[(curves["method"] == method) & (curves["metric"] == metric)]
            if part.empty:
                continue
            std = part["std"].fillna(0)
            line = part["mean"]
            low, high = clip_band(metric, part["mean"] - std, part["mean"] + std)
        steps = part["step"].astype(int).tolist()  # lists: plain JSON, no binary arrays
        drawn += steps
        what = "band" if iqm else "± std"
        n = int(part["n"].max())
        for trace in _band_traces(go, method, colour, steps, line, low, high, n, what, index):
            figure.add_trace(trace)
    if metric == "success_rate" and (trace := _random_trace(go, frame, drawn)) is not None:
        figure.add_trace(trace)
    title = (
        f"success rate: IQM with {CONFIDENCE:.0%} bootstrap bands over done trials per method"
        if iqm
        else f"{metric.replace('_', ' ')}: mean ± std over done trials per method"
    )
    figure.update_layout(
        title=title,
        xaxis_title="environment steps",
        yaxis_title=metric_label(metric, env_of(frame)),
    )
    if metric.endswith("_rate"):  # a rate: its whole range, however low the curves
        figure.update_yaxes(range=[-0.02, 1.02])
    return figure


def _metrics_figure(go, frame, tables: Tables, metrics: list[str]):
    """Every metric of ``metrics`` as ``_curve_figure`` draws it: one metric's figure, or a
    panel per metric (two a row, the legend once)."""
    from plotly.subplots import make_subplots

    if len(metrics) == 1:
        return _curve_figure(go, frame, tables, metrics[0])
    columns = 2
    rows = -(-len(metrics) // columns)
    titles = [metric.replace("_", " ") for metric in metrics]
    figure = make_subplots(rows=rows, cols=columns, shared_xaxes=True, subplot_titles=titles)
    for index, metric in enumerate(metrics):
        row, column = divmod(index, columns)
        for trace in _curve_figure(go, frame, tables, metric).data:
            trace.update(showlegend=index == 0 and trace.showlegend is not False)
            figure.add_trace(trace, row=row + 1, col=column + 1)
        if metric.endswith("_rate"):
            figure.update_yaxes(range=[-0.02, 1.02], row=row + 1, col=column + 1)
    figure.update_xaxes(title_text="environment steps", row=rows)
    figure.update_layout(title="other metrics: mean ± std over done trials per method")
    return figure


def _profile_figure(go, frame, tables: Tables):
    """Performance profiles, a panel per score, with bootstrap bands."""
    from plotly.subplots import make_subplots

    colours = [f"rgba{(*rgb, 1)}" for rgb in PALETTE]
    titles = PROFILE_SCORES.values()
    figure = make_subplots(
        rows=1, cols=len(PROFILE_SCORES), shared_yaxes=True, subplot_titles=[*titles]
    )
    profiles = tables.profiles
    for column, score in enumerate(PROFILE_SCORES, start=1):
        for index, method in enumerate(methods_of(frame)):
            part = profiles[(profiles["method"] == method) & (profiles["score"] == score)]
            if part.empty:
                continue
            colour = colours[index % len(colours)]
            n = int(part["n"].max())
            taus = part["tau"].tolist()
            fraction, low, high = part["fraction"], part["low"], part["high"]
            traces = _band_traces(go, method, colour, taus, fraction, low, high, n, "band", index)
            traces[1].update(
                mode="lines", line={"width": line_width(index, len(methods_of(frame)))}
            )  # 101 thresholds: a line without markers; earlier methods wider
            for trace in traces:
                shown = trace.showlegend is not False and column == 1
                trace.update(legendgroup=method, showlegend=shown)
                figure.add_trace(trace, row=1, col=column)
        figure.update_xaxes(title_text="threshold tau", range=[0, 1], row=1, col=column)
    figure.update_yaxes(title_text="fraction of trials above tau", range=[0, 1.02], row=1, col=1)
    figure.update_layout(title=f"Performance profiles with {CONFIDENCE:.0%} bootstrap bands")
    return figure


#: most trials drawn per method in the dashboard's trial panels (a study attr holds the
#: figure, and hundreds of overlapping lines read no better than a spread of them)
TRIALS_PER_PANEL = 30


def _panel_trials(trials: pd.DataFrame) -> pd.DataFrame:
    """One method's trials to draw: all of them, or ``TRIALS_PER_PANEL`` spread evenly over
    their AUC ranks (best and worst included; trials without an AUC rank last)."""
    if len(trials) <= TRIALS_PER_PANEL:
        return trials
    ranked = by_auc(trials)
    picks = np.unique(np.linspace(0, len(ranked) - 1, TRIALS_PER_PANEL).round().astype(int))
    return ranked.iloc[picks]


def _trials_figure(go, frame: pd.DataFrame):
    """Each method's trials' success rate in a panel of its own; hovering a point names its
    trial (key and number). One trace per method, its trials apart by gaps. The
    dashboard's own intermediate-value plot draws every trial alike."""
    from plotly.subplots import make_subplots

    methods = methods_of(frame)
    columns = min(3, len(methods))
    rows = -(-len(methods) // columns)
    trials = trial_rows(frame[frame["counted"]])
    titles = []
    for method in methods:
        mine = trials[trials["method"] == method]
        shown = len(_panel_trials(mine))
        titles.append(method if shown == len(mine) else f"{method} ({shown} of {len(mine)})")
    figure = make_subplots(
        rows=rows, cols=columns, shared_xaxes=True, shared_yaxes=True, subplot_titles=titles
    )
    evaluated = frame[frame["counted"] & frame["step"].notna()]
    for index, method in enumerate(methods):
        drawn = set(_panel_trials(trials[trials["method"] == method])["trial"])
        mine = evaluated[(evaluated["method"] == method) & evaluated["trial"].isin(drawn)]
        steps, success, names = [], [], []
        for (number, key), part in mine.groupby(["trial", "key"]):
            steps += [*part["step"].astype(int), None]  # None: a gap between two trials
            success += [*part["success_rate"], None]
            names += [f"{key} (trial {number})"] * (len(part) + 1)
        row, column = divmod(index, columns)
        figure.add_trace(
            go.Scatter(
                x=steps,
                y=success,
                text=names,
                mode="lines+markers",
                name=method,
                line={"color": f"rgba{(*PALETTE[index % len(PALETTE)], 1)}", "width": 1},
                hovertemplate="%{text}<br>step %{x}: %{y:.2f}<extra></extra>",
            ),
            row=row + 1,
            col=column + 1,
        )
    figure.update_yaxes(range=[-0.02, 1.02])
    figure.update_layout(
        title="success rate of every trial, a panel per method<br><sup>at most "
        f"{TRIALS_PER_PANEL} per method, spread over AUC ranks; hover: key and trial</sup>",
        showlegend=False,
    )
    return figure


def trials_by_method(frame, study_id: int) -> str:
    """A markdown line per method listing its counted trials' numbers, linked to
    optuna-dashboard's trial list with them selected (its ``numbers`` query: the list keeps
    every trial and shows the selected ones side by side; it has no filter by attribute)."""
    trials = trial_rows(frame[frame["counted"]])
    lines = []
    for method in methods_of(frame):
        numbers = sorted(trials.loc[trials["method"] == method, "trial"].tolist())
        if numbers:
            joined = ",".join(map(str, numbers))
            link = f"/dashboard/studies/{study_id}/trials?numbers={joined}"
            lines.append(
                f"- **{method}**: trials {', '.join(map(str, numbers))} "
                f"([show them side by side]({link}))"
            )
    return "\n".join(lines)


def best_non_control(frame: pd.DataFrame) -> dict[str, Any] | None:
    """The best counted done trial of a method that is not a control (``by_auc``'s first),
    as a trial row, or None when there is none."""
    trials = trial_rows(scored(frame))
    trials = trials[~trials["method"].isin(CONTROLS)]
    return None if trials.empty else by_auc(trials).iloc[0].to_dict()


def best_line(frame: pd.DataFrame) -> str:
    """The best non-control trial in words: "#55 conv/2/0 (conv), AUC 0.120"."""
    best = best_non_control(frame)
    if best is None:
        return "no done trial of a method other than the controls yet"
    return f"#{best['trial']} {best['key']} ({best['method']}), AUC {_fmt(best['auc'], 3)}"


#: the comparison table's columns: header, and the width in pixels its cells need on one
#: line (12 px text and 16 px of padding; the method column's is its longest name's)
_COLUMNS = {
    "rank": ("#", 24),
    "method": ("method", 0),
    "done": ("done", 50),
    "iqm": (f"IQM AUC [{CONFIDENCE:.0%} CI]", 144),
    "next": ("P(improvement) over the next [CI] (pairs)", 150),
    "best": ("best trial", 74),
}
#: pixels per character of a bold method name (12 px Open Sans, measured in Chromium)
BOLD_CHARACTER = 6.6
#: the narrowest table whose method names must show whole, in pixels: the card of a
#: 1024-px wide browser window (half the page beside optuna-dashboard's side bar)
NARROWEST_TABLE = 417


def _column_widths(methods: list[str]) -> list[float]:
    """Relative column widths (plotly's ``columnwidth``: the table fills the card's width
    in these proportions, and a cell's text wraps at its spaces only) that give the method
    column the share of ``NARROWEST_TABLE`` its longest name needs; in a wider card every
    column widens with it (tests/test_browser.py measures the names in Chromium)."""
    need = BOLD_CHARACTER * max((len(m) for m in methods), default=6) + 16
    widths = {k: float(pixels) for k, (_, pixels) in _COLUMNS.items()}
    share = min(need / NARROWEST_TABLE, 0.5)
    widths["method"] = share / (1 - share) * sum(widths.values())
    return list(widths.values())


def _comparison_figure(go, frame: pd.DataFrame, tables: Tables):
    """The comparison as a table on the study page (optuna-dashboard shows the note on a
    page of its own): per method, best first by IQM AUC, its ledger, IQM AUC with its
    interval, its paired probability of improvement over the next method, and its best
    trial; the controls say so, and the subtitle names the best trial of a non-control
    method (optuna-dashboard's own "Best Trial" card ranks every trial, controls
    included)."""
    table = tables.table
    done = table[table["n"] > 0].sort_values("iqm", ascending=False, kind="stable")
    rest = table[table["n"] == 0]
    lookup = {(r.method, r.versus): r for r in tables.improvement.itertuples()}
    rows: dict[str, list[str]] = {k: [] for k in _COLUMNS}
    ordered = [*done.itertuples(), *rest.itertuples()]
    for rank, row in enumerate(ordered, start=1):
        following = ordered[rank] if rank < len(done) else None
        versus = "–"
        r = None if following is None else lookup.get((row.method, following.method))
        if r is not None and r.pairs:
            mark = "*" if r.pairs < MIN_RELIABLE else ""
            versus = (
                f"{_fmt(r.probability, 2)} [{_fmt(r.low, 2)}, {_fmt(r.high, 2)}] ({r.pairs}{mark})"
            )
        rows["rank"].append(str(rank) if row.n else "–")
        control = " <i>(control)</i>" if row.method in CONTROLS else ""
        rows["method"].append(f"<b>{row.method}</b>{control}")
        rows["done"].append(f"{row.done}/{row.planned}")
        rows["iqm"].append(
            f"{_fmt(row.iqm, 3)} [{_fmt(row.iqm_low, 3)}, {_fmt(row.iqm_high, 3)}]"
            if row.n
            else "–"
        )
        rows["next"].append(versus)
        rows["best"].append(f"#{row.best_trial} {_fmt(row.best_auc, 3)}" if row.n else "–")
    figure = go.Figure(
        go.Table(
            columnwidth=_column_widths(table["method"].tolist()),
            header={"values": [f"<b>{h}</b>" for h, _ in _COLUMNS.values()], "align": "left"},
            cells={"values": list(rows.values()), "align": "left", "height": 24},
        )
    )
    random = random_success(frame)
    notes = [f"best non-control trial: {best_line(frame)}"]
    if random is not None:
        notes.append(f"random agent: success {random:.2f}")
    notes.append(f"* fewer than {MIN_RELIABLE} pairs")
    figure.update_layout(
        title={"text": f"Method comparison, ranked by IQM AUC<br><sup>{'; '.join(notes)}</sup>"}
    )
    return figure


def _auc_figure(go, frame: pd.DataFrame, tables: Tables):
    """Every trial's AUC per method, with the method's IQM and its bootstrap CI."""
    done = tables.table[tables.table["n"] > 0]
    aucs = trial_rows(scored(frame))
    figure = go.Figure(
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
    figure.add_trace(
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
    figure.update_layout(
        title=f"AUC per method: IQM with {CONFIDENCE:.0%} stratified bootstrap CI",
        xaxis_title="method",
        yaxis_title="AUC of success rate (normalised, 0..1)",
        yaxis_range=[-0.02, 1.02],
    )
    return figure


#: an axis' layout key (``xaxis``, ``yaxis3``) and the axis id traces refer to it by
_AXIS_KEY = re.compile(r"^([xy])axis(\d*)$")
#: trace types drawn on x/y axes (the others, a table, place themselves by ``domain``)
_CARTESIAN = frozenset({"scatter", "scattergl", "box", "bar", "histogram"})
#: axis attributes that name another axis
_AXIS_REFERENCES = ("anchor", "matches", "overlaying", "scaleanchor")
#: the card's margins: room above for a title of three lines and the buttons; the same in
#: every view, so that the buttons stay where they are
CARD_MARGIN = {"l": 8, "r": 8, "t": 100, "b": 8}
#: where a view's axes go in the card (fractions of the plot area): room at the left and
#: below for the axes' ticks and titles and above for subplot titles, which a table (the
#: comparison) needs none of
AXES_AREA = {"x": (0.1, 1.0), "y": (0.16, 0.93)}
#: what a view other than the comparison says: optuna-dashboard draws its saved figures
#: again at every live update (every 10 s unless switched off), as they are stored
RETURNS = (
    "back to the comparison at the next live update (every 10 s): "
    "Live Update off (left bar) keeps this view"
)
#: the domain of a table in a view that is not its own (``combine_views``)
HIDDEN_DOMAIN = [0.999, 1]


def _with_line(title: str, line: str) -> str:
    """``title`` with ``line`` added to its subtitle (its ``<sup>`` part), or as one."""
    if title.endswith("</sup>"):
        return f"{title.removesuffix('</sup>')}<br>{line}</sup>"
    return f"{title}<br><sup>{line}</sup>"


def _into(letter: str, value: float) -> float:
    """A position ``value`` of a view's own plot area moved into ``AXES_AREA``."""
    low, high = AXES_AREA[letter]
    return low + value * (high - low)


def views(go, frame: pd.DataFrame, tables: Tables) -> list[tuple[str, str, Any]]:
    """The card's views, in its buttons' order: ``(key, button label, plotly figure)``;
    the comparison first, the view the card opens on; the success rate's curves, then the
    other metrics' (a view of their own for one, ``curves-<metric>``, else a panel each in
    ``curves-other``), the AUC per method, the profiles and every trial's curve."""
    metrics = list(study_info(frame).metrics)
    curves = []
    if "success_rate" in metrics:
        success = _curve_figure(go, frame, tables, "success_rate")
        curves.append(("curves-success_rate", "Success rate", success))
    if others := [m for m in metrics if m != "success_rate"]:
        label = others[0].replace("_", " ").capitalize() if len(others) == 1 else "Other metrics"
        key = f"curves-{others[0]}" if len(others) == 1 else "curves-other"
        curves.append((key, label, _metrics_figure(go, frame, tables, others)))
    return [
        ("comparison", "Comparison", _comparison_figure(go, frame, tables)),
        *curves,
        ("auc", "AUC", _auc_figure(go, frame, tables)),
        ("profiles", "Profiles", _profile_figure(go, frame, tables)),
        ("trials", "Every trial", _trials_figure(go, frame)),
    ]


def combine_views(go, shown: list[tuple[str, str, Any]]):
    """One figure holding every view of ``shown`` (``views``), the first one visible and a
    button per view above it that shows that view alone (plotly's ``updatemenus``: each
    button sets which traces, axes and annotations are visible and the title).

    Each view keeps its traces and layout: its axes are renumbered so that no two views
    share one and moved into ``AXES_AREA``, with its subplot titles (annotations), which
    its button swaps in with its title. Every trace's ``meta`` is its view's key;
    ``layout.meta.views`` lists the keys in the buttons' order."""
    data: list[dict[str, Any]] = []
    axes: dict[str, dict[str, Any]] = {}
    parts = []  # per view: its axis layout keys, title, annotations, legend shown
    count = {"x": 0, "y": 0}
    for key, _, figure in shown:
        spec = figure.to_plotly_json()
        layout = spec["layout"]
        ids = {f"{m[1]}{m[2]}" for k in layout if (m := _AXIS_KEY.match(k))}
        for trace in spec["data"]:
            if trace.get("type", "scatter") in _CARTESIAN:
                ids |= {trace.get("xaxis", "x"), trace.get("yaxis", "y")}
        rename = {}
        for old in sorted(ids, key=lambda a: (a[0], int(a[1:] or 1))):
            count[old[0]] += 1
            rename[old] = f"{old[0]}{count[old[0]] if count[old[0]] > 1 else ''}"
        mine = []
        for old, new in rename.items():
            axis = dict(layout.get(f"{old[0]}axis{old[1:]}", {}))
            for attribute in _AXIS_REFERENCES:
                if axis.get(attribute) in rename:
                    axis[attribute] = rename[axis[attribute]]
            axis["domain"] = [_into(old[0], d) for d in axis.get("domain", (0, 1))]
            name = f"{new[0]}axis{new[1:]}"
            axes[name] = axis
            mine.append(name)
        for trace in spec["data"]:
            trace = {**trace, "meta": key, "visible": not parts}
            if trace.get("type") == "table" and parts:  # see the buttons below
                trace |= {"visible": True, "domain": {"x": HIDDEN_DOMAIN, "y": HIDDEN_DOMAIN}}
            if trace.get("type", "scatter") in _CARTESIAN:
                trace["xaxis"] = rename[trace.get("xaxis", "x")]
                trace["yaxis"] = rename[trace.get("yaxis", "y")]
            data.append(trace)
        annotations = []
        for annotation in layout.get("annotations", []):  # subplot titles
            annotation = dict(annotation)
            for letter in "xy":
                ref = annotation.get(f"{letter}ref", "paper")
                if ref in rename:
                    annotation[f"{letter}ref"] = rename[ref]
                elif ref == "paper" and mine:
                    annotation[letter] = _into(letter, annotation.get(letter, 0.5))
            annotations.append(annotation)
        title = {"text": (layout.get("title") or {}).get("text", "")}
        if parts:  # not the view the card opens on, which every live update returns to
            title["text"] = _with_line(title["text"], RETURNS)
        parts.append((key, mine, title, annotations, layout.get("showlegend", True)))
    for name in axes:  # only the first view's axes show at first
        axes[name]["visible"] = name in parts[0][1]
    tables = any(t.get("type") == "table" for t in data)
    buttons = []
    for (key, label, _), (_, mine, title, annotations, legend) in zip(shown, parts, strict=True):
        relayout = {"title.text": title["text"], "annotations": annotations, "showlegend": legend}
        relayout |= {f"{name}.visible": name in mine for name in axes}
        # plotly.js leaves a table drawn as it was when a restyle makes it invisible: a
        # table stays visible, shrunk to a corner's last pixel outside its own view
        restyle: dict[str, list[Any]] = {
            "visible": [t["meta"] == key or t.get("type") == "table" for t in data]
        }
        if tables:
            restyle |= {
                f"domain.{axis}": [[0, 1] if t["meta"] == key else HIDDEN_DOMAIN for t in data]
                for axis in "xy"
            }  # what the other traces get is unused
        buttons.append({"label": label, "method": "update", "args": [restyle, relayout]})
    first = parts[0]
    layout = {
        **axes,
        # the title's top 20 px down: optuna-dashboard's card hides the figure's first ~15 px
        "title": {**first[2], "x": 0.01, "xanchor": "left", "y": 1 - 20 / 450, "yanchor": "top"},
        "annotations": first[3],
        "showlegend": first[4],
        "margin": CARD_MARGIN,
        "template": "plotly_white",
        # every view's axes span the card, and plotly.js paints an overlapping subplot's
        # background over the subplots drawn before it: no background, or one view's
        # background would hide the views before it
        "plot_bgcolor": "rgba(0, 0, 0, 0)",
        "meta": {"views": [key for key, _, _ in shown]},
        "updatemenus": [
            {
                "type": "buttons",
                "direction": "right",
                "active": 0,
                "showactive": True,
                "x": 0,
                "xanchor": "left",
                "y": 1.0,
                "yanchor": "bottom",
                "pad": {"b": 6},
                "font": {"size": 11},
                "buttons": buttons,
            }
        ],
    }
    return go.Figure({"data": data, "layout": layout}, skip_invalid=False)


def split_views(figure: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The views of a figure from ``combine_views``, read back from its JSON: per view key
    (``views``), its button's ``label``, its traces (``data``), its ``title``, subplot
    titles (``annotations``) and its x axes' ids in order (``xaxes``: "x13", ...)."""
    layout = figure["layout"]
    shown = {}
    for key, button in zip(layout["meta"]["views"], layout["updatemenus"][0]["buttons"],
                           strict=True):  # fmt: skip
        relayout = button["args"][1]
        xaxes = [k.split(".")[0] for k, v in relayout.items() if v is True and k[0] == "x"]
        shown[key] = {
            "label": button["label"],
            "data": [t for t in figure["data"] if t.get("meta") == key],
            "title": relayout["title.text"],
            "annotations": relayout["annotations"],
            "xaxes": sorted((a.replace("axis", "") for a in xaxes), key=lambda a: int(a[1:] or 1)),
        }
    return shown


def remove_other_figures(storage, study_id: int) -> None:
    """Delete the figures the sweep saved under ids other than ``COMPARISON_ID`` (a card
    of its own per view, before): optuna-dashboard cannot delete a saved figure, and an
    emptied one would still be listed, as an empty card."""
    from optuna.storages._rdb.models import StudySystemAttributeModel
    from optuna_dashboard._custom_plot_data import SYSTEM_ATTR_PLOT_DATA
    from sqlalchemy import delete

    prefix = SYSTEM_ATTR_PLOT_DATA + FIGURE_PREFIX
    keep = SYSTEM_ATTR_PLOT_DATA + COMPARISON_ID + ":"
    stale = [
        key
        for key in storage.get_study_system_attrs(study_id)
        if key.startswith(prefix) and not key.startswith(keep)
    ]
    if not stale:
        return
    table = StudySystemAttributeModel.__table__
    engine = getattr(storage, "_backend", storage).engine  # Optuna's cache wraps the RDB
    with engine.begin() as connection:
        connection.execute(
            delete(table).where(table.c.study_id == study_id, table.c.key.in_(stale))
        )


def save_to_dashboard(storage, frame: pd.DataFrame, tables: Tables) -> None:
    """The comparison card (``combine_views``: the comparison table and, behind its
    buttons, the curves per metric, AUC, profiles and every trial's curve), the
    objective's name and a note section into the study; the sweep's figures saved before
    under other ids are removed."""
    import optuna
    import plotly.graph_objects as go
    from optuna_dashboard import get_note, save_note, save_plotly_graph_object

    study = optuna.load_study(study_name=study_info(frame).name, storage=storage)
    if study.metric_names != [OBJECTIVE_NAME]:  # studies launched before it was named
        name_objective(study)
    figure = combine_views(go, views(go, frame, tables))
    save_plotly_graph_object(study, figure, graph_object_id=COMPARISON_ID)
    remove_other_figures(study._storage, study._study_id)
    table = tables.table
    section = "\n".join(
        [
            NOTE_BEGIN,
            "",
            "## Method comparison",
            "",
            "*Written by `sweeper launch` as trials finish and by `sweeper aggregate`; this "
            "section is rewritten each time, text outside it is kept.*",
            "",
            ranking_sentence(table, tables.improvement, random_success(frame), CONTROLS),
            "",
            best_trial_markdown(frame, study),
            "",
            table_markdown(table, tables.improvement, pairs=True, controls=CONTROLS),
            "",
            DEFINITIONS,
            "",
            "### Trials by method",
            "",
            trials_by_method(frame, study._study_id),
            "",
            NOTE_END,
        ]
    )
    save_note(study, replace_note_section(get_note(study), section))


def best_trial_markdown(frame: pd.DataFrame, study) -> str:
    """The note's line on the best trial: the best of a non-control method, and what
    optuna-dashboard's "Best Trial" card shows (the best value of every COMPLETE trial,
    controls included) when that is a control's."""
    text = f"**Best non-control trial:** {best_line(frame)}."
    controls = ", ".join(f"`{c}`" for c in CONTROLS)
    try:  # what the card calls, the storage's best trial
        optuna_best = study._storage.get_best_trial(study._study_id)
    except ValueError:  # no COMPLETE trial
        return text
    method = optuna_best.user_attrs.get("method")
    if method in CONTROLS:
        text += (
            f" optuna-dashboard's *Best Trial* card ranks every trial, the controls' "
            f"({controls}) included: it shows #{optuna_best.number}, a trial of the control "
            f"`{method}`."
        )
    return text


def replace_note_section(note: str, section: str) -> str:
    """``note`` with its sweeper section (between the markers, or the markers written
    before, ``OLD_MARKERS``) replaced by ``section``, or ``section`` appended; what the user
    wrote around it is kept."""
    for first, last in ((NOTE_BEGIN, NOTE_END), *OLD_MARKERS):
        begin, end = note.find(first), note.find(last)
        if begin >= 0 and end > begin:
            return note[:begin] + section + note[end + len(last) :]
    return f"{note.rstrip()}\n\n{section}" if note.strip() else section
